"""Prints the nearest-guarded table of docs/notebook/fusion.md from docs/benchmark/nearest-guarded/*/fusion.json."""

import json
import sys
from pathlib import Path

def share(row):
    return f"{100 * row['global_pixel_share']:.2f} %" if "global_pixel_share" in row else "-"


folder = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).parent)
print("| run | global model alone | `nearest` | `nearest-guarded` | guarded - nearest | pixels the guard gave the global model | ms / image nearest / guarded |")
print("|---|---|---|---|---|---|---|")
for table_file in sorted(folder.glob("*/fusion.json")):
    table = json.loads(table_file.read_text())
    near, guard, glob = table["nearest"], table["nearest-guarded"], table["global-only"]
    print(f"| {table_file.parent.name} | {glob['psnr']:.2f} | {near['psnr']:.2f} | {guard['psnr']:.2f} | "
          f"{guard['psnr'] - near['psnr']:+.4f} | {share(guard)} | {near['ms_per_image']:.0f} / {guard['ms_per_image']:.0f} |")
