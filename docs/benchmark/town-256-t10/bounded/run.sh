#!/bin/sh
# The T = 10 town with the scene bounded by its depth images (the default since 2026-11-26):
# one-model runs and the default blocks (auto-parallel: global phase, then the 8 blocks from its
# checkpoint), seeds 1 and 42. Run from the repository root after writing the town:
#   scalar-nerf-make-scene --scene town --output outputs/scenes/town-2x2-rig-256 --blocks-x 2 --blocks-y 2 \
#       --num-images 300 --width 256 --height 192
# Usage: sh docs/benchmark/town-256-t10/bounded/run.sh NAME...   (NAME: ngp10-seed42, ngp10-seed1,
# ngp12-seed1, ngp12-seed42, blocks-seed1, blocks-seed42)
set -e
D=docs/benchmark/town-256-t10/bounded
R=outputs/bench-town256-t10-bounded/runs
mkdir -p $R
for NAME in "$@"; do
    case $NAME in
    blocks-*)
        SEED=${NAME#blocks-}
        python -m scalar_nerfstudio.benchmarking.runner $D/global-$SEED.spec.json > $R/global-$SEED.log 2>&1
        CKPT=$(ls $R/global-$SEED/*/scalar-nerf/*/nerfstudio_models/step-000003599.ckpt | tail -1)
        sed "s#GLOBAL_CHECKPOINT#$CKPT#" $D/$NAME.spec.json > $R/$NAME.spec.json
        python -m scalar_nerfstudio.benchmarking.runner $R/$NAME.spec.json > $R/$NAME.log 2>&1
        ;;
    *)
        python -m scalar_nerfstudio.benchmarking.runner $D/$NAME.spec.json > $R/$NAME.log 2>&1
        ;;
    esac
    echo "$NAME done $(date +%H:%M:%S)"
done
