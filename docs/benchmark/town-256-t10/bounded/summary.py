"""The table of docs/notebook/town.md's section "The scene bounded by its depth images", from the runs of
run.sh: python docs/benchmark/town-256-t10/bounded/summary.py [RUNS_DIR]"""

import json
import sys
from pathlib import Path

import numpy as np

runs = Path(sys.argv[1] if len(sys.argv) > 1 else "outputs/bench-town256-t10-bounded/runs")


def load(name):
    path = runs / f"{name}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def at_wall_clock(result, seconds):
    """PSNR of a one-model run read off its curve at ``seconds`` of training (linear between evaluations)."""
    times = [0.0] + [point["train_s"] for point in result["curve"]]
    psnrs = [float("nan")] + [point["psnr"] for point in result["curve"]]
    if seconds >= times[-1]:
        return psnrs[-1]
    return float(np.interp(seconds, times[1:], psnrs[1:])) if seconds >= times[1] else float("nan")


print("| seed | NGP_10 | NGP_12 | global alone | blocks `nearest` | blocks `nearest-idw` | wall-clock, 8 workers | NGP_10 there | blocks - NGP_10 (equal wall-clock) | blocks - NGP_12 | within 25 %: NGP_10 / NGP_12 / blocks |")
print("|---|---|---|---|---|---|---|---|---|---|---|")
for seed in (1, 42):
    ngp10, ngp12, glob, blocks = (load(f"{n}-seed{seed}") for n in ("ngp10", "ngp12", "global", "blocks"))
    if ngp10 is None or glob is None or blocks is None:
        continue
    wall = glob["train_s"] + max(blocks["block_train_s"].values())
    there = at_wall_clock(ngp10, wall)
    nearest, idw = blocks["fusions"]["nearest"], blocks["fusions"]["nearest-idw"]
    n12 = ngp12["final"]["psnr"] if ngp12 else float("nan")
    d12 = ngp12["final"].get("depth_delta1", float("nan")) if ngp12 else float("nan")
    print(f"| {seed} | {ngp10['final']['psnr']:.2f} | {n12:.2f} | {glob['final']['psnr']:.2f} | {nearest['psnr']:.2f} | {idw['psnr']:.2f} "
          f"| {glob['train_s']:.0f} + {max(blocks['block_train_s'].values()):.0f} = {wall:.0f} s | {there:.2f} "
          f"| **{nearest['psnr'] - there:+.2f}** ({idw['psnr'] - there:+.2f}) | **{nearest['psnr'] - n12:+.2f}** ({idw['psnr'] - n12:+.2f}) "
          f"| {100 * ngp10['final']['depth_delta1']:.1f} / {100 * d12:.1f} / {100 * nearest['depth_delta1']:.1f} % |")
