"""Write a procedural scene's frames in nerfstudio format: one pinhole camera model, a render per pose."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Tuple

import numpy as np
from PIL import Image

__all__ = ["RenderRays", "write_frames"]

#: ``render(origins [P, 3], unit directions [P, 3]) -> (rgb [P, 3] in [0, 1], depth [P])``.
RenderRays = Callable[[np.ndarray, np.ndarray], Tuple[np.ndarray, np.ndarray]]


def write_frames(out_dir: Path, poses: np.ndarray, render: RenderRays, *, width: int, height: int) -> Path:
    """Render ``poses`` ([N, 4, 4] camera-to-world, OpenGL axes) with ``render`` through a pinhole of focal
    length ``0.8 * width`` and write ``images/frame_XXXXX.png`` and ``transforms.json`` to ``out_dir``.

    Returns:
        The path of the written ``transforms.json``.
    """
    out_dir = Path(out_dir)
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    focal = 0.8 * width
    cx, cy = width / 2.0, height / 2.0
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    camera_dirs = np.stack([(u - cx) / focal, -(v - cy) / focal, -np.ones_like(u)], axis=-1).reshape(-1, 3)
    camera_dirs /= np.linalg.norm(camera_dirs, axis=-1, keepdims=True)
    frames = []
    for i, c2w in enumerate(poses):
        directions = camera_dirs @ c2w[:3, :3].T
        origins = np.broadcast_to(c2w[:3, 3], directions.shape)
        rgb, _ = render(origins, directions)
        name = f"images/frame_{i:05d}.png"
        Image.fromarray((rgb.reshape(height, width, 3) * 255.0 + 0.5).astype(np.uint8)).save(out_dir / name)
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
    transforms = {
        "camera_model": "OPENCV",
        "fl_x": focal, "fl_y": focal, "cx": cx, "cy": cy, "w": width, "h": height,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "frames": frames,
    }
    path = out_dir / "transforms.json"
    path.write_text(json.dumps(transforms, indent=2))
    return path
