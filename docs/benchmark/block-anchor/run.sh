#!/bin/sh
# A block's table pulled towards the global model's (docs/notebook/town.md, "A block's table pulled towards
# the global model"): the 8 blocks of the 3 x 3 town at 2^10 (seed 42) trained again from that
# benchmark's global checkpoint with `block_anchor` 1e-6. Run from the repository root after
#   scalar-nerf-benchmark ... --output-dir outputs/bench-town3x3-t10 (docs/notebook/town.md, "The 3 x 3 town at 2^10").
# The option is not in the product (-0.43 dB): apply the patch first (written against 376cea2):
#   git apply docs/benchmark/block-anchor/block-anchor.patch
set -e
python -m scalar_nerfstudio.benchmarking.runner docs/benchmark/block-anchor/anchor1e-6-seed42.spec.json \
    > outputs/bench-town3x3-t10/runs/anchor1e-6.log 2>&1
python -c "import json; r = json.load(open('outputs/bench-town3x3-t10/runs/anchor1e-6.json')); print({k: round(v['psnr'], 2) for k, v in r['fusions'].items()})"
