#!/bin/sh
# The bounded 256 x 192 2 x 2 town with tables of 2^8 (docs/notebook/defaults.md, "Blocks start as copies of the global model"): NGP_8, NGP_10
# and the default blocks of 2^8 (auto-parallel: global phase, then the 8 blocks from its checkpoint),
# seeds 42 and 1. The specs are those of ../town-256-t10/bounded/ with the table changed. Run from the repository root after writing the town:
#   scalar-nerf-make-scene --scene town --output outputs/scenes/town-2x2-rig-256 --blocks-x 2 --blocks-y 2 \
#       --num-images 300 --width 256 --height 192
# Usage: sh docs/benchmark/town-256-t8/run.sh NAME...   (NAME: ngp8-seed42, ngp8-seed1,
# ngp10-seed42, ngp10-seed1, blocks-seed42, blocks-seed1, blocks-fresh-seed42, blocks-fitted-seed42)
set -e
D=docs/benchmark/town-256-t8
R=outputs/bench-town256-t8/runs
mkdir -p $R
for NAME in "$@"; do
    case $NAME in
    blocks-*)
        SEED=${NAME##*-}
        # the global phase once per seed; blocks-fresh-* and blocks-fitted-* start from the same checkpoint
        [ -f $R/global-$SEED.json ] || python -m scalar_nerfstudio.benchmarking.runner $D/global-$SEED.spec.json > $R/global-$SEED.log 2>&1
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
