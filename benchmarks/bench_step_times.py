"""How a training step's cost changes along a run: ms per step, per window of steps, with each window's phase.

    python benchmarks/bench_step_times.py --data SCENE --log2-table 12 --global-steps 400 --block-steps 200 --num-blocks 2

Trains in-process (``scalar-nerf-benchmark``'s runner set-up, every 8th image held out) and prints one line per
``--window`` steps. Run it with nothing else on the machine; the figures are the machine's (say which CPU).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import List, Tuple

from scalar_nerfstudio.benchmarking.runner import setup_trainer, trainer_config
from scalar_nerfstudio.engine.timing import time_train_iterations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--downscale", type=int, default=1)
    parser.add_argument("--log2-table", type=int, default=19)
    parser.add_argument("--global-steps", type=int, default=400)
    parser.add_argument("--block-steps", type=int, default=200)
    parser.add_argument("--num-blocks", type=int, default=2)
    parser.add_argument("--window", type=int, default=50)
    parser.add_argument("--output-dir", type=Path, default=Path("outputs/step-times"))
    args = parser.parse_args()
    spec = {"method": "scalar-nerf", "data": str(args.data), "downscale": args.downscale, "output_dir": str(args.output_dir),
            "overrides": {"pipeline.model.field.log2_hashmap_size": args.log2_table, "pipeline.global_steps": args.global_steps,
                          "pipeline.block_steps": args.block_steps, "pipeline.num_blocks": args.num_blocks}}
    config = trainer_config(spec)
    config.set_timestamp()
    config.save_config()
    trainer = setup_trainer(config)
    times: List[Tuple[int, float]] = []
    time_train_iterations(trainer, lambda step, result, clock: times.append((step, clock.busy_s)))
    trainer.train()
    previous = 0.0
    for index in range(args.window - 1, len(times), args.window):
        step, busy = times[index]
        phase = trainer.pipeline.phase_at(step).name
        print(f"steps {step - args.window + 1}-{step}: {1000 * (busy - previous) / args.window:.0f} ms/step ({phase})")
        previous = busy


if __name__ == "__main__":
    main()
