"""The render march's C++ kernels (``csrc/march.cpp``) agree with the torch code they replace on the CPU.

The torch code (the visibility sampler's rounds, the dense volume rendering) is the path on CUDA, with
gradients and where the extension does not build; these tests run it by hiding the kernels
(``_cpp.march_ops`` returning None) and compare: a round's candidates and kept samples, the compact
volume rendering on ordinary and extreme densities and intervals, whole renders of a model whose grid
prunes, and a render with normals. The kernels' own checks (samples out of order, out of range) raise.
"""

from __future__ import annotations

import pytest
import torch
from conftest import ray_bundle, small_scalar_model, with_torch_code

from scalar_nerfstudio.encodings import _cpp
from scalar_nerfstudio.model_components.rendering import dense_weights, render_kept_samples
from scalar_nerfstudio.models.scalar_model import ScalarModel

pytestmark = pytest.mark.skipif(_cpp.march_ops() is None, reason="the C++ kernels do not build here")


def kept_samples(num_rays: int = 96, num_samples: int = 24, seed: int = 0) -> dict:
    """A random set of kept samples, each ray's in front-to-back order but rays interleaved as the rounds
    give them, with densities from 0 to opaque and extreme values (NaN, inf, huge) on a few rays."""
    generator = torch.Generator().manual_seed(seed)
    keep = torch.rand(num_rays, num_samples, generator=generator) < 0.4
    ids = torch.nonzero(keep.reshape(-1)).squeeze(-1)
    rank = (torch.cumsum(keep.reshape(num_rays, num_samples).long(), dim=1) - 1).reshape(-1)[ids]
    ids = ids[torch.argsort(rank * num_rays * num_samples + ids)]  # round by round: rank first, then ray
    density = torch.rand(ids.numel(), generator=generator) ** 3 * 40.0
    t_starts = torch.sort(torch.rand(num_rays, num_samples, generator=generator) * 10.0, dim=-1).values
    deltas = torch.rand(num_rays, num_samples, generator=generator) * 0.3
    rays_of = torch.div(ids, num_samples, rounding_mode="floor")
    density[rays_of == 0] = float("nan")
    density[rays_of == 1] = float("inf")
    density[rays_of == 2] = 1e30
    deltas[3] = 0.0
    deltas[4] = 1e20
    return {
        "sample_ids": ids, "density": density, "rgb": torch.rand(ids.numel(), 3, generator=generator),
        "deltas": deltas, "t_mid": t_starts + deltas / 2, "fars": torch.full((num_rays, 1), 12.0),
        "background": torch.rand(num_rays, 3, generator=generator),
    }


def render(samples: dict):  # type: ignore[no-untyped-def]
    return render_kept_samples(samples["sample_ids"], samples["density"], samples["rgb"], deltas=samples["deltas"],
                               t_mid=samples["t_mid"], fars=samples["fars"], background=samples["background"])


def test_compact_rendering_equals_the_dense_volume_rendering(monkeypatch: pytest.MonkeyPatch) -> None:
    samples = kept_samples()
    kernel = render(samples)
    reference = with_torch_code(monkeypatch, "march_ops", lambda: render(samples))
    for field in ("rgb", "depth", "accumulation", "sample_weights"):
        assert torch.isfinite(getattr(kernel, field)).all(), field
        torch.testing.assert_close(getattr(kernel, field), getattr(reference, field), atol=1e-5, rtol=0)
    assert float(kernel.accumulation.max()) > 0.99 and float(kernel.accumulation.min()) < 0.5  # opaque and clear rays
    num_rays, num_samples = samples["deltas"].shape
    dense = dense_weights(kernel, samples["sample_ids"], num_rays, num_samples)
    torch.testing.assert_close(dense.sum(dim=-1, keepdim=True), kernel.accumulation, atol=1e-5, rtol=0)
    torch.testing.assert_close(dense, dense_weights(reference, samples["sample_ids"], num_rays, num_samples), atol=1e-5, rtol=0)


def test_rays_without_samples_render_the_background_at_their_far_bound() -> None:
    samples = kept_samples()
    empty = {**samples, "sample_ids": samples["sample_ids"][:0], "density": samples["density"][:0], "rgb": samples["rgb"][:0]}
    rendered = render(empty)
    assert torch.equal(rendered.rgb, samples["background"])
    assert torch.equal(rendered.depth, samples["fars"])
    assert torch.equal(rendered.accumulation, torch.zeros_like(samples["fars"]))


def test_the_compositor_rejects_samples_out_of_order_or_out_of_range() -> None:
    samples = kept_samples()
    num_rays, num_samples = samples["deltas"].shape
    ray_zero = torch.tensor([1, 0], dtype=torch.long)  # ray 0's second sample before its first
    swapped = {**samples, "sample_ids": ray_zero, "density": torch.ones(2), "rgb": torch.ones(2, 3)}
    with pytest.raises(RuntimeError, match="front-to-back order"):
        render(swapped)
    outside = {**swapped, "sample_ids": torch.tensor([0, num_rays * num_samples])}
    with pytest.raises(RuntimeError, match="outside"):
        render(outside)


def test_with_gradients_the_dense_code_renders_and_gradients_flow() -> None:
    samples = kept_samples()
    density = samples["density"].clamp(max=50.0).nan_to_num(0.0).requires_grad_(True)
    rendered = render({**samples, "density": density})
    rendered.rgb.sum().backward()
    assert density.grad is not None and torch.isfinite(density.grad).all()


def test_a_round_keeps_what_the_torch_rounds_keep(monkeypatch: pytest.MonkeyPatch) -> None:
    """The whole front-to-back march of a model whose grid prunes: the same kept samples, densities and
    features with the kernels as with the torch rounds, and so the same image, depth and samples per ray."""
    model = pruned_ball_model()
    rays = camera_rays(384)
    with torch.no_grad():
        samples = model._ray_samples(model.collider(rays), jitter=False)  # noqa: SLF001 - the render's own samples
        deltas = samples.t_ends - samples.t_starts
        kernel = model.visibility().visible_with_features(samples.unit_positions, deltas)
        reference = with_torch_code(monkeypatch, "march_ops", lambda: model.visibility().visible_with_features(samples.unit_positions, deltas))
    assert kernel[0].numel() > 0
    assert torch.equal(kernel[0], reference[0])
    torch.testing.assert_close(kernel[1], reference[1], atol=0, rtol=0)
    torch.testing.assert_close(kernel[2], reference[2], atol=0, rtol=0)


@pytest.mark.parametrize("normals", [False, True])
def test_a_model_renders_the_same_image_with_the_kernels_as_with_the_torch_code(monkeypatch: pytest.MonkeyPatch, normals: bool) -> None:
    model = pruned_ball_model()
    rays = camera_rays(384)
    with torch.no_grad():
        kernel = model.render_rays(rays, normals=normals)
        reference = with_torch_code(monkeypatch, "march_ops", lambda: model.render_rays(rays, normals=normals))
    assert kernel["accumulation"].max() > 0.9 and kernel["accumulation"].min() < 0.1  # rays hit and miss
    for key in ("rgb", "depth", "accumulation", "samples_per_ray", *(["normals"] if normals else [])):
        torch.testing.assert_close(kernel[key], reference[key], atol=1e-5, rtol=0)


def pruned_ball_model() -> ScalarModel:
    """A block-like model (a region centre and radius) whose field is an opaque ball, with a grid that
    prunes and drops transparent samples, in eval mode."""
    base = small_scalar_model(num_train_data=1, num_samples_per_ray=48, occupancy_warmup_steps=0)
    model = ScalarModel(config=base.config, scene_box=base.scene_box, num_train_data=1, region_centre=(0.2, -0.1, 0.0), region_radius=0.8)
    density_at_unit = model.field.density_at_unit

    def ball(unit_positions: torch.Tensor, encoding=None):  # type: ignore[no-untyped-def]
        _, geo_features = density_at_unit(unit_positions)
        inside_ball = (unit_positions - 0.5) * 4.0  # inverse contraction inside the unit ball
        distance = torch.linalg.vector_norm(inside_ball - torch.tensor([0.5, 0.0, 0.0]), dim=-1)
        return torch.where(distance < 0.3, 200.0, torch.where(distance < 0.45, 2.0, 0.0)), geo_features  # a haze around it

    model.field.density_at_unit = ball
    for step in range(0, 16 * 4, 16):
        model.update_occupancy(step)
    assert model.samples_grid().pruning and model.visibility().skips_transparent()
    model.eval()
    return model


def camera_rays(num_rays: int):  # type: ignore[no-untyped-def]
    generator = torch.Generator().manual_seed(0)
    directions = torch.nn.functional.normalize(torch.randn(num_rays, 3, generator=generator), dim=-1)
    return ray_bundle(torch.zeros(num_rays, 3), directions)


def test_threads_split_the_rays_without_changing_a_value() -> None:
    """More rays than one thread's share (the kernels split rays between threads, whole rays each):
    the same kept samples, depths and renders with two threads as with one."""
    samples = kept_samples(num_rays=12000, num_samples=16, seed=3)
    num_rays, _ = samples["deltas"].shape
    ops = _cpp.march_ops()
    assert ops is not None
    rays_of = torch.div(samples["sample_ids"], 16, rounding_mode="floor")
    order = torch.argsort(rays_of * 16 + samples["sample_ids"] % 16)  # ray-major, as one round gives them
    ids, rays_sorted = samples["sample_ids"][order], rays_of[order]
    density = samples["density"][order]
    results = []
    threads = torch.get_num_threads()
    try:
        for count in (1, 2):
            torch.set_num_threads(count)
            depth = torch.rand(num_rays, generator=torch.Generator().manual_seed(1))
            keep = ops.round_keep(ids, rays_sorted, density, samples["deltas"].reshape(-1), depth, 0.01, 0.001)
            results.append((keep, depth, render(samples)))
    finally:
        torch.set_num_threads(threads)
    (keep_one, depth_one, render_one), (keep_two, depth_two, render_two) = results
    assert 0 < int(keep_one.sum()) < keep_one.numel()
    assert torch.equal(keep_one, keep_two) and torch.equal(depth_one, depth_two)
    for field in ("rgb", "depth", "accumulation", "sample_weights"):
        assert torch.equal(getattr(render_one, field), getattr(render_two, field)), field
