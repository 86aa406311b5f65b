"""Where one training step's time goes: torch-profiler table of a `scalar-nerf` step on a real scene.

Trains the registered ``scalar-nerf`` config (its defaults) for ``--steps`` steps, printing seconds
per step, samples per ray evaluated with gradients and the occupied grid fraction every 25 steps,
and the profiler's table for step ``--profile-step`` (after the occupancy warm-up by default).

    python benchmarks/profile_training_step.py --data ../shared/data/castle-P30 --steps 300 --profile-step 280
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from bench_decoder_kernels import PATHS  # the decoder paths' config settings (same directory)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=Path("../shared/data/castle-P30"))
    parser.add_argument("--downscale", type=int, default=4)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--profile-step", type=int, default=280)
    parser.add_argument("--output-dir", type=Path, default=Path("outputs/profile_training_step"))
    parser.add_argument("--decoder-path", choices=["auto", *PATHS], default="auto",
                        help="the decoder's CPU training path, as bench_decoder_kernels.py names them (auto: the config's)")
    args = parser.parse_args()

    from scalar_nerfstudio.benchmarking.runner import setup_trainer, trainer_config
    from scalar_nerfstudio.engine.timing import time_train_iterations

    # the benchmark's trainer set-up: eval every 8th image, no evaluation or checkpoints while training
    config = trainer_config({
        "method": "scalar-nerf", "data": str(args.data), "downscale": args.downscale, "output_dir": str(args.output_dir),
        "overrides": {"max_num_iterations": args.steps, **(PATHS[args.decoder_path][0] if args.decoder_path != "auto" else {})},
    })
    config.set_timestamp()
    trainer = setup_trainer(config)

    iteration = trainer.train_iteration

    on_cuda = torch.device(trainer.pipeline.model.device).type == "cuda"
    activities = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if on_cuda else [])

    def profiled_iteration(step: int):
        if step != args.profile_step:
            return iteration(step)
        with torch.profiler.profile(activities=activities) as profile:
            result = iteration(step)
            if on_cuda:
                torch.cuda.synchronize()
        averages = profile.key_averages()
        print(averages.table(sort_by="self_cpu_time_total", row_limit=20), flush=True)
        if on_cuda:  # the GPU's side: where its time goes, and how many kernels one step launches
            print(averages.table(sort_by="self_cuda_time_total", row_limit=20), flush=True)
            launches = sum(event.count for event in averages if event.key in ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC"))
            kernels = [event for event in averages if event.device_type == torch.autograd.DeviceType.CUDA]  # not the ops that launched them
            busy_ms = sum(event.self_device_time_total for event in kernels) / 1e3
            print(f"one step on {torch.cuda.get_device_name()}: {launches} kernel launches, GPU busy {busy_ms:.1f} ms", flush=True)
        return result

    trainer.train_iteration = profiled_iteration
    window = {"wall_s": 0.0, "steps": 0}

    def report(step: int, result, clock) -> None:  # seconds per step over the last 25 (the profiled step not counted)
        if step == args.profile_step:
            return
        window["steps"] += 1
        if (step + 1) % 25 == 0:
            metrics = result[2]
            print(f"step {step + 1}: {(clock.wall_s - window['wall_s']) / max(window['steps'], 1):.3f} s/step, "
                  f"{float(metrics['samples_per_ray']):.1f} samples/ray with gradients, "
                  f"{float(metrics['occupied_fraction']):.3f} of the grid occupied", flush=True)
            window.update(wall_s=clock.wall_s, steps=0)

    time_train_iterations(trainer, report)
    trainer.train()


if __name__ == "__main__":
    main()
