"""The decoder's CPU training kernels against each other (issue 67), measured in one run.

``--part decoder``: one decoder forward + backward over ``--points`` samples with each path, the
paths taking turns in every round (so a busier moment of the machine hits all of them), median per
path:

* ``torch-float32``: autograd layer by layer in float32 (what a CPU without AVX512-BF16 ran before);
* ``avx2``: the fused float32 kernels (csrc/mlp_f32.cpp, AVX2 + FMA);
* ``torch-bfloat16``: autograd layer by layer under bfloat16 autocast (where the CPU multiplies bfloat16);
* ``avx512bf16``: the fused bfloat16 kernels (csrc/mlp.cpp).

``--part training`` (needs ``--data``): the whole model trained by ``bench_training.py``'s worker
(same set-up, one fresh process per path, the same wall-clock budget each) with
``pipeline.model.field.cpu_decoder_kernel`` set per path, then scored on the held-out views;
``--nerfacto`` adds nerfstudio's nerfacto in the same run for the "x nerfacto" ratio.

    python benchmarks/bench_decoder_kernels.py --points 150000
    python benchmarks/bench_decoder_kernels.py --part training --data ../shared/data/castle-P30 --minutes 4 --nerfacto
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Callable, Dict, List

import torch

# the training part runs bench_training.py's worker (same directory)
sys.path.insert(0, str(Path(__file__).resolve().parent))

# path name -> (field settings for the training part, decoder kernel, bfloat16 autocast)
PATHS: Dict[str, tuple] = {
    "torch-float32": ({"pipeline.model.field.cpu_decoder_kernel": "torch", "pipeline.model.field.decoder_precision": "float32"}, "torch", False),
    "avx2": ({"pipeline.model.field.cpu_decoder_kernel": "avx2"}, "avx2", False),
    "torch-bfloat16": ({"pipeline.model.field.cpu_decoder_kernel": "torch", "pipeline.model.field.decoder_precision": "bfloat16"}, "torch", True),
    "avx512bf16": ({"pipeline.model.field.cpu_decoder_kernel": "avx512bf16"}, "avx512bf16", True),
}


def runnable_paths() -> List[str]:
    """The paths this CPU runs (bfloat16 ones only where it multiplies bfloat16 natively)."""
    from scalar_nerfstudio.fields.fused_mlp import fused_mlp_available
    from scalar_nerfstudio.fields.fused_mlp_float32 import float32_mlp_isa
    from scalar_nerfstudio.fields.scalar_field import cpu_bfloat16_is_fast

    ok = {"torch-float32": True, "avx2": float32_mlp_isa() == "avx2", "torch-bfloat16": cpu_bfloat16_is_fast(),
          "avx512bf16": fused_mlp_available()}
    return [name for name in PATHS if ok[name]]


def decoder_gflop(decoder: torch.nn.Module, points: int) -> float:
    """Multiply-add work of one pass of ``decoder`` in ``decoder_part`` (GFLOP, 2 per multiply-add):
    every layer's forward and weight gradient, and the input gradient of all but the first density
    layer (the benchmark's encoder features take no gradient)."""
    density = [m for m in decoder.density_mlp if isinstance(m, torch.nn.Linear)]
    colour = [m for m in decoder.colour_mlp if isinstance(m, torch.nn.Linear)]
    products = sum(m.in_features * m.out_features for m in density + colour)
    first = density[0].in_features * density[0].out_features
    return 2.0 * points * (3 * products - first) / 1e9


def decoder_part(args: argparse.Namespace, paths: List[str]) -> None:
    from scalar_nerfstudio.engine.allocator import keep_freed_memory
    from scalar_nerfstudio.fields.scalar_field import Decoder

    if not args.fresh_pages:
        keep_freed_memory()  # malloc as training sets it: freed buffers are reused, not faulted in again
    generator = torch.Generator().manual_seed(0)
    features = torch.randn(args.points, 64, generator=generator)
    extra = torch.randn(args.points, 24, generator=generator)

    def make_decoder(kernel: str) -> Decoder:
        torch.manual_seed(0)
        return Decoder(in_dim=64, hidden_dim=args.hidden_dim, geo_feat_dim=15, direction_dim=16, appearance_dim=8,
                       density_bias=-4.0, training_kernel=kernel)

    def step_for(name: str) -> Callable[[], None]:
        _, kernel, bf16 = PATHS[name]
        decoder = make_decoder(kernel)

        def step() -> None:
            decoder.zero_grad(set_to_none=True)
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                density, geo = decoder.density(features)
                rgb = decoder.colour(geo, extra[:, :16], extra[:, 16:])
            (density.float().sum() + rgb.float().sum()).backward()

        return step

    steps = {name: step_for(name) for name in paths}
    gflop = decoder_gflop(make_decoder("torch"), args.points)
    for step in steps.values():  # warm-up (first-call allocations, the extension's build)
        step()
    times: Dict[str, List[float]] = {name: [] for name in paths}
    for _ in range(args.repeats):
        for name, step in steps.items():
            start = time.perf_counter()
            step()
            times[name].append(time.perf_counter() - start)
    median = {name: statistics.median(t) for name, t in times.items()}
    malloc = "glibc's defaults (fresh pages)" if args.fresh_pages else "training's settings"
    print(f"decoder forward + backward, {args.points} points, hidden width {args.hidden_dim}, "
          f"{torch.get_num_threads()} threads, malloc {malloc}, median of {args.repeats} rounds (paths take turns):")
    for name in paths:
        print(f"  {name:<15}{median[name] * 1000:9.1f} ms   {median['torch-float32'] / median[name]:5.2f}x torch-float32"
              f"   {gflop / median[name]:6.1f} GFLOP/s")
    print(f"  ({gflop:.2f} GFLOP per pass: forward, weight and input gradients of the unpadded layers)")
    if "avx2" in median and "avx512bf16" in median:
        print(f"  avx512bf16 / avx2: {median['avx2'] / median['avx512bf16']:.2f}x")


def training_part(args: argparse.Namespace, paths: List[str]) -> None:
    import bench_training

    from scalar_nerfstudio.benchmarking.machine import hash_grid_speed

    if args.data is None:
        raise SystemExit("bench_decoder_kernels: --part training needs --data (a nerfstudio scene folder)")
    runs = [(name, "scalar-nerf", {**PATHS[name][0], "machine.seed": args.seed}) for name in paths] + ([("nerfacto", "nerfacto", {})] if args.nerfacto else [])
    probe_before = hash_grid_speed()
    results = {}
    for label, method, settings in runs:
        workdir = args.workdir / label
        workdir.mkdir(parents=True, exist_ok=True)
        results[label] = bench_training.run_method(method, args, workdir, settings)
    probe_after = hash_grid_speed()
    print(f"\nscene {args.data.name}, downscale {args.downscale}, {args.minutes} min per run, seed {args.seed}, {torch.get_num_threads()} threads; "
          f"machine probe {probe_before:.2f} M points/s before, {probe_after:.2f} after")
    print(f"{'path':<16}{'steps':>7}{'rays/s':>10}{'PSNR':>8}{'SSIM':>7}   ratios")
    reference = results.get("torch-float32")
    for label, r in results.items():
        ratios = []
        if reference is not None and label != "torch-float32":
            ratios.append(f"{r['train_rays_per_sec'] / reference['train_rays_per_sec']:.2f}x torch-float32 rays/s, "
                          f"{r['psnr'] - reference['psnr']:+.2f} dB")
        if "nerfacto" in results and label != "nerfacto":
            ratios.append(f"{r['train_rays_per_sec'] / results['nerfacto']['train_rays_per_sec']:.1f}x nerfacto rays/s")
        print(f"{label:<16}{r['steps']:>7}{r['train_rays_per_sec']:>10.0f}{r['psnr']:>8.2f}{r['ssim']:>7.3f}   {'; '.join(ratios)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--part", choices=["decoder", "training"], default="decoder")
    parser.add_argument("--paths", nargs="+", choices=list(PATHS), default=None,
                        help="paths to measure (default: every path this CPU runs)")
    parser.add_argument("--points", type=int, default=150_000, help="samples per decoder pass (decoder part)")
    parser.add_argument("--hidden-dim", type=int, default=64, help="decoder width in neurons (decoder part)")
    parser.add_argument("--repeats", type=int, default=7, help="timed rounds (decoder part)")
    parser.add_argument("--fresh-pages", action="store_true",
                        help="decoder part: leave glibc's malloc at its defaults, so large buffers are faulted in afresh on "
                             "every pass (the default keeps freed memory, as training does: engine/allocator.py)")
    parser.add_argument("--data", type=Path, default=None, help="nerfstudio scene folder (training part)")
    parser.add_argument("--downscale", type=int, default=4)
    parser.add_argument("--minutes", type=float, default=4.0, help="training wall-clock budget per run (training part)")
    parser.add_argument("--scalar-steps", type=int, default=1800, help="scalar-nerf run length (sets its lr schedule)")
    parser.add_argument("--seed", type=int, default=42, help="machine.seed of every scalar-nerf run (training part; 42 is nerfstudio's default)")
    parser.add_argument("--nerfacto", action="store_true", help="also train nerfacto (training part)")
    parser.add_argument("--device", default="cpu", help=argparse.SUPPRESS)  # bench_training's worker reads it
    parser.add_argument("--rays-per-batch", type=int, default=0, help=argparse.SUPPRESS)  # likewise (0: the default 4096)
    parser.add_argument("--verbose", action="store_true")
    parser.add_argument("--workdir", type=Path, default=Path("outputs/bench_decoder_kernels"))
    args = parser.parse_args()
    available = runnable_paths()
    paths = args.paths or available
    missing = [name for name in paths if name not in available]
    if missing:
        raise SystemExit(f"bench_decoder_kernels: this CPU cannot run {missing} (it runs {available})")
    if "torch-float32" not in paths:
        paths = ["torch-float32", *paths]  # the reference of every ratio
    if args.part == "decoder":
        decoder_part(args, paths)
    else:
        training_part(args, paths)


if __name__ == "__main__":
    main()
