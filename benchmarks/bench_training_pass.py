"""Time of one training step's forward + backward on a trained run, the no-grad pass in 1 or more segments.

A training step first runs the field without gradients over the samples worth evaluating, to find
which ones light reaches; the pass with gradients then runs over those. The no-grad pass goes front
to back in ``RENDER_SEGMENTS`` segments along the rays (as rendering does): the samples behind a
ray's surface are never evaluated. With 1 segment it evaluates every candidate of every ray, which
was the training step before (the kept samples, and so the step's result, are the same).

Loads ``RUN/config.yml``, draws ``--batches`` training batches of the run's datamanager, and times
forward + backward of the global model on each, alternating the segment counts round by round, so a
slow moment of the machine does not fall on one of them only. ``--warm-up-state`` times the model as
during the occupancy grid's warm-up (every cell occupied, ``warmup_samples_per_ray`` intervals).

    python benchmarks/bench_training_pass.py --load-config outputs/bench_training/runs/castle-P30/scalar-nerf/<ts>/config.yml
    python benchmarks/bench_training_pass.py --load-config RUN/config.yml --warm-up-state
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--load-config", type=Path, required=True, help="RUN/config.yml of a trained scalar-nerf run")
    parser.add_argument("--segments", type=int, nargs="+", default=[1, 4], help="segment counts to compare")
    parser.add_argument("--batches", type=int, default=6)
    parser.add_argument("--rounds", type=int, default=4)
    parser.add_argument("--warm-up-state", action="store_true", help="time the model as during the occupancy warm-up")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    if any(count < 1 for count in args.segments) or args.batches < 1 or args.rounds < 1:
        parser.error("--segments, --batches and --rounds must be at least 1")

    import torch
    from nerfstudio.utils.eval_utils import eval_setup

    import scalar_nerfstudio.models.scalar_model as scalar_model_module

    _, pipeline, _, _ = eval_setup(args.load_config, test_mode="val")
    pipeline.train()
    model = pipeline.model.phase_model(None) if hasattr(pipeline.model, "phase_model") else pipeline.model
    if args.warm_up_state:
        model.occupancy.occupied.fill_(True)  # a grid in its warm-up marks nothing empty
        model.update_occupancy(1)  # a step inside the warm-up that is not an update step
    bundles = [pipeline.datamanager.next_train(100_000 + index)[0] for index in range(args.batches)]
    times = {count: [] for count in args.segments}
    samples = {}
    for round_index in range(args.rounds + 1):  # round 0 warms up and is not counted
        for count in args.segments:
            scalar_model_module.RENDER_SEGMENTS = count
            for bundle in bundles:
                torch.manual_seed(round_index)  # the same jittered samples for every segment count
                start = time.perf_counter()
                outputs = model(bundle)
                outputs["rgb"].square().sum().backward()
                if round_index > 0:
                    times[count].append(time.perf_counter() - start)
                samples[count] = float(outputs["samples_per_ray"].mean())
                model.zero_grad(set_to_none=True)
    rays = bundles[0].origins.reshape(-1, 3).shape[0]
    state = "occupancy warm-up" if args.warm_up_state else "trained"
    print(f"{args.load_config}: {rays} rays per batch, {state}, {torch.get_num_threads()} threads, {args.rounds} rounds x {args.batches} batches")
    results = []
    for count in args.segments:
        row = {"segments": count, "median_ms": 1000 * statistics.median(times[count]), "min_ms": 1000 * min(times[count]),
               "samples_per_ray_with_gradients": samples[count]}
        results.append(row)
        print(f"{count} segment(s): median {row['median_ms']:.1f} ms per forward + backward, fastest {row['min_ms']:.1f} ms, "
              f"{row['samples_per_ray_with_gradients']:.2f} samples per ray with gradients")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"config": str(args.load_config), "state": state, "rays": rays, "results": results}, indent=2))


if __name__ == "__main__":
    main()
