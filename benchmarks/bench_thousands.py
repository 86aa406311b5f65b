"""Training at thousands of views: memory, time per step and the plan's time against the number of views.

    python benchmarks/bench_thousands.py [--views 1000 3000] [--size 512 384] [--town 8 8] [--out FILE.json]

For each number of views, one generated town (``scalar-nerf-make-scene``'s: ``--town`` city blocks, an aerial
sweep and a street rig, ``--capture aerial+rig``) is written into ``--work`` (kept: a later call reuses it), and
``ns-train scalar-nerf`` is set up and trained on it in a fresh process, with the method's defaults (automatic K
and tables, the bounded image cache, every 8th view held out) but few steps (``--global-steps``, and
``--block-steps`` for every block). Printed per number of views:

* the scene's writing time;
* the set-up time (parsing the cameras, the plan: K, split and tables, the datamanager and the model) and the plan:
  K, the tables' rows, the steps the default length would train (from the capture, not the few trained here);
* the median time of a global step and of a block step (a block's first steps and the first global ones are
  left out: they build caches), and the whole training time through every block's phase;
* peak resident memory of the training process (``wait4`` of the child).

The last line gives the ratios of the most views' row to the fewest's. ``--resume`` keeps the rows already in
``--out`` (for any number of views) when they were measured with the same other settings, and refuses otherwise.
Run nothing else meanwhile: the times are wall-clock on shared cores; name the CPU with the figures.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Dict, List, Tuple

from bench_scale import run_measured  # a child's own peak RSS (this folder's scripts import each other)

WARMUP_GLOBAL_STEPS = 10
"""Global steps left out of the median (the first steps build caches and the occupancy grid)."""
WARMUP_BLOCK_STEPS = 3
"""Steps of each block left out of the median (its decoder and table are copied on its first step)."""


def town_config(args: argparse.Namespace, views: int, **options: Any):
    """The ``TownConfig`` of ``views`` views from the options this script and bench_process_town.py share
    (``--size``, ``--town``, ``--capture``), with ``options`` on top."""
    from scalar_nerfstudio.scenes.town import TownConfig

    return TownConfig(num_images=views, width=args.size[0], height=args.size[1], blocks_x=args.town[0], blocks_y=args.town[1],
                      capture=args.capture, **options)


def write_scene(folder: Path, views: int, args: argparse.Namespace) -> float:
    """Write the town of ``views`` views into ``folder`` unless a finished one is there; seconds spent (0: reused)."""
    if (folder / "transforms.json").is_file():
        return 0.0
    from scalar_nerfstudio.scenes.town import write_town

    start = time.perf_counter()
    write_town(folder, town_config(args, views), progress=False, overwrite=True, workers=args.workers)
    return time.perf_counter() - start


def train_in_this_process(scene: Path, output: Path, global_steps: int, block_steps: int) -> Dict[str, Any]:
    """Set up and train ``ns-train scalar-nerf`` on ``scene`` (the benchmark runner's set-up); its figures."""
    import torch

    from scalar_nerfstudio.benchmarking.runner import setup_trainer, trainer_config
    from scalar_nerfstudio.blocks.length import length_from_capture
    from scalar_nerfstudio.engine.timing import time_train_iterations

    spec = {"method": "scalar-nerf", "data": str(scene), "downscale": 1, "output_dir": str(output),
            "overrides": {"pipeline.global_steps": global_steps, "pipeline.block_steps": block_steps}}
    config = trainer_config(spec)
    config.set_timestamp()
    start = time.perf_counter()
    trainer = setup_trainer(config)
    setup_s = time.perf_counter() - start
    pipeline = trainer.pipeline
    plan = pipeline.plan
    cameras = pipeline.datamanager.train_dataset.cameras
    pixels = (cameras.width * cameras.height).to(torch.int64).flatten().tolist()  # [N_train]
    held = [plan.split.blocks[k] for k in plan.held_blocks] if not plan.single_model else []
    default_length = length_from_capture(
        replace(config.pipeline.length_settings(), global_steps=None, block_steps=None),
        train_pixels=sum(pixels), block_pixels=[sum(pixels[i] for i in block.image_indices) for block in held],
    )
    busy: List[Tuple[int, float]] = []  # (step, seconds inside the steps so far)
    time_train_iterations(trainer, lambda step, result, clock: busy.append((step, clock.busy_s)))
    start = time.perf_counter()
    trainer.train()
    train_s = time.perf_counter() - start
    global_ms: List[float] = []
    block_ms: List[float] = []
    previous = 0.0
    for step, spent_so_far in busy:
        phase = pipeline.phase_at(step)
        spent, previous = 1000 * (spent_so_far - previous), spent_so_far
        if phase.block is None and step >= WARMUP_GLOBAL_STEPS:
            global_ms.append(spent)
        elif phase.block is not None and step >= phase.start_step + WARMUP_BLOCK_STEPS:
            block_ms.append(spent)
    return {
        "train_images": len(pixels), "train_pixels": sum(pixels), "setup_s": round(setup_s, 1),
        "blocks": plan.split.num_blocks, "auto_blocks": plan.auto_num_blocks,
        "block_log2_tables": sorted({c.log2_hashmap_size for c in plan.capacities.values()}),
        "global_log2_table": int(config.pipeline.model.field.log2_hashmap_size),
        "default_global_steps": default_length.global_steps, "default_block_steps": default_length.block_steps if held else None,
        "global_ms_per_step": round(statistics.median(global_ms), 1) if global_ms else None,
        "block_ms_per_step": round(statistics.median(block_ms), 1) if block_ms else None,
        "steps": len(busy), "train_s": round(train_s, 1),
    }


def measure(views: int, args: argparse.Namespace) -> Dict[str, Any]:
    """One row: the scene written (or reused), then a fresh process sets up and trains on it."""
    name = f"{args.capture}-{views}-{args.size[0]}x{args.size[1]}-{args.town[0]}x{args.town[1]}"
    scene = args.work / f"town-{name}"
    write_s = write_scene(scene, views, args)
    command = [sys.executable, __file__, "--child", str(scene), "--child-output", str(args.work / f"runs-{name}"),
               "--global-steps", str(args.global_steps), "--block-steps", str(args.block_steps)]
    trained = run_measured(command)
    row = json.loads(trained["output"].strip().splitlines()[-1])
    return {"views": views, "write_s": round(write_s, 1), **row, "peak_rss_mib": trained["peak_rss_mib"]}


COLUMNS = (("views", 6), ("write_s", 8), ("setup_s", 8), ("blocks", 6), ("global_log2_table", 6), ("block_log2_tables", 12), ("default_global_steps", 8),
           ("default_block_steps", 8), ("global_ms_per_step", 9), ("block_ms_per_step", 9), ("train_s", 8), ("peak_rss_mib", 9))
HEADER = ("views", "write s", "setup s", "K", "2^T", "blocks 2^", "global", "block", "global ms", "block ms", "train s", "peak MiB")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, nargs="+", default=[1000, 3000], help="views of each town (every 8th held out)")
    parser.add_argument("--size", type=int, nargs=2, default=[512, 384], metavar=("W", "H"))
    parser.add_argument("--town", type=int, nargs=2, default=[8, 8], metavar=("X", "Y"), help="city blocks of the town")
    parser.add_argument("--capture", default="aerial+rig")
    parser.add_argument("--workers", type=int, default=2, help="processes writing a scene's frames")
    parser.add_argument("--global-steps", type=int, default=200)
    parser.add_argument("--block-steps", type=int, default=20)
    parser.add_argument("--work", type=Path, default=Path("outputs/bench-thousands"), help="scenes and runs (kept)")
    parser.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    parser.add_argument("--resume", action="store_true", help="keep the rows already in --out")
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--child-output", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(train_in_this_process(args.child, args.child_output, args.global_steps, args.block_steps)))
        return

    settings = {k: v for k, v in vars(args).items() if k not in ("views", "work", "out", "resume", "child", "child_output")}
    rows: List[Dict[str, Any]] = []
    if args.resume and args.out is not None and args.out.is_file():
        kept = json.loads(json.dumps(settings, default=str))
        saved = json.loads(args.out.read_text())
        if saved["settings"] != kept:
            raise SystemExit(f"--resume: {args.out} was measured with other settings ({saved['settings']}); give those, or another --out")
        rows = saved["rows"]
    args.work.mkdir(parents=True, exist_ok=True)
    print(f"towns of {args.town[0]} x {args.town[1]} city blocks, {args.capture}, {args.size[0]}x{args.size[1]}; "
          f"{args.global_steps} global + K x {args.block_steps} block steps; work folder {args.work}")
    print(" ".join(f"{name:>{width}}" for name, (_, width) in zip(HEADER, COLUMNS)))
    for views in args.views:
        row = next((r for r in rows if r["views"] == views), None)
        if row is None:
            row = measure(views, args)
            rows.append(row)
            if args.out is not None:
                args.out.write_text(json.dumps({"settings": settings, "rows": sorted(rows, key=lambda r: r["views"])},
                                               indent=2, default=str) + "\n")
        print(" ".join(f"{str(row[key]):>{width}}" for key, width in COLUMNS), flush=True)
    rows = sorted((r for r in rows if r["views"] in args.views), key=lambda r: r["views"])
    first, last = rows[0], rows[-1]
    if len(rows) > 1:
        ratios = {key: last[key] / first[key] for key in ("peak_rss_mib", "global_ms_per_step", "block_ms_per_step")
                  if first.get(key) and last.get(key)}
        print(f"{last['views']} views against {first['views']}: " + ", ".join(f"{k} x{v:.2f}" for k, v in ratios.items()))


if __name__ == "__main__":
    main()
