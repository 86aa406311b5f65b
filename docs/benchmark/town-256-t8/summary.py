"""The table of docs/notebook/town.md's section "Tables of 2^8", from the runs of run.sh:
python docs/benchmark/town-256-t8/summary.py [RUNS_DIR]"""

import json
import sys
from pathlib import Path

import numpy as np

runs = Path(sys.argv[1] if len(sys.argv) > 1 else "outputs/bench-town256-t8/runs")


def load(name):
    path = runs / f"{name}.json"
    return json.loads(path.read_text()) if path.is_file() else None


def at_wall_clock(result, seconds):
    """PSNR of a one-model run read off its curve at ``seconds`` of training (linear between evaluations)."""
    times = [point["train_s"] for point in result["curve"]]
    psnrs = [point["psnr"] for point in result["curve"]]
    if seconds >= times[-1]:
        return psnrs[-1]
    return float(np.interp(seconds, times, psnrs)) if seconds >= times[0] else float("nan")


def psnr(result):
    return result["final"]["psnr"] if result else float("nan")


def within(result, key="final"):
    return 100 * result[key]["depth_delta1"] if result else float("nan")


print("| seed | NGP_8 | NGP_10 | NGP_10 - NGP_8 | global alone | blocks `nearest` | blocks `nearest-idw` | wall-clock, 8 workers "
      "| NGP_8 there | blocks - NGP_8 (equal wall-clock) | blocks - NGP_8 (6400 steps per worker) | blocks - NGP_10 "
      "| within 25 %: NGP_8 / NGP_10 / blocks |")
print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
for seed in (42, 1):
    ngp8, ngp10, glob, blocks = (load(f"{n}-seed{seed}") for n in ("ngp8", "ngp10", "global", "blocks"))
    if ngp8 is None or glob is None or blocks is None:
        continue
    slowest = max(blocks["block_train_s"].values())
    wall = glob["train_s"] + slowest
    there = at_wall_clock(ngp8, wall)
    nearest, idw = blocks["fusions"]["nearest"], blocks["fusions"]["nearest-idw"]
    print(f"| {seed} | {psnr(ngp8):.2f} | {psnr(ngp10):.2f} | {psnr(ngp10) - psnr(ngp8):+.2f} | {psnr(glob):.2f} "
          f"| {nearest['psnr']:.2f} | {idw['psnr']:.2f} | {glob['train_s']:.0f} + {slowest:.0f} = {wall:.0f} s | {there:.2f} "
          f"| **{nearest['psnr'] - there:+.2f}** ({idw['psnr'] - there:+.2f}) "
          f"| {nearest['psnr'] - psnr(ngp8):+.2f} "
          f"| **{nearest['psnr'] - psnr(ngp10):+.2f}** ({idw['psnr'] - psnr(ngp10):+.2f}) "
          f"| {within(ngp8):.1f} / {within(ngp10):.1f} / {100 * nearest['depth_delta1']:.1f} % |")

print()
print("| seed 42, the same global model | blocks `nearest` | `nearest-idw` | wall-clock, 8 workers | - NGP_8 (equal wall-clock) | - NGP_10 | within 25 % |")
print("|---|---|---|---|---|---|---|")
ngp8, ngp10, glob = load("ngp8-seed42"), load("ngp10-seed42"), load("global-seed42")
for name, label in (("blocks-seed42", "copies of the global model (`global`, the default)"),
                    ("blocks-fresh-seed42", "fresh tables of 2^8 in the block's frame (`fresh`, the paper's)"),
                    ("blocks-fitted-seed42", "the same, fitted to the global model first (`fitted`)")):
    blocks = load(name)
    if blocks is None or ngp8 is None or glob is None:
        continue
    slowest = max(blocks["block_train_s"].values())
    wall = glob["train_s"] + slowest
    nearest, idw = blocks["fusions"]["nearest"], blocks["fusions"]["nearest-idw"]
    print(f"| {label} | {nearest['psnr']:.2f} | {idw['psnr']:.2f} | {glob['train_s']:.0f} + {slowest:.0f} = {wall:.0f} s "
          f"| {nearest['psnr'] - at_wall_clock(ngp8, wall):+.2f} | {nearest['psnr'] - psnr(ngp10):+.2f} | {100 * nearest['depth_delta1']:.1f} % |")
