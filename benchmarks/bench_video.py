"""How long a video takes: ``ns-render camera-path`` on a trained run, timed as a user runs it.

Writes a camera path through the run's training cameras (positions interpolated between consecutive cameras in
file order, each frame looking as the nearer one does; the vertical field of view of the first camera), runs
``ns-render camera-path`` on it as a subprocess with the run's default fusion, and prints the wall-clock of the
command, of its frames alone (the command's time less that of the same command with one frame, so start-up and
loading are counted once), seconds per frame, and the time of a ``--video-frames`` frame video at that pace.

    python benchmarks/bench_video.py --load-config RUN/config.yml                     # 100 frames at 1280 x 720
    python benchmarks/bench_video.py --load-config RUN/config.yml --frames 20 --json out.json

``--frames`` fewer than ``--video-frames`` measures the pace on a shorter path and states the full video's time as
an extrapolation (the output says so). The frames are written as PNG images into a temporary folder.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List, Tuple

import numpy as np
from bench_render import parse_size  # WIDTHxHEIGHT, as bench_render.py takes it (same directory)


def camera_path(poses: np.ndarray, fov_deg: float, *, frames: int, width: int, height: int) -> Dict[str, Any]:
    """A nerfstudio camera path (the viewer's Render tab format) of ``frames`` poses along ``poses`` [N, 3, 4]
    (camera-to-world in the dataparser's frame, OpenGL axes): positions interpolated linearly along the
    sequence, each frame taking the rotation of the nearer camera."""
    if frames < 1 or len(poses) < 1:
        raise ValueError(f"need at least one frame and one camera, got {frames} frames and {len(poses)} cameras")
    path: List[Dict[str, Any]] = []
    for t in np.linspace(0.0, len(poses) - 1.0, frames):
        i = min(int(math.floor(t)), len(poses) - 1)
        j = min(i + 1, len(poses) - 1)
        w = float(t - i)
        pose = np.eye(4)
        pose[:3, :3] = poses[j if w >= 0.5 else i][:3, :3]
        pose[:3, 3] = (1.0 - w) * poses[i][:3, 3] + w * poses[j][:3, 3]
        path.append({"camera_to_world": pose.reshape(-1).tolist(), "fov": fov_deg, "aspect": width / height})
    return {"render_height": height, "render_width": width, "seconds": frames / 30.0, "fps": 30.0,
            "camera_type": "perspective", "camera_path": path}


def training_poses(config: Path) -> Tuple[np.ndarray, float]:
    """The run's training cameras as [N, 3, 4] camera-to-world in the dataparser's frame, and the vertical
    field of view (degrees) of the first."""
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    cameras = pipeline.datamanager.train_dataset.cameras
    poses = cameras.camera_to_worlds.detach().cpu().numpy()  # [N, 3, 4]
    fov = math.degrees(2.0 * math.atan(float(cameras.cy[0]) / float(cameras.fy[0])))
    return poses, fov


def timed_render(config: Path, path: Dict[str, Any], folder: Path) -> float:
    """Seconds of ``ns-render camera-path`` on ``path``, writing PNG frames into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    path_file = folder / "camera_path.json"
    path_file.write_text(json.dumps(path))
    command = [sys.executable, "-m", "nerfstudio.scripts.render", "camera-path", "--load-config", str(config),
               "--camera-path-filename", str(path_file), "--output-path", str(folder / "frames"),
               "--output-format", "images", "--image-format", "png"]
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - start
    if result.returncode != 0:
        sys.exit(f"ns-render failed ({result.returncode}):\n{result.stdout[-2000:]}\n{result.stderr[-2000:]}")
    written = len(list((folder / "frames").glob("*.png")))
    frames = len(path["camera_path"])
    if written != frames:
        sys.exit(f"ns-render wrote {written} frames, the path has {frames}")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--load-config", type=Path, required=True, help="RUN/config.yml of a trained scalar-nerf run")
    parser.add_argument("--frames", type=int, default=100, help="frames of the timed path (default 100)")
    parser.add_argument("--video-frames", type=int, default=100, help="frames of the video whose time is stated (default 100)")
    parser.add_argument("--size", type=parse_size, default=(1280, 720), metavar="WxH", help="frame size (default 1280x720)")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args()
    from scalar_nerfstudio.benchmarking.machine import describe_cpu

    width, height = args.size
    if not args.load_config.is_file():
        parser.error(f"--load-config {args.load_config}: no such file (a trained run's config.yml)")
    if args.frames < 2 or args.video_frames < 1:
        parser.error("--frames must be at least 2 (one frame is the start-up baseline) and --video-frames at least 1")

    poses, fov = training_poses(args.load_config)
    with tempfile.TemporaryDirectory() as tmp:
        one = timed_render(args.load_config, camera_path(poses, fov, frames=1, width=width, height=height), Path(tmp) / "one")
        full = timed_render(args.load_config, camera_path(poses, fov, frames=args.frames, width=width, height=height),
                            Path(tmp) / "path")
    per_frame = (full - one) / (args.frames - 1)
    video = one + per_frame * (args.video_frames - 1)
    figures = {
        "machine": describe_cpu(),
        "config": str(args.load_config), "size": [width, height], "frames": args.frames,
        "command_one_frame_s": round(one, 2), "command_s": round(full, 2), "per_frame_s": round(per_frame, 3),
        "us_per_pixel": round(per_frame / (width * height) * 1e6, 2),
        "video_frames": args.video_frames, "video_s": round(video, 1), "video_measured": args.frames == args.video_frames,
    }
    print(f"{figures['machine']}; ns-render camera-path, {args.frames} frames at {width} x {height}: {full:.1f} s "
          f"(one frame: {one:.1f} s, start-up and loading included)")
    print(f"{per_frame:.2f} s per frame ({figures['us_per_pixel']} us per pixel); a {args.video_frames}-frame video: "
          f"{video / 60:.1f} min" + ("" if figures["video_measured"] else f" (extrapolated from {args.frames} frames)"))
    if args.json is not None:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
