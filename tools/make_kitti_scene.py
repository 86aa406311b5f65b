#!/usr/bin/env python
"""Build a nerfstudio scene from a KITTI odometry clip with its given poses (no structure-from-motion).

The clips are those of github.com/niconielsen32/ComputerVision (VisualOdometry/KITTI_sequence_1 and
_2: 51 rectified grayscale frames of the left camera, 1226 x 370, with poses.txt, the ground-truth
camera-to-world of each frame in the first camera's frame, metres, and calib.txt, the 3 x 4
projection matrices P0 and P1):

  git clone https://github.com/niconielsen32/ComputerVision
  python tools/make_kitti_scene.py --repo ComputerVision --sequence 1 --output /path/to/kitti-1
  python tools/make_kitti_scene.py --folder ComputerVision/VisualOdometry/KITTI_sequence_1 --output ...

The scene is in metres with +z up (the first camera's up; KITTI's camera frames are x right, y down,
z forward): transforms.json (OPENCV, no distortion: the frames are rectified; OpenGL camera axes),
images/ (the frames as given) and images_2, images_4, images_8. It is written to a staging folder
beside OUTPUT and renamed into place when complete. Keep OUTPUT outside this repository.
"""

from __future__ import annotations

import argparse
import io
import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np
from PIL import Image

#: KITTI's camera-0 frame (x right, y down, z forward) -> the scene's (x right, y forward, z up).
WORLD_FROM_KITTI = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
DOWNSCALES = (2, 4, 8)


def _git_files(repo: Path, sequence: int) -> Dict[str, bytes]:
    """Relative path -> bytes of the clip's files, read from a clone or a bare copy of the repository."""
    git_dir = subprocess.run(["git", "-C", str(repo), "rev-parse", "--absolute-git-dir"], capture_output=True, text=True, check=False)
    if git_dir.returncode != 0:
        sys.exit(f"{repo}: not a git repository")
    git = ["git", "--git-dir", git_dir.stdout.strip()]
    prefix = f"VisualOdometry/KITTI_sequence_{sequence}/"
    listing = subprocess.run([*git, "ls-tree", "-r", "HEAD", "--", prefix], capture_output=True, text=True, check=True).stdout.splitlines()
    if not listing:
        sys.exit(f"{repo}: has no {prefix}")
    files = {}
    for line in listing:
        meta, path = line.split("\t", 1)
        blob = meta.split()[2]
        data = subprocess.run([*git, "cat-file", "blob", blob], capture_output=True, check=False)
        if data.returncode != 0:
            sys.exit(f"{repo}: the blob of {path} is missing (a partial copy?)")
        files[path[len(prefix):]] = data.stdout
    return files


def _folder_files(folder: Path) -> Dict[str, bytes]:
    files = {name: (folder / name).read_bytes() for name in ("poses.txt", "calib.txt") if (folder / name).is_file()}
    files.update({f"image_l/{p.name}": p.read_bytes() for p in sorted((folder / "image_l").glob("*.png"))})
    return files


def _matrices(text: str, what: str) -> np.ndarray:
    """Lines of 12 numbers -> [N, 3, 4]."""
    rows = [line.split() for line in text.splitlines() if line.strip()]
    if not rows or any(len(row) != 12 for row in rows):
        sys.exit(f"{what}: expected lines of 12 numbers (3 x 4 matrices)")
    return np.array(rows, dtype=np.float64).reshape(-1, 3, 4)


def build(files: Dict[str, bytes]) -> Tuple[dict, List[Tuple[str, bytes]]]:
    """(transforms.json, [(image name, PNG bytes)]) of a clip's files."""
    for name in ("poses.txt", "calib.txt"):
        if name not in files:
            sys.exit(f"the clip has no {name}")
    images = sorted((Path(k).name, v) for k, v in files.items() if k.startswith("image_l/") and k.endswith(".png"))
    poses = _matrices(files["poses.txt"].decode(), "poses.txt")
    projection = _matrices(files["calib.txt"].decode(), "calib.txt")[0]  # P0: the left camera
    if len(poses) != len(images):
        sys.exit(f"poses.txt has {len(poses)} poses but image_l/ has {len(images)} frames")
    with Image.open(io.BytesIO(images[0][1])) as first:
        width, height = first.size
    frames = []
    for (name, _), pose in zip(images, poses):
        c2w = np.eye(4)
        c2w[:3, :3] = WORLD_FROM_KITTI @ pose[:, :3]
        c2w[:3, 3] = WORLD_FROM_KITTI @ pose[:, 3]
        c2w[:3, 1:3] *= -1.0  # OpenCV camera axes -> OpenGL
        frames.append({"file_path": f"images/{name}", "transform_matrix": c2w.tolist()})
    transforms = {
        "camera_model": "OPENCV",
        "w": width, "h": height,
        "fl_x": float(projection[0, 0]), "fl_y": float(projection[1, 1]),
        "cx": float(projection[0, 2]), "cy": float(projection[1, 2]),
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "frames": frames,
        "applied_transform": np.eye(4)[:3].tolist(),
        "capture_frame": {"kind": "kitti", "units": "m", "note": "KITTI's first camera frame turned to z up: x right, y forward, z up"},
    }
    return transforms, images


def write(output: Path, transforms: dict, images: List[Tuple[str, bytes]]) -> None:
    staging = output.with_name(f".{output.name}.staging")
    shutil.rmtree(staging, ignore_errors=True)
    try:
        for folder in ("images", *(f"images_{f}" for f in DOWNSCALES)):
            (staging / folder).mkdir(parents=True)
        for name, data in images:
            (staging / "images" / name).write_bytes(data)
            with Image.open(io.BytesIO(data)) as image:
                image.load()
                for factor in DOWNSCALES:
                    size = (int(np.float32(image.size[0]) * np.float32(1.0 / factor)), int(np.float32(image.size[1]) * np.float32(1.0 / factor)))
                    image.resize(size, Image.Resampling.LANCZOS).save(staging / f"images_{factor}" / name)
        (staging / "transforms.json").write_text(json.dumps(transforms, indent=2) + "\n")
        staging.rename(output)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--repo", type=Path, help="a clone or bare copy of niconielsen32/ComputerVision")
    source.add_argument("--folder", type=Path, help="a clip's folder (image_l/, poses.txt, calib.txt)")
    parser.add_argument("--sequence", type=int, choices=(1, 2), default=1, help="--repo: which clip, KITTI_sequence_1 or _2 (default 1)")
    parser.add_argument("--output", type=Path, required=True, help="scene folder to create (must not exist unless --overwrite)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing OUTPUT")
    args = parser.parse_args()
    if args.output.exists() and not args.overwrite:
        sys.exit(f"{args.output} exists; pass --overwrite to replace it")
    files = _git_files(args.repo, args.sequence) if args.repo else _folder_files(args.folder)
    transforms, images = build(files)
    if args.output.exists():
        shutil.rmtree(args.output)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    write(args.output, transforms, images)
    centres = np.array([f["transform_matrix"] for f in transforms["frames"]])[:, :3, 3]
    length = float(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())
    print(f"wrote {args.output}: {len(images)} frames of {transforms['w']}x{transforms['h']}, a {length:.1f} m drive")


if __name__ == "__main__":
    main()
