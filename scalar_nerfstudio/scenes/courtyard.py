"""A procedural courtyard scene written in nerfstudio format: the project's own default scene.

Users outside this repository have no test data, so the quick start generates this one. It has
known geometry (a textured ground plane, textured boxes, a sky gradient at infinity) and cameras
spread over an area like a large-scale capture, so block splitting has something to split.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scalar_nerfstudio.scenes.frames import write_frames

_SKY_ZENITH = np.array([0.35, 0.55, 0.85])
_SKY_HORIZON = np.array([0.85, 0.9, 0.95])


@dataclass(frozen=True)
class Box:
    """An axis-aligned box: [3] minimum and maximum corners (metres) and a base colour in [0, 1]."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    colour: tuple[float, float, float]


DEFAULT_BOXES: tuple[Box, ...] = (
    Box((-5.0, -4.0, 0.0), (-3.5, -1.0, 2.5), (0.8, 0.3, 0.2)),
    Box((3.0, 2.0, 0.0), (5.0, 3.5, 1.5), (0.2, 0.6, 0.3)),
    Box((-1.0, 3.5, 0.0), (1.5, 5.0, 3.0), (0.3, 0.35, 0.8)),
    Box((1.0, -4.5, 0.0), (2.5, -3.0, 1.0), (0.9, 0.8, 0.2)),
    Box((-0.4, -0.4, 0.0), (0.4, 0.4, 0.8), (0.7, 0.4, 0.7)),
    Box((-6.5, -6.5, 0.0), (6.5, -6.0, 2.0), (0.6, 0.55, 0.5)),
    Box((-6.5, 6.0, 0.0), (6.5, 6.5, 2.0), (0.55, 0.5, 0.45)),
    Box((6.0, -6.0, 0.0), (6.5, 6.0, 2.0), (0.5, 0.5, 0.55)),
    Box((-6.5, -6.0, 0.0), (-6.0, 6.0, 2.0), (0.45, 0.5, 0.5)),
)


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[3] camera position and look-at target -> [4, 4] camera-to-world, OpenGL axes (looks along -z)."""
    forward = target - position
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    right = right / np.linalg.norm(right)
    up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -forward, position
    return c2w


def _ray_box(origins: np.ndarray, directions: np.ndarray, box: Box) -> tuple[np.ndarray, np.ndarray]:
    """Slab test: [P, 3] rays -> ([P] entry distance (inf on a miss), [P, 3] outward face normal)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / directions
        t0 = (np.array(box.lo) - origins) * inv
        t1 = (np.array(box.hi) - origins) * inv
    t_near_axes = np.minimum(t0, t1)
    t_near = np.nanmax(t_near_axes, axis=1)
    t_far = np.nanmin(np.maximum(t0, t1), axis=1)
    hit = (t_far >= t_near) & (t_near > 1e-4)
    axis = np.nanargmax(t_near_axes, axis=1)
    normals = np.zeros_like(origins)
    normals[np.arange(len(axis)), axis] = -np.sign(directions[np.arange(len(axis)), axis])
    return np.where(hit, t_near, np.inf), normals


def _texture(points: np.ndarray) -> np.ndarray:
    """[P, 3] world points -> [P] brightness pattern in [0.55, 1] (checker + stripes + ripples)."""
    checker = (np.floor(points[:, 0] * 2.0) + np.floor(points[:, 1] * 2.0) + np.floor(points[:, 2] * 2.0)) % 2
    ripples = 0.5 + 0.5 * np.sin(7.0 * points[:, 0] + 3.0 * np.sin(5.0 * points[:, 1]) + 4.0 * points[:, 2])
    return 0.55 + 0.25 * checker + 0.2 * ripples


def render_rays(origins: np.ndarray, directions: np.ndarray, boxes: tuple[Box, ...] = DEFAULT_BOXES) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast the courtyard.

    Args:
        origins, directions: [P, 3] ray origins (metres) and unit directions.

    Returns:
        rgb: [P, 3] in [0, 1]; depth: [P] distance along the ray to the first hit (inf for sky).
    """
    light = np.array([0.4, 0.3, 0.85]) / np.linalg.norm([0.4, 0.3, 0.85])
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = np.where(directions[:, 2] < -1e-6, -origins[:, 2] / directions[:, 2], np.inf)
    depth = t_ground.copy()
    base = np.tile(np.array([0.55, 0.5, 0.42]), (len(origins), 1))
    normals = np.tile(np.array([0.0, 0.0, 1.0]), (len(origins), 1))
    for box in boxes:
        t_box, box_normals = _ray_box(origins, directions, box)
        closer = t_box < depth
        depth[closer] = t_box[closer]
        base[closer] = box.colour
        normals[closer] = box_normals[closer]
    hit = np.isfinite(depth)
    points = origins + directions * np.where(hit, depth, 0.0)[:, None]
    shade = 0.45 + 0.55 * np.clip(normals @ light, 0.0, 1.0)
    surface = base * (_texture(points) * shade)[:, None]
    up = np.clip(directions[:, 2], 0.0, 1.0)[:, None]
    sky = _SKY_HORIZON * (1.0 - up) + _SKY_ZENITH * up
    return np.clip(np.where(hit[:, None], surface, sky), 0.0, 1.0), depth


def default_camera_poses(num_images: int, seed: int = 0) -> np.ndarray:
    """[N, 4, 4] camera-to-world poses walking a loop through the courtyard, looking around it."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(0.0, 2.0 * np.pi, num_images, endpoint=False)
    radius_x, radius_y = 4.0, 3.0
    poses = []
    for i, angle in enumerate(angles):
        position = np.array([radius_x * np.cos(angle), radius_y * np.sin(angle), 1.4 + 0.2 * rng.random()])
        heading = angle + np.pi + (0.9 if i % 2 else -0.9) + 0.3 * rng.standard_normal()
        target = position + np.array([np.cos(heading), np.sin(heading), -0.25])
        poses.append(look_at(position, target))
    return np.stack(poses)


def write_scene(out_dir: Path, *, num_images: int = 40, width: int = 160, height: int = 120, seed: int = 0) -> Path:
    """Render the courtyard from ``num_images`` cameras and write ``transforms.json`` + ``images/``.

    Returns:
        The path of the written ``transforms.json``.
    """
    return write_frames(out_dir, default_camera_poses(num_images, seed), render_rays, width=width, height=height)
