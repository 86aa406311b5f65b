"""The facade scene: a painted wall whose mural never repeats, its geometry as
written, and ``scalar-nerf-make-scene --scene facade``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from scalar_nerfstudio.scenes.facade import Mural, facade_camera_poses, render_facade


def test_rays_meet_the_wall_and_the_ground_where_they_are() -> None:
    mural = Mural(-10.0, 50.0, seed=0)
    origins = np.array([[5.0, 4.0, 1.5], [5.0, 4.0, 1.5], [5.0, 4.0, 1.5], [5.0, 4.0, 1.5]])
    directions = np.array([[0.0, -1.0, 0.0], [0.0, -0.6, -0.8], [0.0, 0.0, 1.0], [0.0, -0.6, 0.8]])
    rgb, depth = render_facade(origins, directions, mural)
    assert depth[0] == 4.0  # square on to the wall, 4 m away
    assert np.isclose(depth[1], 1.5 / 0.8)  # steeply down: the ground, before the wall
    assert np.isinf(depth[2]) and np.isinf(depth[3])  # straight up, and over the top of the 6 m wall: the sky
    assert np.allclose(rgb[1], rgb[1].mean(), atol=0.05) and not np.allclose(rgb[0], rgb[1])
    assert np.isfinite(rgb).all() and (rgb >= 0).all() and (rgb <= 1).all()


def test_the_mural_does_not_repeat_along_the_wall() -> None:
    """What a model must hold grows with the wall: any two stretches of it are unlike each other."""
    mural = Mural(-10.0, 50.0, seed=0)
    x, z = np.meshgrid(np.linspace(0.0, 5.0, 50), np.linspace(0.5, 4.5, 40))
    stretches = [mural.colour(x.ravel() + offset, z.ravel()) for offset in (0.0, 10.0, 20.0, 30.0)]
    contrast = np.std(stretches[0])
    assert contrast > 0.15, contrast
    for a in range(4):
        for b in range(a + 1, 4):
            assert np.abs(stretches[a] - stretches[b]).mean() > 0.15
    assert not np.allclose(Mural(-10.0, 50.0, seed=1).colour(x.ravel(), z.ravel()), stretches[0])


def test_cameras_walk_the_wall_and_look_at_it() -> None:
    poses = facade_camera_poses(24, length=40.0, seed=0)
    centres, axes = poses[:, :3, 3], -poses[:, :3, 2]
    assert centres[:, 0].min() < 2.0 and centres[:, 0].max() > 38.0 and np.allclose(centres[:, 1], 4.0)
    assert (axes[:, 1] < -0.8).all()  # every camera faces the wall
    assert np.allclose(np.linalg.det(poses[:, :3, :3]), 1.0)


def test_make_scene_writes_the_facade_the_same_for_the_same_seed(tmp_path: Path) -> None:
    def make(folder: str, seed: str) -> Path:
        result = subprocess.run(
            [sys.executable, "-m", "scalar_nerfstudio.scripts.make_scene", "--scene", "facade", "--output", str(tmp_path / folder),
             "--num-images", "6", "--width", "24", "--height", "18", "--wall-length", "12", "--seed", seed],
            capture_output=True, text=True, check=False, timeout=120)
        assert result.returncode == 0, result.stderr
        assert "facade (6 frames along 12 m of wall)" in result.stdout
        return tmp_path / folder

    first, again, other = make("a", "3"), make("b", "3"), make("c", "4")
    transforms = json.loads((first / "transforms.json").read_text())
    assert len(transforms["frames"]) == 6 and (transforms["w"], transforms["h"]) == (24, 18)
    for frame in transforms["frames"]:
        image = Image.open(first / frame["file_path"])
        assert image.size == (24, 18)
        assert (again / frame["file_path"]).read_bytes() == (first / frame["file_path"]).read_bytes()
    assert (other / "images" / "frame_00000.png").read_bytes() != (first / "images" / "frame_00000.png").read_bytes()
