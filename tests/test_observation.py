"""Which space each block's cameras observe (blocks/observation.py), and choosing blocks per ray by it:
on an inward-looking ring the block whose cameras see a wall is chosen, not the one standing under
it; on a forward-facing street the block that sees a point is never dropped."""

from __future__ import annotations

import math
from typing import Dict

import torch

from scalar_nerfstudio.blocks.observation import (
    block_observation,
    grid_cell_centres,
    grid_cell_indices,
    observed_at,
    seen_by_any,
)
from scalar_nerfstudio.fusion import region_scores, select_blocks

FOCAL, SIZE = 50.0, 100  # 90 degrees wide


def _looking_along(direction, position) -> torch.Tensor:
    """[3, 4] OpenGL camera-to-world pose at ``position`` looking along ``direction`` (z up in the world)."""
    forward = torch.nn.functional.normalize(torch.tensor(direction, dtype=torch.float32), dim=0)
    up_world = torch.tensor([0.0, 0.0, 1.0])
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, up_world), dim=0)
    up = torch.linalg.cross(right, forward)
    return torch.cat([torch.stack([right, up, -forward], dim=1), torch.tensor(position, dtype=torch.float32)[:, None]], dim=1)


def _intrinsics(n: int) -> Dict[str, torch.Tensor]:
    full = lambda value: torch.full((n,), float(value))  # noqa: E731
    return {"fx": full(FOCAL), "fy": full(FOCAL), "cx": full(SIZE / 2), "cy": full(SIZE / 2), "width": full(SIZE), "height": full(SIZE)}


def test_a_point_is_seen_in_front_of_a_camera_inside_its_image_only() -> None:
    pose = _looking_along((1.0, 0.0, 0.0), (0.0, 0.0, 0.0))[None]
    points = torch.tensor([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0], [0.5, 0.4, 0.0], [0.5, 0.6, 0.0], [0.5, 0.0, -0.45]])
    # in front; behind; inside the 90-degree cone; outside it; inside vertically
    assert seen_by_any(points, pose, **_intrinsics(1)).tolist() == [True, False, True, False, True]


def test_grid_cells_are_indexed_consistently_with_their_centres() -> None:
    centres = grid_cell_centres(8)
    cells = torch.arange(8**3)
    unit = (torch.stack([cells // 64, (cells // 8) % 8, cells % 8], dim=-1).float() + 0.5) / 8
    reachable = torch.linalg.vector_norm((unit - 0.5) * 4.0, dim=-1) < 1.99  # the cube's corners lie outside the contracted ball
    assert torch.equal(grid_cell_indices(centres[reachable], 8), cells[reachable])
    assert torch.isfinite(centres).all()
    extreme = torch.tensor([[float("inf"), 0.0, 0.0], [float("nan")] * 3, [1e30, -1e30, 0.0]])
    assert ((grid_cell_indices(extreme, 8) >= 0) & (grid_cell_indices(extreme, 8) < 8**3)).all()


def test_on_an_inward_ring_the_wall_goes_to_the_block_that_sees_it_not_the_nearest_box() -> None:
    """Block 0 stands at x = -0.8 looking +x, block 1 at x = +0.8 looking -x. A point on the wall at
    x = +0.95 is nearest block 1's camera box, but only block 0's cameras see it."""
    poses = torch.stack([_looking_along((1.0, 0.0, 0.0), (-0.8, y, 0.0)) for y in (-0.1, 0.1)]
                        + [_looking_along((-1.0, 0.0, 0.0), (0.8, y, 0.0)) for y in (-0.1, 0.1)])
    observation = block_observation(poses, **_intrinsics(4), block_images=[(0, 1), (2, 3)])
    wall = torch.tensor([[0.95, 0.0, 0.0], [-0.95, 0.05, 0.1]])
    usable = observed_at(observation, wall)
    assert usable.tolist() == [[True, False], [False, True]]
    centres, radii = torch.tensor([[-0.8, 0.0, 0.0], [0.8, 0.0, 0.0]]), torch.tensor([0.2, 0.2])
    scores = region_scores(wall, centres, radii)
    assert select_blocks(scores, 1)[:, 0].tolist() == [False, True], "by its box alone the wrong block is chosen"
    chosen = select_blocks(torch.where(usable, scores, torch.full_like(scores, math.inf)), 1, usable)
    assert chosen.tolist() == [[True, False], [False, True]]


def test_on_a_forward_facing_street_a_block_is_never_denied_what_its_cameras_see() -> None:
    """Cameras along a street at x = 0 look at a facade at x = 0.6; two blocks split them by y. Every
    facade point a block's cameras see is observed by that block."""
    poses = torch.stack([_looking_along((1.0, 0.0, 0.0), (0.0, y, 0.0)) for y in torch.linspace(-0.8, 0.8, 8).tolist()])
    blocks = [tuple(range(4)), tuple(range(4, 8))]
    observation = block_observation(poses, **_intrinsics(8), block_images=blocks)
    generator = torch.Generator().manual_seed(0)
    facade = torch.cat([torch.full((400, 1), 0.6), torch.rand(400, 2, generator=generator) * 1.6 - 0.8], dim=1)
    for index, images in enumerate(blocks):
        index_tensor = torch.tensor(images)
        seen = seen_by_any(facade, poses[index_tensor], **{k: t[index_tensor] for k, t in _intrinsics(8).items()})
        assert seen.any()
        assert observed_at(observation, facade)[index][seen].all()
