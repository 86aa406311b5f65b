"""Benchmark: hash-grid encoding forward+backward throughput on CPU or CUDA.

Compares, on the same random inputs in the same process, ``HashGridEncoding`` (C++ and torch
paths; with ``--device cuda`` the CUDA kernel and torch) with nerfstudio's
``HashEncoding(implementation="torch")``, for several feature counts and thread counts, and prints a
table of million points per second (fwd + bwd) and speed-ups.

Example::

    python benchmarks/bench_encoding.py --features 2 4 --threads 1 2 --num-points 262144
    python benchmarks/bench_encoding.py --device cuda --features 2 4 --threads 16 --num-points 1048576
"""

from __future__ import annotations

import argparse
import os

import torch
from nerfstudio.field_components.encodings import HashEncoding
from torch import nn

from scalar_nerfstudio.benchmarking.machine import fwd_bwd_seconds
from scalar_nerfstudio.encodings import HashGridEncoding


def build_modules(features: int, log2_hashmap_size: int, max_resolution: int, kernel: str = "cpp") -> dict[str, nn.Module]:
    """The encoders under test, all with 16 levels from resolution 16 to ``max_resolution`` and hashed
    levels of ``2**log2_hashmap_size`` rows (ours stores the coarse levels densely, hence fewer rows).
    ``kernel``: ``cpp`` or ``cuda``, the implementation of the first entry, ``ours-<kernel>``."""
    return {
        f"ours-{kernel}": HashGridEncoding(num_levels=16, features_per_level=features, log2_hashmap_size=log2_hashmap_size,
                                           base_resolution=16, max_resolution=max_resolution, implementation=kernel),
        "ours-torch": HashGridEncoding(num_levels=16, features_per_level=features, log2_hashmap_size=log2_hashmap_size, base_resolution=16,
                                       max_resolution=max_resolution, implementation="torch"),
        "ns-torch": HashEncoding(
            num_levels=16,
            min_res=16,
            max_res=max_resolution,
            log2_hashmap_size=log2_hashmap_size,
            features_per_level=features,
            implementation="torch",
        ),
    }


def ratio(rates: dict[str, float], numerator: str, denominator: str) -> str:
    """``rates[numerator] / rates[denominator]`` formatted as a speed-up, or "-" if one is missing."""
    if numerator not in rates or denominator not in rates:
        return "-"
    return f"{rates[numerator] / rates[denominator]:.1f}x"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--features", type=int, nargs="+", default=[2, 4], help="features per level F")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="torch.set_num_threads values")
    parser.add_argument("--num-points", type=int, default=2**18, help="points per batch N")
    parser.add_argument("--log2-hashmap-size", type=int, default=19)
    parser.add_argument("--max-resolution", type=int, default=2048)
    parser.add_argument("--warmup", type=int, default=2, help="untimed iterations before timing")
    parser.add_argument("--repeats", type=int, default=5, help="timed iterations (median reported)")
    parser.add_argument("--ns-warmup", type=int, default=1, help="untimed iterations for the slow nerfstudio baseline")
    parser.add_argument("--ns-repeats", type=int, default=3, help="timed iterations for the slow nerfstudio baseline")
    parser.add_argument("--skip-ns", action="store_true", help="do not run the nerfstudio baseline")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help="cuda: the CUDA kernel against torch on the GPU")
    args = parser.parse_args()
    device = torch.device(args.device)
    kernel = "cuda" if device.type == "cuda" else "cpp"
    gpu = f", {torch.cuda.get_device_name(device)}" if device.type == "cuda" else ""

    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs{gpu}, load average before: {os.getloadavg()[0]:.2f}")
    generator = torch.Generator().manual_seed(args.seed)
    positions = torch.rand(args.num_points, 3, generator=generator).to(device)
    names = [f"ours-{kernel}", "ours-torch"] + ([] if args.skip_ns else ["ns-torch"])
    rows: list[list[str]] = []
    for features in args.features:
        built = build_modules(features, args.log2_hashmap_size, args.max_resolution, kernel)
        modules = {name: module.to(device) for name, module in built.items()}
        upstream = torch.randn(args.num_points, 16 * features, generator=generator).to(device)
        for threads in args.threads:
            torch.set_num_threads(threads)
            rates: dict[str, float] = {}
            for name in names:
                baseline = name == "ns-torch"
                seconds = fwd_bwd_seconds(
                    modules[name],
                    positions,
                    upstream,
                    warmup=args.ns_warmup if baseline else args.warmup,
                    repeats=args.ns_repeats if baseline else args.repeats,
                )
                rates[name] = args.num_points / seconds / 1e6
            row = [str(features), str(threads)] + [f"{rates[name]:.3f}" for name in names]
            row += [ratio(rates, f"ours-{kernel}", "ns-torch"), ratio(rates, "ours-torch", "ns-torch")]
            row.append(ratio(rates, f"ours-{kernel}", "ours-torch"))
            rows.append(row)
            print("  ".join(row), flush=True)

    header = ["F", "threads"] + [f"{name} Mpts/s" for name in names] + [f"{kernel}/ns", "torch/ns", f"{kernel}/torch"]
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    print(
        f"\nfwd+bwd throughput (M points/s), N={args.num_points}, 16 levels, T=2^{args.log2_hashmap_size}, "
        f"max_res={args.max_resolution}, median of {args.repeats} (ns-torch: {args.ns_repeats}); "
        f"load average after: {os.getloadavg()[0]:.2f}"
    )
    print(" | ".join(h.rjust(w) for h, w in zip(header, widths)))
    print("-+-".join("-" * w for w in widths))
    for row in rows:
        print(" | ".join(c.rjust(w) for c, w in zip(row, widths)))


if __name__ == "__main__":
    main()
