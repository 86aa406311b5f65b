"""The town's layout: its street grid and its box buildings with their per-building appearance.

:func:`build_town` turns a :class:`~.config.TownConfig` into a :class:`Town` (deterministic in the
seed): a grid of streets (``blocks_x`` x ``blocks_y`` city blocks) lined with axis-aligned box
buildings of varied footprints and heights, enclosed by a ring of buildings so that every street
ends at a facade. Geometry is rounded to the millimetre, so scene.json records it exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, List, Tuple

import numpy as np

from scalar_nerfstudio.scenes.town.config import TownConfig

__all__ = ["STYLES", "Town", "build_town", "points_inside_buildings", "points_on_streets", "town_boxes"]

# Palettes (RGB in [0, 1]) each building draws its colours from.
_BRICK = np.array([(0.55, 0.25, 0.18), (0.62, 0.33, 0.22), (0.47, 0.22, 0.16), (0.72, 0.56, 0.38), (0.45, 0.30, 0.25)])
_PLASTER = np.array([(0.86, 0.78, 0.62), (0.78, 0.82, 0.86), (0.88, 0.70, 0.60), (0.70, 0.78, 0.65), (0.90, 0.88, 0.82), (0.80, 0.62, 0.45)])
_CONCRETE = np.array([(0.62, 0.62, 0.60), (0.55, 0.56, 0.58), (0.70, 0.68, 0.63)])
_TRIM = np.array([(0.92, 0.90, 0.85), (0.28, 0.28, 0.30), (0.55, 0.40, 0.28), (0.80, 0.80, 0.78), (0.35, 0.45, 0.35)])
_GLASS = np.array([(0.22, 0.32, 0.42), (0.28, 0.38, 0.40), (0.18, 0.22, 0.28), (0.32, 0.40, 0.50)])
_ROOF = np.array([(0.35, 0.33, 0.32), (0.45, 0.42, 0.38), (0.30, 0.30, 0.33), (0.50, 0.36, 0.30)])
#: Facade materials (:attr:`Town.style` indexes this).
STYLES = ("brick", "plaster", "concrete")


@dataclass(frozen=True, eq=False)
class Town:
    """The generated geometry and per-building appearance (B buildings, C cells).

    Buildings are sorted by cell (a city block or a piece of the ring); cell ``c`` holds boxes
    ``cell_start[c]:cell_start[c + 1]`` inside its bounding box ``cell_lo[c]..cell_hi[c]``.
    """

    config: TownConfig
    street_x: np.ndarray
    """[blocks_x + 1] x of the north-south street centre lines."""
    street_y: np.ndarray
    """[blocks_y + 1] y of the east-west street centre lines."""
    lo: np.ndarray
    """[B, 3] building minimum corners (z = 0)."""
    hi: np.ndarray
    """[B, 3] building maximum corners."""
    cell: np.ndarray
    """[B] cell of each building."""
    cell_lo: np.ndarray
    """[C, 3] cell bounding boxes, minimum corners."""
    cell_hi: np.ndarray
    """[C, 3] cell bounding boxes, maximum corners."""
    cell_start: np.ndarray
    """[C + 1] first building of each cell."""
    style: np.ndarray
    """[B] facade material: index into ("brick", "plaster", "concrete")."""
    wall: np.ndarray
    """[B, 3] wall base colour."""
    trim: np.ndarray
    """[B, 3] window frames, floor bands, parapet."""
    glass: np.ndarray
    """[B, 3] window glass."""
    roof: np.ndarray
    """[B, 3] roof colour."""
    floor_height: np.ndarray
    """[B] storey height."""
    window_pitch: np.ndarray
    """[B] horizontal spacing of the windows."""
    window_size: np.ndarray
    """[B, 2] window width and height."""
    sill: np.ndarray
    """[B] window sill height above each floor."""
    shops: np.ndarray
    """[B] bool: ground floor is a row of shop fronts with coloured signs."""
    texture_salt: int
    """Hash salt of the texture noise (from the seed)."""

    @property
    def num_buildings(self) -> int:
        return len(self.lo)


def _split_lots(rect: Tuple[float, float, float, float], rng: np.random.Generator, max_lot: float, min_lot: float) -> List[Tuple[float, float, float, float]]:
    """Recursively split ``(x0, y0, x1, y1)`` into lots no side longer than ``max_lot``."""
    x0, y0, x1, y1 = rect
    sx, sy = x1 - x0, y1 - y0
    if max(sx, sy) <= max_lot:
        return [rect]
    if sx >= sy:
        cut = x0 + sx * rng.uniform(0.35, 0.65)
        cut = min(max(cut, x0 + min_lot), x1 - min_lot)
        return _split_lots((x0, y0, cut, y1), rng, max_lot, min_lot) + _split_lots((cut, y0, x1, y1), rng, max_lot, min_lot)
    cut = y0 + sy * rng.uniform(0.35, 0.65)
    cut = min(max(cut, y0 + min_lot), y1 - min_lot)
    return _split_lots((x0, y0, x1, cut), rng, max_lot, min_lot) + _split_lots((x0, cut, x1, y1), rng, max_lot, min_lot)


def _strip_lots(rect: Tuple[float, float, float, float], along_x: bool, rng: np.random.Generator) -> List[Tuple[float, float, float, float]]:
    """Cut a ring strip ``(x0, y0, x1, y1)`` across its length into lots of 8-16 m."""
    x0, y0, x1, y1 = rect
    start, stop = (x0, x1) if along_x else (y0, y1)
    cuts = [start]
    while stop - cuts[-1] > 16.0:
        cuts.append(cuts[-1] + rng.uniform(8.0, 16.0))
    if stop - cuts[-1] < 4.0 and len(cuts) > 1:
        cuts.pop()
    cuts.append(stop)
    return [(a, y0, b, y1) if along_x else (x0, a, x1, b) for a, b in zip(cuts[:-1], cuts[1:])]


def build_town(config: TownConfig) -> Town:
    """Generate the town's streets and buildings from ``config`` (deterministic in ``config.seed``)."""
    rng = np.random.default_rng([config.seed, 0x70E1])
    half = config.street_width / 2.0
    pitch = config.block_size + config.street_width
    sx, sy = config.street_extent
    street_x = np.round(-sx / 2.0 + half + pitch * np.arange(config.blocks_x + 1), 6)
    street_y = np.round(-sy / 2.0 + half + pitch * np.arange(config.blocks_y + 1), 6)
    ring = config.ring_depth
    x_out = (street_x[0] - half - ring, street_x[-1] + half + ring)
    y_out = (street_y[0] - half - ring, street_y[-1] + half + ring)

    # Cells: the city blocks, then the ring cut at the street centre lines.
    cells: List[Tuple[Tuple[float, float, float, float], str]] = []
    for j in range(config.blocks_y):
        for i in range(config.blocks_x):
            cells.append(((street_x[i] + half, street_y[j] + half, street_x[i + 1] - half, street_y[j + 1] - half), "block"))
    xs = [x_out[0], *street_x.tolist(), x_out[1]]
    for a, b in zip(xs[:-1], xs[1:]):
        cells.append(((a, y_out[0], b, street_y[0] - half), "ring_x"))
        cells.append(((a, street_y[-1] + half, b, y_out[1]), "ring_x"))
    ys = [street_y[0] - half, *street_y[1:-1].tolist(), street_y[-1] + half]
    for a, b in zip(ys[:-1], ys[1:]):
        cells.append(((x_out[0], a, street_x[0] - half, b), "ring_y"))
        cells.append(((street_x[-1] + half, a, x_out[1], b), "ring_y"))

    boxes: List[Tuple[float, ...]] = []
    cell_of: List[int] = []
    attributes: List[Tuple[Any, ...]] = []
    cell_bounds: List[Tuple[float, ...]] = []
    for rect, kind in cells:
        cx0, cy0, cx1, cy1 = rect
        if kind == "block":
            lots = _split_lots(rect, rng, max_lot=18.0, min_lot=6.0)
        else:
            lots = _strip_lots(rect, along_x=kind == "ring_x", rng=rng)
        cell_boxes: List[Tuple[float, ...]] = []
        for x0, y0, x1, y1 in lots:
            if kind == "block" and rng.random() < 0.06:  # an empty lot: a small square
                continue
            bounds = [x0, y0, x1, y1]
            for side, (value, edge, sign) in enumerate(((x0, cx0, +1), (y0, cy0, +1), (x1, cx1, -1), (y1, cy1, -1))):
                on_street = abs(value - edge) < 1e-6
                if on_street:
                    inset = 0.0 if (kind != "block" or rng.random() < 0.75) else rng.uniform(0.5, 2.0)
                else:
                    inset = 0.0 if rng.random() < 0.55 else rng.uniform(0.3, 1.5)
                bounds[side] = value + sign * inset
            if bounds[2] - bounds[0] < 3.0 or bounds[3] - bounds[1] < 3.0:
                continue
            floor_height = rng.uniform(3.0, 3.6)
            floors = int(rng.integers(9, 15)) if (kind == "block" and rng.random() < 0.12) else int(rng.integers(2, 8 if kind == "block" else 7))
            height = floors * floor_height + rng.uniform(0.4, 1.0)
            style = int(rng.integers(0, 3))
            palette = (_BRICK, _PLASTER, _CONCRETE)[style]
            wall = palette[rng.integers(len(palette))] * rng.uniform(0.9, 1.1, size=3)
            window_pitch = rng.uniform(2.4, 3.6)
            window_w = min(rng.uniform(0.9, 1.6), window_pitch - 0.7)
            window_h = min(rng.uniform(1.3, 1.9), floor_height - 1.2)
            sill = rng.uniform(0.75, 0.95)
            shops = bool(rng.random() < 0.55)
            attributes.append((
                style, wall, _TRIM[rng.integers(len(_TRIM))], _GLASS[rng.integers(len(_GLASS))], _ROOF[rng.integers(len(_ROOF))],
                floor_height, window_pitch, (window_w, window_h), sill, shops,
            ))
            cell_boxes.append((bounds[0], bounds[1], 0.0, bounds[2], bounds[3], height))
        if not cell_boxes:
            continue
        boxes.extend(cell_boxes)
        cell_of.extend([len(cell_bounds)] * len(cell_boxes))
        top = max(b[5] for b in cell_boxes)
        cell_bounds.append((min(b[0] for b in cell_boxes), min(b[1] for b in cell_boxes), 0.0, max(b[3] for b in cell_boxes), max(b[4] for b in cell_boxes), top))

    box_array = np.round(np.array(boxes, dtype=np.float64), 3)  # millimetre geometry: exact in scene.json
    cell_array = np.round(np.array(cell_bounds, dtype=np.float64), 3)
    cell = np.array(cell_of, dtype=np.int64)
    counts = np.bincount(cell, minlength=len(cell_array))
    column = list(zip(*attributes))
    return Town(
        config=config,
        street_x=street_x,
        street_y=street_y,
        lo=box_array[:, :3].copy(),
        hi=box_array[:, 3:].copy(),
        cell=cell,
        cell_lo=cell_array[:, :3].copy(),
        cell_hi=cell_array[:, 3:].copy(),
        cell_start=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        style=np.array(column[0], dtype=np.int64),
        wall=np.clip(np.array(column[1]), 0.0, 1.0),
        trim=np.array(column[2]),
        glass=np.array(column[3]),
        roof=np.array(column[4]),
        floor_height=np.array(column[5]),
        window_pitch=np.array(column[6]),
        window_size=np.array(column[7]),
        sill=np.array(column[8]),
        shops=np.array(column[9], dtype=bool),
        texture_salt=int(rng.integers(1, 2**31)),
    )


def town_boxes(town: Town) -> np.ndarray:
    """[B, 2, 3] every building's minimum and maximum corner (metres)."""
    return np.stack([town.lo, town.hi], axis=1)


def points_inside_buildings(points: np.ndarray, town: Town, margin: float = 0.0) -> np.ndarray:
    """[N, 3] points -> [N] bool: inside a building grown by ``margin`` metres on every side."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    inside = np.zeros(len(points), dtype=bool)
    for start in range(0, len(points), 4096):
        p = points[start : start + 4096, None, :]
        inside[start : start + 4096] = ((p >= town.lo[None] - margin) & (p <= town.hi[None] + margin)).all(axis=-1).any(axis=1)
    return inside


def points_on_streets(points: np.ndarray, town: Town) -> np.ndarray:
    """[N, 2 or 3] points -> [N] bool: (x, y) lies on a street of the grid (between building lines)."""
    points = np.asarray(points, dtype=np.float64)
    x, y = points[:, 0], points[:, 1]
    half = town.config.street_width / 2.0
    ax = np.abs(x[:, None] - town.street_x[None]).min(axis=1)
    ay = np.abs(y[:, None] - town.street_y[None]).min(axis=1)
    inside_grid = (x >= town.street_x[0] - half) & (x <= town.street_x[-1] + half) & (y >= town.street_y[0] - half) & (y <= town.street_y[-1] + half)
    return inside_grid & ((ax < half) | (ay < half))
