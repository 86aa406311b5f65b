"""Peak memory of the training datamanager against the number of images, with and without a bounded
image cache (``--pipeline.datamanager.image-cache-mib``).

    python benchmarks/bench_image_cache.py [--images 100 800] [--budgets none 100] [--steps 300]

Each configuration runs in a fresh process (peak RSS is per process): it writes the courtyard scene
at 320x240 with N views, sets the datamanager up as training does and draws ``--steps`` batches.
The scene is written before the clock and the datamanager start, in the same process, so every row
carries the same scene-writing baseline.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def measure(num_images: int, budget: str, steps: int) -> dict:
    """One configuration, in this process."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from scalar_nerfstudio.data.datamanager import ScalarDataManagerConfig
    from scalar_nerfstudio.scenes.courtyard import write_scene

    scene = Path(tempfile.mkdtemp(prefix="bench-image-cache-"))
    write_scene(scene, num_images=num_images, width=320, height=240)
    start = time.perf_counter()
    datamanager = ScalarDataManagerConfig(
        data=scene, dataparser=NerfstudioDataParserConfig(eval_mode="interval", eval_interval=8),
        image_cache_mib=None if budget == "none" else float(budget),
    ).setup(device="cpu", test_mode="val")
    for step in range(steps):
        datamanager.next_train(step)
    return {
        "images": num_images, "budget_mib": budget, "steps": steps, "seconds": round(time.perf_counter() - start, 2),
        "cached_train_images": datamanager.train_image_dataloader.num_images_to_sample_from,
        "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=int, nargs="+", default=[100, 800])
    parser.add_argument("--budgets", nargs="+", default=["none", "100"], help="MiB, or none for the default (a quarter of available memory)")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--one", nargs=2, metavar=("IMAGES", "BUDGET"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(measure(int(args.one[0]), args.one[1], args.steps)))
        return
    print(f"{'images':>7} {'budget MiB':>11} {'cached':>7} {'peak RSS MiB':>13} {'s':>6}")
    for budget in args.budgets:
        for num_images in args.images:
            out = subprocess.run([sys.executable, __file__, "--one", str(num_images), budget, "--steps", str(args.steps)],
                                 capture_output=True, text=True, check=True).stdout
            row = json.loads(out.strip().splitlines()[-1])
            print(f"{row['images']:>7} {row['budget_mib']:>11} {row['cached_train_images']:>7} {row['peak_rss_mib']:>13} {row['seconds']:>6}")


if __name__ == "__main__":
    main()
