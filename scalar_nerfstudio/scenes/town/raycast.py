"""Ray casting the town: the first surface (ground or building face) along each ray.

Rays are tested against the ground plane and against the buildings with a slab test vectorised over
boxes. The boxes are grouped by cell (a city block or a piece of the ring), the cells taken nearest
first, and a ray only tests a cell whose bounding box it enters before its current hit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from scalar_nerfstudio.scenes.town.layout import Town

__all__ = ["CHUNK_RAYS", "GROUND", "SKY", "TownHits", "intersect_town"]

#: Rays cast at once: bounds the temporaries ([rays, boxes of a cell] at most 2^18 entries).
CHUNK_RAYS = 16384

# Ids of the two surfaces that are no building, in TownHits.surface.
GROUND = -1
SKY = -2


@dataclass(frozen=True)
class TownHits:
    """First surface along each of N rays."""

    depth: np.ndarray
    """[N] distance along the normalised ray (inf: sky)."""
    surface: np.ndarray
    """[N] building index, GROUND (-1) or SKY (-2)."""
    axis: np.ndarray
    """[N] axis of the hit face's normal (0, 1, 2; -1 for sky)."""
    normal: np.ndarray
    """[N, 3] outward unit normal of the hit face (0 for sky)."""


def _safe_inverse(directions: np.ndarray) -> np.ndarray:
    """[P, 3] -> [P, 3] 1 / d, with components of |d| < 1e-12 treated as +-1e-12 (no NaN in slabs)."""
    tiny = np.where(directions < 0, -1e-12, 1e-12)
    return 1.0 / np.where(np.abs(directions) < 1e-12, tiny, directions)


def _slab(origins: np.ndarray, inverse: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Rays [P, 3] (origins, 1 / directions) vs boxes [M, 3] -> ([P, M] entry t, [P, M] exit t).

    One axis at a time on [P, M] arrays (no reductions over a length-3 axis, which numpy does slowly).
    """

    def axis(k: int) -> Tuple[np.ndarray, np.ndarray]:
        """[P, M] entry and exit t of the slabs along axis ``k``."""
        t0 = (lo[None, :, k] - origins[:, None, k]) * inverse[:, None, k]
        t1 = (hi[None, :, k] - origins[:, None, k]) * inverse[:, None, k]
        return np.minimum(t0, t1), np.maximum(t0, t1)

    near, far = axis(0)
    for k in (1, 2):
        lower, upper = axis(k)
        np.maximum(near, lower, out=near)
        np.minimum(far, upper, out=far)
    return near, far


def _entry_axis(origins: np.ndarray, inverse: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Rays [P, 3] vs one box each ([P, 3] corners) -> [P] axis of the face the ray enters through."""
    t0 = (lo - origins) * inverse
    t1 = (hi - origins) * inverse
    return np.minimum(t0, t1).argmax(axis=1)


def intersect_town(origins: np.ndarray, directions: np.ndarray, town: Town, *, chunk_rays: Optional[int] = None,
                   min_t: float = 1e-6) -> TownHits:
    """First hit of each ray with the ground (z = 0) or a building.

    Args:
        origins: [N, 3] ray origins (metres), outside the buildings (a ray starting inside a
            building does not see that building).
        directions: [N, 3] ray directions (normalised here; depth is along the unit direction).
        town: the town.
        chunk_rays: rays per chunk (bounds the memory; default 16384).
        min_t: hits closer than this are ignored.
    """
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if origins.shape != directions.shape:
        raise ValueError(f"intersect_town: origins {origins.shape} and directions {directions.shape} differ in shape")
    norms = np.linalg.norm(directions, axis=1, keepdims=True)
    if not (np.isfinite(origins).all() and np.isfinite(directions).all() and (norms > 0).all()):
        raise ValueError("intersect_town: ray origins and directions must be finite, directions non-zero")
    directions = directions / norms
    n = len(origins)
    chunk = chunk_rays or CHUNK_RAYS
    depth = np.full(n, np.inf)
    surface = np.full(n, SKY, dtype=np.int64)
    axis = np.full(n, -1, dtype=np.int64)
    for start in range(0, n, chunk):
        stop = min(start + chunk, n)
        o, d = origins[start:stop], directions[start:stop]
        inv = _safe_inverse(d)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_ground = np.where((d[:, 2] < -1e-12) & (o[:, 2] > 0), -o[:, 2] / d[:, 2], np.inf)
        t = t_ground
        s = np.where(np.isfinite(t_ground), GROUND, SKY)
        a = np.where(np.isfinite(t_ground), 2, -1)
        # Cells nearest to the chunk's mean origin first (for one camera's rays: exact front-to-back
        # order). A cell is only tested against rays that can still reach it: not stopped before
        # the lower bound of their distance to it, nor above every building.
        centre = o.mean(axis=0)
        spread = float(np.linalg.norm(o - centre, axis=1).max())
        gap = np.linalg.norm(np.maximum(np.maximum(town.cell_lo - centre, centre - town.cell_hi), 0.0), axis=1)
        top = float(town.cell_hi[:, 2].max())
        with np.errstate(divide="ignore", invalid="ignore"):
            t_top = np.where(d[:, 2] > 1e-12, (top - o[:, 2]) / d[:, 2], np.inf)  # < 0: above every building, going up
        for c in np.argsort(gap, kind="stable"):
            bound = gap[c] - spread
            reach = np.minimum(t, t_top)
            if bound >= reach.max():
                break
            active = np.flatnonzero(reach > bound)
            near, far = _slab(o[active], inv[active], town.cell_lo[c : c + 1], town.cell_hi[c : c + 1])
            near = np.maximum(near[:, 0], 0.0)
            rays = active[(far[:, 0] >= near) & (near < t[active])]
            if len(rays) == 0:
                continue
            b0, b1 = int(town.cell_start[c]), int(town.cell_start[c + 1])
            step = max(256, (1 << 18) // max(b1 - b0, 1))
            for r0 in range(0, len(rays), step):
                r = rays[r0 : r0 + step]
                near, far = _slab(o[r], inv[r], town.lo[b0:b1], town.hi[b0:b1])
                hit_t = np.where((far >= near) & (near > min_t), near, np.inf)
                k = hit_t.argmin(axis=1)
                rows = np.arange(len(r))
                best = hit_t[rows, k]
                closer = best < t[r]
                if not closer.any():
                    continue
                rc = r[closer]
                t[rc] = best[closer]
                s[rc] = b0 + k[closer]
        boxes = np.flatnonzero(s >= 0)
        if len(boxes):
            a[boxes] = _entry_axis(o[boxes], inv[boxes], town.lo[s[boxes]], town.hi[s[boxes]])
        depth[start:stop], surface[start:stop], axis[start:stop] = t, s, a
    normal = np.zeros((n, 3))
    hit = axis >= 0
    rows = np.flatnonzero(hit)
    normal[rows, axis[hit]] = -np.sign(directions[rows, axis[hit]])
    return TownHits(depth=depth, surface=surface, axis=axis, normal=normal)
