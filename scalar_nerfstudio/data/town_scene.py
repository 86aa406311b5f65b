"""A large procedural town written in nerfstudio format: the project's own scene that is too big
for one hash table.

The town is a grid of streets (``blocks_x`` x ``blocks_y`` city blocks) lined with axis-aligned box
buildings of varied footprints and heights, enclosed by a ring of buildings so that every street
ends at a facade. Street-level cameras (1.5-2 m high) drive the streets on a rig, as in Block-NeRF's
capture: the vehicle stops at even intervals and each of its cameras (by default two, 30 degrees
left and right of the driving direction) takes a frame (``capture="rig"``). The older ``walk``
capture (one frame per position, random heading) stays available. The ``aerial`` capture flies a
drone over the whole town in parallel flight lines (a survey's lawnmower), looking down, 6-14
degrees forward of the vertical: each frame sees a patch of roofs and streets a few tens of metres across,
so the cameras of one block see mostly that block's part of the town (the regime of the paper's
large-area captures, where blocks split the scene's content and not only its views).

Everything is ray-cast with numpy: rays against the ground plane and against the buildings (a slab
test vectorised over boxes; the boxes are grouped by city block, the blocks taken nearest first,
and a ray only tests a block whose bounding box it enters before its current hit). The texture is a pure function of the 3-D
hit point and of the surface it lies on (building, face), so every view agrees (multi-view
consistent) and the lighting is fixed (Lambertian, a sun that does not move). It has detail at
several scales, from asphalt speckle (4 cm), bricks (7.5 x 22.5 cm), pavement tiles and sign
lettering (~10 cm) through window frames and mullions, windows (~1 m) and floors (~3 m) to whole
buildings (10-40 m): more than a small hash table can hold.

Output (``write_town``)::

    OUT/transforms.json        nerfstudio format (OPENCV, no distortion; OpenGL camera axes)
    OUT/images/frame_XXXXX.png RGB, frames numbered along the walk
    OUT/depths/frame_XXXXX.png 16-bit depth in millimetres along the optical axis (z-depth, the
                               convention of nerfstudio's depth loaders, is_euclidean_depth=False);
                               0 = sky or farther than 65.535 m
    OUT/scene.json             generator options, streets and the list of boxes

The frames are numbered in walking order, so nerfstudio's ``--eval-mode interval
--eval-interval 8`` holds out every 8th frame along the same paths (nerfstudio sorts frames by file
name). The exact float depth of any frame is available again with :func:`load_town` and
:func:`render_town_image`.

The module needs only numpy and PIL (a progress bar uses rich or tqdm when installed).
"""

from __future__ import annotations

import ctypes
import json
import math
import multiprocessing
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np
from PIL import Image

__all__ = [
    "DEPTH_PNG_UNIT_M",
    "Town",
    "TownConfig",
    "TownHits",
    "blocks_for_extent",
    "build_town",
    "intersect_town",
    "iter_frames",
    "load_town",
    "points_inside_buildings",
    "points_on_streets",
    "read_depth_png",
    "render_town_image",
    "render_town_rays",
    "town_boxes",
    "town_camera_poses",
    "town_intrinsics",
    "write_town",
]

#: Generator version written to scene.json (bump when the same options give other pixels).
#: Version 2 added the ``rig`` capture (the default); version 1 scenes (``walk``) still load.
GENERATOR_VERSION = 2
#: Generator versions whose scene.json :func:`load_town` reads.
READABLE_VERSIONS = (1, 2)
#: The ways the cameras capture the town (:attr:`TownConfig.capture`).
CAPTURES = ("rig", "walk", "aerial")
#: Metres per unit of the 16-bit depth PNGs (nerfstudio's default ``depth_unit_scale_factor``).
DEPTH_PNG_UNIT_M = 1e-3
#: The largest depth a 16-bit PNG in millimetres holds; farther points are written as 0 (unknown).
DEPTH_PNG_MAX_M = 65535 * DEPTH_PNG_UNIT_M

#: Rays cast at once: bounds the temporaries ([rays, boxes of a cell] at most 2^18 entries).
_CHUNK_RAYS = 16384

# Ids of the two surfaces that are no building, in TownHits.surface.
GROUND = -1
SKY = -2

_SUN = np.array([0.5, 0.35, 0.79]) / np.linalg.norm([0.5, 0.35, 0.79])
_SKY_ZENITH = np.array([0.30, 0.50, 0.85])
_SKY_HORIZON = np.array([0.82, 0.88, 0.95])

_BRICK = np.array([(0.55, 0.25, 0.18), (0.62, 0.33, 0.22), (0.47, 0.22, 0.16), (0.72, 0.56, 0.38), (0.45, 0.30, 0.25)])
_PLASTER = np.array([(0.86, 0.78, 0.62), (0.78, 0.82, 0.86), (0.88, 0.70, 0.60), (0.70, 0.78, 0.65), (0.90, 0.88, 0.82), (0.80, 0.62, 0.45)])
_CONCRETE = np.array([(0.62, 0.62, 0.60), (0.55, 0.56, 0.58), (0.70, 0.68, 0.63)])
_TRIM = np.array([(0.92, 0.90, 0.85), (0.28, 0.28, 0.30), (0.55, 0.40, 0.28), (0.80, 0.80, 0.78), (0.35, 0.45, 0.35)])
_GLASS = np.array([(0.22, 0.32, 0.42), (0.28, 0.38, 0.40), (0.18, 0.22, 0.28), (0.32, 0.40, 0.50)])
_ROOF = np.array([(0.35, 0.33, 0.32), (0.45, 0.42, 0.38), (0.30, 0.30, 0.33), (0.50, 0.36, 0.30)])
_SIGN = np.array([
    (0.80, 0.10, 0.10), (0.10, 0.35, 0.75), (0.10, 0.55, 0.25), (0.95, 0.75, 0.10),
    (0.60, 0.15, 0.60), (0.95, 0.45, 0.10), (0.10, 0.60, 0.65), (0.12, 0.12, 0.12),
])
_STYLES = ("brick", "plaster", "concrete")


# --------------------------------------------------------------------------------------- options


@dataclass(frozen=True)
class TownConfig:
    """Options of the procedural town and its capture (all lengths in metres).

    The defaults (300 images of 320 x 240, 45 degrees wide, over a 4 x 3-block street grid of
    230 x 176 m, 258 x 204 m with its ring of buildings) give scalar-nerf an automatic K > 1 with
    tables of 2^19 rows (blocks/capacity.py).
    """

    num_images: int = 300
    """Images along the walk (frames are numbered in walking order)."""
    width: int = 320
    """Image width in pixels."""
    height: int = 240
    """Image height in pixels."""
    fov_x_deg: float = 45.0
    """Horizontal field of view in degrees (square pixels, principal point at the centre)."""
    blocks_x: int = 4
    """City blocks along x (east); there are blocks_x + 1 north-south streets."""
    blocks_y: int = 3
    """City blocks along y (north); there are blocks_y + 1 east-west streets."""
    block_size: float = 40.0
    """Side of a square city block, between the streets' building lines."""
    street_width: float = 14.0
    """Building line to building line: the road plus a pavement on each side."""
    road_width: float = 8.0
    """Asphalt width (lanes between the kerbs)."""
    ring_depth: float = 14.0
    """Depth of the ring of buildings that encloses the town (every street ends at a facade)."""
    camera_height: Tuple[float, float] = (1.5, 2.0)
    """Camera heights are uniform in this range (``walk``; a rig's cameras stay at its mid-height)."""
    capture: str = "rig"
    """``rig``: a vehicle drives the streets and stops at even intervals; at each stop every camera of
    the rig (``rig_headings``) takes a frame, as Block-NeRF's capture does. A camera's frames at
    neighbouring stops see the same facades from nearby at the same angle, so a held-out frame lies
    between training frames of its own camera. ``walk``: one frame per position with a random
    heading (along the street, sideways or diagonal), the only capture before generator version 2;
    half of its held-out frames have no training frame looking their way within 2.5 stop spacings."""
    rig_headings: Tuple[float, ...] = (30.0, -30.0)
    """``rig`` only: the cameras' headings in degrees from the driving direction (positive: left)."""
    aerial_altitude: float = 55.0
    """``aerial`` only: flight altitude above the ground in metres (each frame jitters by up to
    0.5 m). It must clear the tallest roof by 2 m, and keep every ground pixel within the depth
    PNGs' 65.5 m (58 m at most for the default 45-degree views of 4:3)."""
    supersample: int = 1
    """Colour samples per pixel along each axis (ss x ss, averaged: anti-aliasing); depth is the
    pixel centre's."""
    seed: int = 0
    """Seed of the buildings, the textures and the walk; the same seed gives byte-identical files."""

    def __post_init__(self) -> None:
        def positive_int(name: str) -> None:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"TownConfig.{name} must be a positive integer, got {value!r}")

        for name in ("num_images", "width", "height", "blocks_x", "blocks_y", "supersample"):
            positive_int(name)
        for name in ("block_size", "street_width", "road_width", "ring_depth", "fov_x_deg"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float, np.floating, np.integer)) and math.isfinite(value) and value > 0):
                raise ValueError(f"TownConfig.{name} must be a positive finite number, got {value!r}")
        if not self.fov_x_deg < 170.0:
            raise ValueError(f"TownConfig.fov_x_deg must be below 170 degrees, got {self.fov_x_deg!r}")
        if self.block_size < 8.0:
            raise ValueError(f"TownConfig.block_size must be at least 8 m (one building lot), got {self.block_size!r}")
        if self.ring_depth < 4.0:
            raise ValueError(f"TownConfig.ring_depth must be at least 4 m, got {self.ring_depth!r}")
        if not (2.0 <= self.road_width <= self.street_width - 2.0):
            raise ValueError(
                f"TownConfig.road_width must be at least 2 m and leave pavements of 1 m each side within street_width "
                f"({self.street_width!r} m), got {self.road_width!r}"
            )
        low, high = self.camera_height
        if not (0.1 <= low <= high < 6.0):
            raise ValueError(f"TownConfig.camera_height must be a range (low, high) with 0.1 <= low <= high < 6 m, got {self.camera_height!r}")
        if self.capture not in CAPTURES:
            raise ValueError(f"TownConfig.capture must be one of {list(CAPTURES)}, got {self.capture!r}")
        altitude = self.aerial_altitude
        if not (isinstance(altitude, (int, float, np.integer, np.floating)) and math.isfinite(altitude) and 0.0 < altitude < DEPTH_PNG_MAX_M):
            raise ValueError(f"TownConfig.aerial_altitude must be a positive number of metres below {DEPTH_PNG_MAX_M:.1f}, got {altitude!r}")
        headings = self.rig_headings
        if not (isinstance(headings, tuple) and headings and all(isinstance(h, (int, float, np.integer, np.floating)) and math.isfinite(h) and -180.0 <= h <= 180.0 for h in headings)):
            raise ValueError(f"TownConfig.rig_headings must be a non-empty tuple of headings in degrees within [-180, 180], got {headings!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ValueError(f"TownConfig.seed must be a non-negative integer, got {self.seed!r}")

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (fl_x = fl_y)."""
        return 0.5 * self.width / math.tan(math.radians(self.fov_x_deg) / 2.0)

    @property
    def street_extent(self) -> Tuple[float, float]:
        """(x, y) size of the street grid, outer building line to outer building line."""
        pitch = self.block_size + self.street_width
        return self.blocks_x * pitch + self.street_width, self.blocks_y * pitch + self.street_width

    @property
    def extent(self) -> Tuple[float, float]:
        """(x, y) size of the whole town, its ring of buildings included."""
        sx, sy = self.street_extent
        return sx + 2.0 * self.ring_depth, sy + 2.0 * self.ring_depth

    def to_json(self) -> Dict[str, Any]:
        """The options as JSON-ready values."""
        values = asdict(self)
        values["camera_height"] = list(self.camera_height)
        values["rig_headings"] = [float(h) for h in self.rig_headings]
        values["aerial_altitude"] = float(self.aerial_altitude)
        return values

    @classmethod
    def from_json(cls, values: Dict[str, Any]) -> "TownConfig":
        """Inverse of :meth:`to_json` (unknown keys are refused)."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"TownConfig: unknown option(s) {unknown}")
        values = dict(values)
        if "camera_height" in values:
            values["camera_height"] = tuple(float(v) for v in values["camera_height"])
        if "rig_headings" in values:
            values["rig_headings"] = tuple(float(v) for v in values["rig_headings"])
        values.setdefault("capture", "walk")  # scenes of generator version 1 (no capture key) walked
        return cls(**values)


def blocks_for_extent(extent: float, block_size: float = TownConfig.block_size, street_width: float = TownConfig.street_width) -> int:
    """City blocks along one axis for a street grid about ``extent`` metres across (at least 1)."""
    if not (math.isfinite(extent) and extent > 0):
        raise ValueError(f"extent must be a positive number of metres, got {extent!r}")
    return max(1, int(round((extent - street_width) / (block_size + street_width))))


# ------------------------------------------------------------------------------------ the town


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


# ----------------------------------------------------------------------------- ray casting


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
    near = far = None
    for k in range(3):
        t0 = (lo[None, :, k] - origins[:, None, k]) * inverse[:, None, k]
        t1 = (hi[None, :, k] - origins[:, None, k]) * inverse[:, None, k]
        lower, upper = np.minimum(t0, t1), np.maximum(t0, t1)
        if near is None:
            near, far = lower, upper
        else:
            np.maximum(near, lower, out=near)
            np.minimum(far, upper, out=far)
    return near, far


def _entry_axis(origins: np.ndarray, inverse: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Rays [P, 3] vs one box each ([P, 3] corners) -> [P] axis of the face the ray enters through."""
    t0 = (lo - origins) * inverse
    t1 = (hi - origins) * inverse
    return np.minimum(t0, t1).argmax(axis=1)


def intersect_town(origins: np.ndarray, directions: np.ndarray, town: Town, chunk_rays: Optional[int] = None, min_t: float = 1e-6) -> TownHits:
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
    chunk = chunk_rays or _CHUNK_RAYS
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


# --------------------------------------------------------------------------------- texture

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _hash(salt: int, *coords: np.ndarray) -> np.ndarray:
    """Integer lattice coordinates ([P] arrays, any int/float dtype holding integers) -> [P] uniform [0, 1)."""
    h = np.full(np.shape(coords[0]), (salt * 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF, dtype=np.uint64)
    for c in coords:
        h = (h ^ np.asarray(c).astype(np.int64).astype(np.uint64)) * _M1
        h ^= h >> np.uint64(31)
        h = (h + _GOLDEN) * _M2
        h ^= h >> np.uint64(29)
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def _value_noise(salt: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Smooth 2-D value noise in [0, 1) on the unit lattice: [P] coordinates -> [P]."""
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = u - iu, v - iv
    fu, fv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    a, b = _hash(salt, iu, iv), _hash(salt, iu + 1, iv)
    c, d = _hash(salt, iu, iv + 1), _hash(salt, iu + 1, iv + 1)
    return (a * (1 - fu) + b * fu) * (1 - fv) + (c * (1 - fu) + d * fu) * fv


def _facade_colour(town: Town, building: np.ndarray, face: np.ndarray, u: np.ndarray, v: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Facade texture.

    Args:
        building: [P] building index; face: [P] face id (0..3) of that building.
        u: [P] metres along the facade from its left end; v: [P] height (z); width: [P] facade width.

    Returns:
        [P, 3] albedo.
    """
    salt = town.texture_salt
    fid = building * 4 + face
    height = town.hi[building, 2]
    floor_h = town.floor_height[building]
    pitch = town.window_pitch[building]
    win_w, win_h = town.window_size[building, 0], town.window_size[building, 1]
    style = town.style[building]
    wall = town.wall[building]
    trim = town.trim[building]
    colour = np.empty((len(u), 3))

    # Wall material at three scales.
    brick = style == 0
    if brick.any():
        ub, vb, fb = u[brick], v[brick], fid[brick]
        row = np.floor(vb / 0.075)
        along = (ub + (row % 2) * 0.1125) / 0.225
        col = np.floor(along)
        mortar = ((along - col) * 0.225 < 0.012) | ((vb - row * 0.075) < 0.011)
        tone = 0.78 + 0.3 * _hash(salt + 1, col, row, fb)
        tint = 0.06 * (_hash(salt + 2, col, row, fb) - 0.5)
        bricks = wall[brick] * tone[:, None] + np.array([tint, 0.5 * tint, 0.0 * tint]).T
        colour[brick] = np.where(mortar[:, None], np.array([0.74, 0.71, 0.65]), bricks)
    plaster = style == 1
    if plaster.any():
        up, vp, fp = u[plaster], v[plaster], fid[plaster]
        tone = 0.86 + 0.1 * _value_noise(salt + 3, up / 0.8 + 7.0 * fp, vp / 0.8) + 0.06 * _hash(salt + 4, np.floor(up / 0.04), np.floor(vp / 0.04), fp)
        groove = (vp < floor_h[plaster]) & ((vp % 0.45) < 0.025)  # rusticated ground floor
        colour[plaster] = wall[plaster] * (tone * np.where(groove, 0.75, 1.0))[:, None]
    concrete = style == 2
    if concrete.any():
        uc, vc, fc = u[concrete], v[concrete], fid[concrete]
        ph = floor_h[concrete] / 2.0
        pu, pv = np.floor(uc / 1.5), np.floor(vc / ph)
        joint = ((uc - pu * 1.5) < 0.02) | ((vc - pv * ph) < 0.02)
        hole = ((uc % 0.6) - 0.3) ** 2 + ((vc % 0.6) - 0.3) ** 2 < 0.022**2
        tone = (0.84 + 0.16 * _hash(salt + 5, pu, pv, fc)) * (0.96 + 0.06 * _hash(salt + 6, np.floor(uc / 0.05), np.floor(vc / 0.05), fc))
        colour[concrete] = wall[concrete] * (tone * np.where(joint | hole, 0.6, 1.0))[:, None]

    # Storeys: floor bands and the parapet.
    floor = np.floor(v / floor_h)
    fv = v - floor * floor_h
    parapet_base = np.floor((height - 0.4) / floor_h) * floor_h
    band = (floor >= 1) & (fv < 0.16) & (style != 2) & (v < parapet_base)
    colour[band] = trim[band] * 0.92
    parapet = v >= parapet_base + 0.05
    coping = v > height - 0.12
    colour[parapet] = colour[parapet] * 0.88
    colour[coping] = trim[coping]

    # Windows: a centred grid, one row per floor, with frames, mullions, transoms and sills.
    count = np.maximum(np.floor((width - 1.0) / pitch), 0.0)
    offset = (width - count * pitch) / 2.0
    column = np.floor((u - offset) / pitch)
    fu = u - offset - column * pitch - (pitch - win_w) / 2.0
    wy = fv - town.sill[building]
    shop_floor = town.shops[building] & (floor == 0)
    rows_ok = (column >= 0) & (column < count) & (v < parapet_base) & ~shop_floor
    frame_t = 0.07
    in_outer = rows_ok & (fu >= -frame_t) & (fu < win_w + frame_t) & (wy >= -frame_t) & (wy < win_h + frame_t)
    in_glass = rows_ok & (fu >= 0) & (fu < win_w) & (wy >= 0) & (wy < win_h)
    mullion = in_glass & ((np.abs(fu - win_w / 2.0) < 0.025) | (np.abs(wy - 0.64 * win_h) < 0.025))
    sill = rows_ok & (fu >= -0.12) & (fu < win_w + 0.12) & (wy >= -frame_t - 0.07) & (wy < -frame_t)
    colour[sill] = np.array([0.82, 0.8, 0.76])
    colour[in_outer & ~in_glass] = trim[in_outer & ~in_glass]
    glass = in_glass & ~mullion
    if glass.any():
        g = np.flatnonzero(glass)
        wid_a, wid_b = column[g], floor[g]
        lit = _hash(salt + 7, wid_a, wid_b, fid[g])
        pane = town.glass[building[g]] * (0.6 + 0.5 * _hash(salt + 8, wid_a, wid_b, fid[g]))[:, None]
        pane = pane + 0.25 * np.clip(wy[g] / win_h[g], 0.0, 1.0)[:, None] * np.array([0.55, 0.65, 0.8])  # baked sky reflection
        curtain = np.array([0.85, 0.78, 0.6]) * (0.7 + 0.3 * _hash(salt + 9, wid_a, wid_b, fid[g]))[:, None]
        colour[g] = np.where((lit > 0.82)[:, None], curtain, pane)
    colour[mullion] = trim[mullion]

    # Ground-floor shops: shop windows, doors and coloured sign boards with lettering.
    shop = shop_floor & (u > 0.3) & (u < width - 0.3)
    if shop.any():
        sidx = np.flatnonzero(shop)
        us, fs, bs = u[sidx], fv[sidx], building[sidx]
        index = np.floor(us / 6.0)
        su = us - index * 6.0
        sign_colour = _SIGN[(_hash(salt + 10, index, fid[sidx]) * len(_SIGN)).astype(np.int64)]
        part = colour[sidx]
        window = (su > 0.4) & (su < 5.6) & (fs > 0.15) & (fs < 2.35)
        door = (su > 0.8) & (su < 1.9) & (fs < 2.2)
        bars = window & ((((su - 0.4) % 1.3) < 0.06) | (fs < 0.22) | (fs > 2.28))
        part[window] = town.glass[bs[window]] * 0.7 + 0.12
        part[bars] = trim[sidx][bars] * 0.8
        part[door] = sign_colour[door] * 0.35 + 0.08
        board = (su > 0.25) & (su < 5.75) & (fs > 2.5) & (fs < 2.95)
        part[board] = sign_colour[board]
        # Lettering: glyph cells of 8 x 8 cm, 5 rows, letters 5 cells wide with a blank column.
        gu, gv = np.floor((su - 0.9) / 0.08), np.floor((fs - 2.55) / 0.08)
        letter = board & (su > 0.9) & (su < 5.1) & (gv >= 0) & (gv < 5) & ((gu % 6) != 5)
        ink = letter & (_hash(salt + 11, gu, gv, np.floor(gu / 6.0) + 17.0 * index, fid[sidx]) > 0.45)
        luminance = sign_colour @ np.array([0.3, 0.59, 0.11])
        part[ink] = np.where((luminance[ink] > 0.5)[:, None], np.array([0.08, 0.08, 0.1]), np.array([0.97, 0.96, 0.9]))
        colour[sidx] = part
    # Ambient occlusion at the foot of the wall.
    return colour * (1.0 - 0.28 * np.exp(-v / 0.6))[:, None]


def _roof_colour(town: Town, building: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """[P] building index and roof point (x, y) -> [P, 3] roof albedo (gravel, seams, vents, coping)."""
    salt = town.texture_salt
    tone = (0.78 + 0.22 * _hash(salt + 20, np.floor(x / 0.05), np.floor(y / 0.05))) * (0.9 + 0.12 * _value_noise(salt + 21, x / 2.5, y / 2.5))
    colour = town.roof[building] * tone[:, None]
    seam = ((x % 2.0) < 0.04) | ((y % 2.0) < 0.04)
    colour[seam] *= 0.7
    cx, cy = np.floor(x / 5.0), np.floor(y / 5.0)
    ox, oy = x - cx * 5.0, y - cy * 5.0
    vent = (_hash(salt + 22, cx, cy) > 0.6) & (ox > 1.9) & (ox < 3.1) & (oy > 1.9) & (oy < 3.1)
    colour[vent] = np.array([0.62, 0.63, 0.65]) * np.where(((ox[vent] - 1.9) % 0.15) < 0.05, 0.7, 1.0)[:, None]
    edge = np.minimum.reduce([x - town.lo[building, 0], town.hi[building, 0] - x, y - town.lo[building, 1], town.hi[building, 1] - y])
    colour[edge < 0.3] = town.trim[building[edge < 0.3]]
    return colour


def _ground_colour(town: Town, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """[P] ground points (x, y) -> [P, 3] albedo: asphalt with lane markings and crossings,
    kerbs, tiled pavements, and grass in the empty lots."""
    salt = town.texture_salt
    config = town.config
    half_road, half_street = config.road_width / 2.0, config.street_width / 2.0
    dx = x - town.street_x[np.abs(x[:, None] - town.street_x[None]).argmin(axis=1)]
    dy = y - town.street_y[np.abs(y[:, None] - town.street_y[None]).argmin(axis=1)]
    ax, ay = np.abs(dx), np.abs(dy)
    road_v, road_h = ax < half_road, ay < half_road  # north-south road, east-west road
    street_v, street_h = ax < half_street, ay < half_street
    road = road_v | road_h
    pavement = (street_v | street_h) & ~road

    colour = np.empty((len(x), 3))
    # Asphalt: speckle (4 cm), patches (~2 m), repairs (~8 m).
    speckle = _hash(salt + 30, np.floor(x / 0.04), np.floor(y / 0.04))
    tone = (0.84 + 0.22 * speckle) * (0.9 + 0.14 * _value_noise(salt + 31, x / 2.0, y / 2.0))
    tone *= np.where(_value_noise(salt + 32, x / 8.0, y / 8.0) > 0.72, 0.85, 1.0)
    colour[:] = np.array([0.25, 0.25, 0.26]) * tone[:, None]
    paint = np.zeros(len(x), dtype=bool)
    # Lane markings away from the crossings: dashed centre line (3 m on, 3 m off), solid edge lines.
    mid_v = road_v & ~street_h
    mid_h = road_h & ~street_v
    paint |= mid_v & (ax < 0.075) & ((y % 6.0) < 3.0)
    paint |= mid_h & (ay < 0.075) & ((x % 6.0) < 3.0)
    paint |= mid_v & (np.abs(ax - (half_road - 0.35)) < 0.06)
    paint |= mid_h & (np.abs(ay - (half_road - 0.35)) < 0.06)
    # Zebra crossings just before each crossing: 0.5 m stripes.
    zebra_v = mid_v & (ay >= half_street + 0.3) & (ay < half_street + 3.3) & ((dx % 1.0) < 0.5) & (ax < half_road - 0.5)
    zebra_h = mid_h & (ax >= half_street + 0.3) & (ax < half_street + 3.3) & ((dy % 1.0) < 0.5) & (ay < half_road - 0.5)
    zebra_zone_v = mid_v & (ay >= half_street) & (ay < half_street + 3.6)
    zebra_zone_h = mid_h & (ax >= half_street) & (ax < half_street + 3.6)
    paint &= ~(zebra_zone_v | zebra_zone_h)
    paint |= zebra_v | zebra_h
    colour[paint] = np.array([0.9, 0.9, 0.86]) * (0.86 + 0.14 * speckle[paint])[:, None]

    # Pavement: 45 cm tiles with grout, and kerb stones (1 m) along the road.
    tx, ty = np.floor(x / 0.45), np.floor(y / 0.45)
    grout = ((x - tx * 0.45) < 0.015) | ((y - ty * 0.45) < 0.015)
    tile = np.array([0.63, 0.61, 0.57]) * (0.84 + 0.22 * _hash(salt + 33, tx, ty))[:, None]
    tile[grout] = np.array([0.42, 0.41, 0.39])
    kerb_v = street_v & ~road & (ax < half_road + 0.25) & ~road_h
    kerb_h = street_h & ~road & (ay < half_road + 0.25) & ~road_v
    kerb_joint = np.where(kerb_v, (y % 1.0) < 0.02, (x % 1.0) < 0.02)
    tile[kerb_v | kerb_h] = np.array([0.74, 0.74, 0.72])
    tile[(kerb_v | kerb_h) & kerb_joint] = np.array([0.5, 0.5, 0.49])
    colour[pavement] = tile[pavement]

    # Empty lots and the rest: grass.
    lot = ~(road | pavement)
    grass = np.array([0.28, 0.42, 0.18]) * ((0.7 + 0.45 * _hash(salt + 34, np.floor(x / 0.05), np.floor(y / 0.05))) * (0.85 + 0.2 * _value_noise(salt + 35, x, y)))[:, None]
    colour[lot] = grass[lot]
    return colour


def _sky_colour(directions: np.ndarray) -> np.ndarray:
    """[P, 3] unit directions -> [P, 3] sky at infinity (a gradient with a soft glow towards the sun)."""
    up = np.clip(directions[:, 2], 0.0, 1.0)[:, None]
    glow = np.clip(directions @ _SUN, 0.0, 1.0)[:, None] ** 8
    return _SKY_HORIZON * (1.0 - up) + _SKY_ZENITH * up + 0.15 * glow


def _shade(town: Town, origins: np.ndarray, directions: np.ndarray, hits: TownHits) -> np.ndarray:
    """Colour of each ray's hit: albedo x (ambient + sun) for surfaces, the sky gradient otherwise ([P, 3])."""
    rgb = _sky_colour(directions)
    hit = hits.surface != SKY
    points = origins + directions * np.where(hit, hits.depth, 0.0)[:, None]
    ground = np.flatnonzero(hits.surface == GROUND)
    albedo = np.zeros_like(rgb)
    if len(ground):
        albedo[ground] = _ground_colour(town, points[ground, 0], points[ground, 1])
    roofs = np.flatnonzero((hits.surface >= 0) & (hits.axis == 2))
    if len(roofs):
        albedo[roofs] = _roof_colour(town, hits.surface[roofs], points[roofs, 0], points[roofs, 1])
    walls = np.flatnonzero((hits.surface >= 0) & (hits.axis != 2))
    if len(walls):
        b = hits.surface[walls]
        ax = hits.axis[walls]
        p = points[walls]
        along = 1 - ax  # facade normal along x -> u runs along y, and vice versa
        rows = np.arange(len(walls))
        u = p[rows, along] - town.lo[b, along]
        width = town.hi[b, along] - town.lo[b, along]
        face = ax * 2 + (hits.normal[walls, ax] > 0)
        albedo[walls] = _facade_colour(town, b, face, u, p[:, 2], width)
    light = 0.5 + 0.55 * np.clip(hits.normal @ _SUN, 0.0, 1.0)
    surface_rgb = albedo * light[:, None]
    rgb[hit] = surface_rgb[hit]
    return np.clip(rgb, 0.0, 1.0)


def render_town_rays(origins: np.ndarray, directions: np.ndarray, town: Town) -> Tuple[np.ndarray, np.ndarray]:
    """Ray-cast the town.

    Args:
        origins: [N, 3] ray origins (metres), outside the buildings.
        directions: [N, 3] ray directions (need not be normalised).
        town: from :func:`build_town` or :func:`load_town`.

    Returns:
        rgb: [N, 3] colour in [0, 1]; depth: [N] distance to the first hit along the normalised
        direction (inf for the sky).
    """
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if origins.shape != directions.shape:
        raise ValueError(f"render_town_rays: origins {origins.shape} and directions {directions.shape} differ in shape")
    rgb = np.empty_like(origins)
    depth = np.empty(len(origins))
    # Chunks of a few thousand rays keep every temporary small (cache-friendly, no page faults).
    chunk = _CHUNK_RAYS
    for start in range(0, len(origins), chunk):
        o, d = origins[start : start + chunk], directions[start : start + chunk]
        hits = intersect_town(o, d, town, chunk_rays=chunk)
        unit = d / np.linalg.norm(d, axis=1, keepdims=True)
        rgb[start : start + chunk] = _shade(town, o, unit, hits)
        depth[start : start + chunk] = hits.depth
    return rgb, depth


# --------------------------------------------------------------------------------- cameras


def town_intrinsics(config: TownConfig) -> Dict[str, float]:
    """The pinhole intrinsics of every frame (nerfstudio transforms.json keys)."""
    focal = config.focal_px
    return {"fl_x": focal, "fl_y": focal, "cx": config.width / 2.0, "cy": config.height / 2.0, "w": config.width, "h": config.height}


def _camera_to_world(position: np.ndarray, yaw: float, pitch: float) -> np.ndarray:
    """[3] position, heading (yaw from +x, radians) and pitch -> [4, 4] camera-to-world, OpenGL
    axes (looks along -z, y up), as nerfstudio's transforms.json expects."""
    forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -forward, position
    return c2w


def _walk_segments(town: Town) -> List[Tuple[np.ndarray, np.ndarray]]:
    """Street centre lines in walking order: east-west streets in alternating directions, then
    north-south streets in alternating directions ([2] start, [2] end each)."""
    segments = []
    x0, x1 = float(town.street_x[0]), float(town.street_x[-1])
    y0, y1 = float(town.street_y[0]), float(town.street_y[-1])
    for j, y in enumerate(town.street_y):
        a, b = (x0, x1) if j % 2 == 0 else (x1, x0)
        segments.append((np.array([a, y]), np.array([b, y])))
    for i, x in enumerate(town.street_x):
        a, b = (y0, y1) if i % 2 == 0 else (y1, y0)
        segments.append((np.array([x, a]), np.array([x, b])))
    return segments


def town_camera_poses(town: Town) -> np.ndarray:
    """[N, 4, 4] camera-to-world poses (OpenGL axes), in frame order, of the town's capture
    (:attr:`TownConfig.capture`)."""
    capture = town.config.capture
    if capture == "aerial":
        return _aerial_poses(town)
    return _rig_poses(town) if capture == "rig" else _walk_poses(town)


def _street_positions(town: Town, arc: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """[P] distances along the concatenated street centre lines (clipped to their length) ->
    ([P, 2] points on them, [P, 2] unit driving directions)."""
    segments = _walk_segments(town)
    lengths = np.array([np.linalg.norm(b - a) for a, b in segments])
    arc = np.clip(arc, 0.0, float(lengths.sum()) - 1e-9)
    ends = np.cumsum(lengths)
    which = np.minimum(np.searchsorted(ends, arc, side="right"), len(segments) - 1)
    local = arc - (ends[which] - lengths[which])
    points = np.empty((len(arc), 2))
    directions = np.empty((len(arc), 2))
    for k, segment in enumerate(which):
        start, end = segments[segment]
        directions[k] = (end - start) / np.linalg.norm(end - start)
        points[k] = start + directions[k] * local[k]
    return points, directions


def _rig_poses(town: Town) -> np.ndarray:
    """The ``rig`` capture: ceil(N / R) stops evenly spread over the streets, R = len(rig_headings)
    frames per stop (the last stop keeps the first cameras only). The vehicle weaves slowly across
    the lanes; each camera's heading jitters by about 3 degrees and its pitch by a few degrees up."""
    config = town.config
    rng = np.random.default_rng([config.seed, 0x816])
    segments = _walk_segments(town)
    total = float(sum(np.linalg.norm(b - a) for a, b in segments))
    headings = np.radians(np.asarray(config.rig_headings, dtype=float))
    num_stops = -(-config.num_images // len(headings))
    arc = (np.arange(num_stops) + 0.5) * (total / num_stops)
    points, directions = _street_positions(town, arc)
    yaws = np.arctan2(directions[:, 1], directions[:, 0])
    lateral_max = 0.45 * (config.street_width / 2.0 - 1.0)
    lateral = lateral_max * np.sin(arc / 23.0)
    height = 0.5 * (config.camera_height[0] + config.camera_height[1])
    poses = np.empty((num_stops * len(headings), 4, 4))
    for stop in range(num_stops):
        left = np.array([-math.sin(yaws[stop]), math.cos(yaws[stop])])
        xy = points[stop] + left * lateral[stop]
        for c, heading in enumerate(headings):
            yaw = yaws[stop] + heading + math.radians(rng.normal(0.0, 3.0))
            pitch = math.radians(rng.uniform(0.0, 12.0) if abs(heading) >= math.radians(60.0) else rng.uniform(-2.0, 8.0))
            poses[stop * len(headings) + c] = _camera_to_world(np.array([xy[0], xy[1], height]), yaw, pitch)
    return poses[: config.num_images]


def _walk_poses(town: Town) -> np.ndarray:
    """The ``walk`` capture: positions spread evenly (with jitter along and across the street) over
    the concatenated street centre lines; each camera looks along the street (forward or back),
    sideways at a facade, or diagonally, with a small random yaw and an upward-biased pitch."""
    config = town.config
    rng = np.random.default_rng([config.seed, 0xCA3E])
    total = float(np.array([np.linalg.norm(b - a) for a, b in _walk_segments(town)]).sum())
    n = config.num_images
    points, directions = _street_positions(town, (np.arange(n) + 0.5 + rng.uniform(-0.3, 0.3, size=n)) * (total / n))
    lateral_max = 0.45 * (config.street_width / 2.0 - 1.0)
    headings = np.array([0.0, 180.0, 90.0, -90.0, 45.0, -45.0])
    weights = np.array([0.22, 0.1, 0.24, 0.24, 0.1, 0.1])
    choice = rng.choice(len(headings), size=n, p=weights)
    yaw_jitter = rng.normal(0.0, 8.0, size=n)
    lateral = rng.uniform(-lateral_max, lateral_max, size=n)
    low, high = config.camera_height
    heights = rng.uniform(low, high, size=n)
    pitch_forward = rng.uniform(-4.0, 10.0, size=n)
    pitch_side = rng.uniform(2.0, 22.0, size=n)
    poses = np.empty((n, 4, 4))
    for k in range(n):
        direction = directions[k]
        left = np.array([-direction[1], direction[0]])
        xy = points[k] + left * lateral[k]
        walk_yaw = math.atan2(direction[1], direction[0])
        offset = headings[choice[k]]
        yaw = walk_yaw + math.radians(offset + yaw_jitter[k])
        pitch = math.radians(pitch_side[k] if abs(offset) == 90.0 else pitch_forward[k])
        poses[k] = _camera_to_world(np.array([xy[0], xy[1], heights[k]]), yaw, pitch)
    return poses


#: ``aerial``: how far each frame's optical axis leans forward from the vertical (degrees, uniform
#: in this range). Always forward: the cameras' mean "up" then points up, which nerfstudio's
#: default orientation (``--orientation-method up``) needs; with no lean, or a lean either way,
#: the back-and-forth flight lines' "up" vectors cancel and the town would come out tilted.
AERIAL_TILT_DEG: Tuple[float, float] = (6.0, 14.0)
#: ``aerial``: the least height above the tallest roof (metres).
AERIAL_CLEARANCE_M: float = 2.0
#: ``aerial``: each frame's altitude is uniform within this many metres of ``aerial_altitude``.
AERIAL_ALTITUDE_JITTER_M: float = 0.5


def _aerial_poses(town: Town) -> np.ndarray:
    """The ``aerial`` capture: a drone flies parallel flight lines along x over the whole town (its
    ring included), alternating direction (an even number of lines, so as many frames fly each
    way), lines at most half a footprint apart (50 % side overlap or more), with
    ``num_images`` frames evenly spread along the whole flight (frames are numbered in flight order,
    so a held-out frame lies between training frames a few metres away). Each camera's image rows
    run across the flight line; its axis leans forward from the vertical by ``AERIAL_TILT_DEG``;
    altitude jitters by ``AERIAL_ALTITUDE_JITTER_M`` and heading by 3 degrees.

    Raises:
        ValueError: when the altitude does not clear the tallest roof by ``AERIAL_CLEARANCE_M``, or
            when a ground pixel would lie beyond the depth PNGs' range (both name the altitude
            that would do).
    """
    config = town.config
    altitude = float(config.aerial_altitude)
    lowest, highest = altitude - AERIAL_ALTITUDE_JITTER_M, altitude + AERIAL_ALTITUDE_JITTER_M
    tallest = float(town.hi[:, 2].max()) if town.num_buildings else 0.0
    if lowest < tallest + AERIAL_CLEARANCE_M:
        raise ValueError(
            f"TownConfig.aerial_altitude {altitude:g} m does not clear this town's tallest roof ({tallest:.1f} m) by "
            f"{AERIAL_CLEARANCE_M:g} m; fly at {math.ceil(tallest + AERIAL_CLEARANCE_M + AERIAL_ALTITUDE_JITTER_M):g} m or more"
        )
    rng = np.random.default_rng([config.seed, 0xAE21])
    half_x = math.tan(math.radians(config.fov_x_deg) / 2.0)
    half_y = half_x * config.height / config.width
    # The deepest ground pixel: an image corner on the side the axis leans to, at the highest jitter.
    tilt = math.radians(AERIAL_TILT_DEG[1])
    corner_down = (math.cos(tilt) - half_y * math.sin(tilt))  # -z of the unnormalised corner ray (z = -1 forward)
    deepest = highest / corner_down if corner_down > 0 else math.inf
    if not deepest <= DEPTH_PNG_MAX_M:
        limit = DEPTH_PNG_MAX_M * corner_down - AERIAL_ALTITUDE_JITTER_M
        raise ValueError(
            f"TownConfig.aerial_altitude {altitude:g} m puts ground pixels {deepest:.1f} m deep, beyond the depth PNGs' "
            f"{DEPTH_PNG_MAX_M:.1f} m; fly at {limit:.1f} m or less (or narrow the field of view)"
        )
    across = 2.0 * altitude * half_x  # the footprint across the flight line (image rows run across it)
    length, width = config.extent  # the town is centred on the origin; lines run along x
    num_lines = 2 * max(1, math.ceil(width / across))
    line_y = -width / 2.0 + (np.arange(num_lines) + 0.5) * (width / num_lines)
    arc = (np.arange(config.num_images) + 0.5) * (num_lines * length / config.num_images)
    line = np.minimum((arc // length).astype(np.int64), num_lines - 1)
    along = arc - line * length
    forward = line % 2 == 0
    x = np.where(forward, along - length / 2.0, length / 2.0 - along)
    yaw = np.where(forward, 0.0, math.pi) + np.radians(rng.normal(0.0, 3.0, size=config.num_images))
    lean = np.radians(rng.uniform(*AERIAL_TILT_DEG, size=config.num_images))
    z = rng.uniform(lowest, highest, size=config.num_images)
    poses = np.empty((config.num_images, 4, 4))
    for k in range(config.num_images):
        poses[k] = _camera_to_world(np.array([x[k], line_y[line[k]], z[k]]), float(yaw[k]), -0.5 * math.pi + float(lean[k]))
    return poses


def _pixel_directions(config: TownConfig, offsets: Sequence[Tuple[float, float]]) -> np.ndarray:
    """[S, H * W, 3] camera-space ray directions (OpenGL: -z forward) through the pixel at
    sub-pixel ``offsets`` (0.5, 0.5 = centre), not normalised (z = -1)."""
    focal = config.focal_px
    cx, cy = config.width / 2.0, config.height / 2.0
    out = []
    for du, dv in offsets:
        u, v = np.meshgrid(np.arange(config.width) + du, np.arange(config.height) + dv)
        out.append(np.stack([(u - cx) / focal, -(v - cy) / focal, -np.ones_like(u)], axis=-1).reshape(-1, 3))
    return np.stack(out)


def render_town_image(town: Town, camera_to_world: np.ndarray, supersample: Optional[int] = None) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one frame of ``town.config``'s size from a [4, 4] (or [3, 4]) OpenGL camera-to-world.

    Args:
        supersample: colour samples per pixel along each axis (default ``town.config.supersample``).

    Returns:
        rgb: [H, W, 3] float colour in [0, 1]; ray_depth: [H, W] distance from the camera centre
        to the pixel centre's hit (inf: sky); z_depth: [H, W] the same along the optical axis
        (what the depth PNGs hold, in millimetres).
    """
    config = town.config
    ss = config.supersample if supersample is None else int(supersample)
    if ss < 1:
        raise ValueError(f"render_town_image: supersample must be >= 1, got {ss}")
    c2w = np.asarray(camera_to_world, dtype=np.float64)[:3, :4]
    centre = _pixel_directions(config, [(0.5, 0.5)])[0]  # [H*W, 3]
    cos = 1.0 / np.linalg.norm(centre, axis=1)
    directions = centre @ c2w[:3, :3].T
    origins = np.broadcast_to(c2w[:3, 3], directions.shape)
    if ss == 1:
        rgb, depth = render_town_rays(origins, directions, town)
    else:
        depth = intersect_town(origins, directions, town).depth
        offsets = [((a + 0.5) / ss, (b + 0.5) / ss) for b in range(ss) for a in range(ss)]
        rgb = np.zeros_like(directions)
        for sub in _pixel_directions(config, offsets):
            rgb += render_town_rays(origins, sub @ c2w[:3, :3].T, town)[0]
        rgb /= len(offsets)
    shape = (config.height, config.width)
    return rgb.reshape(*shape, 3), depth.reshape(shape), (depth * cos).reshape(shape)


def read_depth_png(path: Path) -> np.ndarray:
    """[H, W] metres from a depth PNG written by :func:`write_town` (0 where unknown: sky or too far)."""
    with Image.open(path) as image:
        return np.asarray(image, dtype=np.float64) * DEPTH_PNG_UNIT_M


def _depth_png(z_depth: np.ndarray) -> np.ndarray:
    """[H, W] metres -> [H, W] uint16 millimetres; inf and > 65.535 m -> 0 (unknown to nerfstudio)."""
    mm = np.where(np.isfinite(z_depth), np.round(z_depth / DEPTH_PNG_UNIT_M), 0.0)
    return np.where(mm > 65535, 0, mm).astype(np.uint16)


# ---------------------------------------------------------------------------------- writing

_WORKER_TOWN: Optional[Town] = None
_ALLOCATOR_TUNED = False


def _keep_freed_memory() -> None:
    """On glibc, let freed memory stay with the process (malloc trim threshold 256 MiB, mmap
    threshold 32 MiB) instead of going back to the OS after every numpy temporary.

    Rendering allocates and frees a few MiB of temporaries per chunk of rays; with glibc's defaults
    each round trip costs page faults, which were half of the wall time of ``write_town`` (about
    22000 faults per 256 x 192 frame). The setting is process-wide and holds at most the peak memory
    of the rendering (tens of MiB). Elsewhere (other C libraries) this does nothing.
    """
    global _ALLOCATOR_TUNED
    if _ALLOCATOR_TUNED or not sys.platform.startswith("linux"):
        return
    _ALLOCATOR_TUNED = True
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-1, 256 << 20)  # M_TRIM_THRESHOLD
        libc.mallopt(-3, 32 << 20)  # M_MMAP_THRESHOLD
    except (OSError, AttributeError):
        pass


def _frame_names(num_images: int) -> List[str]:
    digits = max(5, len(str(num_images - 1)))
    return [f"frame_{k:0{digits}d}.png" for k in range(num_images)]


def _write_frames(town: Town, out_dir: Path, poses: np.ndarray, names: Sequence[str], indices: Sequence[int]) -> int:
    """Render and write frames ``indices`` (image + depth PNG); returns how many."""
    for k in indices:
        rgb, _, z_depth = render_town_image(town, poses[k])
        Image.fromarray((rgb * 255.0 + 0.5).astype(np.uint8)).save(out_dir / "images" / names[k], format="PNG")
        Image.fromarray(_depth_png(z_depth)).save(out_dir / "depths" / names[k], format="PNG")
    return len(indices)


def _worker_init(config_json: Dict[str, Any]) -> None:
    global _WORKER_TOWN
    _keep_freed_memory()
    _WORKER_TOWN = build_town(TownConfig.from_json(config_json))


def _worker_frames(out_dir: str, indices: List[int]) -> int:
    assert _WORKER_TOWN is not None
    town = _WORKER_TOWN
    return _write_frames(town, Path(out_dir), town_camera_poses(town), _frame_names(town.config.num_images), indices)


class _Progress:
    """A progress bar over ``total`` frames: rich, else tqdm, else nothing."""

    def __init__(self, total: int, description: str, enabled: bool) -> None:
        self._advance: Callable[[int], None] = lambda n: None
        self._close: Callable[[], None] = lambda: None
        if not enabled:
            return
        try:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

            progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn())
            progress.start()
            task = progress.add_task(description, total=total)
            self._advance = lambda n: progress.advance(task, n)
            self._close = progress.stop
            return
        except ImportError:
            pass
        try:
            from tqdm import tqdm

            bar = tqdm(total=total, desc=description, unit="frame")
            self._advance = bar.update
            self._close = bar.close
        except ImportError:
            pass

    def advance(self, n: int = 1) -> None:
        self._advance(n)

    def close(self) -> None:
        self._close()


def _scene_description(town: Town, names: Sequence[str]) -> Dict[str, Any]:
    config = town.config
    return {
        "generator": "scalar_nerfstudio.data.town_scene",
        "version": GENERATOR_VERSION,
        "config": config.to_json(),
        "units": "metres; z up; ground at z = 0",
        "extent": list(config.extent),
        "street_extent": list(config.street_extent),
        "street_x": town.street_x.tolist(),
        "street_y": town.street_y.tolist(),
        "street_width": config.street_width,
        "road_width": config.road_width,
        "depth_png": {
            "folder": "depths",
            "unit_m": DEPTH_PNG_UNIT_M,
            "kind": "z-depth along the optical axis (nerfstudio's is_euclidean_depth=False convention)",
            "zero_means": f"sky, or farther than {DEPTH_PNG_MAX_M} m",
        },
        "frames": len(names),
        "boxes": [
            {"lo": town.lo[b].tolist(), "hi": town.hi[b].tolist(), "cell": int(town.cell[b]), "style": _STYLES[int(town.style[b])], "shops": bool(town.shops[b])}
            for b in range(town.num_buildings)
        ],
    }


def _prepare_output(out_dir: Path, overwrite: bool) -> None:
    """Create ``out_dir`` (must be empty unless ``overwrite``) and check that it is writable."""
    if out_dir.exists() and not out_dir.is_dir():
        raise FileExistsError(f"The output {out_dir} exists and is not a folder.")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise FileExistsError(f"The output folder {out_dir} is not empty; choose another folder or pass overwrite=True (--overwrite).")
    try:
        (out_dir / "images").mkdir(parents=True, exist_ok=True)
        (out_dir / "depths").mkdir(parents=True, exist_ok=True)
        probe = out_dir / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        raise PermissionError(f"The output folder {out_dir} cannot be written: {error.strerror or error}.") from None
    if overwrite:  # stale frames of an earlier, larger scene would be left behind
        for folder in ("images", "depths"):
            for stale in (out_dir / folder).glob("frame_*.png"):
                stale.unlink()
        for name in ("transforms.json", "scene.json"):
            if (out_dir / name).exists():
                (out_dir / name).unlink()


def write_town(out_dir: Path, config: Optional[TownConfig] = None, progress: bool = True, overwrite: bool = False, workers: int = 1) -> Path:
    """Generate the town, render every frame and write the nerfstudio scene (see the module docstring).

    Args:
        out_dir: the scene folder (created; must be empty unless ``overwrite``).
        config: the options (default :class:`TownConfig`()).
        progress: show a progress bar (rich or tqdm, when installed).
        overwrite: write into a non-empty folder, replacing an earlier scene's frames.
        workers: processes rendering frames at once (the output does not depend on it).

    On glibc this keeps freed memory in the process for reuse (see ``_keep_freed_memory``): it
    halves the wall time of rendering.

    Returns:
        The path of the written ``transforms.json`` (written last: its presence means a complete scene).
    """
    config = config or TownConfig()
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"write_town: workers must be a positive integer, got {workers!r}")
    out_dir = Path(out_dir)
    town = build_town(config)
    poses = town_camera_poses(town)  # raises on a capture that cannot be flown, before anything is written
    _prepare_output(out_dir, overwrite)
    _keep_freed_memory()
    names = _frame_names(config.num_images)
    bar = _Progress(config.num_images, f"Rendering the town ({config.num_images} frames)", progress)
    try:
        batches = [list(range(k, min(k + 4, config.num_images))) for k in range(0, config.num_images, 4)]
        if workers == 1:
            for batch in batches:
                bar.advance(_write_frames(town, out_dir, poses, names, batch))
        else:
            # spawn, not fork: the caller may hold threads (torch, a viewer) that a fork would copy mid-lock.
            context = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_worker_init, initargs=(config.to_json(),)) as pool:
                for done in pool.map(_worker_frames, [str(out_dir)] * len(batches), batches):
                    bar.advance(done)
    finally:
        bar.close()
    frames = [
        {"file_path": f"images/{name}", "depth_file_path": f"depths/{name}", "transform_matrix": pose.tolist()}
        for name, pose in zip(names, poses)
    ]
    transforms = {
        "camera_model": "OPENCV",
        **town_intrinsics(config),
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "frames": frames,
    }
    (out_dir / "scene.json").write_text(json.dumps(_scene_description(town, names), indent=1))
    path = out_dir / "transforms.json"
    path.write_text(json.dumps(transforms, indent=2))
    return path


def load_town(scene: Path) -> Town:
    """The :class:`Town` of a scene written by :func:`write_town` (rebuilt from its scene.json
    options; the geometry is checked against the boxes recorded there)."""
    scene = Path(scene)
    path = scene if scene.suffix == ".json" else scene / "scene.json"
    if path.name == "transforms.json":
        path = path.parent / "scene.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: not a town scene written by write_town.")
    content = json.loads(path.read_text())
    if content.get("generator") != "scalar_nerfstudio.data.town_scene":
        raise ValueError(f"{path} was not written by scalar_nerfstudio.data.town_scene.")
    if content.get("version") not in READABLE_VERSIONS:
        raise ValueError(f"{path} was written by town generator version {content.get('version')}; this one (version {GENERATOR_VERSION}) reads versions {list(READABLE_VERSIONS)}.")
    town = build_town(TownConfig.from_json(content["config"]))
    recorded = np.array([[*box["lo"], *box["hi"]] for box in content["boxes"]])
    if recorded.shape != (town.num_buildings, 6) or not np.array_equal(recorded, np.concatenate([town.lo, town.hi], axis=1)):
        raise ValueError(f"{path}: the recorded boxes differ from the ones its options generate (edited file or other numpy version?).")
    return town


def iter_frames(scene: Path) -> Iterator[Tuple[str, np.ndarray]]:
    """(file_path, [4, 4] camera-to-world) of every frame of a written scene's transforms.json."""
    content = json.loads((Path(scene) / "transforms.json").read_text())
    for frame in content["frames"]:
        yield frame["file_path"], np.array(frame["transform_matrix"], dtype=np.float64)
