"""Tests for scalar_nerfstudio.fusion (final image blending, Sec. 3.4)."""

from __future__ import annotations

import contextlib
import math

import pytest
import torch

from scalar_nerfstudio.fusion import (
    FUSION_MODES,
    FusionModeError,
    ParsedFusionMode,
    fuse_global_guided,
    fuse_outputs,
    fuse_weighted,
    guard_transparent,
    idw_weights,
    nearest_block,
    nearest_blocks,
    nearest_idw_weights,
    parse_fusion_mode,
    select_winner,
    transparent_pixels,
)

NAN, INF = float("nan"), float("inf")


def _brute_force_global(block_rgb: torch.Tensor, global_rgb: torch.Tensor) -> torch.Tensor:
    winners = []
    for n in range(block_rgb.shape[1]):
        best, best_d = -1, INF
        for k in range(block_rgb.shape[0]):
            d = sum((float(block_rgb[k, n, c]) - float(global_rgb[n, c])) ** 2 for c in range(3))
            if math.isfinite(d) and d < best_d:
                best, best_d = k, d
        winners.append(best)
    return torch.tensor(winners)


# --------------------------------------------------------------------------- global guidance


def test_global_matches_brute_force() -> None:
    gen = torch.Generator().manual_seed(0)
    block_rgb = torch.rand(4, 257, 3, generator=gen)
    global_rgb = torch.rand(257, 3, generator=gen)
    fused, winner = fuse_global_guided(block_rgb, global_rgb)
    assert winner.dtype == torch.int64 and winner.shape == (257,)
    assert torch.equal(winner, _brute_force_global(block_rgb, global_rgb))
    assert torch.equal(fused, block_rgb[winner, torch.arange(257)])


def test_global_hand_made_and_ties() -> None:
    global_rgb = torch.tensor([[0.5, 0.5, 0.5], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    block_rgb = torch.tensor(
        [
            [[0.4, 0.5, 0.5], [0.2, 0.0, 0.0], [0.0, 0.0, 0.0]],
            [[0.5, 0.5, 0.5], [0.2, 0.0, 0.0], [0.9, 1.0, 1.0]],
            [[0.6, 0.5, 0.5], [0.0, 0.2, 0.0], [0.5, 0.5, 0.5]],
        ]
    )
    fused, winner = fuse_global_guided(block_rgb, global_rgb)
    assert winner.tolist() == [1, 0, 1]  # pixel 1: three-way tie -> lowest index
    assert torch.equal(fused, torch.stack([block_rgb[1, 0], block_rgb[0, 1], block_rgb[1, 2]]))


def test_global_ignores_nan_inf_and_invalid() -> None:
    global_rgb = torch.full((4, 3), 0.5)
    block_rgb = torch.tensor(
        [
            [[NAN, 0.5, 0.5], [0.5, 0.5, 0.5], [INF, 0.5, 0.5], [0.5, 0.5, 0.5]],
            [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [NAN, NAN, NAN], [0.4, 0.4, 0.4]],
        ]
    )
    valid = torch.tensor([[True, True, True, False], [True, True, True, True]])
    fused, winner = fuse_global_guided(block_rgb, global_rgb, valid)
    assert winner.tolist() == [1, 0, -1, 1]
    assert torch.isfinite(fused).all()
    assert torch.equal(fused[2], global_rgb[2])  # no usable block -> global colour
    assert torch.equal(fused[3], block_rgb[1, 3])  # invalid block 0 never chosen, though closer


def test_global_all_invalid_falls_back() -> None:
    block_rgb = torch.rand(3, 5, 3)
    global_rgb = torch.rand(5, 3)
    fused, winner = fuse_global_guided(block_rgb, global_rgb, torch.zeros(3, 5, dtype=torch.bool))
    assert (winner == -1).all() and torch.equal(fused, global_rgb)


def test_global_nonfinite_global_colour_picks_lowest_usable_block() -> None:
    block_rgb = torch.tensor([[[NAN, 0.0, 0.0]], [[0.2, 0.2, 0.2]], [[0.3, 0.3, 0.3]]])
    fused, winner = fuse_global_guided(block_rgb, torch.tensor([[NAN, 0.0, 0.0]]))
    assert winner.tolist() == [1] and torch.equal(fused[0], block_rgb[1, 0])


def test_global_shape_errors() -> None:
    with pytest.raises(ValueError, match=r"global_rgb must have shape \[5, 3\]"):
        fuse_global_guided(torch.rand(2, 5, 3), torch.rand(4, 3))
    with pytest.raises(ValueError, match=r"\[K, N, C\]"):
        fuse_global_guided(torch.rand(5, 3), torch.rand(5, 3))
    with pytest.raises(ValueError, match="valid must have shape"):
        fuse_global_guided(torch.rand(2, 5, 3), torch.rand(5, 3), torch.ones(5, dtype=torch.bool))


# --------------------------------------------------------------------------- select / weighted


def test_select_winner_and_fallback() -> None:
    values = torch.arange(2 * 3 * 1, dtype=torch.float32).reshape(2, 3, 1)
    out = select_winner(values, torch.tensor([1, 0, -1]), fallback=torch.full((3, 1), -7.0))
    assert out[:, 0].tolist() == [3.0, 1.0, -7.0]
    with pytest.raises(ValueError, match="no fallback"):
        select_winner(values, torch.tensor([1, 0, -1]))
    with pytest.raises(ValueError, match=r"in \[-1, 2\)"):
        select_winner(values, torch.tensor([2, 0, 0]))


def test_fuse_weighted_ignores_nonfinite() -> None:
    values = torch.tensor([[[1.0], [1.0], [NAN]], [[3.0], [INF], [NAN]]])
    out = fuse_weighted(values, torch.tensor([0.25, 0.75]))
    assert out[0, 0] == pytest.approx(2.5)
    assert out[1, 0] == pytest.approx(1.0)  # inf dropped, weight renormalised
    assert torch.isnan(out[2, 0])
    out = fuse_weighted(values, torch.tensor([0.25, 0.75]), fallback=torch.full((3, 1), 9.0))
    assert out[2, 0] == 9.0
    per_pixel = fuse_weighted(values[:, :1], torch.tensor([[1.0], [0.0]]))
    assert per_pixel[0, 0] == 1.0
    with pytest.raises(ValueError, match="non-negative"):
        fuse_weighted(values, torch.tensor([-1.0, 2.0]))


# --------------------------------------------------------------------------- idw / nearest


CENTRES = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]])


def test_idw_weights_sum_to_one_and_inverse_distance() -> None:
    origin = torch.tensor([2.0, 0.0, 0.0])
    w = idw_weights(origin, CENTRES)
    assert w.shape == (3,) and float(w.sum()) == pytest.approx(1.0)
    d = torch.linalg.vector_norm(CENTRES - origin, dim=-1)
    assert torch.allclose(w, (1 / d) / (1 / d).sum())
    assert w.argmax().item() == 0


def test_idw_camera_at_centre_is_finite() -> None:
    w = idw_weights(CENTRES[1], CENTRES)
    assert w.tolist() == [0.0, 1.0, 0.0]
    doubled = torch.cat([CENTRES, CENTRES[1:2]])
    w = idw_weights(CENTRES[1], doubled, gamma=3.0)
    assert w.tolist() == [0.0, 0.5, 0.0, 0.5]
    tiny = idw_weights(CENTRES[1] + 1e-30, CENTRES, gamma=50.0)
    assert torch.isfinite(tiny).all() and float(tiny.sum()) == pytest.approx(1.0)


def test_idw_gamma_effect_and_validity() -> None:
    origin = torch.tensor([2.0, 1.0, 0.0])
    uniform = idw_weights(origin, CENTRES, gamma=0.0)
    assert torch.allclose(uniform, torch.full((3,), 1 / 3))
    w1, w4 = idw_weights(origin, CENTRES, gamma=1.0), idw_weights(origin, CENTRES, gamma=4.0)
    assert w4[0] > w1[0] > uniform[0]
    huge = idw_weights(origin * 1e6, CENTRES * 1e6, gamma=200.0)  # d^-gamma underflows in linear space
    assert torch.isfinite(huge).all() and float(huge.sum()) == pytest.approx(1.0)
    masked = idw_weights(origin, CENTRES, valid=torch.tensor([False, True, True]))
    assert masked[0] == 0 and float(masked.sum()) == pytest.approx(1.0)
    at_invalid = idw_weights(CENTRES[0], CENTRES, valid=torch.tensor([False, True, True]))
    assert at_invalid[0] == 0 and float(at_invalid.sum()) == pytest.approx(1.0)
    none_valid = idw_weights(origin, CENTRES, valid=torch.zeros(3, dtype=torch.bool))
    assert torch.equal(none_valid, torch.zeros(3))
    with pytest.raises(ValueError, match="gamma"):
        idw_weights(origin, CENTRES, gamma=-1.0)


def test_idw_per_ray_origins() -> None:
    origins = torch.tensor([[0.0, 0.0, 0.0], [9.0, 0.0, 0.0], [1.0, 8.0, 0.0], [6.0, 6.0, 0.0]])
    w = idw_weights(origins, CENTRES)
    assert w.shape == (3, 4)
    assert torch.allclose(w.sum(dim=0), torch.ones(4))
    assert w.argmax(dim=0).tolist() == [0, 1, 2, 1]  # last: equidistant from 1 and 2 -> argmax first
    for n in range(4):
        assert torch.allclose(w[:, n], idw_weights(origins[n], CENTRES))


def test_nearest_block() -> None:
    assert nearest_block(torch.tensor([9.0, 1.0, 0.0]), CENTRES).item() == 1
    assert nearest_block(torch.tensor([6.0, 6.0, 0.0]), CENTRES).item() == 1  # tie 1 vs 2 -> lowest
    assert nearest_block(torch.tensor([5.0, 5.0, 0.0]), CENTRES).item() == 0  # three-way tie
    origins = torch.tensor([[0.1, 0.0, 0.0], [0.0, 9.0, 0.0]])
    assert nearest_block(origins, CENTRES).tolist() == [0, 2]
    assert nearest_block(origins, CENTRES, valid=torch.tensor([False, True, True])).tolist() == [1, 2]
    assert nearest_block(origins[0], CENTRES, valid=torch.zeros(3, dtype=torch.bool)).item() == -1
    with pytest.raises(ValueError, match="camera_origin must have shape"):
        nearest_block(torch.zeros(2), CENTRES)
    with pytest.raises(ValueError, match="finite"):
        nearest_block(torch.tensor([NAN, 0.0, 0.0]), CENTRES)


def test_nearest_idw_weights_blend_the_nearest_blocks_by_inverse_distance() -> None:
    origin = torch.tensor([2.0, 1.0, 0.0])  # nearest block 0, then 1, then 2
    d = torch.linalg.vector_norm(CENTRES - origin, dim=-1)
    w = nearest_idw_weights(origin, CENTRES, num_nearest=2, gamma=2.0)
    expected = torch.tensor([d[0] ** -2, d[1] ** -2, 0.0])
    assert torch.allclose(w, expected / expected.sum())
    # one block: the nearest as one-hot weights; every block: plain idw
    assert nearest_idw_weights(origin, CENTRES, num_nearest=1).tolist() == [1.0, 0.0, 0.0]
    assert torch.allclose(nearest_idw_weights(origin, CENTRES, num_nearest=3, gamma=2.0), idw_weights(origin, CENTRES, gamma=2.0))
    assert torch.allclose(nearest_idw_weights(origin, CENTRES, num_nearest=99, gamma=1.0), idw_weights(origin, CENTRES, gamma=1.0))
    # gamma 0: equal shares between the chosen blocks
    assert torch.allclose(nearest_idw_weights(origin, CENTRES, num_nearest=2, gamma=0.0), torch.tensor([0.5, 0.5, 0.0]))


def test_nearest_blocks_marks_the_nearest_valid_blocks() -> None:
    origins = torch.tensor([[2.0, 1.0, 0.0], [6.0, 6.0, 0.0]])
    # a tie 1 vs 2 at the second
    assert nearest_blocks(origins, CENTRES, num_nearest=2).t().tolist() == [[True, True, False], [False, True, True]]
    assert nearest_blocks(origins[0], CENTRES, num_nearest=1).tolist() == [True, False, False]
    assert nearest_blocks(origins[0], CENTRES, num_nearest=2, valid=torch.tensor([False, True, True])).tolist() == [False, True, True]
    assert nearest_blocks(origins, CENTRES, num_nearest=None).all() and nearest_blocks(origins, CENTRES, num_nearest=9).all()
    with pytest.raises(ValueError, match="num_nearest"):
        nearest_blocks(origins, CENTRES, num_nearest=0)


def test_nearest_idw_weights_per_ray_validity_ties_and_extremes() -> None:
    origins = torch.tensor([[0.0, 0.0, 0.0], [9.0, 1.0, 0.0], [6.0, 6.0, 0.0]])
    w = nearest_idw_weights(origins, CENTRES, num_nearest=2)
    assert w.shape == (3, 3) and torch.allclose(w.sum(dim=0), torch.ones(3))
    assert w[0, 0] == 1.0  # a camera at a block's centre takes all the weight
    assert w[2, 1] == 0.0 and w[:, 1].tolist()[2] == 0.0  # second ray: blocks 1 and 0 nearest, block 2 left out
    assert (w[:, 2] > 0).sum() == 2  # tie between blocks 1 and 2 at the third ray: both chosen with block 0 left out
    assert w[0, 2] == 0.0
    # an invalid block is neither chosen nor weighted: the next nearest takes its place
    valid = torch.tensor([[False, True, True], [True, True, True], [True, True, True]])
    masked = nearest_idw_weights(origins, CENTRES, num_nearest=2, valid=valid)
    assert masked[0, 0] == 0.0 and (masked[1:, 0] > 0).all() and float(masked[:, 0].sum()) == pytest.approx(1.0)
    none_valid = nearest_idw_weights(origins[0], CENTRES, num_nearest=2, valid=torch.zeros(3, dtype=torch.bool))
    assert torch.equal(none_valid, torch.zeros(3))
    far = nearest_idw_weights(torch.tensor([1e30, 0.0, 0.0]), CENTRES, num_nearest=2, gamma=50.0)  # d^-gamma underflows
    assert torch.isfinite(far).all() and float(far.sum()) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="num_nearest"):
        nearest_idw_weights(origins, CENTRES, num_nearest=0)
    with pytest.raises(ValueError, match="gamma"):
        nearest_idw_weights(origins, CENTRES, num_nearest=2, gamma=float("inf"))
    with pytest.raises(ValueError, match="finite"):
        nearest_idw_weights(torch.tensor([NAN, 0.0, 0.0]), CENTRES, num_nearest=2)


def test_fuse_outputs_nearest_idw_blends_two_blocks_and_falls_back() -> None:
    gen = torch.Generator().manual_seed(5)
    blocks = [_outputs(gen, (4, 5)) for _ in range(3)]
    glob = _outputs(gen, (4, 5))
    origin = torch.tensor([2.0, 1.0, 0.0])
    out = fuse_outputs("nearest-idw", blocks, glob, camera_origin=origin, block_centres=CENTRES, gamma=2.0, blocks_per_ray=2)
    w = nearest_idw_weights(origin, CENTRES, num_nearest=2, gamma=2.0)
    for key in ("rgb", "depth", "accumulation"):
        assert torch.allclose(out[key], w[0] * blocks[0][key] + w[1] * blocks[1][key], atol=1e-6)
    assert (out["block_winner"] == 0).all()
    # the nearest block missing at a pixel (not rendered there): the two nearest that are there
    blocks[0]["rgb"][1, 2] = NAN
    out = fuse_outputs("nearest-idw", blocks, glob, camera_origin=origin, block_centres=CENTRES, gamma=2.0, blocks_per_ray=2)
    w12 = nearest_idw_weights(origin, CENTRES[1:], num_nearest=2, gamma=2.0)
    assert torch.allclose(out["rgb"][1, 2], w12[0] * blocks[1]["rgb"][1, 2] + w12[1] * blocks[2]["rgb"][1, 2], atol=1e-6)
    # no block at a pixel: the global model's values
    for b in blocks:
        b["rgb"][3, 4] = NAN
    out = fuse_outputs("nearest-idw", blocks, glob, camera_origin=origin, block_centres=CENTRES, blocks_per_ray=2)
    assert torch.equal(out["rgb"][3, 4], glob["rgb"][3, 4]) and out["block_winner"][3, 4] == -1
    assert parse_fusion_mode(" Nearest-IDW ").kind == "nearest-idw" and "nearest-idw" in FUSION_MODES


def test_nearest_guarded_gives_the_global_model_where_the_block_is_transparent_and_it_is_opaque() -> None:
    # Camera nearest block 0. Pixels: 0 both opaque; 1 the block transparent, the global model opaque;
    # 2 both transparent (the sky); 3 the block opaque, the global model not; 4 the global model not rendered.
    origin = torch.tensor([1.0, 0.0, 0.0])
    block0 = {"rgb": torch.full((5, 3), 0.2), "depth": torch.full((5, 1), 1.0),
              "accumulation": torch.tensor([[0.9], [0.1], [0.1], [0.9], [0.1]])}
    block1 = {"rgb": torch.full((5, 3), 0.8), "depth": torch.full((5, 1), 3.0), "accumulation": torch.full((5, 1), 0.9)}
    glob = {"rgb": torch.full((5, 3), 0.5), "depth": torch.full((5, 1), 2.0),
            "accumulation": torch.tensor([[0.9], [0.9], [0.2], [0.1], [NAN]])}
    out = fuse_outputs("nearest-guarded", [block0, block1], glob, camera_origin=origin, block_centres=CENTRES[:2])
    assert out["rgb"][:, 0].tolist() == pytest.approx([0.2, 0.5, 0.2, 0.2, 0.2])
    assert out["depth"][:, 0].tolist() == pytest.approx([1.0, 2.0, 1.0, 1.0, 1.0])  # depth and accumulation follow the colour
    assert out["accumulation"][1, 0] == pytest.approx(0.9)
    assert out["block_winner"].tolist() == [0, -1, 0, 0, 0]
    unguarded = fuse_outputs("nearest", [block0, block1], glob, camera_origin=origin, block_centres=CENTRES[:2])
    assert (unguarded["block_winner"] == 0).all()  # nearest: no guard
    lenient = fuse_outputs("nearest-guarded", [block0, block1], glob, camera_origin=origin, block_centres=CENTRES[:2],
                           guard_accumulation=0.05)
    assert (lenient["block_winner"] == 0).all()  # 0.1 is opaque enough at this threshold
    with pytest.raises(ValueError, match="global model's outputs"):
        fuse_outputs("nearest-guarded", [block0, block1], None, camera_origin=origin, block_centres=CENTRES[:2])
    with pytest.raises(ValueError, match="accumulation"):
        fuse_outputs("nearest-guarded", [{"rgb": block0["rgb"]}, {"rgb": block1["rgb"]}], {"rgb": glob["rgb"]}, camera_origin=origin,
                     block_centres=CENTRES[:2])


def test_guard_transparent_on_missing_and_extreme_values() -> None:
    weights = torch.tensor([[1.0, 0.0, 1.0, 0.5, 1.0, 1.0], [0.0, 1.0, 0.0, 0.5, 0.0, 0.0]])
    blocks = torch.tensor([[0.0, NAN, INF, 0.2, -INF, 0.3], [0.0, 0.0, 0.0, 0.6, 0.0, 0.0]])
    glob = torch.tensor([1.0, 1.0, 1.0, 1.0, INF, -INF])
    guarded = guard_transparent(weights, blocks, glob)
    # 0: transparent block, opaque global: guarded. 1: the chosen block 1 is transparent: guarded.
    # 2: a non-finite block value is not used, so no block gives an opaque render: guarded (the global
    # model's values, not a block whose accumulation is broken). 3: blended 0.4 < 0.5: guarded.
    # 4: -inf is not usable either (the global accumulation +inf counts as opaque). 5: the global
    # accumulation -inf is below the threshold: kept.
    assert transparent_pixels(weights, blocks).tolist() == [True, True, True, True, True, True]
    assert transparent_pixels(weights, blocks, threshold=0.25).tolist() == [True, True, True, False, True, False]
    assert guarded[:, 5].tolist() == [1.0, 0.0]
    assert (guarded[:, :5] == 0).all()
    assert torch.isfinite(guarded).all()
    nan_global = glob.clone()
    nan_global[0] = NAN  # the global model did not render pixel 0: no guard there
    assert torch.equal(guard_transparent(weights, blocks, nan_global)[:, 0], weights[:, 0])
    assert torch.equal(guard_transparent(weights, blocks[..., None], glob[:, None], threshold=1.0)[:, 5], weights[:, 5])
    for threshold in (0.0, 1.5, NAN):
        with pytest.raises(ValueError, match="threshold"):
            guard_transparent(weights, blocks, glob, threshold=threshold)
    with pytest.raises(ValueError, match="block_accumulation"):
        guard_transparent(weights, blocks[:1], glob)
    with pytest.raises(ValueError, match="global_accumulation"):
        guard_transparent(weights, blocks, glob[:3])


@contextlib.contextmanager
def _float64_ops():
    """Collects the names of the torch ops run inside that produce a float64 tensor."""
    from torch.utils._python_dispatch import TorchDispatchMode

    found: list = []

    class Recorder(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            if any(isinstance(t, torch.Tensor) and t.dtype == torch.float64 for t in (out if isinstance(out, (tuple, list)) else [out])):
                found.append(str(func))
            return out

    with Recorder():
        yield found


@pytest.mark.parametrize("gamma", [0.0, 1.0, 4.0, 200.0])
@pytest.mark.parametrize("scale", [1e-30, 1e-3, 1.0, 1e6, 1e30])
def test_float32_stays_float32_and_matches_float64_on_extreme_inputs(gamma: float, scale: float) -> None:
    """float32 in, float32 out (no silent float64: slow on consumer GPUs, missing on MPS), and the same
    weights and fused values as the float64 computation of the same inputs, for tiny and huge scenes
    (squared distances under- or overflow float32 at these scales) and steep exponents."""
    gen = torch.Generator().manual_seed(5)
    centres = (CENTRES + 0.1 * torch.rand(3, 3, generator=gen)) * scale
    origins = torch.cat([centres[1:2] + scale * 1e-3, torch.rand(63, 3, generator=gen) * 10 * scale])
    values = torch.rand(3, 64, 4, generator=gen) * 1e30
    values[0, 5] = NAN
    valid = torch.rand(3, 64, generator=gen) > 0.2
    with _float64_ops() as promoted:
        weights = idw_weights(origins, centres, gamma=gamma, valid=valid)
        fused = fuse_weighted(values, weights)
        nearest = nearest_block(origins, centres, valid)
    assert not promoted, f"float64 computed from float32 inputs: {sorted(set(promoted))}"
    assert fused.dtype == torch.float32 and nearest.dtype == torch.int64
    expected = idw_weights(origins.double(), centres.double(), gamma=gamma, valid=valid)
    assert weights.dtype == torch.float32 and expected.dtype == torch.float64
    torch.testing.assert_close(weights.double(), expected, rtol=1e-4, atol=1e-6)
    for raw_weights in (weights, torch.rand(3, 64, generator=gen) * 1e-40, torch.rand(3, 64, generator=gen) * 1e37):
        fused = fuse_weighted(values, raw_weights)
        assert fused.dtype == torch.float32
        torch.testing.assert_close(fused.double(), fuse_weighted(values.double(), raw_weights.double()), rtol=1e-5, atol=0.0, equal_nan=True)
    assert torch.equal(nearest, nearest_block(origins.double(), centres.double(), valid))


# --------------------------------------------------------------------------- modes


def test_parse_fusion_mode() -> None:
    assert set(FUSION_MODES) == {"global", "surface", "idw", "nearest", "nearest-guarded", "nearest-idw", "global-only"}
    for mode in FUSION_MODES:
        assert parse_fusion_mode(mode) == ParsedFusionMode(kind=mode)  # type: ignore[arg-type]
    assert parse_fusion_mode(" IDW ").kind == "idw"
    parsed = parse_fusion_mode("block:2")
    assert parsed == ParsedFusionMode(kind="block", block_index=2) and str(parsed) == "block:2"
    with pytest.raises(FusionModeError, match=r"unknown fusion mode 'average'.*'global'.*block:<k>"):
        parse_fusion_mode("average")
    with pytest.raises(FusionModeError, match="non-negative integer"):
        parse_fusion_mode("block:-1")
    with pytest.raises(FusionModeError, match="non-negative integer"):
        parse_fusion_mode("block:x")
    with pytest.raises(FusionModeError, match="out of range, there are 2 blocks"):
        parse_fusion_mode("block:2", num_blocks=2)
    with pytest.raises(ValueError):  # FusionModeError is a ValueError
        fuse_outputs("bogus", [], {"rgb": torch.zeros(2, 3)}, camera_origin=None, block_centres=None)


def _outputs(gen: torch.Generator, shape: tuple[int, ...]) -> dict[str, torch.Tensor]:
    return {
        "rgb": torch.rand(*shape, 3, generator=gen),
        "depth": torch.rand(*shape, 1, generator=gen) * 10,
        "accumulation": torch.rand(*shape, 1, generator=gen),
    }


@pytest.mark.parametrize("shape", [(50,), (6, 7)])
def test_fuse_outputs_global_depth_follows_colour_winner(shape: tuple[int, ...]) -> None:
    gen = torch.Generator().manual_seed(1)
    blocks = [_outputs(gen, shape) for _ in range(3)]
    glob = _outputs(gen, shape)
    blocks[2]["rgb"].view(-1, 3)[0] = NAN  # block 2 broken at pixel 0
    out = fuse_outputs("global", blocks, glob, camera_origin=None, block_centres=None)
    assert set(out) == {"rgb", "depth", "accumulation", "block_winner"}
    assert out["rgb"].shape == (*shape, 3) and out["depth"].shape == (*shape, 1)
    assert out["block_winner"].shape == shape and out["block_winner"].dtype == torch.int64
    winner = out["block_winner"].reshape(-1)
    expected = _brute_force_global(torch.stack([b["rgb"].reshape(-1, 3) for b in blocks]), glob["rgb"].reshape(-1, 3))
    assert torch.equal(winner, expected)
    for key in ("rgb", "depth", "accumulation"):
        stacked = torch.stack([b[key].reshape(winner.numel(), -1) for b in blocks])
        assert torch.equal(out[key].reshape(winner.numel(), -1), stacked[winner, torch.arange(winner.numel())])


def test_fuse_outputs_idw_uses_same_weights() -> None:
    gen = torch.Generator().manual_seed(2)
    blocks = [_outputs(gen, (4, 5)) for _ in range(3)]
    origin = torch.tensor([2.0, 1.0, 0.0])
    out = fuse_outputs("idw", blocks, None, camera_origin=origin, block_centres=CENTRES, gamma=2.0)
    w = idw_weights(origin, CENTRES, gamma=2.0)
    for key in ("rgb", "depth", "accumulation"):
        expected = sum(w[k] * blocks[k][key] for k in range(3))
        assert torch.allclose(out[key], expected, atol=1e-6)
    assert (out["block_winner"] == 0).all()
    per_pixel = torch.zeros(4, 5, 3)
    per_pixel[:, 3:] = torch.tensor([10.0, 0.0, 0.0])
    out = fuse_outputs("idw", blocks, None, camera_origin=per_pixel, block_centres=CENTRES)
    assert (out["block_winner"][:, :3] == 0).all() and (out["block_winner"][:, 3:] == 1).all()


def test_fuse_outputs_idw_nonfinite_block_falls_back() -> None:
    gen = torch.Generator().manual_seed(3)
    blocks = [_outputs(gen, (5,)) for _ in range(2)]
    glob = _outputs(gen, (5,))
    blocks[0]["depth"][1] = INF
    blocks[0]["rgb"][2] = NAN
    blocks[1]["rgb"][2] = NAN
    out = fuse_outputs("idw", blocks, glob, camera_origin=torch.tensor([1.0, 0.0, 0.0]), block_centres=CENTRES[:2])
    assert out["depth"][1] == blocks[1]["depth"][1]  # only the finite block contributes
    assert torch.equal(out["rgb"][2], glob["rgb"][2])  # no finite block -> global fallback


def test_fuse_outputs_nearest_block_and_global_only() -> None:
    gen = torch.Generator().manual_seed(4)
    blocks = [_outputs(gen, (3, 2)) for _ in range(3)]
    glob = _outputs(gen, (3, 2))
    out = fuse_outputs("nearest", blocks, glob, camera_origin=torch.tensor([1.0, 9.0, 0.0]), block_centres=CENTRES)
    assert (out["block_winner"] == 2).all()
    assert all(torch.equal(out[k], blocks[2][k]) for k in ("rgb", "depth", "accumulation"))
    out = fuse_outputs("block:1", blocks, None, camera_origin=None, block_centres=None)
    assert (out["block_winner"] == 1).all() and torch.equal(out["depth"], blocks[1]["depth"])
    out = fuse_outputs("global-only", [], glob, camera_origin=None, block_centres=None)
    assert (out["block_winner"] == -1).all() and out["block_winner"].shape == (3, 2)
    assert all(torch.equal(out[k], glob[k]) for k in ("rgb", "depth", "accumulation"))
    with pytest.raises(FusionModeError, match="out of range"):
        fuse_outputs("block:3", blocks, None, camera_origin=None, block_centres=None)
    with pytest.raises(ValueError, match="needs the global model"):
        fuse_outputs("global", blocks, None, camera_origin=None, block_centres=None)
    with pytest.raises(ValueError, match="needs camera_origin"):
        fuse_outputs("idw", blocks, glob, camera_origin=None, block_centres=CENTRES)
    with pytest.raises(ValueError, match="2 block centres for 3 block outputs"):
        fuse_outputs("nearest", blocks, glob, camera_origin=torch.zeros(3), block_centres=CENTRES[:2])


def test_fuse_outputs_rgb_only() -> None:
    blocks = [{"rgb": torch.rand(4, 3)} for _ in range(2)]
    out = fuse_outputs("global", blocks, {"rgb": torch.rand(4, 3), "depth": torch.rand(4, 1)}, camera_origin=None, block_centres=None)
    assert set(out) == {"rgb", "block_winner"}


def test_the_fusion_package_exports_every_name_and_needs_torch_alone() -> None:
    import ast
    import pathlib

    from scalar_nerfstudio import fusion

    assert all(hasattr(fusion, name) for name in fusion.__all__)
    for path in pathlib.Path(fusion.__file__).parent.glob("*.py"):
        tree = ast.parse(path.read_text())
        modules = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        modules |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        allowed = {"__future__", "collections", "dataclasses", "typing", "math", "torch", "scalar_nerfstudio"}
        assert {m.split(".")[0] for m in modules} <= allowed, (path.name, modules)
        assert all(m.startswith("scalar_nerfstudio.fusion.") for m in modules if m.startswith("scalar_nerfstudio")), path.name
