"""The town's options (:class:`TownConfig`) and the constants of its scene files.

Every length is in metres. :class:`TownConfig` checks its values when it is made, so a bad option is
refused before anything is generated or written.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Dict, Tuple

import numpy as np

__all__ = [
    "CAPTURES", "DEPTH_PNG_MAX_M", "DEPTH_PNG_UNIT_M", "GENERATOR_ID", "GENERATOR_VERSION", "READABLE_VERSIONS", "TEXTURES",
    "TownConfig", "blocks_for_extent",
]

#: The generator's name in scene.json: the module that first wrote town scenes. It names the file
#: format, not a module to import; kept so that scenes written before stay readable and identical.
GENERATOR_ID = "scalar_nerfstudio.data.town_scene"
#: Generator version written to scene.json (bump when the same options give other pixels).
#: Version 2 added the ``rig`` capture (the default); version 1 scenes (``walk``) still load. Version 3
#: filters the textures by each sample's footprint (``textures``); ``point-sampled`` gives version 2's pixels.
GENERATOR_VERSION = 3
#: Generator versions whose scene.json :func:`load_town` reads.
READABLE_VERSIONS = (1, 2, 3)
#: The ways the cameras capture the town (:attr:`TownConfig.capture`).
CAPTURES = ("rig", "walk", "aerial", "aerial+rig")
#: How surface detail meets the pixels (:attr:`TownConfig.textures`).
TEXTURES = ("filtered", "point-sampled")
#: Metres per unit of the 16-bit depth PNGs (nerfstudio's default ``depth_unit_scale_factor``).
DEPTH_PNG_UNIT_M = 1e-3
#: The largest depth a 16-bit PNG in millimetres holds: street frames write farther points as 0 (unknown); a
#: flight whose ground lies farther writes its depth as float32 ``.npy`` in the same unit instead.
DEPTH_PNG_MAX_M = 65535 * DEPTH_PNG_UNIT_M


@dataclass(frozen=True)
class TownConfig:
    """Options of the procedural town and its capture (all lengths in metres).

    The defaults (300 images of 320 x 240, 45 degrees wide, over a 4 x 3-block street grid of
    230 x 176 m, 258 x 204 m with its ring of buildings) give scalar-nerf an automatic K > 1 with
    tables of 2^19 rows (blocks/capacity.py).
    """

    num_images: int = 300
    """Frames of the capture (numbered in capture order)."""
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
    """How the cameras capture the town: ``rig`` (a vehicle stops at even intervals along the streets and each
    camera of ``rig_headings`` takes a frame), ``walk`` (one street-level frame per position, random
    heading; generator version 1's capture), ``aerial`` (a drone's parallel flight lines, looking down) or
    ``aerial+rig`` (the first half of the frames from the drone, the rest from the rig)."""
    rig_headings: Tuple[float, ...] = (30.0, -30.0)
    """``rig`` only: the cameras' headings in degrees from the driving direction (positive: left)."""
    aerial_altitude: float = 55.0
    """``aerial`` only: flight altitude above the ground in metres (each frame jitters by up to 0.5 m); it
    must clear the tallest roof by 2 m. Above about 60 m (ground pixels beyond the 16-bit PNGs' 65.5 m) the
    scene's depth images are written as ``.npy`` instead of PNG."""
    supersample: int = 1
    """Colour samples per pixel along each axis (ss x ss, averaged: anti-aliasing); depth is the
    pixel centre's."""
    textures: str = "filtered"
    """How surface detail meets the pixels: ``filtered`` (each colour sample averages the detail finer than the
    surface it covers, and the ground and roofs carry weathering at 0.3-2 m: what a camera records, and what structure-from-motion
    matches between photos) or ``point-sampled`` (each sample takes the colour at its
    point, a speckle that changes with the view: generator version 2's pixels)."""
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
        if self.textures not in TEXTURES:
            raise ValueError(f"TownConfig.textures must be one of {list(TEXTURES)}, got {self.textures!r}")
        if self.capture not in CAPTURES:
            raise ValueError(f"TownConfig.capture must be one of {list(CAPTURES)}, got {self.capture!r}")
        altitude = self.aerial_altitude
        if not (isinstance(altitude, (int, float, np.integer, np.floating)) and math.isfinite(altitude) and altitude > 0.0):
            raise ValueError(f"TownConfig.aerial_altitude must be a positive finite number of metres, got {altitude!r}")
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
        values.setdefault("textures", "point-sampled")  # scenes of generator versions 1 and 2 (no textures key)
        return cls(**values)


def blocks_for_extent(extent: float, block_size: float = TownConfig.block_size, street_width: float = TownConfig.street_width) -> int:
    """City blocks along one axis for a street grid about ``extent`` metres across (at least 1)."""
    if not (math.isfinite(extent) and extent > 0):
        raise ValueError(f"extent must be a positive number of metres, got {extent!r}")
    return max(1, int(round((extent - street_width) / (block_size + street_width))))
