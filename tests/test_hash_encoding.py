"""Tests of the multi-resolution hash-grid encoding (torch, C++ and, on a CUDA machine, CUDA paths vs the reference)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import pytest
import torch
import torch.utils.cpp_extension
from torch import Tensor

from scalar_nerfstudio.encodings import (
    GridLayout,
    HashGridEncoding,
    _cpp,
    cpp_extension_available,
    cpp_extension_error,
    grid_resolutions,
    hash_encoding_cpp,
    hash_encoding_cuda,
    hash_encoding_torch,
    level_corners,
    level_row_counts,
)
from scalar_nerfstudio.encodings._reference import reference_hash_encoding
from scalar_nerfstudio.encodings.hash_grid import sanitise_positions

Encode = Callable[[Tensor, Tensor, GridLayout], Tensor]

FORWARD_ATOL = 1e-6


def assert_grad_close(actual: Tensor, expected: Tensor) -> None:
    """Gradients accumulate many contributions per row, in a different order than the reference."""
    torch.testing.assert_close(actual, expected, atol=1e-5, rtol=1e-5)


def skip_without_cpp() -> None:
    if not cpp_extension_available():
        pytest.skip(f"C++ hash-grid extension unavailable: {cpp_extension_error()}")


needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def encode_on_cuda(positions: Tensor, table: Tensor, layout: GridLayout) -> Tensor:
    """The CUDA kernel's encoding of CPU tensors, returned on the CPU (the table's gradient flows back
    through the copies). On a CUDA machine the kernel must build: a failed build fails the test."""
    return hash_encoding_cuda(positions.cuda(), table.cuda(), layout).cpu()


@pytest.fixture(params=["torch", "cpp", pytest.param("cuda", marks=needs_cuda)])
def encode(request: pytest.FixtureRequest) -> Encode:
    """The encoding function of one implementation; the C++ one is skipped if it cannot be built,
    the CUDA one without a GPU."""
    if request.param == "cpp":
        skip_without_cpp()
        return hash_encoding_cpp
    if request.param == "cuda":
        return encode_on_cuda
    return hash_encoding_torch


def make_encoding(
    features: int, num_levels: int = 8, log2_hashmap_size: int = 12, max_resolution: int = 256
) -> HashGridEncoding:
    """A small seeded grid with O(1) table entries (so that 1e-6 tolerances are meaningful).

    With the defaults, T = 4096 and resolutions 4, 7, 13 are dense ((R + 1)^3 <= 4096), 23 .. 256
    hashed.
    """
    torch.manual_seed(0)
    return HashGridEncoding(num_levels=num_levels, features_per_level=features, log2_hashmap_size=log2_hashmap_size, base_resolution=4,
                            max_resolution=max_resolution, init_scale=1.0)


def special_points(resolutions: list[int]) -> Tensor:
    """[M, 3] points on 0, 1, cell boundaries of every level, just inside/outside [0, 1], far
    outside, infinite and NaN, mixed across coordinates."""
    values = [0.0, 1.0, -0.0, 0.5, 1e-45, 1.0 - 2**-24, 1.0 + 2**-23, -1e-7, 2.0, -3.0, 1e30, -1e30]
    values += [math.inf, -math.inf, math.nan]
    for res in resolutions:
        values += [m / res for m in (1, res // 2, res - 1)]
    column = torch.tensor(values, dtype=torch.float32)
    generator = torch.Generator().manual_seed(1)
    return torch.stack([column[torch.randperm(len(values), generator=generator)] for _ in range(3)], dim=1)


def sample_points(resolutions: list[int], num_random: int = 3000) -> Tensor:
    """Random points in [0, 1]^3 followed by :func:`special_points`."""
    generator = torch.Generator().manual_seed(2)
    return torch.cat([torch.rand(num_random, 3, generator=generator), special_points(resolutions)])


def reference(enc: HashGridEncoding, positions: Tensor) -> Tensor:
    return reference_hash_encoding(positions, enc.table, level_offsets=enc.level_offsets, resolutions=enc.resolutions,
                                   hashmap_size=enc.hashmap_size)


@pytest.mark.parametrize("features", [2, 4])
def test_forward_matches_reference(encode: Encode, features: int) -> None:
    enc = make_encoding(features)
    positions = sample_points(enc.resolutions)
    with torch.no_grad():
        expected = reference(enc, positions)
        actual = encode(positions, enc.table, enc.layout)
    assert actual.shape == (positions.shape[0], enc.get_out_dim())
    assert torch.isfinite(actual).all()
    torch.testing.assert_close(actual, expected, atol=FORWARD_ATOL, rtol=0)


@pytest.mark.parametrize("features", [1, 2, 4, 8])
def test_backward_matches_reference(encode: Encode, features: int) -> None:
    enc = make_encoding(features)
    positions = sample_points(enc.resolutions)
    upstream = torch.randn(positions.shape[0], enc.get_out_dim(), generator=torch.Generator().manual_seed(3))
    (expected,) = torch.autograd.grad(reference(enc, positions), enc.table, upstream)
    (actual,) = torch.autograd.grad(encode(positions, enc.table, enc.layout), enc.table, upstream)
    assert torch.isfinite(actual).all()
    assert_grad_close(actual, expected)



@pytest.mark.parametrize("implementation", ["torch", "cpp", pytest.param("cuda", marks=needs_cuda)])
def test_an_encoding_computed_without_autograd_gets_the_tables_gradient(implementation: str) -> None:
    """A training step encodes its samples once, in the no-grad pass; joined to the table's graph
    later, that encoding gives the table exactly the gradient of encoding them again (on CUDA, up to
    the order of the kernel's atomic sums)."""
    if implementation == "cpp":
        skip_without_cpp()
    device = torch.device("cuda" if implementation == "cuda" else "cpu")
    torch.manual_seed(0)
    enc = HashGridEncoding(num_levels=8, features_per_level=4, log2_hashmap_size=12, base_resolution=4, max_resolution=256,
                           implementation=implementation, init_scale=1.0).to(device)
    assert enc.active_implementation == implementation
    positions = sample_points(enc.resolutions).to(device)  # NaN, infinities and points outside [0, 1] included
    upstream = torch.randn(positions.shape[0], enc.get_out_dim(), generator=torch.Generator().manual_seed(3)).to(device)
    (expected,) = torch.autograd.grad(enc(positions), enc.table, upstream)
    with torch.no_grad():
        encoding = enc(positions)
    joined = enc.with_table_gradient(positions, encoding)
    assert joined.requires_grad and torch.equal(joined, encoding)
    (actual,) = torch.autograd.grad(joined, enc.table, upstream)
    assert torch.isfinite(actual).all()
    if implementation == "cuda":  # two backward passes, each summing with atomics in its own order
        assert_grad_close(actual, expected)
    else:
        torch.testing.assert_close(actual, expected, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match=r"encoding \[N, 32\]"):
        enc.with_table_gradient(positions, encoding[:, :16])


def test_cpp_is_deterministic_across_thread_counts() -> None:
    """Forward splits points over threads, backward splits levels: both are bitwise independent of
    the thread count, and match the reference with 2 threads."""
    skip_without_cpp()
    enc = make_encoding(2)
    positions = sample_points(enc.resolutions, num_random=8192)
    upstream = torch.randn(positions.shape[0], enc.get_out_dim(), generator=torch.Generator().manual_seed(4))
    previous = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            out = hash_encoding_cpp(positions, enc.table, enc.layout)
            (grad,) = torch.autograd.grad(out, enc.table, upstream)
            results.append((out.detach(), grad))
    finally:
        torch.set_num_threads(previous)
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])
    expected = reference(enc, positions)
    (grad_expected,) = torch.autograd.grad(expected, enc.table, upstream)
    torch.testing.assert_close(results[1][0], expected.detach(), atol=FORWARD_ATOL, rtol=0)
    assert_grad_close(results[1][1], grad_expected)


def test_nan_is_zero_and_outside_is_clamped(encode: Encode) -> None:
    enc = make_encoding(2)
    nan, inf = math.nan, math.inf
    raw = torch.tensor([[nan, 0.3, 0.7], [0.2, -5.0, 7.0], [inf, -inf, 1e30], [nan, nan, nan]])
    clean = torch.tensor([[0.0, 0.3, 0.7], [0.2, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    with torch.no_grad():
        torch.testing.assert_close(
            encode(raw, enc.table, enc.layout), encode(clean, enc.table, enc.layout), atol=0, rtol=0
        )


@pytest.mark.parametrize("log2_hashmap_size", [12, 19])
def test_corner_rows_in_range_for_extreme_inputs(log2_hashmap_size: int) -> None:
    hashmap_size = 2**log2_hashmap_size
    resolutions = grid_resolutions(16, 16, 2**23)  # up to the largest supported resolution range
    rows_per_level = level_row_counts(resolutions, hashmap_size)
    extreme = torch.tensor([0.0, 1.0, 1e30, -1e30, math.inf, -math.inf, math.nan, 1.0 - 2**-24, 3.4e38])
    positions = torch.cartesian_prod(extreme, extreme, extreme)
    coords = sanitise_positions(positions).t().contiguous()
    for res, num_rows in zip(resolutions, rows_per_level):
        rows, weights = level_corners(coords, res, hashmap_size)
        assert rows.dtype == torch.int64 and rows.shape == (8, positions.shape[0])
        assert int(rows.min()) >= 0 and int(rows.max()) < num_rows
        assert torch.isfinite(weights).all() and (weights >= 0).all()
        torch.testing.assert_close(weights.sum(dim=0), torch.ones(positions.shape[0]))


def test_extreme_inputs_finite_outputs_and_gradients(encode: Encode) -> None:
    enc = make_encoding(4, max_resolution=4096)
    extreme = torch.tensor([0.0, 1.0, 1e30, -1e30, math.inf, -math.inf, math.nan, 0.999999])
    positions = torch.cartesian_prod(extreme, extreme, extreme)
    out = encode(positions, enc.table, enc.layout)
    (grad,) = torch.autograd.grad(out.sum(), enc.table)
    assert torch.isfinite(out).all() and torch.isfinite(grad).all()
    torch.testing.assert_close(out.detach(), reference(enc, positions).detach(), atol=FORWARD_ATOL, rtol=0)


def test_dense_and_hashed_level_sizes() -> None:
    enc = HashGridEncoding(num_levels=16, features_per_level=2, log2_hashmap_size=19)
    hashmap_size = 2**19
    assert enc.resolutions[0] == 16 and enc.resolutions[-1] == 2048
    counts = [int(enc.level_offsets[level + 1] - enc.level_offsets[level]) for level in range(enc.num_levels)]
    for res, count in zip(enc.resolutions, counts):
        if (res + 1) ** 3 <= hashmap_size:
            assert count == (res + 1) ** 3
        else:
            assert count == hashmap_size
    assert counts[0] == 17**3 and counts[-1] == hashmap_size
    assert sum(1 for res in enc.resolutions if (res + 1) ** 3 <= hashmap_size) == 5  # R = 16 .. 58
    assert enc.table.shape == (sum(counts), 2)
    assert sum(p.numel() for p in enc.parameters()) == sum(counts) * 2
    assert enc.level_offsets.dtype == torch.int64 and enc.level_offsets.shape == (17,)


def test_resolutions_are_geometric() -> None:
    assert grid_resolutions(1, 16, 2048) == [16]
    assert grid_resolutions(4, 8, 64) == [8, 16, 32, 64]
    assert grid_resolutions(16, 16, 4096)[-1] == 4096  # not 4095 from float round-off
    growth = math.exp((math.log(2048) - math.log(16)) / 15)
    assert grid_resolutions(16, 16, 2048) == [math.floor(16 * growth**level + 1e-6) for level in range(16)]


def test_module_interface() -> None:
    enc = HashGridEncoding(num_levels=8, features_per_level=4, log2_hashmap_size=12, implementation="torch")
    assert enc.get_out_dim() == 32
    assert enc.active_implementation == "torch"
    assert float(enc.table.detach().abs().max()) <= 1e-4
    positions = torch.rand(2, 5, 3, dtype=torch.float64, requires_grad=True)  # batch dims, float64
    out = enc(positions)
    assert out.shape == (2, 5, 32) and out.dtype == torch.float32
    out.sum().backward()
    assert positions.grad is None and enc.table.grad is not None
    with pytest.raises(ValueError, match="shape"):
        enc(torch.rand(4, 2))


def test_auto_uses_cpp_on_cpu_when_available() -> None:
    enc = HashGridEncoding(num_levels=8, log2_hashmap_size=12)
    expected = "cpp" if cpp_extension_available() else "torch"
    assert enc.active_implementation == expected
    odd = HashGridEncoding(num_levels=2, features_per_level=3, log2_hashmap_size=12, max_resolution=32)
    assert odd.active_implementation == "torch"  # F the C++ kernel is not specialised for
    assert odd(torch.rand(5, 3)).shape == (5, 6)
    with pytest.raises(ValueError, match="features_per_level"):
        HashGridEncoding(features_per_level=3, implementation="cpp")


def test_cpp_rejects_bad_inputs() -> None:
    skip_without_cpp()
    enc = make_encoding(2)
    positions = torch.rand(10, 3)
    with pytest.raises(RuntimeError, match="contiguous"):
        hash_encoding_cpp(torch.rand(3, 10).t(), enc.table, enc.layout)
    with pytest.raises(RuntimeError, match="float32"):
        hash_encoding_cpp(positions.double(), enc.table, enc.layout)
    with pytest.raises(RuntimeError, match=r"\[N, 3\]"):
        hash_encoding_cpp(torch.rand(10, 4), enc.table, enc.layout)
    with pytest.raises(RuntimeError, match="row count"):
        hash_encoding_cpp(positions, enc.table[:-1], enc.layout)


def make_builds_fail(monkeypatch: pytest.MonkeyPatch, extension: _cpp.JitExtension, message: str) -> None:
    """A fresh loader state for ``extension`` (restored by monkeypatch) with a build that fails with ``message``."""

    def failing_load(*args: object, **kwargs: object) -> None:
        raise OSError(message)

    monkeypatch.setattr(extension, "_attempted", False)
    monkeypatch.setattr(extension, "_ops", None)
    monkeypatch.setattr(extension, "_error", None)
    monkeypatch.setattr(torch.utils.cpp_extension, "load", failing_load)


def test_build_failure_falls_back_to_torch(monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    make_builds_fail(monkeypatch, _cpp.CPU_KERNELS, "no C++ compiler")
    with caplog.at_level(logging.WARNING, logger=_cpp.__name__):
        enc = HashGridEncoding(num_levels=4, features_per_level=2, log2_hashmap_size=12, max_resolution=64)
        assert enc.active_implementation == "torch"
        assert enc(torch.rand(10, 3)).shape == (10, 8)
        assert not cpp_extension_available()
    assert len(caplog.records) == 1 and "falling back" in caplog.records[0].getMessage()
    assert "no C++ compiler" in (cpp_extension_error() or "")
    with pytest.raises(RuntimeError, match="no C\\+\\+ compiler"):
        HashGridEncoding(num_levels=4, log2_hashmap_size=12, implementation="cpp")(torch.rand(10, 3))


def test_cuda_build_failure_falls_back_to_torch(monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """A CUDA machine without nvcc (or where the build fails) trains with the torch hash grid after
    one warning; asking for the kernel by name is an error that says why. Runs without a GPU: only
    the choice is made, nothing is allocated on the device."""
    make_builds_fail(monkeypatch, _cpp.CUDA_HASH_GRID, "CUDA_HOME environment variable is not set")
    with caplog.at_level(logging.WARNING, logger=_cpp.__name__):
        assert make_encoding(2).implementation_for("cuda") == "torch"
        assert make_encoding(2).implementation_for("cuda") == "torch"  # the build is tried once
    assert len(caplog.records) == 1 and "CUDA hash-grid kernels" in caplog.records[0].getMessage()
    with pytest.raises(RuntimeError, match="implementation='cuda' but the CUDA hash-grid kernels are unavailable: .*CUDA_HOME"):
        HashGridEncoding(num_levels=4, log2_hashmap_size=12, implementation="cuda").implementation_for("cuda")
    cpp_on_cuda = HashGridEncoding(num_levels=4, log2_hashmap_size=12, implementation="cpp")
    assert cpp_on_cuda.implementation_for("cuda") == "torch"  # "cpp" names the CPU's kernel only


@needs_cuda
@pytest.mark.parametrize("implementation", ["auto", "torch"])
def test_cuda_matches_cpu_reference(implementation: str) -> None:
    """On a CUDA table, "auto" runs the CUDA kernel (it must build where there is a GPU) and "torch"
    the torch code; both give the reference's features and table gradient."""
    enc = make_encoding(2)
    enc.implementation = implementation  # type: ignore[assignment]
    positions = sample_points(enc.resolutions)
    upstream = torch.randn(positions.shape[0], enc.get_out_dim(), generator=torch.Generator().manual_seed(3))
    expected = reference(enc, positions)
    (grad_expected,) = torch.autograd.grad(expected, enc.table, upstream)
    enc_cuda = enc.cuda()
    assert enc_cuda.active_implementation == ("cuda" if implementation == "auto" else "torch")
    actual = enc_cuda(positions.cuda())
    (grad_actual,) = torch.autograd.grad(actual, enc_cuda.table, upstream.cuda())
    torch.testing.assert_close(actual.cpu().detach(), expected.detach(), atol=FORWARD_ATOL, rtol=0)
    assert_grad_close(grad_actual.cpu(), grad_expected)


@needs_cuda
def test_cuda_kernel_rejects_bad_inputs() -> None:
    enc = make_encoding(2).cuda()
    positions = torch.rand(10, 3, device="cuda")
    with pytest.raises(RuntimeError, match="contiguous"):
        hash_encoding_cuda(torch.rand(3, 10, device="cuda").t(), enc.table, enc.layout)
    with pytest.raises(RuntimeError, match="float32"):
        hash_encoding_cuda(positions.double(), enc.table, enc.layout)
    with pytest.raises(RuntimeError, match=r"\[N, 3\], got \[10, 4\]"):
        hash_encoding_cuda(torch.rand(10, 4, device="cuda"), enc.table, enc.layout)
    with pytest.raises(RuntimeError, match="row count"):
        hash_encoding_cuda(positions, enc.table[:-1], enc.layout)
    with pytest.raises(RuntimeError, match="must be a CUDA tensor"):
        hash_encoding_cuda(positions.cpu(), enc.table, enc.layout)


@pytest.mark.parametrize("implementation", ["torch", "auto"])
def test_fitting_a_smooth_function_lowers_the_loss(implementation: str) -> None:
    torch.manual_seed(0)
    enc = HashGridEncoding(
        num_levels=8,
        features_per_level=2,
        log2_hashmap_size=14,
        base_resolution=4,
        max_resolution=128,
        implementation=implementation,  # type: ignore[arg-type]
    )
    head = torch.nn.Linear(enc.get_out_dim(), 1)
    optimizer = torch.optim.Adam([*enc.parameters(), *head.parameters()], lr=1e-2)
    positions = torch.rand(2048, 3)
    target = torch.sin(2 * math.pi * positions[:, 0]) * torch.cos(2 * math.pi * positions[:, 1]) + positions[:, 2]
    losses = []
    for _ in range(30):
        loss = torch.nn.functional.mse_loss(head(enc(positions)).squeeze(-1), target)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.1 * losses[0]
