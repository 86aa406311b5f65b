"""The town's cameras: their intrinsics and, for each capture, the camera-to-world pose of every frame.

Poses are [4, 4] camera-to-world matrices with OpenGL camera axes (the camera looks along -z, y up),
as nerfstudio's transforms.json expects, in frame order.

* ``rig``: a vehicle drives the streets and stops at even intervals; each of its cameras
  (:attr:`~.config.TownConfig.rig_headings`) takes a frame at every stop, as Block-NeRF's capture does.
* ``walk``: one frame per position along the streets, with a random heading.
* ``aerial``: a drone flies parallel flight lines over the whole town (a survey's lawnmower) looking
  down, leaning forward from the vertical by :data:`AERIAL_TILT_DEG`.
* ``aerial+rig``: both, as a city survey combines them: the first half of the frames from the drone, the
  rest from the vehicle's rig (each spread over the whole town).
"""

from __future__ import annotations

import math
from typing import Dict, List, Tuple

import numpy as np

from scalar_nerfstudio.scenes.town.config import TownConfig
from scalar_nerfstudio.scenes.town.layout import Town

__all__ = ["AERIAL_ALTITUDE_JITTER_M", "AERIAL_CLEARANCE_M", "AERIAL_TILT_DEG", "deepest_aerial_depth_m", "town_camera_poses", "town_intrinsics"]

#: ``aerial``: how far each frame's optical axis leans forward from the vertical (degrees, uniform
#: in this range). Always forward: the cameras' mean "up" then points up, which nerfstudio's
#: default orientation (``--orientation-method up``) needs; with no lean, or a lean either way,
#: the back-and-forth flight lines' "up" vectors cancel and the town would come out tilted.
AERIAL_TILT_DEG: Tuple[float, float] = (6.0, 14.0)
#: ``aerial``: the least height above the tallest roof (metres).
AERIAL_CLEARANCE_M: float = 2.0
#: ``aerial``: each frame's altitude is uniform within this many metres of ``aerial_altitude``.
AERIAL_ALTITUDE_JITTER_M: float = 0.5


def deepest_aerial_depth_m(config: TownConfig) -> float:
    """The z-depth in metres of the deepest ground pixel an ``aerial`` frame can see: an image corner on the
    side the axis leans to, at the highest lean and the highest jitter (inf when that corner looks at the
    horizon or above). The scene writer picks its depth format from it."""
    half_x = math.tan(math.radians(config.fov_x_deg) / 2.0)
    half_y = half_x * config.height / config.width
    tilt = math.radians(AERIAL_TILT_DEG[1])
    corner_down = math.cos(tilt) - half_y * math.sin(tilt)  # -z of the unnormalised corner ray (z = -1 forward)
    highest = float(config.aerial_altitude) + AERIAL_ALTITUDE_JITTER_M
    return highest / corner_down if corner_down > 0 else math.inf


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
    capture, n = town.config.capture, town.config.num_images
    if capture == "aerial":
        return _aerial_poses(town, n)
    if capture == "aerial+rig":
        aerial = (n + 1) // 2
        return np.concatenate([_aerial_poses(town, aerial), _rig_poses(town, n - aerial)])
    return _rig_poses(town, n) if capture == "rig" else _walk_poses(town)


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


def _rig_poses(town: Town, num_images: int) -> np.ndarray:
    """The ``rig`` capture of ``num_images`` = N frames: ceil(N / R) stops evenly spread over the streets, R = len(rig_headings)
    frames per stop (the last stop keeps the first cameras only). The vehicle weaves slowly across
    the lanes; each camera's heading jitters by about 3 degrees and its pitch by a few degrees up."""
    config = town.config
    rng = np.random.default_rng([config.seed, 0x816])
    segments = _walk_segments(town)
    total = float(sum(np.linalg.norm(b - a) for a, b in segments))
    headings = np.radians(np.asarray(config.rig_headings, dtype=float))
    num_stops = -(-num_images // len(headings))
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
    return poses[:num_images]


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


def _aerial_poses(town: Town, num_images: int) -> np.ndarray:
    """The ``aerial`` capture of ``num_images`` frames: a drone flies parallel flight lines along x over the whole town (its
    ring included), alternating direction (an even number of lines, so as many frames fly each
    way), lines at most half a footprint apart (50 % side overlap or more), with
    ``num_images`` frames evenly spread along the whole flight (frames are numbered in flight order,
    so a held-out frame lies between training frames a few metres away). Each camera's image rows
    run across the flight line; its axis leans forward from the vertical by ``AERIAL_TILT_DEG``;
    altitude jitters by ``AERIAL_ALTITUDE_JITTER_M`` and heading by 3 degrees.

    Raises:
        ValueError: when the altitude does not clear the tallest roof by ``AERIAL_CLEARANCE_M`` (naming
            the altitude that would do), or when the field of view reaches the horizon.
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
    if not math.isfinite(deepest_aerial_depth_m(config)):
        raise ValueError(f"TownConfig.fov_x_deg {config.fov_x_deg:g}: the aerial frames' corners would see the horizon; narrow the field of view")
    across = 2.0 * altitude * half_x  # the footprint across the flight line (image rows run across it)
    length, width = config.extent  # the town is centred on the origin; lines run along x
    num_lines = 2 * max(1, math.ceil(width / across))
    line_y = -width / 2.0 + (np.arange(num_lines) + 0.5) * (width / num_lines)
    arc = (np.arange(num_images) + 0.5) * (num_lines * length / num_images)
    line = np.minimum((arc // length).astype(np.int64), num_lines - 1)
    along = arc - line * length
    forward = line % 2 == 0
    x = np.where(forward, along - length / 2.0, length / 2.0 - along)
    yaw = np.where(forward, 0.0, math.pi) + np.radians(rng.normal(0.0, 3.0, size=num_images))
    lean = np.radians(rng.uniform(*AERIAL_TILT_DEG, size=num_images))
    z = rng.uniform(lowest, highest, size=num_images)
    poses = np.empty((num_images, 4, 4))
    for k in range(num_images):
        poses[k] = _camera_to_world(np.array([x[k], line_y[line[k]], z[k]]), float(yaw[k]), -0.5 * math.pi + float(lean[k]))
    return poses
