"""Contraction, sampling, occupancy grid, volume rendering and the lr schedule on normal and extreme inputs."""

from __future__ import annotations

import math
import warnings
from typing import List

import pytest
import torch
from conftest import ray_bundle, small_scalar_model

from scalar_nerfstudio.engine.schedulers import hold_then_restart_factor, warmup_exponential_decay_factor
from scalar_nerfstudio.fields.scalar_field import contract, contract_to_unit_cube
from scalar_nerfstudio.model_components.rendering import render_depth, render_weights
from scalar_nerfstudio.model_components.sampling import (
    OccupancyGrid,
    lin_disp_spacing,
    lin_disp_spacing_inverse,
    sample_intervals,
    sphere_interval,
)
from scalar_nerfstudio.models.scalar_model import ScalarModel


def test_contraction_matches_mipnerf360_and_stays_in_the_ball() -> None:
    inside = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.4, 0.5]])
    assert torch.equal(contract(inside), inside)
    x = torch.tensor([[3.0, 4.0, 0.0]])  # |x| = 5
    assert torch.allclose(contract(x), (2.0 - 1.0 / 5.0) * x / 5.0)
    eps = 1e-6
    extreme = torch.tensor([
        [1.0 - eps, 0.0, 0.0], [1.0 + eps, 0.0, 0.0], [1e6, 0.0, 0.0], [1e30, -1e30, 1e30],
        [float("inf"), 0.0, 0.0], [-float("inf"), float("inf"), 0.0], [float("nan"), 1.0, 0.0], [3e38, 3e38, 3e38],
    ])
    out = contract(extreme)
    assert torch.isfinite(out).all()
    assert (torch.linalg.vector_norm(out, dim=-1) <= 2.0 + 1e-6).all()
    assert torch.allclose(out[2], torch.tensor([2.0, 0.0, 0.0]), atol=1e-5)
    assert torch.allclose(out[4], torch.tensor([2.0, 0.0, 0.0]), atol=1e-5)
    unit = contract_to_unit_cube(extreme)
    assert ((unit >= 0) & (unit <= 1)).all()


def test_contraction_is_continuous_at_the_unit_sphere() -> None:
    direction = torch.nn.functional.normalize(torch.randn(100, 3), dim=-1)
    below, above = contract(direction * (1 - 1e-5)), contract(direction * (1 + 1e-5))
    assert (below - above).abs().max() < 1e-4


def test_spacing_round_trip_and_sorted_intervals() -> None:
    t = torch.tensor([0.0, 0.5, 1.0, 2.0, 100.0, 1e4])
    assert torch.allclose(lin_disp_spacing_inverse(lin_disp_spacing(t)), t, rtol=1e-3)
    nears, fars = torch.full((5, 1), 0.05), torch.full((5, 1), 1000.0)
    starts, ends = sample_intervals(nears, fars, num_samples=32, jitter=True)
    assert starts.shape == (5, 32)
    assert (ends >= starts).all() and (starts[:, 1:] >= starts[:, :-1]).all()
    assert (starts >= 0.05 - 1e-6).all() and (ends <= 1000.0 + 1e-3).all()


@pytest.mark.parametrize("density", [0.0, 1e-8, 1.0, 1e6, float("inf"), float("nan")])
def test_volume_rendering_weights_stay_valid(density: float) -> None:
    deltas = torch.tensor([[0.0, 1e-9, 0.1, 1.0, 1e4]]).repeat(3, 1)
    densities = torch.full_like(deltas, density).requires_grad_(True)
    weights, transmittance = render_weights(densities, deltas)
    assert torch.isfinite(weights).all() and (weights >= 0).all() and (weights <= 1).all()
    assert (weights.sum(-1) <= 1 + 1e-6).all()
    assert (transmittance[:, 1:] <= transmittance[:, :-1] + 1e-7).all()
    weights.sum().backward()
    assert torch.isfinite(densities.grad).all()


def test_empty_ray_renders_background_depth_far() -> None:
    weights, _ = render_weights(torch.zeros(2, 4), torch.ones(2, 4))
    assert torch.equal(weights, torch.zeros(2, 4))
    depth = render_depth(weights, torch.arange(4.0).repeat(2, 1), torch.full((2, 1), 50.0))
    assert torch.equal(depth, torch.full((2, 1), 50.0))


def test_opaque_surface_gets_all_the_weight_and_its_depth() -> None:
    densities = torch.tensor([[0.0, 0.0, 1e6, 0.0]])
    weights, _ = render_weights(densities, torch.ones(1, 4))
    assert torch.allclose(weights, torch.tensor([[0.0, 0.0, 1.0, 0.0]]))
    depth = render_depth(weights, torch.tensor([[1.0, 2.0, 3.0, 4.0]]), torch.tensor([[10.0]]))
    assert torch.allclose(depth, torch.tensor([[3.0]]))


def _sphere_density(unit: torch.Tensor) -> torch.Tensor:
    return torch.where(torch.linalg.vector_norm(unit - 0.5, dim=-1) < 0.2, 100.0, 0.0)


def test_occupancy_grid_marks_dense_cells_and_indexes_in_range() -> None:
    grid = OccupancyGrid(resolution=8, update_every=1, warmup_steps=1)
    assert grid.occupied.all()  # nothing is skipped before the first update
    grid.update(0, _sphere_density)
    assert grid.occupied.all()  # warm-up: densities are estimated everywhere, nothing is marked empty yet
    grid.update(1, _sphere_density)
    centre, corner = torch.tensor([[0.5, 0.5, 0.5]]), torch.tensor([[0.02, 0.02, 0.02]])
    assert grid.is_occupied(centre).item() and not grid.is_occupied(corner).item()
    assert 0.0 < grid.occupied_fraction() < 0.2
    wild = torch.tensor([[-1.0, 2.0, float("nan")], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]])
    indices = grid.cell_indices(wild)
    assert ((indices >= 0) & (indices < 8**3)).all()


def test_the_grid_forgets_the_warm_up_haze_at_its_first_update_after_it() -> None:
    """A young field is hazy everywhere; the update that ends the warm-up starts the estimates from the
    field as it is then, so the haze does not keep empty space occupied for the rest of the run."""
    grid = OccupancyGrid(resolution=8, update_every=4, warmup_steps=8)
    for step in (0, 4):
        grid.update(step, lambda unit: torch.full(unit.shape[:1], 100.0))
        assert grid.warming_up and grid.occupied.all()
    grid.update(8, _sphere_density)
    assert not grid.warming_up
    centre, corner = torch.tensor([[0.5, 0.5, 0.5]]), torch.tensor([[0.02, 0.02, 0.02]])
    assert grid.is_occupied(centre).item() and not grid.is_occupied(corner).item()
    assert 0.0 < grid.occupied_fraction() < 0.2
    # later updates keep the decaying maximum: a cell seen dense stays occupied for a while
    grid.update(12, lambda unit: torch.zeros(unit.shape[:1]))
    assert grid.is_occupied(centre).item()


def test_a_seeded_grid_keeps_its_estimates_past_the_warm_up_step() -> None:
    grid = OccupancyGrid(resolution=8, update_every=4, warmup_steps=8)
    grid.seed(torch.full((8**3,), 100.0))
    assert not grid.warming_up
    grid.update(8, _sphere_density)
    assert grid.is_occupied(torch.tensor([[0.02, 0.02, 0.02]])).item()  # decayed from the seed, not restarted



def test_refreshing_the_grid_forgets_the_haze_it_remembers_and_is_deterministic() -> None:
    """Late in training a cell's estimate is the decaying maximum of what it has seen, so haze the
    field has since cleared keeps cells occupied; the refresh at the end of training re-estimates
    every cell from the field as it is (at the cell centres) and marks them again."""
    torch.manual_seed(0)  # the partial updates draw their cells from the global generator
    haze = lambda unit: torch.full(unit.shape[:1], 100.0)  # noqa: E731
    grid = OccupancyGrid(resolution=8, update_every=4, warmup_steps=8)
    grid.update(0, haze)
    grid.update(8, _sphere_density)  # the restart after the warm-up
    for step in range(12, 12 + 4 * 16, 4):  # every cell seen hazy again (a quarter per update)
        grid.update(step, haze)
    grid.update(12 + 4 * 16, _sphere_density)
    corner, centre = torch.tensor([[0.02, 0.02, 0.02]]), torch.tensor([[0.5, 0.5, 0.5]])
    assert grid.is_occupied(corner).item() and grid.occupied_fraction() > 0.9  # the haze is remembered
    grid.refresh(_sphere_density)
    assert grid.is_occupied(centre).item() and not grid.is_occupied(corner).item()
    assert 0.0 < grid.occupied_fraction() < 0.2
    assert grid.pruning is True
    fresh = OccupancyGrid(resolution=8, update_every=4, warmup_steps=8)
    fresh.refresh(_sphere_density)  # a grid never updated: built from the field alone, no warm-up
    assert not fresh.warming_up and torch.equal(fresh.occupied, grid.occupied)
    first = (grid.density_ema.clone(), grid.occupied.clone())
    grid.refresh(_sphere_density)
    assert torch.equal(grid.density_ema, first[0]) and torch.equal(grid.occupied, first[1])
    # NaN and infinite densities stay usable estimates
    grid.refresh(lambda unit: torch.full(unit.shape[:1], float("nan")))
    assert torch.isfinite(grid.density_ema).all()


def test_a_refreshed_grid_keeps_a_thin_surface_that_misses_every_cell_centre() -> None:
    """A slab thinner than a cell lying between two layers of cell centres: the cells it crosses
    stay occupied (their estimates are the largest density at their corners) and its samples are
    worth evaluating; cells away from it are empty."""
    g = 8

    def slab(unit: torch.Tensor) -> torch.Tensor:  # dense where x is within 0.01 of 3 / 8 (a cell face)
        return torch.where((unit[:, 0] - 3.0 / g).abs() < 0.01, 1000.0, 0.0)

    grid = OccupancyGrid(resolution=g, neighbourhood_alpha_test=False)
    grid.refresh(slab)
    on_slab = torch.tensor([[3.0 / g + 0.005, 0.5, 0.5], [3.0 / g - 0.005, 0.3, 0.7]])
    away = torch.tensor([[0.5 + 1.0 / g, 0.5, 0.5], [0.05, 0.05, 0.05]])
    assert grid.is_occupied(on_slab).all() and not grid.is_occupied(away).any()
    assert grid.worth_evaluating(on_slab, torch.full((2,), 0.01), alpha_threshold=0.01).all()
    assert slab((torch.arange(g, dtype=torch.float32)[:, None].expand(g, 3) + 0.5) / g).max() == 0  # no centre sees it


def test_the_grids_cached_answers_follow_its_cells() -> None:
    """``pruning`` and the neighbourhood estimates are cached; in-place writes and swapped storage
    (a block's tensors installed from its file) renew them."""
    grid = OccupancyGrid(resolution=4, update_every=1, warmup_steps=0)
    assert grid.pruning is False
    grid.occupied[0] = False
    assert grid.pruning is True
    grid.occupied.data = torch.ones(4**3, dtype=torch.bool)
    assert grid.pruning is False
    grid.density_ema.copy_(torch.zeros(4**3))
    assert grid.neighbourhood_estimates().max().item() == 0.0
    grid.density_ema[5] = 3.0
    assert grid.neighbourhood_estimates().max().item() == 3.0
    grid.density_ema.data = torch.full((4**3,), 7.0)
    assert grid.neighbourhood_estimates().min().item() == 7.0


def test_a_sample_is_worth_evaluating_when_its_cells_estimate_makes_it_opaque_enough() -> None:
    """Samples of an occupied cell are evaluated only when the largest density estimate around the
    cell, over the sample's own interval, reaches the opacity threshold; cells never evaluated, NaN
    and infinite intervals count as opaque, and an empty cell is never evaluated."""
    grid = OccupancyGrid(resolution=8, update_every=1, warmup_steps=0)
    estimates = torch.zeros(8, 8, 8)
    estimates[:4] = 1.0  # haze at 1 / unit in the half x < 0.5
    estimates[0, 0, 0] = 50.0  # a dense corner cell: its face neighbours are evaluated too
    estimates[7, 7, 7] = float("inf")  # never evaluated
    grid.density_ema.copy_(estimates.reshape(-1))
    grid.occupied.copy_(grid.density_ema > 0)

    def centre(x: int, y: int, z: int) -> torch.Tensor:
        return (torch.tensor([x, y, z], dtype=torch.float32) + 0.5) / 8

    hazy, beside_dense, never, empty = centre(2, 3, 4), centre(1, 0, 0), centre(7, 7, 7), centre(6, 2, 2)
    positions = torch.stack([hazy, hazy, hazy, hazy, hazy, beside_dense, never, never, empty, empty])
    deltas = torch.tensor([0.005, 0.0101, 1.0, float("nan"), float("inf"), 0.005, 0.0, 1e-30, 1e6, float("nan")])
    worth = grid.worth_evaluating(positions, deltas, alpha_threshold=0.01)
    # 1 - exp(-0.005) < 0.01 <= 1 - exp(-0.0101); 50 / unit over 0.005 is opacity 0.22
    assert worth.tolist() == [False, True, True, True, True, True, True, True, False, False]
    assert grid.worth_evaluating(positions, deltas, alpha_threshold=0.0).tolist() == grid.is_occupied(positions).tolist()
    assert grid.worth_evaluating(positions[2:3], deltas[2:3], alpha_threshold=1.0).tolist() == [False]  # opacity 0.63 < 1
    assert grid.worth_evaluating(positions[4:5], deltas[4:5], alpha_threshold=1.0).tolist() == [True]
    # the neighbourhood follows the estimates: an update replaces the cached maximum
    grid.update(0, lambda unit: torch.full(unit.shape[:1], 0.5))  # restart: every estimate is 0.5 now
    assert grid.is_occupied(positions[5:6]).item()
    assert not grid.worth_evaluating(positions[5:6], deltas[5:6], alpha_threshold=0.01).item()  # 0.5 over 0.005


def test_skipping_hazy_samples_by_the_grid_renders_the_same_image_with_fewer_evaluations(monkeypatch: pytest.MonkeyPatch) -> None:
    """An opaque ball in faint haze: the haze's samples are below the opacity threshold, so the field
    drops them after evaluating them; the grid's estimate drops them before. Same image, fewer
    field evaluations (rendering and the training step's no-grad pass)."""
    images, evaluated = {}, {}
    for skip in (False, True):
        model = small_scalar_model(num_train_data=1, num_samples_per_ray=64, occupancy_warmup_steps=0, grid_alpha_skip=skip)
        density_at_unit = model.field.density_at_unit
        counts = []

        def ball_in_haze(unit_positions: torch.Tensor, encoding=None):
            counts.append(unit_positions.shape[0])
            _, geo_features = density_at_unit(unit_positions)
            world = (unit_positions - 0.5) * 4.0  # inverse contraction inside the unit ball
            inside = torch.linalg.vector_norm(world - torch.tensor([0.5, 0.0, 0.0]), dim=-1) < 0.2
            hazy = torch.linalg.vector_norm(world, dim=-1) < 0.9  # opacity 0.0125 per cell, 0.006 per sample
            return torch.where(inside, 200.0, torch.where(hazy, 0.2, 0.0)), geo_features

        model.field.density_at_unit = ball_in_haze
        for step in range(0, 16 * 8, 16):  # every cell seen (a quarter per update after the first)
            model.update_occupancy(step)
        assert model.occupancy.pruning
        generator = torch.Generator().manual_seed(0)
        directions = torch.nn.functional.normalize(torch.cat([torch.ones(128, 1), (torch.rand(128, 2, generator=generator) - 0.5) * 0.5], dim=-1), dim=-1)
        rays = ray_bundle(torch.zeros(128, 3), directions)
        model.eval()
        counts.clear()
        with torch.no_grad():
            images[skip] = model(rays)
        evaluated[skip] = sum(counts)
        model.train()
        counts.clear()
        torch.manual_seed(0)
        model(rays)["rgb"].sum().backward()  # the training step's no-grad pass, then its pass with gradients
        evaluated[(skip, "train")] = counts[0]
    assert images[True]["accumulation"].min() > 0.9  # every ray hits the ball
    for key in ("rgb", "depth", "accumulation"):
        torch.testing.assert_close(images[True][key], images[False][key], atol=1e-3, rtol=0)
    assert evaluated[True] < 0.8 * evaluated[False], evaluated
    assert evaluated[(True, "train")] < 0.8 * evaluated[(False, "train")], evaluated


def test_a_model_that_finishes_training_renders_the_same_image_with_fewer_evaluations() -> None:
    """A field that was hazy earlier in training and is now an opaque ball: the grid still marks
    the haze's cells; once the model finishes its training (the grid re-estimated from the final
    field), rendering skips them, and the image is the same."""
    model = small_scalar_model(num_train_data=1, num_samples_per_ray=64, occupancy_warmup_steps=0)
    density_at_unit = model.field.density_at_unit
    counts: List[int] = []
    hazy = [True]

    def field(unit_positions: torch.Tensor, encoding=None):
        counts.append(unit_positions.shape[0])
        _, geo_features = density_at_unit(unit_positions)
        world = (unit_positions - 0.5) * 4.0  # inverse contraction inside the unit ball
        inside = torch.linalg.vector_norm(world - torch.tensor([0.5, 0.0, 0.0]), dim=-1) < 0.2
        haze = torch.linalg.vector_norm(world, dim=-1) < 0.9
        return torch.where(inside, 200.0, torch.where(haze & torch.tensor(hazy[0]), 5.0, 0.0)), geo_features

    model.field.density_at_unit = field
    for step in range(0, 16 * 8, 16):  # the hazy field seen in every cell
        model.update_occupancy(step)
    hazy[0] = False  # the haze has cleared; the grid's decaying estimates still remember it
    model.update_occupancy(16 * 8)
    generator = torch.Generator().manual_seed(0)
    directions = torch.nn.functional.normalize(torch.cat([torch.ones(128, 1), (torch.rand(128, 2, generator=generator) - 0.5) * 0.5], dim=-1), dim=-1)
    rays = ray_bundle(torch.zeros(128, 3), directions)
    model.eval()
    images, evaluated = [], []
    for finish in (False, True):
        if finish:
            model.finish_training()
        counts.clear()
        with torch.no_grad():
            images.append(model(rays))
        evaluated.append(sum(counts))
    assert images[1]["accumulation"].min() > 0.9  # every ray hits the ball
    for key in ("rgb", "depth", "accumulation"):
        torch.testing.assert_close(images[1][key], images[0][key], atol=1e-4, rtol=0)
    assert evaluated[1] < 0.7 * evaluated[0], evaluated


def test_a_saved_render_grid_loads_where_it_fits_and_is_set_aside_where_it_does_not() -> None:
    """A model's render grid travels with its state; a state without one (written before it existed)
    or with one of another resolution loads too, and renders use the training grid."""
    source = small_scalar_model(render_occupancy_resolution=8)
    assert source.render_occupancy is not None
    source.render_occupancy.refresh(_sphere_density)
    source.render_occupancy_ready.fill_(True)
    state = source.state_dict()
    same = small_scalar_model(render_occupancy_resolution=8)
    same.load_state_dict(state, strict=True)
    same.eval()
    assert bool(same.render_occupancy_ready) and same.samples_grid() is same.render_occupancy
    assert torch.equal(same.render_occupancy.occupied, source.render_occupancy.occupied)
    same.train()
    assert same.samples_grid() is same.occupancy  # training always uses the training grid
    older = {k: v for k, v in state.items() if not k.startswith("render_occupancy")}
    for resolution, saved, warns in ((8, older, False), (4, state, True), (0, state, True)):
        model = small_scalar_model(render_occupancy_resolution=resolution)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            model.load_state_dict(dict(saved), strict=True)
        assert any("render grid" in str(w.message) for w in caught) == warns
        model.eval()
        assert not bool(model.render_occupancy_ready) and model.samples_grid() is model.occupancy


def test_schedule_warms_up_linearly_then_decays_to_a_tenth() -> None:
    factors = [warmup_exponential_decay_factor(s, 1000, warmup_fraction=0.025, final_factor=0.1) for s in range(1001)]
    assert factors[0] == pytest.approx(1 / 25) and factors[12] == pytest.approx(12 / 25)
    assert factors[25] == pytest.approx(1.0)
    assert factors[1000] == pytest.approx(0.1)
    assert all(isinstance(f, float) and math.isfinite(f) for f in factors)
    assert all(a >= b for a, b in zip(factors[25:], factors[26:]))


def test_schedule_with_a_restart_holds_then_restarts_scaled() -> None:
    factors = [hold_then_restart_factor(s, 1000, warmup_fraction=0.025, final_factor=0.1, restart_fraction=0.4,
                                        restart_factor=4.0) for s in range(1001)]
    assert factors[0] == pytest.approx(1 / 10) and factors[10] == pytest.approx(1.0)  # warm-up over 2.5 % of 400
    assert factors[10:400] == pytest.approx([1.0] * 390)  # held
    assert factors[400] == pytest.approx(4.0 / 15)  # warms up again over 2.5 % of 600
    assert factors[415] == pytest.approx(4.0) and factors[1000] == pytest.approx(0.4)
    assert all(a >= b for a, b in zip(factors[415:], factors[416:]))
    plain = [warmup_exponential_decay_factor(s, 1000, warmup_fraction=0.025, final_factor=0.1) for s in range(1001)]
    for no_restart in (0.0, 0.0001, 1.0):
        assert [hold_then_restart_factor(s, 1000, warmup_fraction=0.025, final_factor=0.1, restart_fraction=no_restart,
                                         restart_factor=4.0) for s in range(1001)] == plain


def _model_with_opaque_ball(reset_near_plane: bool) -> ScalarModel:
    """A fresh model whose density is an opaque ball of radius 0.04 around the origin, empty elsewhere."""
    model = small_scalar_model(num_train_data=1, reset_near_plane=reset_near_plane)
    density_at_unit = model.field.density_at_unit

    def ball(unit_positions: torch.Tensor, encoding=None):
        _, geo_features = density_at_unit(unit_positions)
        world = (unit_positions - 0.5) * 4.0  # inverse contraction inside the unit ball
        return torch.where(torch.linalg.vector_norm(world, dim=-1) < 0.04, 1e3, 0.0), geo_features

    model.field.density_at_unit = ball
    return model


def _accumulation(model: ScalarModel, origin: tuple, direction: tuple) -> float:
    with torch.no_grad():
        return float(model(ray_bundle(torch.tensor([origin]), torch.tensor([direction])))["accumulation"])


@pytest.mark.parametrize("reset_near_plane", [False, True])
def test_rendering_keeps_the_training_near_plane_unless_reset(reset_near_plane: bool) -> None:
    """What lies within the near plane of a camera is never trained from that camera: evaluation and
    the viewer do not show it either, unless the near plane is reset (nerfstudio's default)."""
    model = _model_with_opaque_ball(reset_near_plane)
    assert model.collider.near_plane == 0.05
    model.train()
    assert _accumulation(model, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0)) < 1e-3  # training never sees it from inside
    model.eval()
    inside = _accumulation(model, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    assert (inside > 0.99) if reset_near_plane else (inside < 1e-3)
    # from farther than the near plane the ball is seen either way
    assert _accumulation(model, (-0.5, 0.0, 0.0), (1.0, 0.0, 0.0)) > 0.99


def test_sphere_interval_enters_and_leaves_where_the_ray_crosses_the_sphere() -> None:
    origins = torch.tensor([[0.0, 0, 0], [0.5, 0, 0], [-3.0, 0, 0], [-3.0, 2.5, 0], [-3.0, 0, 0]])
    directions = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0], [-1.0, 0, 0]])
    t_entry, t_exit = sphere_interval(origins, directions, 2.0)
    assert t_entry.shape == t_exit.shape == (5, 1)
    assert t_entry[:, 0].tolist() == pytest.approx([-2.0, -1.5, 1.0, 0.0, -5.0])  # a miss: 0, 0
    assert t_exit[:, 0].tolist() == pytest.approx([2.0, 2.5, 5.0, 0.0, -1.0])  # behind the camera: both < 0
    # random rays that cross it: both points lie on the sphere
    generator = torch.Generator().manual_seed(0)
    origins = torch.randn(200, 3, generator=generator) * 2.0
    directions = torch.nn.functional.normalize(torch.randn(200, 3, generator=generator), dim=-1)
    t_entry, t_exit = sphere_interval(origins, directions, 1.5)
    hit = (t_exit > t_entry)[:, 0]
    assert 20 < int(hit.sum()) < 200
    for t in (t_entry, t_exit):
        radii = (origins + directions * t)[hit].norm(dim=-1)
        assert torch.allclose(radii, torch.full_like(radii, 1.5), atol=1e-4)


def test_sphere_interval_stays_finite_on_extreme_rays() -> None:
    origins = torch.tensor([[1e30, 0, 0], [1e30, 1e30, 0], [float("nan"), 0, 0], [0.0, 0, 0], [3e38, -3e38, 3e38]])
    directions = torch.tensor([[-1.0, 0, 0], [0.0, 0, 1], [1.0, 0, 0], [float("inf"), 0, 0], [1.0, 0, 0]])
    t_entry, t_exit = sphere_interval(origins, directions, 1.0)
    assert torch.isfinite(t_entry).all() and torch.isfinite(t_exit).all()
    assert t_exit[0, 0] - t_entry[0, 0] >= 0  # straight at it from 1e30 away: it may round to one point, never NaN
    assert t_entry[1:, 0].tolist() == t_exit[1:, 0].tolist() == [0.0] * 4  # misses, NaN and inf: empty


def _model_with_density(density_of_world, **config) -> ScalarModel:
    """A fresh model (training image 0) whose density is ``density_of_world([N, 3] world positions)``
    inside the unit ball of the contraction (radius 1 around the origin) and, beyond it, at the
    contracted point's direction times 2 (what the contraction maps there, closest to the ball)."""
    model = small_scalar_model(num_train_data=1, **config)
    density_at_unit = model.field.density_at_unit

    def density(unit_positions: torch.Tensor, encoding=None):
        _, geo_features = density_at_unit(unit_positions)
        contracted = (unit_positions - 0.5) * 4.0  # in the ball of radius 2
        norm = torch.linalg.vector_norm(contracted, dim=-1, keepdim=True).clamp_min(1e-9)
        world = torch.where(norm <= 1.0, contracted, contracted / norm / (2.0 - norm).clamp_min(1e-6))
        return density_of_world(world), geo_features

    model.field.density_at_unit = density
    return model


def test_a_scene_radius_ends_rays_where_they_leave_it() -> None:
    """With a scene radius, a model renders nothing beyond the sphere (haze behind a wall of the
    scene cannot be put there), still renders what lies inside it from a camera outside, and a ray
    that misses the sphere renders the background with no weight."""

    def wall_beyond_3(world: torch.Tensor) -> torch.Tensor:
        return torch.where(world.norm(dim=-1) > 3.0, 1e3, 0.0) + torch.where(world.norm(dim=-1) < 0.2, 1e3, 0.0)

    unbounded = _model_with_density(wall_beyond_3)
    bounded = _model_with_density(wall_beyond_3, scene_radius=2.0)
    assert bounded.collider.scene_radius == 2.0 and unbounded.collider.scene_radius is None
    for model in (unbounded, bounded):
        model.eval()
    outward = ((0.5, 0.0, 0.0), (0.0, 1.0, 0.0))  # from inside, away from the ball: only the far wall
    assert _accumulation(unbounded, *outward) > 0.99
    assert _accumulation(bounded, *outward) < 1e-3
    with torch.no_grad():
        from_outside = bounded(ray_bundle(torch.tensor([[-10.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]])))
        missing = bounded(ray_bundle(torch.tensor([[-10.0, 5.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]])))
    assert float(from_outside["accumulation"]) > 0.99 and float(from_outside["depth"]) == pytest.approx(9.8, abs=0.1)
    assert float(missing["accumulation"]) == 0.0
    assert all(torch.isfinite(value).all() for value in missing.values() if isinstance(value, torch.Tensor))
    with pytest.raises(ValueError, match="scene radius -1.0"):
        small_scalar_model(scene_radius=-1.0)
