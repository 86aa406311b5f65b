"""Blocks whose own field ends near the block (``--pipeline.model.block-reach``) against the same
blocks without it, from the same global checkpoint (docs/notebook/town.md, "A block's field that ends near
the block"). Reads the result JSONs kept beside this script and the baselines' in
docs/benchmark/town-3x3/t10/runs/ and docs/benchmark/town-256-t8/.

Usage: python docs/benchmark/block-reach/summary.py
"""

from __future__ import annotations

import json
from pathlib import Path

HERE = Path(__file__).resolve().parent
BENCH = HERE.parent

ROWS = [
    # (setting, blocks, result JSON)
    ("3 x 3 town, 128 x 96, 2^10, seed 42", "copies (the default, no reach)", BENCH / "town-3x3/t10/runs/auto-parallel.json"),
    ("3 x 3 town, 128 x 96, 2^10, seed 42", "reach 2", HERE / "reach2-seed42.json"),
    ("3 x 3 town, 128 x 96, 2^10, seed 42", "reach 1", HERE / "reach1-seed42.json"),
    ("2 x 2 town, 256 x 192, 2^8, seed 42", "copies (the default, no reach)", BENCH / "town-256-t8/blocks-seed42.json"),
    ("2 x 2 town, 256 x 192, 2^8, seed 42", "reach 2", HERE / "t8-reach2-seed42.json"),
]


def main() -> None:
    print("| setting | blocks | nearest-guarded (nearest) PSNR | SSIM | depth within 25 % | slowest block, s |")
    print("|---|---|---|---|---|---|")
    for setting, label, path in ROWS:
        if not path.exists():
            print(f"| {setting} | {label} | not run ({path.name} missing) | | | |")
            continue
        result = json.loads(path.read_text())
        fusions = result["fusions"]
        fused = fusions.get("nearest-guarded") or fusions["nearest"]
        nearest = fusions.get("nearest", fused)
        slowest = max(result["block_train_s"].values())
        print(f"| {setting} | {label} | {fused['psnr']:.2f} ({nearest['psnr']:.2f}) | {fused['ssim']:.3f} | "
              f"{100 * fused.get('depth_delta1', float('nan')):.1f} % | {slowest:.0f} |")


if __name__ == "__main__":
    main()
