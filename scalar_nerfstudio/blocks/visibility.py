"""Which blocks a view can see: a conservative view-frustum test of a block's scaled AABB.

Pure numpy. Cameras follow nerfstudio's (OpenGL) convention: camera-to-world ``[3, 4]``, the
camera looks down its -z axis, x right, y up; pixel (u, v) has direction
((u - cx) / fx, -(v - cy) / fy, -1) in camera coordinates.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np


def box_corners(aabb_min: Sequence[float], aabb_max: Sequence[float]) -> np.ndarray:
    """[8, 3] corners of an axis-aligned box."""
    lo, hi = np.asarray(aabb_min, dtype=np.float64), np.asarray(aabb_max, dtype=np.float64)
    return np.array([[(hi if (i >> a) & 1 else lo)[a] for a in range(3)] for i in range(8)])


def aabb_in_frustum(
    camera_to_world: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width: float,
    height: float,
    aabb_min: Sequence[float],
    aabb_max: Sequence[float],
    margin: float = 0.1,
) -> bool:
    """False only when the box is certainly outside the view frustum (all corners beyond one plane).

    Args:
        camera_to_world: [3, 4] (or [4, 4]) pose, world units.
        fx, fy, cx, cy, width, height: pinhole intrinsics and image size, pixels.
        aabb_min, aabb_max: [3] box corners, world units.
        margin: the image rectangle is widened by this fraction on each side (distortion, safety).
    """
    pose = np.asarray(camera_to_world, dtype=np.float64)[:3, :4]
    if not np.isfinite(pose).all():
        return True  # cannot decide: keep the block
    rotation, origin = pose[:, :3], pose[:, 3]
    local = (box_corners(aabb_min, aabb_max) - origin) @ rotation  # [8, 3] camera coordinates
    depth = -local[:, 2]
    x_lo, x_hi = (-cx - margin * width) / fx, (width - cx + margin * width) / fx
    y_lo, y_hi = (cy - height - margin * height) / fy, (cy + margin * height) / fy
    planes = (
        depth,                              # in front of the camera
        local[:, 0] - x_lo * depth,         # right of the left edge
        x_hi * depth - local[:, 0],         # left of the right edge
        local[:, 1] - y_lo * depth,         # above the bottom edge
        y_hi * depth - local[:, 1],         # below the top edge
    )
    return not any(bool((values < 0).all()) for values in planes)
