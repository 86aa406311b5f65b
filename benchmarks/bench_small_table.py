"""Where one table is too small: blocks against one model of the same table on a tiny aerial town.

The suite's test of the method's story (tests/test_method_story.py) trains this setting once and asks
that the blocks win by a margin. This script measures that margin over seeds, so the test's margin is
read from figures, not guessed:

    python benchmarks/bench_small_table.py --seeds 0 1 2 3 --json outputs/small_table.json

For each seed (of the training; the town is the same) it trains, in this process:

* **blocks**: ``ns-train scalar-nerf``'s phases, the global model for ``--global-steps`` and each of
  the K blocks for ``--block-steps``, then evaluates the default fusion and the global model alone;
* **one model**: the same table for ``--global-steps`` + ``--block-steps`` steps, the steps of the
  blocks' critical path on K workers (the global phase, then one block): a block's step costs at least a
  global step, so the one model gets at least the blocks' wall-clock on K workers.

It prints each seed's held-out PSNR and, over the seeds, the smallest and mean lead of the fusion over
the one model and over its own global model. Run it with nothing else on the machine only for the
timings it prints; the PSNRs do not depend on the machine's speed.
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List

#: The tiny aerial town: 3 x 2 city blocks seen from a drone, 48 frames of 64 x 48 (every 8th held out).
TOWN = dict(num_images=48, width=64, height=48, blocks_x=3, blocks_y=2, capture="aerial", seed=5)


def small_table_config(scene: Path, output_dir: Path, *, seed: int, log2_table: int, num_blocks: int, global_steps: int,
                       block_steps: int, one_model: bool) -> Any:
    """The run's ``ns-train scalar-nerf`` config: tiny sampling, the table of 2^``log2_table`` rows."""
    from scalar_nerfstudio.method_configs import scalar_nerf

    config = copy.deepcopy(scalar_nerf.config)
    config.data = scene
    config.pipeline.datamanager.data = scene
    config.output_dir = output_dir
    config.vis = "tensorboard"
    config.logging.local_writer.enable = False
    config.machine.seed = seed
    config.steps_per_save = 100_000
    field = config.pipeline.model.field
    field.log2_hashmap_size = log2_table
    field.max_resolution = 512
    config.pipeline.model.num_samples_per_ray = 32
    config.pipeline.model.occupancy_warmup_steps = 16
    config.pipeline.datamanager.train_num_rays_per_batch = 1024
    pipeline = config.pipeline
    pipeline.num_blocks = 1 if one_model else num_blocks
    pipeline.train_blocks = not one_model
    pipeline.global_steps = global_steps + block_steps if one_model else global_steps
    pipeline.block_steps = block_steps
    config.set_timestamp()
    config.save_config()
    return config


def train_and_score(config: Any) -> Dict[str, float]:
    """Train ``config`` in this process; held-out PSNR of its default fusion and of its global model alone."""
    import torch

    from scalar_nerfstudio.fusion_eval import render_eval_images

    started = time.perf_counter()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    train_s = time.perf_counter() - started
    pipeline = trainer.pipeline
    pipeline.eval()
    scores = {"train_s": train_s}
    with torch.no_grad():
        modes = ["global-only"] if config.pipeline.num_blocks == 1 else [str(pipeline.model.config.fusion), "global-only"]
        for mode in modes:
            scores[mode] = float(render_eval_images(pipeline, mode)[0]["psnr"])
    return scores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--log2-table", type=int, default=10)
    parser.add_argument("--num-blocks", type=int, default=4)
    parser.add_argument("--global-steps", type=int, default=300)
    parser.add_argument("--block-steps", type=int, default=200)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    from scalar_nerfstudio.scenes.town import TownConfig, write_town

    rows: List[Dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as folder:
        scene = Path(folder) / "town"
        write_town(scene, TownConfig(**TOWN), progress=False)
        for seed in args.seeds:
            common = dict(seed=seed, log2_table=args.log2_table, num_blocks=args.num_blocks, global_steps=args.global_steps,
                          block_steps=args.block_steps)
            blocks = train_and_score(small_table_config(scene, Path(folder) / f"blocks-{seed}", one_model=False, **common))
            one = train_and_score(small_table_config(scene, Path(folder) / f"one-{seed}", one_model=True, **common))
            fusion = next(k for k in blocks if k not in ("train_s", "global-only"))
            row = {"seed": seed, "fusion": fusion, "blocks": blocks[fusion], "global_of_blocks": blocks["global-only"],
                   "one_model": one["global-only"], "blocks_train_s": blocks["train_s"], "one_model_train_s": one["train_s"]}
            rows.append(row)
            print(f"seed {seed}: blocks ({fusion}) {row['blocks']:.2f} dB, their global model {row['global_of_blocks']:.2f}, "
                  f"one model {row['one_model']:.2f} (train {row['blocks_train_s']:.0f} s / {row['one_model_train_s']:.0f} s)",
                  flush=True)
    over_one = [r["blocks"] - r["one_model"] for r in rows]
    over_global = [r["blocks"] - r["global_of_blocks"] for r in rows]
    summary = {"town": TOWN, "settings": vars(args) | {"json": str(args.json)}, "rows": rows,
               "lead_over_one_model_db": {"min": min(over_one), "mean": statistics.mean(over_one)},
               "lead_over_its_global_model_db": {"min": min(over_global), "mean": statistics.mean(over_global)}}
    print(f"lead over one model: min {min(over_one):+.2f}, mean {statistics.mean(over_one):+.2f} dB; over its global model: "
          f"min {min(over_global):+.2f}, mean {statistics.mean(over_global):+.2f} dB ({len(rows)} seeds)")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=2))


if __name__ == "__main__":
    sys.exit(main())
