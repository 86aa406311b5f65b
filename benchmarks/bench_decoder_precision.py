"""Decoder forward+backward time in float32 vs bfloat16 autocast on CPU (a lever for issue 3).

    python benchmarks/bench_decoder_precision.py --points 150000
"""

from __future__ import annotations

import argparse

import torch

from scalar_nerfstudio.engine.timing import median_seconds
from scalar_nerfstudio.fields.scalar_field import Decoder


def fwd_bwd_seconds(decoder: Decoder, features: torch.Tensor, extra: torch.Tensor, bf16: bool, repeats: int) -> float:
    """Median wall time of one decoder forward+backward over all points."""

    def step() -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            density, geo = decoder.density(features)
            rgb = decoder.colour(geo, extra[:, :16], extra[:, 16:])
        (density.float().sum() + rgb.float().sum()).backward()

    return median_seconds(step, repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=150_000)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    decoder = Decoder(in_dim=64, hidden_dim=128, geo_feat_dim=15, direction_dim=16, appearance_dim=8, density_bias=-4.0)
    features, extra = torch.randn(args.points, 64), torch.randn(args.points, 24)
    fp32 = fwd_bwd_seconds(decoder, features, extra, bf16=False, repeats=args.repeats)
    bf16 = fwd_bwd_seconds(decoder, features, extra, bf16=True, repeats=args.repeats)
    print(f"decoder fwd+bwd, {args.points} points, {torch.get_num_threads()} threads: fp32 {fp32:.3f} s, bf16 autocast {bf16:.3f} s ({fp32 / bf16:.2f}x)")


if __name__ == "__main__":
    main()
