#!/bin/sh
# Blocks whose own field ends `block_reach` region radii from their centre (the global model's field
# beyond), trained from the global checkpoints of two earlier benchmarks (docs/notebook/town.md, "A block's
# field that ends near the block"). Run from the repository root after those benchmarks:
#   3 x 3 town at 2^10: scalar-nerf-benchmark ... --output-dir outputs/bench-town3x3-t10 (docs/notebook/town.md, "The 3 x 3 town at 2^10")
#   2 x 2 town at 256 x 192, 2^8: sh docs/benchmark/town-256-t8/run.sh blocks-seed42
# The option is not in the product (it did not help): apply block-reach.patch first (it was written
# against commit 376cea2): git apply docs/benchmark/block-reach/block-reach.patch
# Usage: sh docs/benchmark/block-reach/run.sh NAME...   (NAME: reach1-seed42, reach2-seed42, t8-reach2-seed42)
# then: python docs/benchmark/block-reach/summary.py
set -e
D=docs/benchmark/block-reach
for NAME in "$@"; do
    case $NAME in
    t8-*)
        R=outputs/bench-town256-t8/runs
        CKPT=$(ls $R/global-seed42/*/scalar-nerf/*/nerfstudio_models/step-000003599.ckpt | tail -1)
        sed "s#GLOBAL_CHECKPOINT#$CKPT#" $D/$NAME.spec.json > $R/$NAME.spec.json
        SPEC=$R/$NAME.spec.json
        ;;
    *)
        R=outputs/bench-town3x3-t10/runs
        SPEC=$D/$NAME.spec.json
        ;;
    esac
    python -m scalar_nerfstudio.benchmarking.runner $SPEC > $R/$NAME.log 2>&1
    echo "$NAME done $(date +%H:%M:%S)"
done
