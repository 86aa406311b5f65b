"""Resident memory of an evaluation over a trained run's eval views, with and without giving the freed
memory back to the operating system (``scalar_nerfstudio/engine/memory.py``).

    python benchmarks/bench_eval_memory.py --load-config RUN/config.yml [--views 40]

Each configuration runs in a fresh process (peak RSS is per process): it loads the run as ``ns-eval``
does, renders its first ``--views`` eval views one after the other as nerfstudio's evaluation does
(camera render, then metrics), and prints the resident memory after loading and its peak, and the
render time per view. Releases: ``off`` never (the behaviour before 2026-11-27), ``every`` after
every view, ``default`` once resident memory has grown by 2 GiB since the last release.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import resource
import subprocess
import sys
import time
from pathlib import Path
from unittest import mock

RELEASES = ("off", "every", "default")


def measure(config: Path, views: int, release: str) -> dict:
    """One configuration, in this process."""
    import torch
    from nerfstudio.utils.eval_utils import eval_setup

    from scalar_nerfstudio.engine.memory import HeapRelease, resident_mib

    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    pipeline.eval()
    loaded_mib = resident_mib()
    loader = pipeline.datamanager.fixed_indices_eval_dataloader
    count = min(views, len(loader))
    if release == "every":
        pipeline.model.heap_release = HeapRelease(growth_mib=0.0)
    never = mock.patch.object(HeapRelease, "__call__", lambda self: False)
    start = time.perf_counter()
    with torch.no_grad(), (never if release == "off" else contextlib.nullcontext()):
        for index in range(count):
            camera, batch = loader.get_camera(loader.image_indices[index])
            outputs = pipeline.model.get_outputs_for_camera(camera=camera)
            pipeline.model.get_image_metrics_and_images(outputs, batch)
            del outputs
    seconds = time.perf_counter() - start
    return {
        "release": release, "views": count, "loaded_rss_mib": round(loaded_mib),
        "peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "end_rss_mib": round(resident_mib()), "ms_per_view": round(1000 * seconds / max(count, 1)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--load-config", type=Path, required=True, help="a trained run's config.yml")
    parser.add_argument("--views", type=int, default=40, help="eval views to render (the first ones)")
    parser.add_argument("--releases", nargs="+", choices=RELEASES, default=list(RELEASES))
    parser.add_argument("--one", choices=RELEASES, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(measure(args.load_config, args.views, args.one)))
        return
    print(f"{'release':>8} {'views':>6} {'RSS loaded MiB':>15} {'peak RSS MiB':>13} {'RSS at end MiB':>15} {'ms/view':>8}")
    for release in args.releases:
        out = subprocess.run([sys.executable, __file__, "--load-config", str(args.load_config), "--views", str(args.views), "--one", release],
                             capture_output=True, text=True, check=False)
        if out.returncode != 0:
            raise SystemExit(f"release {release} failed:\n{out.stderr[-2000:]}")
        row = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"{row['release']:>8} {row['views']:>6} {row['loaded_rss_mib']:>15} {row['peak_rss_mib']:>13} {row['end_rss_mib']:>15} {row['ms_per_view']:>8}")


if __name__ == "__main__":
    main()
