"""How fast this machine is right now: a few seconds of the hash grid's forward + backward.

The project's 2-core development machine ran the same code up to 1.5-2.9x apart from one hour to
the next (docs/notebook/defaults.md). A benchmark's ratios are measured within one run, but its absolute
figures (rays/s, ms per view) depend on the machine's state. So the training benchmark probes
the machine before and after its runs and prints both figures beside its own. The probe is
section 1's measurement (`benchmarks/bench_encoding.py --features 4 --threads 2 --skip-ns`):
forward + backward of ``HashGridEncoding`` on 2^18 random points, 16 levels, 2^19 rows, F = 4.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor, nn

from scalar_nerfstudio.encodings import HashGridEncoding
from scalar_nerfstudio.engine.timing import median_seconds


def fwd_bwd_seconds(module: nn.Module, positions: Tensor, upstream: Tensor, *, warmup: int, repeats: int) -> float:
    """Median seconds of one ``module(positions)`` forward + backward of ``upstream`` (its parameters'
    gradients are reset before each call; on CUDA each call waits for its kernels to finish).

    Args:
        module: an encoder whose output is [N, D].
        positions: [N, 3] points in [0, 1]^3.
        upstream: [N, D] gradient of the output.
        warmup: untimed calls first.
        repeats: timed calls (the median is returned).
    """
    params = [p for p in module.parameters() if p.requires_grad]
    on_cuda = positions.device.type == "cuda"

    def step() -> None:
        for p in params:
            p.grad = None
        module(positions).backward(upstream)
        if on_cuda:
            torch.cuda.synchronize(positions.device)

    return median_seconds(step, repeats, warmup)


def hash_grid_speed(
    *,
    num_points: int = 1 << 18,
    features: int = 4,
    log2_hashmap_size: int = 19,
    threads: Optional[int] = 2,
    warmup: int = 2,
    repeats: int = 5,
    seed: int = 0,
) -> float:
    """Million points per second of the hash grid's forward + backward on random points.

    Uses the C++ kernel where it builds, otherwise the torch implementation: the figure is only
    comparable between runs that used the same one. Torch's thread count is restored afterwards.

    Args:
        num_points: points per call.
        features: features per level (16 levels from resolution 16 to 2048).
        log2_hashmap_size: rows of a hashed level, log2.
        threads: torch threads while probing (None: leave as is).
        warmup: untimed calls.
        repeats: timed calls (median).
        seed: random points and gradients.
    """
    if num_points < 1 or repeats < 1 or warmup < 0:
        raise ValueError(f"hash_grid_speed: need num_points >= 1, repeats >= 1, warmup >= 0, got {num_points}, {repeats}, {warmup}")
    generator = torch.Generator().manual_seed(seed)
    encoder = HashGridEncoding(num_levels=16, features_per_level=features, log2_hashmap_size=log2_hashmap_size, base_resolution=16,
                               max_resolution=2048)
    positions = torch.rand(num_points, 3, generator=generator)
    upstream = torch.randn(num_points, encoder.get_out_dim(), generator=generator)
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        seconds = fwd_bwd_seconds(encoder, positions, upstream, warmup=warmup, repeats=repeats)
    finally:
        torch.set_num_threads(previous)
    return num_points / seconds / 1e6


def describe_cpu() -> str:
    """E.g. ``"AMD EPYC, 2 cores, AVX2 and FMA (no AVX-512), no GPU"``: which of the project's two kinds
    of CPU (with AVX512-BF16/AMX, or AVX2 and FMA only) a figure came from."""
    import os

    model, flags = "unknown CPU", set()
    try:
        for line in open("/proc/cpuinfo", encoding="utf-8"):
            if line.startswith("model name") and model == "unknown CPU":
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags") and not flags:
                flags = set(line.split(":", 1)[1].split())
    except OSError:
        pass
    if "avx512_bf16" in flags or "amx_bf16" in flags:
        isa = "AVX512-BF16" + ("/AMX" if "amx_bf16" in flags else "")
    elif "avx2" in flags:
        isa = "AVX2 and FMA (no AVX-512)" if "fma" in flags else "AVX2"
    else:
        isa = "no AVX2"
    gpu = ", CUDA" if torch.cuda.is_available() else ", no GPU"
    return f"{model}, {os.cpu_count()} cores, {isa}{gpu}"
