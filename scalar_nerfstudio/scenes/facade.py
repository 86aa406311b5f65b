"""A procedural facade scene written in nerfstudio format: a long painted wall photographed on a walk along it.

The scene where one small hash table runs out of room and blocks do not: the wall carries a mural of random
colours at three scales (no two stretches alike), so what a model must hold grows with the wall's length, while
each camera sees only a few metres of it and the geometry (a plane over a plain ground) is learnt in a few steps.
A model of each stretch (a block) holds a fraction of the mural in a table of the same size. Written for the
search for a scene small enough for the test suite on which blocks beat one table (docs/notebook/story-test.md);
``scalar-nerf-make-scene --scene facade`` writes it.

Frame: the wall is the plane ``y = 0`` facing ``+y``, from ``z = 0`` to :data:`WALL_HEIGHT`; the ground is
``z = 0``; cameras walk along ``x`` at ``y = distance``, looking at the wall with headings that alternate left and
right of it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Tuple

import numpy as np

from scalar_nerfstudio.scenes.courtyard import look_at
from scalar_nerfstudio.scenes.frames import write_frames

__all__ = ["MURAL_CELLS_M", "Mural", "WALL_HEIGHT", "facade_camera_poses", "render_facade", "write_scene"]

#: Height of the wall (metres); above it, the sky.
WALL_HEIGHT: float = 6.0
#: The mural's three scales: lattice spacing (metres) and weight of each layer of random colours.
MURAL_CELLS_M: Tuple[Tuple[float, float], ...] = ((1.6, 0.4), (0.8, 0.3), (0.4, 0.3))
#: The layers' sum is stretched about mid-grey by this factor (their mean alone is a washed-out grey).
MURAL_CONTRAST: float = 1.8
#: How far the mural runs past the walk's ends (metres): the end cameras look along the wall.
_MARGIN_M: float = 12.0
_GROUND = np.array([0.5, 0.48, 0.45])
_SKY = np.array([0.7, 0.8, 0.95])


class Mural:
    """Random colours on lattices of :data:`MURAL_CELLS_M` over ``x`` in ``[x0, x1]``, interpolated bilinearly."""

    def __init__(self, x0: float, x1: float, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self.x0 = x0
        self.layers = []
        for cell, weight in MURAL_CELLS_M:
            shape = (int(np.ceil(WALL_HEIGHT / cell)) + 2, int(np.ceil((x1 - x0) / cell)) + 2, 3)
            self.layers.append((cell, weight, rng.random(shape)))

    def colour(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        """[P] wall coordinates (metres) -> [P, 3] colours in [0, 1]."""
        out = np.zeros((len(x), 3))
        for cell, weight, lattice in self.layers:
            gx = np.clip((x - self.x0) / cell, 0.0, lattice.shape[1] - 1.001)
            gz = np.clip(z / cell, 0.0, lattice.shape[0] - 1.001)
            ix, iz = np.floor(gx).astype(int), np.floor(gz).astype(int)
            fx, fz = (gx - ix)[:, None], (gz - iz)[:, None]
            top = lattice[iz, ix] * (1 - fx) + lattice[iz, ix + 1] * fx
            bottom = lattice[iz + 1, ix] * (1 - fx) + lattice[iz + 1, ix + 1] * fx
            out += weight * (top * (1 - fz) + bottom * fz)
        return np.clip(0.5 + MURAL_CONTRAST * (out - 0.5), 0.0, 1.0)


def render_facade(origins: np.ndarray, directions: np.ndarray, mural: Mural) -> Tuple[np.ndarray, np.ndarray]:
    """Ray-cast the facade.

    Args:
        origins, directions: [P, 3] ray origins (metres, ``y > 0``) and unit directions.

    Returns:
        rgb: [P, 3] in [0, 1]; depth: [P] distance along the ray to the first hit (inf for sky).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        t_wall = np.where(directions[:, 1] < -1e-9, -origins[:, 1] / directions[:, 1], np.inf)
        t_ground = np.where(directions[:, 2] < -1e-9, -origins[:, 2] / directions[:, 2], np.inf)
    wall_z = origins[:, 2] + np.where(np.isfinite(t_wall), t_wall, 0.0) * directions[:, 2]
    on_wall = np.isfinite(t_wall) & (wall_z <= WALL_HEIGHT) & (t_wall <= t_ground)
    depth = np.where(on_wall, t_wall, t_ground)
    rgb = np.tile(_SKY, (len(origins), 1))
    ground = ~on_wall & np.isfinite(t_ground)
    rgb[ground] = _GROUND
    if on_wall.any():
        hits = origins[on_wall] + t_wall[on_wall, None] * directions[on_wall]
        rgb[on_wall] = mural.colour(hits[:, 0], hits[:, 2])
    return np.clip(rgb, 0.0, 1.0), depth


def facade_camera_poses(num_images: int, *, length: float, distance: float = 4.0, seed: int = 0) -> np.ndarray:
    """[N, 4, 4] camera-to-world poses (OpenGL axes) walking along a wall ``length`` metres long at ``distance``
    metres from it, at eye height, looking at it 25 degrees left and right of square in turn."""
    rng = np.random.default_rng(seed + 1)
    xs = np.linspace(1.0, length - 1.0, num_images) + 0.1 * rng.standard_normal(num_images)
    poses = []
    for i, x in enumerate(xs):
        position = np.array([x, distance, 1.5 + 0.2 * rng.random()])
        heading = np.deg2rad((25.0 if i % 2 else -25.0) + 5.0 * rng.standard_normal())
        target = np.array([x + distance * np.tan(heading), 0.0, 1.2 + 0.6 * rng.random()])
        poses.append(look_at(position, target))
    return np.stack(poses)


def write_scene(out_dir: Path, *, num_images: int = 48, width: int = 96, height: int = 72, length: float = 40.0,
                seed: int = 0) -> Path:
    """Render the facade from ``num_images`` cameras and write ``transforms.json`` + ``images/``.

    Returns:
        The path of the written ``transforms.json``.
    """
    mural = Mural(-_MARGIN_M, length + _MARGIN_M, seed)
    return write_frames(out_dir, facade_camera_poses(num_images, length=length, seed=seed),
                        lambda origins, directions: render_facade(origins, directions, mural), width=width, height=height)
