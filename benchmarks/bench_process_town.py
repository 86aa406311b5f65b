"""Photos to poses at scale: ``scalar-nerf-process-data`` on the generated town's photos, against its known cameras.

    python benchmarks/bench_process_town.py [--views 1000] [--size 512 384] [--town 8 8] [--out FILE.json]

Writes the town (``scalar-nerf-make-scene``'s, ``--views`` frames) and its frames as JPEG photos with the
camera's GPS position and focal length in their EXIF (``--photos``) into ``--work`` (kept: a later call reuses
them), then runs ``scalar-nerf-process-data --images PHOTOS --output SCENE`` as a user does (a child process;
it resumes its own finished stages when run again). Printed: the command's time, the mapper it chose, the photos
registered, and the recovered cameras against the true ones after a similarity fitted to their centres:
centre errors in metres and in per cent of the capture's extent (the longest side of the true centres' box),
rotation errors in degrees. A capture the command cannot pose is reported with its error and none registered
(its log is kept beside the scene).

Run nothing else meanwhile: the time is wall-clock on shared cores; name the CPU with the figures.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import time
from pathlib import Path
from typing import Any, Dict

import numpy as np
from bench_thousands import town_config  # the town options both scripts take (same directory)


def write_capture(work: Path, args: argparse.Namespace) -> Dict[str, float]:
    """The town and its photos in ``work`` (each only when not there yet); seconds spent on each."""
    from scalar_nerfstudio.scenes.town import write_town
    from scalar_nerfstudio.scenes.town.photos import write_photos

    scene, photos = work / "town", work / "photos"
    spent = {"write_scene_s": 0.0, "write_photos_s": 0.0}
    if not (scene / "transforms.json").is_file():
        start = time.perf_counter()
        write_town(scene, town_config(args, args.views, textures=args.textures, aerial_altitude=args.altitude), progress=False, overwrite=True, workers=args.threads)
        spent["write_scene_s"] = round(time.perf_counter() - start, 1)
    if not photos.is_dir() or len(list(photos.glob("*.jpg"))) != args.views:
        start = time.perf_counter()
        write_photos(scene, photos)
        spent["write_photos_s"] = round(time.perf_counter() - start, 1)
    return spent


def camera_errors(processed: Path, scene: Path) -> Dict[str, Any]:
    """Registered photos and their cameras' errors against the town's after a similarity (recovered -> true)."""
    from scalar_nerfstudio.process import geo
    from scalar_nerfstudio.scenes.town import iter_frames

    truth = {Path(file_path).stem: pose for file_path, pose in iter_frames(scene)}  # name -> [4, 4] camera-to-world
    frames = json.loads((processed / "transforms.json").read_text())["frames"]
    recovered = {Path(f["file_path"]).stem: np.array(f["transform_matrix"], dtype=np.float64) for f in frames}
    names = sorted(set(recovered) & set(truth))
    if len(names) < 3:  # a similarity needs three cameras
        return {"photos": len(truth), "registered": len(names), "registered_share": round(len(names) / len(truth), 4)}
    rec = np.stack([recovered[n] for n in names])  # [N, 4, 4]
    true = np.stack([truth[n] for n in names])  # [N, 4, 4]
    similarity = geo.umeyama(rec[:, :3, 3], true[:, :3, 3])
    aligned = similarity.apply_to_poses(rec)
    centre_m = np.linalg.norm(aligned[:, :3, 3] - true[:, :3, 3], axis=1)  # [N]
    rotation_deg = geo.rotation_angle_deg(aligned[:, :3, :3], true[:, :3, :3])  # [N]
    centres = np.stack(list(truth.values()))[:, :3, 3]
    extent = float(np.max(centres.max(axis=0) - centres.min(axis=0)))
    return {
        "photos": len(truth), "registered": len(names), "registered_share": round(len(names) / len(truth), 4),
        "extent_m": round(extent, 2), "centre_median_m": round(float(np.median(centre_m)), 3),
        "centre_max_m": round(float(centre_m.max()), 3),
        "centre_max_share_of_extent": round(float(centre_m.max()) / extent, 5),
        "centres_within_1pc": round(float(np.mean(centre_m <= 0.01 * extent)), 4),
        "rotation_median_deg": round(float(np.median(rotation_deg)), 3), "rotation_max_deg": round(float(rotation_deg.max()), 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=1000, help="frames of the town, all written as photos")
    parser.add_argument("--size", type=int, nargs=2, default=[512, 384], metavar=("W", "H"))
    parser.add_argument("--town", type=int, nargs=2, default=[8, 8], metavar=("X", "Y"), help="city blocks of the town")
    parser.add_argument("--capture", default="aerial", help="the town's capture (scalar-nerf-make-scene --capture)")
    parser.add_argument("--textures", default="filtered", help="the town's textures (scalar-nerf-make-scene --textures)")
    parser.add_argument("--altitude", type=float, default=90.0,
                        help="flight altitude in metres (scalar-nerf-make-scene --aerial-altitude); the town's roofs reach about 50 m, "
                             "and a drone just above them sees a few roofs fill each frame, a poor geometry for structure-from-motion")
    parser.add_argument("--threads", type=int, default=2, help="process-data's --threads (and the scene writer's processes)")
    parser.add_argument("--work", type=Path, default=Path("outputs/bench-process-town"), help="town, photos and scene (kept)")
    parser.add_argument("--out", type=Path, default=None, help="write the figures as JSON here")
    args = parser.parse_args()

    work = args.work / f"{args.capture}-{args.textures}-{args.views}-{args.size[0]}x{args.size[1]}-{args.town[0]}x{args.town[1]}-{args.altitude:g}m"
    work.mkdir(parents=True, exist_ok=True)
    written = write_capture(work, args)
    command = ["scalar-nerf-process-data", "--images", str(work / "photos"), "--output", str(work / "scene"),
               "--threads", str(args.threads)]
    start = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - start
    (work / "process-data.log").write_text(result.stdout + result.stderr)
    mapper = re.search(r"mapping \((\w+)", result.stdout + result.stderr)
    figures = {"command": " ".join(command), **written, "process_data_s": round(seconds, 1), "mapper": mapper.group(1) if mapper else None,
               # the command resumes the stages an earlier call finished: its time is then that of the rest only
               "resumed_stages": "done earlier" in result.stdout + result.stderr}
    if result.returncode == 0:
        figures.update(camera_errors(work / "scene", work / "town"))
    else:  # a capture it cannot pose is a result too: its one-line error, nothing registered
        errors = [line for line in result.stderr.splitlines() if "error:" in line]
        figures.update({"photos": args.views, "registered": 0, "error": errors[-1] if errors else result.stderr[-500:]})
    for key, value in figures.items():
        print(f"{key:>28}: {value}")
    if args.out is not None:
        args.out.write_text(json.dumps({"settings": {k: v for k, v in vars(args).items() if k != "out"}, "figures": figures},
                                       indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
