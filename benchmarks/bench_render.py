"""Render time of a trained run's held-out views (issue 18: a 192x128 view of a global model in <= 0.3 s).

Loads ``RUN/config.yml`` as ``ns-eval`` does, renders every eval view once to warm up (kernel builds,
the allocator's first growth), then renders them ``--rounds`` more times per fusion mode and prints
the median and fastest time per view, and the held-out PSNR of the last round. Each mode is timed
in alternating rounds, so a slow moment of the machine does not fall on one mode only.

    python benchmarks/bench_render.py --load-config outputs/bench_training/runs/castle-P30/scalar-nerf/<ts>/config.yml
    python benchmarks/bench_render.py --load-config RUN/config.yml --fusion nearest global-only --json out.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Dict, List


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--load-config", type=Path, required=True, help="RUN/config.yml of a trained scalar-nerf run")
    parser.add_argument("--fusion", nargs="+", default=["global-only"], help="fusion modes to time (a run with K = 1 has global-only)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    import torch
    from nerfstudio.utils.eval_utils import eval_setup

    from scalar_nerfstudio.metrics import psnr

    _, pipeline, _, _ = eval_setup(args.load_config, test_mode="test")
    model = pipeline.model
    dataset = pipeline.datamanager.eval_dataset
    cameras = dataset.cameras
    targets = [dataset[i]["image"][..., :3] for i in range(len(cameras))]
    times: Dict[str, List[float]] = {mode: [] for mode in args.fusion}
    scores: Dict[str, List[float]] = {}
    with torch.no_grad():
        for round_index in range(args.rounds + 1):  # round 0 warms up and is not counted
            for mode in args.fusion:
                model.set_fusion(mode)
                scores[mode] = []
                for index in range(len(cameras)):
                    start = time.perf_counter()
                    outputs = model.get_outputs_for_camera(cameras[index : index + 1])
                    if round_index > 0:
                        times[mode].append(time.perf_counter() - start)
                    scores[mode].append(float(psnr(outputs["rgb"].clamp(0.0, 1.0), targets[index].to(outputs["rgb"]))))
    height, width = int(cameras.height[0]), int(cameras.width[0])
    results = []
    print(f"{args.load_config}: {len(cameras)} eval views of {width}x{height}, {torch.get_num_threads()} threads, {args.rounds} rounds")
    for mode in args.fusion:
        row = {"fusion": mode, "median_ms": 1000 * statistics.median(times[mode]), "min_ms": 1000 * min(times[mode]),
               "psnr": sum(scores[mode]) / len(scores[mode]), "views": len(cameras), "width": width, "height": height}
        results.append(row)
        print(f"{mode:<12} median {row['median_ms']:.0f} ms / view, fastest {row['min_ms']:.0f} ms, held-out PSNR {row['psnr']:.2f} dB")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"config": str(args.load_config), "threads": torch.get_num_threads(), "rounds": args.rounds, "results": results}, indent=2))


if __name__ == "__main__":
    main()
