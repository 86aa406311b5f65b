"""The C++ sampling kernels (``csrc/sampling.cpp``) agree with the torch code they replace on the CPU.

The torch code is the path on CUDA and where the extension does not build; these tests run it
by hiding the kernels (``_cpp.sampling_ops`` returning None) and compare, on ordinary and on
extreme inputs (NaN and infinite origins, directions and distances, huge coordinates, positions
on cell boundaries, cells never evaluated, NaN and zero intervals).
"""

from __future__ import annotations

import math

import pytest
import torch
from conftest import ray_bundle, small_scalar_model, with_torch_code

from scalar_nerfstudio.encodings import _cpp
from scalar_nerfstudio.fields.scalar_field import contract_rays_to_unit_cube
from scalar_nerfstudio.model_components.sampling import OccupancyGrid
from scalar_nerfstudio.models.scalar_model import ScalarModel

pytestmark = pytest.mark.skipif(_cpp.sampling_ops() is None, reason="the C++ kernels do not build here")


def extreme_rays(num_rays: int = 64, num_samples: int = 16) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """([R, 3] origins, [R, 3] directions, [R, S] distances): ordinary rays, then rays with NaN,
    infinite and huge values in each input."""
    generator = torch.Generator().manual_seed(0)
    origins = torch.randn(num_rays, 3, generator=generator) * 2.0
    directions = torch.nn.functional.normalize(torch.randn(num_rays, 3, generator=generator), dim=-1)
    t = torch.sort(torch.rand(num_rays, num_samples, generator=generator) * 50.0, dim=-1).values
    origins[0] = float("nan")
    origins[1, 0] = float("inf")
    origins[2] = torch.tensor([-1e30, 1e30, 0.0])
    directions[3] = float("nan")
    directions[4] = 0.0
    t[5, -1] = float("inf")
    t[6, 3] = float("nan")
    t[7] = 1e25
    t[8] = 0.0
    origins[9] = torch.tensor([1.0, 0.0, 0.0])  # on the unit sphere, where the contraction changes
    directions[9] = torch.tensor([1.0, 0.0, 0.0])
    return origins, directions, t


@pytest.mark.parametrize("centre, radius", [((0.0, 0.0, 0.0), 1.0), ((0.3, -2.0, 1.5), 0.25)])
def test_the_kernel_places_samples_in_the_unit_cube_as_the_torch_code_does(
    monkeypatch: pytest.MonkeyPatch, centre: tuple[float, float, float], radius: float
) -> None:
    origins, directions, t = extreme_rays()
    centre_tensor = torch.tensor(centre)
    kernel = contract_rays_to_unit_cube(origins, directions, t, centre=centre_tensor, radius=radius)
    reference = with_torch_code(monkeypatch, "sampling_ops", lambda: contract_rays_to_unit_cube(origins, directions, t, centre=centre_tensor,
                                                                                radius=radius))
    assert kernel.shape == (t.numel(), 3) and kernel.dtype == torch.float32
    assert torch.isfinite(kernel).all() and (kernel >= 0).all() and (kernel <= 1).all()
    torch.testing.assert_close(kernel, reference, atol=1e-6, rtol=0)


def test_the_kernel_rejects_samples_that_do_not_match_their_rays() -> None:
    origins, directions, t = extreme_rays()
    # the message names the sizes (built without iostreams: csrc/check.h)
    with pytest.raises(RuntimeError, match="t must be \\[R, S\\] with R = 64, got \\[63, 16\\]"):
        contract_rays_to_unit_cube(origins, directions, t[:-1], centre=torch.zeros(3), radius=1.0)


@pytest.mark.parametrize("neighbourhood_alpha_test", [True, False])
def test_the_kernel_picks_the_samples_worth_evaluating_as_the_torch_code_does(
    monkeypatch: pytest.MonkeyPatch, neighbourhood_alpha_test: bool
) -> None:
    g = 16
    generator = torch.Generator().manual_seed(1)
    grid = OccupancyGrid(resolution=g, neighbourhood_alpha_test=neighbourhood_alpha_test)
    densities = torch.rand(g**3, generator=generator) * 20.0 * (torch.rand(g**3, generator=generator) < 0.4)
    grid.seed(densities)
    grid.density_ema[:50] = float("inf")  # cells never evaluated
    positions = torch.rand(4000, 3, generator=generator)
    positions[:200] = torch.randint(0, g + 1, (200, 3), generator=generator).float() / g  # on cell faces, 0 and 1
    positions[200] = float("nan")
    deltas = torch.rand(4000, generator=generator) * 0.05
    deltas[300:310] = 0.0
    deltas[310:320] = float("nan")
    deltas[320:330] = float("inf")
    for alpha_threshold in (0.0, 0.01, 0.5):
        kernel = grid.worth_evaluating(positions, deltas, alpha_threshold)
        reference = with_torch_code(monkeypatch, "sampling_ops", lambda: grid.worth_evaluating(positions, deltas, alpha_threshold))
        assert torch.equal(kernel, reference), alpha_threshold
        assert 0 < int(kernel.sum()) < kernel.numel()  # a test that can tell the samples apart
    occupied = grid.is_occupied(positions)
    assert torch.equal(occupied, with_torch_code(monkeypatch, "sampling_ops", lambda: grid.is_occupied(positions)))
    assert torch.equal(grid.worth_evaluating(positions, deltas, 0.0), occupied)


def test_a_model_renders_the_same_image_with_the_kernels_as_with_the_torch_code(monkeypatch: pytest.MonkeyPatch) -> None:
    """A block-like model (a region centre and radius) with a grid that prunes: the same image, depth
    and samples per ray either way."""
    base = small_scalar_model(num_train_data=1, num_samples_per_ray=48, occupancy_warmup_steps=0)
    model = ScalarModel(config=base.config, scene_box=base.scene_box, num_train_data=1, region_centre=(0.2, -0.1, 0.0), region_radius=0.8)
    model.field.density_at_unit = _ball_field(model.field.density_at_unit)
    for step in range(0, 16 * 4, 16):
        model.update_occupancy(step)
    assert model.samples_grid().pruning
    generator = torch.Generator().manual_seed(0)
    directions = torch.nn.functional.normalize(torch.randn(256, 3, generator=generator), dim=-1)
    rays = ray_bundle(torch.zeros(256, 3), directions)
    model.eval()
    with torch.no_grad():
        kernel = model(rays)
        reference = with_torch_code(monkeypatch, "sampling_ops", lambda: model(rays))
    assert kernel["accumulation"].max() > 0.9 and kernel["accumulation"].min() < 0.1  # rays hit and miss
    for key in ("rgb", "depth", "accumulation", "samples_per_ray"):
        torch.testing.assert_close(kernel[key], reference[key], atol=1e-5, rtol=0)


def _ball_field(density_at_unit):  # type: ignore[no-untyped-def]
    """A field that is an opaque ball of world radius 0.3 at (0.5, 0, 0) in the model's region frame,
    with the real field's geometry features."""

    def field(unit_positions: torch.Tensor, encoding=None):  # type: ignore[no-untyped-def]
        _, geo_features = density_at_unit(unit_positions)
        inside_ball = (unit_positions - 0.5) * 4.0  # inverse contraction inside the unit ball
        inside = torch.linalg.vector_norm(inside_ball - torch.tensor([0.5, 0.0, 0.0]), dim=-1) < 0.3
        return torch.where(inside, 200.0, 0.0), geo_features

    return field


def test_nan_intervals_and_never_evaluated_cells_count_as_worth_evaluating() -> None:
    """The kernel's own edge cases, without the torch code: an infinite estimate times a zero
    interval (NaN) and a NaN interval are evaluated; a zero interval in a finite cell is not."""
    grid = OccupancyGrid(resolution=4, neighbourhood_alpha_test=False)
    grid.seed(torch.ones(64))
    grid.density_ema[0] = float("inf")
    positions = torch.tensor([[0.01, 0.01, 0.01], [0.6, 0.6, 0.6], [0.6, 0.6, 0.6], [0.6, 0.6, 0.6]])
    deltas = torch.tensor([0.0, float("nan"), 0.0, 1.0])
    worth = grid.worth_evaluating(positions, deltas, 0.01)
    assert worth.tolist() == [True, True, False, True]
    assert -math.log1p(-0.01) < 1.0  # the last sample's optical depth (1.0) is above the threshold
