"""Choosing blocks per ray (``blocks_per_ray``) and the ``surface`` fusion rule.

The pure functions are checked on hand-made numbers; the scene model is checked against a reference
that renders every block on every ray and applies the rule by hand, so rendering only the chosen
blocks on only their rays must give the same image while each ray renders ``blocks_per_ray`` blocks.
"""

from __future__ import annotations

from typing import List

import pytest
import torch
from conftest import SMALL_FIELD, ray_bundle
from nerfstudio.data.scene_box import SceneBox

from scalar_nerfstudio.blocks.split import Block, BlockSplit
from scalar_nerfstudio.fields.scalar_field import ScalarFieldConfig
from scalar_nerfstudio.fusion import (
    fuse_global_guided,
    fuse_outputs,
    parse_fusion_mode,
    region_scores,
    score_weights,
    select_blocks,
    surface_points,
    weights_winner,
)
from scalar_nerfstudio.models.block_selection import BlockRegions, blocks_for, select_rays
from scalar_nerfstudio.models.scene_model import ScalarSceneModel, ScalarSceneModelConfig

NAN, INF = float("nan"), float("inf")


# ------------------------------------------------------------------------------ pure functions


def test_region_scores_are_at_most_one_inside_a_block_and_grow_outside() -> None:
    centres = torch.tensor([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]])
    radii = torch.tensor([1.0, 2.0])
    points = torch.tensor([[0.5, -0.9, 0.2], [3.0, 1.0, 0.0], [10.0, 0.0, 0.0], [NAN, 0.0, 0.0], [INF, 0.0, 0.0]])
    scores = region_scores(points, centres, radii)
    assert scores.shape == (2, 5)
    assert torch.allclose(scores[:, 0], torch.tensor([0.9, 3.5 / 2.0]))
    assert torch.allclose(scores[:, 1], torch.tensor([3.0, 0.5]))  # the Chebyshev distance over the block's half-size
    assert torch.allclose(scores[:, 2], torch.tensor([10.0, 3.0]))
    assert torch.isinf(scores[:, 3:]).all()  # a non-finite point is in no block
    with pytest.raises(ValueError, match="radii"):
        region_scores(points, centres, torch.tensor([1.0, 0.0]))
    with pytest.raises(ValueError, match="radii"):
        region_scores(points, centres, torch.tensor([1.0]))


def test_region_scores_stay_finite_for_huge_and_tiny_coordinates() -> None:
    centres = torch.tensor([[1e30, 0.0, 0.0], [0.0, 0.0, 0.0]])
    radii = torch.tensor([1e-30, 1e30])
    scores = region_scores(torch.tensor([[1e30, 0.0, 0.0], [0.0, 1e-30, 0.0]]), centres, radii)
    assert not torch.isnan(scores).any()
    assert scores[0, 0] == 0.0 and scores[1, 1] < 1.0


def test_select_blocks_keeps_the_lowest_scores_per_pixel() -> None:
    scores = torch.tensor([[0.5, 3.0, 1.0, NAN], [0.2, 2.0, 1.0, 4.0], [0.9, 1.0, 1.0, 5.0]])
    one = select_blocks(scores, 1)
    assert one.tolist() == [[False, False, True, False], [True, False, False, True], [False, True, False, False]]  # ties: lowest index
    two = select_blocks(scores, 2)
    assert two.sum(dim=0).tolist() == [2, 2, 2, 2]
    assert two[:, 0].tolist() == [True, True, False] and two[:, 3].tolist() == [False, True, True]  # NaN ranks last
    assert select_blocks(scores, 5).all()  # more than K: every block
    usable = torch.tensor([True, False, True])
    assert select_blocks(scores, 1, usable)[1].sum() == 0 and select_blocks(scores, 1, usable).sum(dim=0).tolist() == [1, 1, 1, 1]
    with pytest.raises(ValueError, match="blocks_per_ray"):
        select_blocks(scores, 0)


def test_score_weights_favour_the_block_holding_the_point() -> None:
    scores = torch.tensor([[0.25, 0.0, 2.0, 1.0], [0.75, 0.5, 2.0, 3.0], [5.0, 0.0, 2.0, 1.0]])
    selected = torch.tensor([[True, True, True, False], [True, True, True, False], [False, True, False, False]])
    weights = score_weights(scores, selected, gamma=1.0)
    assert torch.allclose(weights[:, 0], torch.tensor([0.75, 0.25, 0.0]))  # 1/0.25 : 1/0.75
    assert torch.allclose(weights[:, 1], torch.tensor([0.5, 0.0, 0.5]))  # two points at a centre share it all
    assert torch.allclose(weights[:, 2], torch.tensor([0.5, 0.5, 0.0]))
    assert (weights[:, 3] == 0).all()  # nothing selected: the caller's fallback
    assert weights_winner(weights).tolist() == [0, 0, 0, -1]


def test_surface_points_fall_back_to_the_origin_for_bad_depths() -> None:
    origins = torch.tensor([[0.0, 0.0, 0.0]] * 4)
    directions = torch.tensor([[1.0, 0.0, 0.0]] * 4)
    points = surface_points(origins, directions, torch.tensor([[2.0], [NAN], [INF], [-1.0]]))
    assert points.tolist() == [[2.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]


def test_blocks_for_a_mode_are_the_started_ones_it_uses() -> None:
    started = [0, 2]
    assert blocks_for(parse_fusion_mode("global-only"), started) == []
    assert blocks_for(parse_fusion_mode("block:2"), started) == [2]
    assert blocks_for(parse_fusion_mode("block:1"), started) == []  # not started: the global model renders
    assert blocks_for(parse_fusion_mode("nearest"), started) == started


def test_select_rays_reads_the_global_depth_only_for_the_rules_that_need_it() -> None:
    centres = torch.tensor([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 5.0]])
    radii = torch.ones(3)
    origins = torch.tensor([[-0.9, 0.0, -3.0], [0.9, 0.0, -3.0]])
    directions = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    calls: List[int] = []

    def global_depth() -> torch.Tensor:
        calls.append(1)
        return torch.full((2, 1), 3.0)  # the surface points (-0.9, 0, 0) and (0.9, 0, 0)

    def select(mode: str, block_ids: List[int], per_ray: int, observation=None):
        return select_rays(parse_fusion_mode(mode), block_ids, origins=origins, directions=directions,
                           regions=BlockRegions(centres, radii, observation), blocks_per_ray=per_ray, global_depth=global_depth)

    selected, scores = select("nearest", [0, 1, 2], 2)
    assert selected.tolist() == [[True, False], [False, True], [False, False]] and scores is None
    selected, _ = select("global", [0, 1, 2], 0)  # every block on every ray
    assert bool(selected.all()) and calls == []
    selected, scores = select("surface", [1, 0], 1)  # rows follow block_ids
    assert calls == [1] and selected.tolist() == [[False, True], [True, False]] and scores.shape == (2, 2)
    observation = torch.ones(2, 4**3, dtype=torch.bool)
    observation[1] = False  # block 1 observes nothing
    selected, _ = select("surface", [0, 1], 1, observation)
    assert selected.tolist() == [[True, True], [False, False]]  # block 1's ray takes block 0, the one observing it
    selected, _ = select("block:0", [0], 1)
    assert selected.tolist() == [[True, True]]


def test_surface_fusion_takes_the_block_holding_the_surface_and_never_a_missing_one() -> None:
    # Three pixels, two blocks; block 0 was not rendered at pixel 1 (NaN) and neither block at pixel 2.
    block_rgb = [torch.tensor([[0.1, 0.1, 0.1], [NAN, NAN, NAN], [NAN, NAN, NAN]]),
                 torch.tensor([[0.9, 0.9, 0.9], [0.7, 0.7, 0.7], [NAN, NAN, NAN]])]
    global_rgb = torch.tensor([[0.5, 0.5, 0.5], [0.4, 0.4, 0.4], [0.3, 0.3, 0.3]])
    scores = torch.tensor([[0.2, 0.1, 0.1], [3.0, 0.9, 0.5]])  # pixel 0 in block 0, pixel 1 nearer block 0's centre
    fused = fuse_outputs("surface", [{"rgb": v} for v in block_rgb], {"rgb": global_rgb}, camera_origin=None, block_centres=None,
                         block_scores=scores, blocks_per_ray=1)
    assert torch.allclose(fused["rgb"], torch.tensor([[0.1] * 3, [0.7] * 3, [0.3] * 3]))
    assert fused["block_winner"].tolist() == [0, 1, -1]
    with pytest.raises(ValueError, match="block_scores"):
        fuse_outputs("surface", [{"rgb": v} for v in block_rgb], {"rgb": global_rgb}, camera_origin=None, block_centres=None)


# ------------------------------------------------------------------------------ the scene model


def _scene_model(fusion: str, blocks_per_ray: int) -> ScalarSceneModel:
    """Three started blocks along x (centres -0.6, 0, 0.6, half-size 0.3), every table random, so
    every model renders a different image; the occupancy grid is full (nothing skipped)."""
    torch.manual_seed(0)
    blocks = tuple(
        Block(index=k, image_indices=(0, 1), aabb_min=(x - 0.3, -0.3, -0.3), aabb_max=(x + 0.3, 0.3, 0.3), centre=(x, 0.0, 0.0))
        for k, x in enumerate((-0.6, 0.0, 0.6))
    )
    config = ScalarSceneModelConfig(field=ScalarFieldConfig(**SMALL_FIELD), fusion=fusion, blocks_per_ray=blocks_per_ray,
                                    num_samples_per_ray=32, render_normals="never", seed_block_occupancy=False)
    model = ScalarSceneModel(config=config, scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=2,
                             split=BlockSplit(blocks=blocks, aabb_scale=(1.0, 1.0, 1.0), seed=0))
    for block in range(3):
        model.begin_block(block)  # weights in memory
    with torch.no_grad():
        for index, sub in enumerate([model.global_model, *model.blocks.values()]):
            generator = torch.Generator().manual_seed(index)
            for parameter in sub.field.parameters():
                parameter.copy_(torch.randn(parameter.shape, generator=generator) * (2.0 if parameter.ndim == 2 and parameter.shape[1] > 8 else 0.3))
    return model.eval()


def _rays(num: int = 96):
    generator = torch.Generator().manual_seed(3)
    origins = torch.cat([torch.rand(num, 1, generator=generator) * 1.6 - 0.8, torch.full((num, 1), -0.9), torch.zeros(num, 1)], dim=-1)
    targets = torch.cat([torch.rand(num, 1, generator=generator) * 1.6 - 0.8, torch.full((num, 1), 0.9), torch.rand(num, 1, generator=generator) * 0.4 - 0.2], dim=-1)
    return ray_bundle(origins, torch.nn.functional.normalize(targets - origins, dim=-1))


def _every_block(model: ScalarSceneModel, rays) -> List[torch.Tensor]:
    with torch.no_grad():
        return [model.blocks[str(k)].render_rays(rays, normals=False)["rgb"] for k in range(3)]


def test_surface_rule_renders_one_block_per_ray_and_matches_rendering_every_block() -> None:
    model = _scene_model("surface", blocks_per_ray=1)
    rays = _rays()
    model.rays_rendered_by_block = {}
    with torch.no_grad():
        fused = model.get_outputs(rays)
        depth = model.global_model.render_depth_only(rays)["depth"]
    assert sum(model.rays_rendered_by_block.values()) == 96  # one block per ray, whatever K
    assert len([k for k, n in model.rays_rendered_by_block.items() if n > 0]) >= 2  # the rays do cross blocks
    points = surface_points(rays.origins, rays.directions, depth)
    best = region_scores(points, model.block_centres, model.block_radii).argmin(dim=0)  # [R]
    reference = torch.stack(_every_block(model, rays))[best, torch.arange(96)]
    assert torch.allclose(fused["rgb"], reference, atol=1e-5)
    assert fused["block_winner"].reshape(-1).long().tolist() == best.tolist()


def test_global_rule_over_chosen_blocks_and_over_every_block() -> None:
    rays = _rays()
    every = _scene_model("global", blocks_per_ray=0)
    every.rays_rendered_by_block = {}
    with torch.no_grad():
        fused = every.get_outputs(rays)
        global_rgb = every.global_model.render_rays(rays, normals=False)["rgb"]
    assert sum(every.rays_rendered_by_block.values()) == 3 * 96
    reference, _ = fuse_global_guided(torch.stack(_every_block(every, rays)), global_rgb)
    assert torch.allclose(fused["rgb"], reference, atol=1e-5)  # the paper's rule over all blocks

    chosen = _scene_model("global", blocks_per_ray=2)
    chosen.rays_rendered_by_block = {}
    with torch.no_grad():
        fused_chosen = chosen.get_outputs(rays)
        depth = chosen.global_model.render_depth_only(rays)["depth"]
    assert sum(chosen.rays_rendered_by_block.values()) == 2 * 96
    scores = region_scores(surface_points(rays.origins, rays.directions, depth), chosen.block_centres, chosen.block_radii)
    masked = torch.stack(_every_block(chosen, rays))
    masked[~select_blocks(scores, 2)] = NAN
    reference_chosen, _ = fuse_global_guided(masked, global_rgb)
    assert torch.allclose(fused_chosen["rgb"], reference_chosen, atol=1e-5)


def test_nearest_renders_each_ray_once() -> None:
    model = _scene_model("nearest", blocks_per_ray=2)
    rays = _rays()
    model.rays_rendered_by_block = {}
    with torch.no_grad():
        fused = model.get_outputs(rays)
    assert sum(model.rays_rendered_by_block.values()) == 96
    nearest = torch.cdist(rays.origins, model.block_centres).argmin(dim=1)
    reference = torch.stack(_every_block(model, rays))[nearest, torch.arange(96)]
    assert torch.allclose(fused["rgb"], reference, atol=1e-5)


def test_nearest_idw_renders_the_two_nearest_blocks_per_ray_and_matches_blending_every_block() -> None:
    model = _scene_model("nearest-idw", blocks_per_ray=2)
    rays = _rays()
    model.rays_rendered_by_block = {}
    with torch.no_grad():
        fused = model.get_outputs(rays)
    assert sum(model.rays_rendered_by_block.values()) == 2 * 96  # two blocks per ray, whatever K
    dist = torch.cdist(rays.origins, model.block_centres)  # [R, K]
    order = dist.argsort(dim=1)[:, :2]
    weights = torch.zeros_like(dist).scatter_(1, order, dist.gather(1, order) ** -model.config.nearest_idw_gamma)
    weights = weights / weights.sum(dim=1, keepdim=True)  # [R, K]
    reference = (weights.t()[..., None] * torch.stack(_every_block(model, rays))).sum(dim=0)
    assert torch.allclose(fused["rgb"], reference, atol=1e-5)
    assert fused["block_winner"].reshape(-1).long().tolist() == order[:, 0].tolist()
    blends = (weights > 0).sum(dim=1)
    assert bool((blends == 2).all()) and float(weights.max(dim=1).values.min()) < 0.99  # some rays do mix two blocks


def test_nearest_guarded_gives_the_global_model_where_the_nearest_block_learnt_nothing() -> None:
    rays = _rays()
    nearest, guarded = _scene_model("nearest", blocks_per_ray=1), _scene_model("nearest-guarded", blocks_per_ray=1)
    with torch.no_grad():
        glob = guarded.global_model.render_rays(rays, normals=False)
        expected, healthy = nearest.get_outputs(rays), guarded.get_outputs(rays)
    global_opaque = glob["accumulation"][:, 0] >= 0.5
    guarded_rays = (expected["accumulation"][:, 0] < 0.5) & global_opaque
    kept = ~guarded_rays
    assert torch.equal(healthy["rgb"][kept], expected["rgb"][kept])  # nearest's image wherever its block is opaque or both are not
    assert torch.allclose(healthy["rgb"][guarded_rays], glob["rgb"][guarded_rays], atol=1e-5)
    assert (healthy["block_winner"][guarded_rays] == -1).all() and (healthy["block_winner"][kept] >= 0).all()

    # Block 1 learnt nothing (it renders the background everywhere): the guard gives its rays to the global model.
    for model in (nearest, guarded):
        model.blocks["1"].field.decoder.density_bias = -100.0
    guarded.rays_rendered_by_block = {}
    with torch.no_grad():
        empty, rescued = nearest.get_outputs(rays), guarded.get_outputs(rays)
    ones = (expected["block_winner"][:, 0] == 1) & global_opaque
    assert int(ones.sum()) >= 10, "the test needs rays of block 1 where the global model is opaque"
    assert float(empty["accumulation"][ones].max()) < 1e-3  # nearest shows the empty block there
    assert torch.allclose(rescued["rgb"][ones], glob["rgb"][ones], atol=1e-5)
    assert torch.allclose(rescued["accumulation"][ones], glob["accumulation"][ones], atol=1e-5)
    assert (rescued["block_winner"][ones] == -1).all()
    assert sum(guarded.rays_rendered_by_block.values()) == 96  # still one block render per ray; the global model only where needed
    assert float(((rescued["rgb"] - glob["rgb"]) ** 2).mean()) < float(((empty["rgb"] - glob["rgb"]) ** 2).mean())


# ------------------------------------------------------------------------------ a block's occupancy from the global model


def test_unit_cube_to_world_inverts_the_contraction() -> None:
    from scalar_nerfstudio.fields.scalar_field import contract_to_unit_cube, unit_cube_to_world

    points = torch.cat([torch.rand(500, 3) * 2 - 1, (torch.rand(500, 3) * 2 - 1) * 50.0])
    assert torch.allclose(unit_cube_to_world(contract_to_unit_cube(points)), points, rtol=1e-3, atol=1e-4)
    corners = unit_cube_to_world(torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.5, 1.0]]))
    assert torch.isfinite(corners).all()


BALL_CENTRE = (0.5, 0.0, 0.0)


def _ball_global_model_and_fresh_block():
    """A global model whose density is a ball of radius 0.1 at :data:`BALL_CENTRE` (400 inside, empty
    elsewhere), and a fresh block around it (centre x = 0.4, radius 0.3), its grid not seeded yet."""
    from conftest import small_scalar_model

    from scalar_nerfstudio.fields.scalar_field import unit_cube_to_world
    from scalar_nerfstudio.models.scalar_model import ScalarModel

    ball = torch.tensor(BALL_CENTRE)
    global_model = small_scalar_model()

    def ball_density(unit: torch.Tensor, encoding=None):
        inside = torch.linalg.vector_norm(unit_cube_to_world(unit) - ball, dim=-1) < 0.1
        return 400.0 * inside.float(), torch.zeros(unit.shape[0], 15)

    global_model.field.density_at_unit = ball_density
    block = ScalarModel(config=global_model.config, scene_box=global_model.scene_box, num_train_data=2,
                        region_centre=(0.4, 0.0, 0.0), region_radius=0.3)
    return global_model, block


def test_a_block_grid_seeded_from_the_global_density_skips_empty_space_at_once() -> None:
    from scalar_nerfstudio.fields.scalar_field import contract_to_unit_cube

    global_model, block = _ball_global_model_and_fresh_block()
    ball = torch.tensor(BALL_CENTRE)
    assert not block.occupancy.pruning
    block.seed_occupancy_from(global_model)
    grid = block.occupancy
    assert grid.pruning and 0.0 < grid.occupied_fraction() < 0.05
    inside = contract_to_unit_cube(block._to_region(torch.stack([ball, torch.tensor([0.45, 0.05, 0.0])])))
    outside = contract_to_unit_cube(block._to_region(torch.tensor([[0.2, 0.0, 0.0], [0.4, 0.25, 0.1]])))
    assert grid.is_occupied(inside).all() and not grid.is_occupied(outside).any()
    occupied_before = grid.occupied.clone()
    grid.update(0, lambda unit: torch.zeros(unit.shape[0]))  # step 0 of the block: no warm-up re-opens every cell
    assert grid.pruning and torch.equal(grid.occupied, occupied_before)


def test_a_fresh_field_in_a_seeded_grid_gets_samples_until_it_has_settled() -> None:
    """A fresh block's field is nearly transparent where the global model (which seeded its grid) has
    a surface. Dropping its samples for that transparency from its first step left it without a
    sample, hence without a gradient, for good (the town at 2^8, 2026-11-27). For the grid's warm-up
    length it evaluates every sample in an occupied cell; after it, transparent samples are dropped
    as in any trained model."""
    global_model, block = _ball_global_model_and_fresh_block()
    block.field.decoder.density_bias = -12.0  # nearly transparent everywhere: alpha far below the threshold
    block.seed_occupancy_from(global_model)
    assert block.occupancy.pruning
    rays = ray_bundle(torch.tensor([[0.0, 0.0, 0.0]] * 4), torch.tensor([[1.0, 0.0, 0.0]] * 4))
    block.train()
    for step in (0, block.config.occupancy_warmup_steps - 1):
        block.update_occupancy(step)
        outputs = block.render_rays(rays)
        assert (outputs["samples_per_ray"] > 0).all(), step  # samples in the ball's cells are evaluated ...
        outputs["rgb"].sum().backward()
        assert block.field.encoder.table.grad.abs().sum() > 0  # ... so the fresh table learns
        block.zero_grad()
    block.update_occupancy(block.config.occupancy_warmup_steps)
    assert (block.render_rays(rays)["samples_per_ray"] == 0).all()  # settled: transparent samples are skipped


def test_global_rule_with_one_block_per_ray_is_the_surface_rule() -> None:
    rays = _rays()
    with torch.no_grad():
        global_one = _scene_model("global", blocks_per_ray=1).get_outputs(rays)
        surface_one = _scene_model("surface", blocks_per_ray=1).get_outputs(rays)
    assert torch.equal(global_one["rgb"], surface_one["rgb"]) and torch.equal(global_one["block_winner"], surface_one["block_winner"])


def test_a_block_started_from_the_global_model_renders_as_the_global_model() -> None:
    torch.manual_seed(0)
    blocks = (Block(index=0, image_indices=(1, 2), aabb_min=(-0.3, -0.3, -0.3), aabb_max=(0.3, 0.3, 0.3), centre=(0.0, 0.0, 0.0)),)
    config = ScalarSceneModelConfig(field=ScalarFieldConfig(**SMALL_FIELD), num_samples_per_ray=32, render_normals="never")
    model = ScalarSceneModel(config=config, scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=3,
                             split=BlockSplit(blocks=blocks, aabb_scale=(1.0, 1.0, 1.0), seed=0), block_init="global")
    with torch.no_grad():
        for parameter in model.global_model.parameters():
            parameter.copy_(torch.randn(parameter.shape) * 0.5)
        model.global_model.occupancy.update(0, model.global_model._density_no_grad)
    block = model.blocks["0"]
    assert block.region_radius == 1.0 and not block.region_centre.any()  # the global model's frame
    model.begin_block(0)
    model.eval()
    # the block's image j is the global model's image_indices[j]
    assert torch.equal(block.field.appearance.weight, model.global_model.field.appearance.weight[[1, 2]])
    assert torch.equal(block.occupancy.occupied, model.global_model.occupancy.occupied)
    with torch.no_grad():  # rendering uses the mean embedding: make the global model's mean the block's
        model.global_model.field.appearance.weight[0] = block.field.appearance.weight.mean(dim=0)
        model.global_model.field.appearance.weight[1:] = block.field.appearance.weight
        rays = _rays(32)
        assert torch.allclose(block.render_rays(rays, normals=False)["rgb"], model.global_model.render_rays(rays, normals=False)["rgb"], atol=1e-6)
    with pytest.raises(ValueError, match="block_init"):
        ScalarSceneModel(config=config, scene_box=model.scene_box, num_train_data=3,
                         split=BlockSplit(blocks=blocks, aabb_scale=(1.0, 1.0, 1.0), seed=0), block_init="copy")


def test_depth_from_the_occupancy_grid_is_close_to_the_fields() -> None:
    from conftest import small_scalar_model

    from scalar_nerfstudio.fields.scalar_field import unit_cube_to_world

    model = small_scalar_model(num_samples_per_ray=64, occupancy_warmup_steps=0)
    model.field.density_at_unit = lambda unit, encoding=None: (  # a wall filling x > 0.4
        200.0 * torch.sigmoid((unit_cube_to_world(unit)[:, 0] - 0.4) / 0.01), torch.zeros(unit.shape[0], 15))
    model.eval()
    for step in range(0, 16 * 8, 16):  # every cell seen (a quarter per update after the warm-up: several updates)
        model.update_occupancy(step)
    generator = torch.Generator().manual_seed(0)
    directions = torch.nn.functional.normalize(torch.cat([torch.ones(64, 1), (torch.rand(64, 2, generator=generator) - 0.5) * 0.4], dim=-1), dim=-1)
    rays = ray_bundle(torch.zeros(64, 3), directions)
    field = model.render_depth_only(rays, source="field")["depth"].reshape(-1)
    grid = model.render_depth_only(rays, source="grid")["depth"].reshape(-1)
    expected = 0.4 / directions[:, 0]
    assert torch.allclose(field, expected, atol=0.03)
    assert (grid - expected).abs().max() < 0.1 and bool(torch.isfinite(grid).all())  # within ~1.5 grid cells (4 / 64 wide)


def test_only_blocks_whose_cameras_observe_the_surface_are_chosen_and_unobserved_rays_are_global() -> None:
    model = _scene_model("surface", blocks_per_ray=1)
    rays = _rays()
    observation = torch.ones(3, 8**3, dtype=torch.bool)
    observation[1] = False  # block 1's cameras see none of the scene
    model.block_observation = observation
    with torch.no_grad():
        model.rays_rendered_by_block = {}
        model.get_outputs(rays)
    assert model.rays_rendered_by_block.get(1, 0) == 0 and sum(model.rays_rendered_by_block.values()) == 96
    model.block_observation = torch.zeros(3, 8**3, dtype=torch.bool)  # no block sees anything
    with torch.no_grad():
        fused = model.get_outputs(rays)
        alone = model.global_model.render_rays(rays, normals=False)
    assert torch.equal(fused["rgb"], alone["rgb"]) and bool((fused["block_winner"] == -1).all())
