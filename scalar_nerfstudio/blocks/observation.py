"""The space each block's cameras observe: the region a block models, for choosing blocks per ray.

A block's camera box (Alg. 1) says where its cameras stand, not what they see: on a ring of cameras
looking inward (castle-P30), the wall a view shows lies outside every camera box, and the box nearest
to it belongs to the cameras standing under that wall and looking away from it. Here a block observes
a cell of a coarse grid over the global model's contracted cube when the cell's centre projects into
one of the block's training images, in front of its camera (no occlusion test: a cell a block could
see counts). The grid is dilated by one cell, so a block is never denied a cell it partly sees.

Pure torch, CPU or GPU; cameras are nerfstudio's (OpenGL camera-to-world, looking down -z).
"""

from __future__ import annotations

from typing import Any, Optional, Sequence

import torch
from torch import Tensor

from scalar_nerfstudio.fields.scalar_field import contract_to_unit_cube, unit_cube_to_world
from scalar_nerfstudio.model_components.sampling import cell_coordinates, flat_cell_indices

#: Cells per axis of the observation grid over the contracted unit cube (the inner ball |x| <= 1,
#: where the cameras are, spans half of it: 16 cells, 1/8 of the camera layout each).
OBSERVATION_RESOLUTION = 32
_CHUNK = 1 << 15


def grid_cell_centres(resolution: int) -> Tensor:
    """[G^3, 3] world positions of the cell centres of a G^3 grid over the contracted unit cube."""
    return unit_cube_to_world((cell_coordinates(torch.arange(resolution**3), resolution) + 0.5) / resolution)


def grid_cell_indices(points: Tensor, resolution: int) -> Tensor:
    """[N, 3] world points -> [N] flat indices of their cells (non-finite points: the cube's edge cells)."""
    return flat_cell_indices(contract_to_unit_cube(points.float()), resolution)


def seen_by_any(points: Tensor, camera_to_worlds: Tensor, *, fx: Tensor, fy: Tensor, cx: Tensor, cy: Tensor,
                width: Tensor, height: Tensor) -> Tensor:
    """[P] bool: the point [P, 3] projects inside at least one of the N images, in front of its camera.

    Args:
        camera_to_worlds: [N, 3, 4] OpenGL poses (x right, y up, looking down -z).
        fx, fy, cx, cy, width, height: [N] intrinsics in pixels.
    """
    seen = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    if camera_to_worlds.shape[0] == 0:
        return seen
    rotations = camera_to_worlds[:, :3, :3].float()  # [N, 3, 3]
    centres = camera_to_worlds[:, :3, 3].float()  # [N, 3]
    for start in range(0, points.shape[0], _CHUNK):
        chunk = points[start:start + _CHUNK].float()
        local = torch.einsum("nji,npj->npi", rotations, chunk[None] - centres[:, None])  # [N, P, 3] R^T (p - c)
        depth = -local[..., 2]
        safe = depth.clamp_min(1e-9)
        u = fx.float()[:, None] * local[..., 0] / safe + cx.float()[:, None]
        v = -fy.float()[:, None] * local[..., 1] / safe + cy.float()[:, None]
        inside = (depth > 0) & (u >= 0) & (u < width.float()[:, None]) & (v >= 0) & (v < height.float()[:, None])
        seen[start:start + _CHUNK] = inside.any(dim=0)
    return seen


def block_observation(camera_to_worlds: Tensor, *, fx: Tensor, fy: Tensor, cx: Tensor, cy: Tensor, width: Tensor, height: Tensor,
                      block_images: Sequence[Sequence[int]], resolution: int = OBSERVATION_RESOLUTION) -> Tensor:
    """[K, G^3] bool: the cells each block's training images observe, dilated by one cell.

    Args:
        camera_to_worlds, fx, fy, cx, cy, width, height: the training cameras ([N, 3, 4] and [N]).
        block_images: for each block, the indices of its training images (into the N cameras).
    """
    centres = grid_cell_centres(resolution).to(camera_to_worlds.device)
    observed = []
    for images in block_images:
        index = torch.as_tensor(list(images), dtype=torch.long, device=camera_to_worlds.device)
        seen = seen_by_any(centres, camera_to_worlds[index], fx=fx[index], fy=fy[index], cx=cx[index], cy=cy[index], width=width[index],
                           height=height[index])
        grid = seen.reshape(1, 1, resolution, resolution, resolution).float()
        dilated = torch.nn.functional.max_pool3d(grid, kernel_size=3, stride=1, padding=1) > 0
        observed.append(dilated.reshape(-1))
    return torch.stack(observed) if observed else torch.zeros(0, resolution**3, dtype=torch.bool)


def split_observation(cameras: Any, block_images: Sequence[Sequence[int]]) -> Optional[Tensor]:
    """[K, G^3] bool (:func:`block_observation`) of the training ``cameras`` (nerfstudio's ``Cameras``: ``camera_to_worlds``
    [N, 3, 4] and [N, 1] intrinsics) split into the blocks' ``block_images``; None for one block (nothing to choose)."""
    if len(block_images) <= 1:
        return None
    flat = {name: getattr(cameras, name).reshape(-1) for name in ("fx", "fy", "cx", "cy", "width", "height")}
    return block_observation(cameras.camera_to_worlds, **flat, block_images=block_images)


def observed_at(observation: Tensor, points: Tensor) -> Tensor:
    """[K, N] bool: whether each block observes the cell of each world point [N, 3]."""
    resolution = round(observation.shape[1] ** (1.0 / 3.0))
    if resolution**3 != observation.shape[1]:
        raise ValueError(f"observation must be [K, G^3], got {list(observation.shape)}")
    return observation[:, grid_cell_indices(points, resolution).to(observation.device)]
