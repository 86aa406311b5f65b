"""Training benchmark: scalar-nerf (global model) vs nerfstudio's nerfacto (torch implementation).

Each method trains in its own process for the same wall-clock budget on the same scene and
split, then renders the eval views. Printed and written as JSON: steps, training rays/s,
held-out PSNR / SSIM, render time per image, the mean-training-image baseline, and the
machine's speed before and after the runs (``benchmarking/machine.py``: absolute figures move with
it, ratios within one run much less). Each
trained model is also scored with the other near-plane rule: nerfstudio's models start
evaluation rays at the camera (near plane reset to 0), scalar-nerf keeps the training near plane.

nerfacto builds LPIPS (which downloads AlexNet weights) when it is constructed; offline that
dies, so this benchmark replaces LPIPS by a stub for nerfacto and reports no LPIPS for it.

    python benchmarks/bench_training.py --data ../shared/data/castle-P30 --minutes 12 --json outputs/bench_training.json
"""

from __future__ import annotations

import argparse
import ast
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List


def parse_settings(items: List[str]) -> Dict[str, object]:
    """``["pipeline.model.occupancy_resolution=128", ...]`` -> {dotted name: value} (values read as JSON
    or as Python literals where they parse, so ``false`` and ``False`` are both the boolean; anything
    else is kept as a string)."""
    settings: Dict[str, object] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise SystemExit(f"bench_training: --scalar-set {item!r}: expected NAME=VALUE, e.g. pipeline.model.occupancy_resolution=128")
        try:
            settings[name] = json.loads(text)
        except json.JSONDecodeError:
            try:
                settings[name] = ast.literal_eval(text)
            except (ValueError, SyntaxError):
                settings[name] = text
    return settings


def train_one(method: str, data: str, *, downscale: int, seconds: float, steps: int, out: Path, settings: Dict[str, object],
              device: str = "cpu", rays_per_batch: int = 0) -> None:
    """Train ``method`` for ``seconds`` of wall clock (or ``steps``) on ``device`` ("cpu" or "cuda"),
    evaluate, write ``out`` (JSON).

    Runs in a process of its own (``--worker``), so that each method starts from a fresh process.
    On "cuda" both methods train with nerfstudio's mixed precision (fp16 autocast), as ``ns-train`` does there.
    ``rays_per_batch`` > 0 sets the rays per step of either method; 0 leaves each its default (4096).
    """
    import torch

    from scalar_nerfstudio.benchmarking.runner import setup_trainer, trainer_config
    from scalar_nerfstudio.engine.timing import time_train_iterations

    # the benchmark runner's set-up (every 8th image held out, no evaluation or checkpoints while
    # training; LPIPS stubbed out for nerfacto, whose weights would be downloaded), on ``device``
    overrides: Dict[str, object] = {"machine.device_type": device, "mixed_precision": device == "cuda"}
    if rays_per_batch > 0:
        overrides["pipeline.datamanager.train_num_rays_per_batch"] = rays_per_batch
    if method == "scalar-nerf":
        overrides["max_num_iterations"] = steps
        overrides.update(settings)
    config = trainer_config({"method": method, "data": data, "downscale": downscale, "output_dir": str(out.parent / "runs"), "overrides": overrides})
    config.set_timestamp()
    trainer = setup_trainer(config)

    def stop_when_out_of_time(step: int, result, clock) -> None:
        if clock.wall_s >= seconds:
            trainer.stop_training = True

    # wall clock from the first iteration on, callbacks (e.g. grid updates) included
    clock = time_train_iterations(trainer, stop_when_out_of_time)
    trainer.train()
    pipeline = trainer.pipeline
    pipeline.eval()
    start = time.perf_counter()
    metrics = pipeline.get_average_eval_image_metrics()
    num_eval = len(pipeline.datamanager.fixed_indices_eval_dataloader)
    render_ms = 1000.0 * (time.perf_counter() - start) / max(num_eval, 1)
    rays_per_step = pipeline.datamanager.get_train_rays_per_batch()
    collider = pipeline.model.collider
    result = {
        "method": method,
        "steps": clock.steps,
        "rays_per_step": rays_per_step,
        "train_seconds": clock.wall_s,
        "train_rays_per_sec": clock.steps * rays_per_step / max(clock.wall_s, 1e-9),
        "psnr": metrics["psnr"],
        "ssim": metrics["ssim"],
        "render_ms_per_image": render_ms,
        "eval_images": num_eval,
        "threads": torch.get_num_threads(),
        "device": torch.cuda.get_device_name() if device == "cuda" else "cpu",
        # training and evaluation together; reserved: what the caching allocator held of the GPU
        "gpu_peak_mib": torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else None,
        "gpu_peak_reserved_mib": torch.cuda.max_memory_reserved() / 2**20 if device == "cuda" else None,
        "near_plane": collider.near_plane,
        "reset_near_plane": collider.reset_near_plane,
        "settings": settings if method == "scalar-nerf" else {},
    }
    if method != "nerfacto" and "lpips" in metrics:
        result["lpips"] = metrics["lpips"]
    # the same trained model rendered with the other near-plane rule (nerfstudio resets the near plane
    # to 0 outside training by default; scalar-nerf keeps the training one)
    collider.reset_near_plane = not collider.reset_near_plane
    other = pipeline.get_average_eval_image_metrics()
    result["other_near_plane"] = {"reset_near_plane": collider.reset_near_plane, "psnr": other["psnr"], "ssim": other["ssim"]}
    out.write_text(json.dumps(result))


def mean_image_baseline(data: Path, downscale: int) -> float:
    """Held-out PSNR of the mean training image (what a model that learned nothing scores)."""
    import torch
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
    from nerfstudio.data.datasets.base_dataset import InputDataset

    parser = NerfstudioDataParserConfig(data=data, downscale_factor=downscale, eval_mode="interval", eval_interval=8).setup()
    train, test = InputDataset(parser.get_dataparser_outputs("train")), InputDataset(parser.get_dataparser_outputs("test"))
    mean = torch.stack([train[i]["image"][..., :3] for i in range(len(train))]).mean(0)
    scores = [float(-10 * torch.log10(torch.mean((test[i]["image"][..., :3] - mean) ** 2))) for i in range(len(test))]
    return sum(scores) / len(scores)


def run_method(method: str, args: argparse.Namespace, workdir: Path, settings: Dict[str, object]) -> Dict:
    out = workdir / f"{method}.json"
    steps = args.scalar_steps if method == "scalar-nerf" else 100000
    command = [sys.executable, str(Path(__file__).resolve()), "--worker", method, str(args.data), str(args.downscale),
               str(args.minutes * 60), str(steps), str(out), json.dumps(settings), args.device, str(args.rays_per_batch)]
    print(f"[{time.strftime('%H:%M:%S')}] training {method} on {args.device} for {args.minutes} min ...", flush=True)
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL if not args.verbose else None)
    return json.loads(out.read_text())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=Path("../shared/data/castle-P30"))
    parser.add_argument("--downscale", type=int, default=4)
    parser.add_argument("--minutes", type=float, default=12.0, help="training wall-clock budget per method")
    parser.add_argument("--scalar-steps", type=int, default=1800, help="scalar-nerf run length (sets its lr schedule); the time budget may stop it earlier")
    parser.add_argument("--methods", nargs="+", default=["scalar-nerf", "nerfacto"])
    parser.add_argument("--workdir", type=Path, default=Path("outputs/bench_training"))
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    parser.add_argument("--scalar-set", nargs="*", default=[], metavar="NAME=VALUE",
                        help="trainer-config settings for scalar-nerf, e.g. pipeline.model.occupancy_resolution=128")
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                        help="where both methods train (cuda: with nerfstudio's mixed precision, as ns-train there)")
    parser.add_argument("--rays-per-batch", type=int, default=0,
                        help="rays per training step for every method (0: each method's default, 4096 for both)")
    parser.add_argument("--verbose", action="store_true")
    parser.add_argument("--worker", nargs=9, help=argparse.SUPPRESS)  # one method, in its own process (run_method)
    args = parser.parse_args()
    if args.worker:
        method, data, downscale, seconds, steps, out, settings, device, rays = args.worker
        train_one(method, data, downscale=int(downscale), seconds=float(seconds), steps=int(steps), out=Path(out),
                  settings=json.loads(settings), device=device, rays_per_batch=int(rays))
        return
    settings = parse_settings(args.scalar_set)  # a malformed setting is refused before anything trains
    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise SystemExit("bench_training: --device cuda, but torch sees no CUDA device on this machine")
    args.workdir.mkdir(parents=True, exist_ok=True)
    from scalar_nerfstudio.benchmarking.machine import hash_grid_speed

    probe = {"before": hash_grid_speed()}
    print(f"[{time.strftime('%H:%M:%S')}] machine probe: {probe['before']:.2f} M points/s (hash grid fwd + bwd, 2 threads)", flush=True)
    results: List[Dict] = [run_method(m, args, args.workdir, settings) for m in args.methods]
    probe["after"] = hash_grid_speed()
    baseline = mean_image_baseline(args.data, args.downscale)

    print(f"\ndevice {results[0].get('device', args.device)}; scene {args.data.name}, downscale {args.downscale}, eval every 8th image, budget {args.minutes} min, mean-image baseline {baseline:.2f} dB")
    print(f"{'method':<14}{'rays/step':>10}{'steps':>7}{'train s':>9}{'rays/s':>10}{'PSNR':>8}{'SSIM':>7}{'render ms/img':>15}   PSNR / SSIM with the other near-plane rule")
    for r in results:
        other = r["other_near_plane"]
        rule = "near plane reset to 0" if other["reset_near_plane"] else f"near plane kept at {r['near_plane']}"
        print(f"{r['method']:<14}{r['rays_per_step']:>10}{r['steps']:>7}{r['train_seconds']:>9.0f}{r['train_rays_per_sec']:>10.0f}{r['psnr']:>8.2f}{r['ssim']:>7.3f}{r['render_ms_per_image']:>15.0f}"
              f"   {other['psnr']:.2f} / {other['ssim']:.3f} ({rule})")
    print(f"machine probe (hash grid fwd + bwd, 2^18 points, F=4, 2 threads; 2.8 on docs/notebook/defaults.md's fastest machine): "
          f"{probe['before']:.2f} M points/s before the runs, {probe['after']:.2f} after")
    by_name = {r["method"]: r for r in results}
    if {"scalar-nerf", "nerfacto"} <= by_name.keys():
        ours, peer = by_name["scalar-nerf"], by_name["nerfacto"]
        print(f"scalar-nerf / nerfacto: {ours['train_rays_per_sec'] / peer['train_rays_per_sec']:.1f}x rays/s, "
              f"{ours['psnr'] - peer['psnr']:+.2f} dB PSNR, {peer['render_ms_per_image'] / ours['render_ms_per_image']:.1f}x faster render")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"device": args.device, "scene": str(args.data.name), "downscale": args.downscale, "minutes": args.minutes,
                                         "mean_image_psnr": baseline, "machine_probe_mpts_per_s": probe,
                                         "results": results}, indent=2))


if __name__ == "__main__":
    main()
