"""The CPU speed levers of the field and the model: a bfloat16 decoder, opacity-based sample skipping and
front-to-back rendering that stops at surfaces.

Both must leave what is rendered and learned as it was, up to the precision they trade away.
"""

from __future__ import annotations

import copy

import pytest
import torch
from conftest import SMALL_FIELD, ray_bundle, small_scalar_model
from nerfstudio.cameras.rays import RayBundle

from scalar_nerfstudio.fields import scalar_field
from scalar_nerfstudio.fields.scalar_field import ScalarField, ScalarFieldConfig
from scalar_nerfstudio.model_components import visibility as visibility_module
from scalar_nerfstudio.model_components.sampling import OccupancyGrid
from scalar_nerfstudio.model_components.visibility import VisibilitySampler
from scalar_nerfstudio.models.scalar_model import ScalarModel


def _field(precision: str) -> ScalarField:
    torch.manual_seed(0)
    return ScalarFieldConfig(**SMALL_FIELD, decoder_precision=precision).setup(num_images=3)


def _outputs_and_decoder_grads(field: ScalarField, points: torch.Tensor, directions: torch.Tensor):
    field.zero_grad()
    density, geo = field.density_at_unit(points)
    rgb = field.colour(geo, directions, torch.arange(points.shape[0]), camera_indices=torch.zeros(points.shape[0], dtype=torch.long))
    (density.log1p().sum() + rgb.square().sum()).backward()
    grads = torch.cat([p.grad.reshape(-1) for p in field.decoder.parameters()])
    return density, rgb, grads


def test_bfloat16_decoder_matches_float32_and_keeps_float32_outputs_and_grads() -> None:
    fp32, bf16 = _field("float32"), _field("bfloat16")
    bf16.load_state_dict(fp32.state_dict())
    assert bf16.cpu_bfloat16 and not fp32.cpu_bfloat16
    generator = torch.Generator().manual_seed(1)
    points = torch.rand(4096, 3, generator=generator)
    directions = torch.nn.functional.normalize(torch.randn(4096, 3, generator=generator), dim=-1)
    density32, rgb32, grads32 = _outputs_and_decoder_grads(fp32, points, directions)
    density16, rgb16, grads16 = _outputs_and_decoder_grads(bf16, points, directions)
    assert density16.dtype == rgb16.dtype == torch.float32
    assert all(p.dtype == torch.float32 and p.grad.dtype == torch.float32 for p in bf16.decoder.parameters())
    assert torch.allclose(density16, density32, rtol=0.05, atol=1e-4)
    assert (rgb16 - rgb32).abs().max() < 0.01
    assert torch.nn.functional.cosine_similarity(grads16, grads32, dim=0) > 0.99
    # the encoder (C++ or torch kernel) gets float32 gradients either way
    assert all(p.grad is None or p.grad.dtype == torch.float32 for p in bf16.encoder.parameters())


@pytest.mark.skipif(not scalar_field.fused_linear_available(), reason="this torch has no oneDNN fused linear kernel")
@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_evaluation_without_autograd_runs_the_fused_decoder_and_gives_the_training_path_outputs(
    precision: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    if precision == "bfloat16" and not scalar_field.cpu_bfloat16_is_fast():
        pytest.skip("oneDNN's bfloat16 inner product needs AVX512-BF16 or AMX (this CPU has neither)")
    field = _field(precision)
    with torch.no_grad():  # a trained-looking decoder: weights well away from their initial scale
        for parameter in field.decoder.parameters():
            parameter.mul_(3.0)
    generator = torch.Generator().manual_seed(3)
    points = torch.rand(5000, 3, generator=generator)
    directions = torch.nn.functional.normalize(torch.randn(5000, 3, generator=generator), dim=-1)
    camera_indices = torch.zeros(5000, dtype=torch.long)
    fused_calls = []  # oneDNN's fused layers, or the AVX2 tile kernels where the float32 decoder trains through them
    run_fused, run_tiles = scalar_field.run_mlp_fused, scalar_field.mlp_float32_inference
    monkeypatch.setattr(scalar_field, "run_mlp_fused", lambda *args: fused_calls.append(1) or run_fused(*args))
    monkeypatch.setattr(scalar_field, "mlp_float32_inference", lambda *args: fused_calls.append(1) or run_tiles(*args))

    density_grad, geo_grad = field.density_at_unit(points)  # autograd on: nn.Linear as in training
    rgb_grad = field.colour(geo_grad, directions, torch.arange(5000), camera_indices=camera_indices)
    assert not fused_calls and density_grad.requires_grad
    with torch.no_grad():
        density, geo = field.density_at_unit(points)
        rgb = field.colour(geo, directions, torch.arange(5000), camera_indices=camera_indices)
    assert len(fused_calls) == 2  # density head and colour head
    assert density.dtype == rgb.dtype == torch.float32
    # the same products in the same precision: only the order of the bias addition may differ
    tolerance = 1e-5 if precision == "float32" else 1e-2
    assert torch.allclose(density, density_grad.detach(), rtol=tolerance, atol=1e-6)
    assert (rgb - rgb_grad.detach()).abs().max() < tolerance


def test_colour_of_samples_takes_its_direction_and_appearance_from_the_sample_s_ray() -> None:
    field = _field("float32").train()
    generator = torch.Generator().manual_seed(4)
    with torch.no_grad():
        field.appearance.weight.normal_(generator=generator)  # images that look different
    ray_directions = torch.nn.functional.normalize(torch.randn(6, 3, generator=generator), dim=-1)
    camera_indices = torch.tensor([0, 1, 2, 0, 1, 2])
    ray_ids = torch.tensor([5, 0, 0, 3, 1, 1, 1, 4, 2])  # samples of 6 rays, in any order
    _, geo = field.density_at_unit(torch.rand(9, 3, generator=generator))
    per_ray = field.colour(geo, ray_directions, ray_ids, camera_indices=camera_indices)
    per_sample = field.colour(geo, ray_directions[ray_ids], torch.arange(9), camera_indices=camera_indices[ray_ids])
    assert torch.allclose(per_ray, per_sample)
    other_image = field.colour(geo, ray_directions, ray_ids, camera_indices=(camera_indices + 1) % 3)
    assert (other_image - per_ray).abs().max() > 1e-4  # the appearance of each ray's image is used


def test_the_fused_decoder_takes_only_linear_and_relu_layers() -> None:
    mlp = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Sigmoid(), torch.nn.Linear(8, 2))
    with pytest.raises(TypeError, match="Sigmoid"):
        scalar_field.run_mlp_fused(mlp, torch.zeros(3, 4), torch.float32)


@pytest.mark.parametrize("fast", [True, False])
def test_auto_precision_uses_bfloat16_only_where_the_cpu_has_it(monkeypatch: pytest.MonkeyPatch, fast: bool) -> None:
    monkeypatch.setattr(scalar_field, "cpu_bfloat16_is_fast", lambda: fast)
    assert _field("auto").cpu_bfloat16 is fast
    assert _field("float32").cpu_bfloat16 is False


def _hazy_model(alpha_threshold: float) -> ScalarModel:
    """A fresh model: a thin uniform haze (density ~exp(-4) per unit) with nothing occluded."""
    return small_scalar_model(num_samples_per_ray=32, alpha_threshold=alpha_threshold).eval()


def _rays(num_rays: int) -> RayBundle:
    directions = torch.nn.functional.normalize(torch.randn(num_rays, 3, generator=torch.Generator().manual_seed(2)), dim=-1)
    return ray_bundle(torch.zeros(num_rays, 3), directions)


def test_alpha_threshold_skips_only_transparent_samples_and_only_after_the_grid_warm_up() -> None:
    reference, skipping = _hazy_model(0.0), _hazy_model(0.01)
    skipping.load_state_dict(reference.state_dict())
    rays = _rays(256)
    with torch.no_grad():
        before_warm_up = skipping(rays)
        exact = reference(rays)
        assert torch.equal(before_warm_up["samples_per_ray"], exact["samples_per_ray"])  # nothing skipped while warming up
        for model in (skipping, reference):  # the grid has warmed up and marked one far corner cell empty
            model.occupancy.occupied[0] = False
        skipped = skipping(rays)
        exact = reference(rays)
    # the haze's short near intervals are below 1 % opacity; the long far ones are not
    assert 0 < skipped["samples_per_ray"].mean() < 0.8 * exact["samples_per_ray"].mean()
    # what is skipped is nearly transparent: a little opacity is lost and the image barely changes
    # (the near half of each ray holds about 1 - exp(-0.018) ~ 2 % opacity of haze)
    dropped = exact["accumulation"] - skipped["accumulation"]
    assert (dropped >= -1e-6).all() and dropped.max() < 0.03
    assert (skipped["rgb"] - exact["rgb"]).abs().max() < 0.03


def test_sample_skipping_starts_with_the_grid_pruning_and_is_restored_from_a_checkpoint() -> None:
    model = _hazy_model(0.01)

    def ball(unit: torch.Tensor) -> torch.Tensor:
        return torch.where(torch.linalg.vector_norm(unit - 0.5, dim=-1) < 0.2, 100.0, 0.0)

    model.occupancy.update(0, ball)
    assert not model.occupancy.pruning  # warm-up: nothing is marked empty, nothing is skipped
    model.occupancy.update(model.occupancy.warmup_steps, ball)
    assert model.occupancy.pruning
    restored = _hazy_model(0.01)
    restored.load_state_dict(copy.deepcopy(model.state_dict()))
    assert restored.occupancy.pruning and torch.equal(restored.occupancy.occupied, model.occupancy.occupied)


@pytest.mark.parametrize("opacity", [0.3, 3.0])
def test_rendering_front_to_back_in_rounds_gives_the_one_pass_image_with_fewer_evaluations(opacity: float, monkeypatch: pytest.MonkeyPatch) -> None:
    """Rays that turned opaque stop being evaluated, and the image is the one-pass image."""
    torch.manual_seed(0)
    model = small_scalar_model()
    with torch.no_grad():
        for parameter in model.field.parameters():
            parameter.copy_(torch.randn(parameter.shape) * (opacity if parameter.ndim == 2 and parameter.shape[1] > 8 else 0.3))
    model.eval()
    origins = torch.rand(300, 3) * 0.4 - 0.2
    rays = ray_bundle(origins, torch.nn.functional.normalize(torch.randn(300, 3), dim=-1))
    evaluated = []
    density_at_unit = model.field.density_at_unit

    def counting(unit_positions, encoding=None):
        evaluated[-1] += unit_positions.shape[0]
        return density_at_unit(unit_positions, encoding=encoding)

    monkeypatch.setattr(model.field, "density_at_unit", counting)
    outputs = {}
    groups = (64, 4, 1)  # 64: every candidate of a ray in one round (the samples per ray), as one pass
    for group in groups:
        monkeypatch.setattr(visibility_module, "RENDER_GROUP", group)
        evaluated.append(0)
        with torch.no_grad():
            outputs[group] = model.render_rays(rays, normals=False)
    for group in groups[1:]:
        for key in ("rgb", "depth", "accumulation", "samples_per_ray"):
            assert torch.allclose(outputs[group][key], outputs[64][key], atol=1e-6), (group, key)
    assert evaluated[2] <= evaluated[1] <= evaluated[0], evaluated
    if opacity > 1.0:  # opaque surfaces: the samples behind them are skipped
        assert evaluated[1] < 0.8 * evaluated[0], evaluated


def test_training_rays_are_coarse_only_during_the_occupancy_warm_up() -> None:
    """While the grid warms up (nothing skipped, every interval with gradients) a training ray has
    ``warmup_samples_per_ray`` intervals; after the warm-up, and outside training, the full count."""
    model = small_scalar_model(num_samples_per_ray=32, warmup_samples_per_ray=8, occupancy_warmup_steps=4, transmittance_threshold=0.0)
    rays = _rays(64)
    model.train()
    model.update_occupancy(0)
    assert model.occupancy.warming_up
    assert int(model(rays)["samples_per_ray"].max()) == 8
    model.eval()
    with torch.no_grad():
        assert int(model(rays)["samples_per_ray"].max()) == 32  # evaluation always samples fully
    model.train()
    model.update_occupancy(5)  # past the warm-up, although no cell was marked empty
    assert not model.occupancy.warming_up and not model.occupancy.pruning
    assert int(model(rays)["samples_per_ray"].max()) == 32


def test_a_seeded_grid_has_no_coarse_warm_up() -> None:
    model = small_scalar_model(num_samples_per_ray=32, warmup_samples_per_ray=8, transmittance_threshold=0.0).train()
    model.occupancy.seed(torch.ones(model.occupancy.resolution**3))
    model.update_occupancy(0)
    assert not model.occupancy.warming_up
    assert int(model(_rays(16))["samples_per_ray"].max()) == 32


def test_a_training_step_encodes_each_sample_once_with_the_gradients_of_encoding_twice(monkeypatch: pytest.MonkeyPatch) -> None:
    """The pass with gradients reuses the no-grad pass's hash-grid encoding of the kept samples: the
    encoder runs over each candidate once, and the table gets the gradient it got when the kept
    samples were encoded again."""
    # without the grid's own opacity test, the no-grad pass is what drops samples here
    model = small_scalar_model(num_samples_per_ray=32, occupancy_warmup_steps=0, background_color="grey", grid_alpha_skip=False)
    model.train()
    model.update_occupancy(0)
    generator = torch.Generator().manual_seed(0)
    rays = ray_bundle(torch.rand(256, 3, generator=generator) * 0.4 - 0.2,
                      torch.nn.functional.normalize(torch.randn(256, 3, generator=generator), dim=-1))
    encoder = model.field.encoder
    encoded = []
    original_forward = encoder.forward

    def counting_forward(positions: torch.Tensor) -> torch.Tensor:
        encoded.append(positions.reshape(-1, 3).shape[0])
        return original_forward(positions)

    def gradients() -> tuple:
        model.zero_grad()
        torch.manual_seed(1)  # the same jittered samples in both passes
        outputs = model(rays)
        outputs["rgb"].square().sum().backward()
        return outputs, model.field.encoder.table.grad.clone(), model.field.decoder.density_mlp[0].weight.grad.clone()

    monkeypatch.setattr(visibility_module, "DENSITY_CHUNK", 500)  # the no-grad pass in several chunks
    monkeypatch.setattr(encoder, "forward", counting_forward)
    outputs, table_grad, decoder_grad = gradients()
    kept = int(outputs["samples_per_ray"].sum())
    assert len(encoded) > 2 and 0 < kept < sum(encoded)  # the no-grad pass over the candidates, nothing after it
    assert encoded[:-1] == [500] * (len(encoded) - 1)
    encoded.clear()
    monkeypatch.setattr(encoder, "with_table_gradient", lambda positions, encoding: counting_forward(positions))
    again, table_grad_again, decoder_grad_again = gradients()  # the kept samples encoded a second time
    assert encoded[-1] == kept and int(again["samples_per_ray"].sum()) == kept  # the kept samples encoded again
    assert table_grad.abs().sum() > 0
    torch.testing.assert_close(table_grad, table_grad_again, atol=1e-7, rtol=0)
    torch.testing.assert_close(decoder_grad, decoder_grad_again, atol=1e-7, rtol=0)


class _WallField:
    """A field stub: an opaque wall at unit-cube x >= 0.6, empty before it; counts its evaluations."""

    def __init__(self) -> None:
        self.evaluated = 0

    def encoder(self, unit_positions: torch.Tensor) -> torch.Tensor:
        return unit_positions * 2.0

    def density_at_unit(self, unit_positions: torch.Tensor, encoding=None):
        self.evaluated += unit_positions.shape[0]
        density = torch.where(unit_positions[:, 0] >= 0.6, 1e4, 0.0)
        return density, unit_positions[:, :2]


def test_the_visibility_sampler_keeps_the_samples_up_to_the_first_opaque_one(monkeypatch: pytest.MonkeyPatch) -> None:
    num_rays, num_samples = 3, 10
    xs = torch.linspace(0.05, 0.95, num_samples)
    unit_positions = torch.stack([xs, torch.full_like(xs, 0.5), torch.full_like(xs, 0.5)], dim=-1).repeat(num_rays, 1)  # [R*S, 3]
    deltas = torch.full((num_rays, num_samples), 0.1)
    grid = OccupancyGrid(resolution=8)  # fresh: every cell occupied, not pruning
    field = _WallField()
    sampler = VisibilitySampler(grid, field, transmittance_threshold=1e-3, alpha_threshold=0.01, grid_alpha_skip=True)
    assert not sampler.skips_transparent()
    first_wall = int((xs >= 0.6).nonzero()[0])
    expected = [r * num_samples + s for r in range(num_rays) for s in range(first_wall + 1)]  # empty space, then the wall's first sample
    ids, encoding = sampler.visible(unit_positions, deltas)
    assert ids.tolist() == expected and torch.equal(encoding, unit_positions[ids] * 2.0)
    field.evaluated = 0
    ids_rendered, density, geo = sampler.visible_with_features(unit_positions, deltas)
    assert sorted(ids_rendered.tolist()) == expected and density.shape == (len(expected),) and geo.shape == (len(expected), 2)
    assert field.evaluated <= len(expected) + num_rays * (visibility_module.RENDER_GROUP - 1)  # at most a round's rest behind the wall
    monkeypatch.setattr(visibility_module, "RENDER_GROUP", 1)  # one candidate per round: nothing behind the wall is evaluated
    field.evaluated = 0
    assert sorted(sampler.visible_with_features(unit_positions, deltas)[0].tolist()) == expected and field.evaluated == len(expected)
    every = VisibilitySampler(grid, field, transmittance_threshold=0.0, alpha_threshold=0.01, grid_alpha_skip=True)
    ids, encoding = every.visible(unit_positions, deltas)
    assert ids.numel() == num_rays * num_samples and encoding is None  # no occlusion test: every occupied sample
