"""How many blocks a scene needs and how large each block's hash table is, from the camera layout.

The rule
--------
A hash-grid level of ``T`` rows stores, without collisions, a surface of ``sqrt(T) x sqrt(T)``
cells (scenes are surfaces; a 2^19 table holds a 724 x 724 sheet). What the images can resolve
is set by the training resolution: at the cameras' viewing distance ``d`` one pixel spans
``d / f`` (``f``: focal length in training pixels), so the whole camera layout, of largest extent
``L``, is

    R = f * L / d   pixels across

and a model that resolves it needs ``R * R`` surface cells. So

* **number of blocks** ``K = ceil(R^2 / T)``, at most ``num_images // min_images_per_block`` (a block
  needs images to train) and ``max_blocks``, at least 1. An object-centric capture (cameras around
  an object at the distance they see it from: ``L / d`` ~ 1.5) stays at ``R`` ~ 1.5 image widths,
  so K = 1 there; a walk around a courtyard seen from a fraction of its size gives ``L / d`` > 2
  and, at full resolution, K > 1.
* **table of block k**: ``log2 T_k = ceil(log2(min(R_k^2, P_k)))`` within ``[min, max]``, where
  ``R_k = f * L_k / d`` is the block's own extent in pixels (``L_k``: its scaled AABB's largest
  extent) and ``P_k`` the pixels of its training images (a table with more rows than observed
  pixels cannot be filled).
* **finest resolution of block k**: ``2 * R_k`` cells per side, within ``[min, max]``: the local
  model's frame maps the block's AABB to the inner half of the contracted cube, so the cube needs
  twice the block's pixels across.

The viewing distance ``d`` is the median distance, along each camera's optical axis, to the point
the axes pass closest to (least squares). When the axes do not converge in front of the cameras
(parallel views: aerial nadir strips, a forward-looking drive), or that point lies off the axis of
most cameras (a street capture looking every way), ``d`` falls back to ``L / 2``.
All lengths are in the units of the camera centres (the ratios do not depend on them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Tuple

import numpy as np

__all__ = ["BlockCapacity", "LayoutScale", "auto_num_blocks", "block_capacity", "layout_scale"]

#: The least-squares convergence point is used when the optical axes' normal matrix is this well
#: conditioned (smallest / largest eigenvalue); below it the axes are (nearly) parallel.
MIN_CONVERGENCE_CONDITION: float = 1e-3
#: ... and when at least half the cameras have the point less than this ratio of its distance off
#: their axis (tan 63 degrees). Object and courtyard captures: 75-100 % of the cameras; the town's
#: street captures: 34-37 %.
MAX_CONVERGENCE_OFFSET: float = 2.0


@dataclass(frozen=True)
class LayoutScale:
    """How large the camera layout looks at the training resolution.

    Attributes:
        extent: largest axis-aligned extent of the camera centres (scene units).
        viewing_distance: typical camera-to-content distance ``d`` (scene units).
        focal_px: median focal length in training pixels.
        converged: whether ``d`` came from the optical axes' convergence point (else ``extent / 2``).
    """

    extent: float
    viewing_distance: float
    focal_px: float
    converged: bool

    @property
    def pixel_size(self) -> float:
        """Scene units one pixel spans at the viewing distance."""
        return self.viewing_distance / self.focal_px

    def pixels_across(self, extent: float) -> float:
        """Pixels (at the viewing distance, training resolution) that ``extent`` scene units span."""
        return extent / self.pixel_size

    @property
    def layout_pixels(self) -> float:
        """R: pixels the whole camera layout spans."""
        return self.pixels_across(self.extent)


@dataclass(frozen=True)
class BlockCapacity:
    """A block model's hash-table size and finest grid resolution."""

    log2_hashmap_size: int
    max_resolution: int


def layout_scale(centres: np.ndarray, directions: np.ndarray, focal_px: np.ndarray) -> LayoutScale:
    """Extent, viewing distance and focal length of a camera layout.

    Args:
        centres: [N, 3] camera centres.
        directions: [N, 3] viewing directions (optical axes; normalised here).
        focal_px: [N] focal lengths in training pixels.
    """
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    focal = np.asarray(focal_px, dtype=np.float64).reshape(-1)
    if not (len(centres) == len(directions) == len(focal) and len(centres) > 0):
        raise ValueError(f"layout_scale: {len(centres)} centres, {len(directions)} directions, {len(focal)} focal lengths")
    if not (np.isfinite(centres).all() and np.isfinite(directions).all() and np.isfinite(focal).all() and (focal > 0).all()):
        raise ValueError("layout_scale: camera centres, directions and focal lengths must be finite (focal > 0)")
    norms = np.linalg.norm(directions, axis=1, keepdims=True)
    if (norms <= 0).any():
        raise ValueError("layout_scale: a camera has a zero viewing direction")
    directions = directions / norms
    extent = float((centres.max(axis=0) - centres.min(axis=0)).max())
    if extent <= 0:  # every camera at one place: the layout is a point, one block
        return LayoutScale(extent=0.0, viewing_distance=1.0, focal_px=float(np.median(focal)), converged=False)
    # Least-squares point closest to all optical axes: sum (I - z z^T) p = sum (I - z z^T) c.
    projectors = np.eye(3)[None] - directions[:, :, None] * directions[:, None, :]  # [N, 3, 3]
    normal = projectors.sum(axis=0)
    eigenvalues = np.linalg.eigvalsh(normal)
    distance = extent / 2.0
    converged = False
    if eigenvalues[0] > MIN_CONVERGENCE_CONDITION * eigenvalues[-1]:
        point = np.linalg.solve(normal, (projectors @ centres[:, :, None]).sum(axis=0)).reshape(3)
        offsets = point[None] - centres  # [N, 3]
        along_axis = (offsets * directions).sum(axis=1)  # [N]
        across_axis = np.linalg.norm(offsets - along_axis[:, None] * directions, axis=1)  # [N]
        # The axes must pass near the point, not only have it in front: a street capture's axes spread
        # over every direction and have a least-squares point that no camera looks at.
        in_view = across_axis < MAX_CONVERGENCE_OFFSET * np.maximum(along_axis, 0.0)
        if np.median(along_axis) > 0 and np.mean(in_view) >= 0.5:
            distance = float(np.median(along_axis))
            converged = True
    return LayoutScale(extent=extent, viewing_distance=max(distance, 1e-6 * extent), focal_px=float(np.median(focal)), converged=converged)


def auto_num_blocks(scale: LayoutScale, *, log2_hashmap_size: int, num_images: int, min_images_per_block: int, max_blocks: int) -> int:
    """``ceil(R^2 / T)`` blocks for a layout ``R`` pixels across and tables of ``T`` rows, within
    ``[1, min(max_blocks, num_images // min_images_per_block)]``."""
    if min_images_per_block < 1 or max_blocks < 1:
        raise ValueError("auto_num_blocks: min_images_per_block and max_blocks must be >= 1")
    pixels = scale.layout_pixels
    wanted = math.ceil(pixels * pixels / float(1 << log2_hashmap_size)) if pixels > 0 else 1
    return max(1, min(wanted, max_blocks, num_images // min_images_per_block))


def block_capacity(
    scale: LayoutScale,
    *,
    block_extent: float,
    block_pixels: int,
    log2_hashmap_bounds: Tuple[int, int],
    max_resolution_bounds: Tuple[int, int],
) -> BlockCapacity:
    """Table size and finest resolution for a block ``block_extent`` scene units wide seen in
    ``block_pixels`` training pixels (see the module docstring)."""
    low, high = log2_hashmap_bounds
    res_low, res_high = max_resolution_bounds
    if not (1 <= low <= high and 1 <= res_low <= res_high):
        raise ValueError(f"block_capacity: bounds must be ordered and positive, got {log2_hashmap_bounds} and {max_resolution_bounds}")
    pixels = scale.pixels_across(block_extent)
    cells = max(min(pixels * pixels, float(block_pixels)), 2.0)
    log2_size = min(max(math.ceil(math.log2(cells)), low), high)
    resolution = min(max(int(math.ceil(2.0 * pixels)), res_low), res_high)
    return BlockCapacity(log2_hashmap_size=log2_size, max_resolution=resolution)
