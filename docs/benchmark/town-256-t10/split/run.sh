#!/bin/sh
# The split of the step budget on the bounded T = 10 town: a 1600-step global phase (instead of
# 3600), then the 8 default blocks 5800 steps each (instead of 2800), so that on 8 workers the run
# ends at about the same wall-clock as the default split (global phase + slowest block, ~550 s).
# Run from the repository root after writing the town (see ../bounded/run.sh).
# Usage: sh docs/benchmark/town-256-t10/split/run.sh blocks1600-seed1 [blocks1600-seed42]
set -e
D=docs/benchmark/town-256-t10/split
R=outputs/bench-town256-t10-split/runs
mkdir -p $R
for NAME in "$@"; do
    SEED=${NAME#blocks1600-}
    python -m scalar_nerfstudio.benchmarking.runner $D/global1600-$SEED.spec.json > $R/global1600-$SEED.log 2>&1
    CKPT=$(ls $R/global1600-$SEED/*/scalar-nerf/*/nerfstudio_models/step-000001599.ckpt | tail -1)
    sed "s#GLOBAL_CHECKPOINT#$CKPT#" $D/$NAME.spec.json > $R/$NAME.spec.json
    python -m scalar_nerfstudio.benchmarking.runner $R/$NAME.spec.json > $R/$NAME.log 2>&1
    echo "$NAME done $(date +%H:%M:%S)"
done
