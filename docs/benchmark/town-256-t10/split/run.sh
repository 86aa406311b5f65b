#!/bin/sh
# The split of the step budget on the bounded T = 10 town, against the default 3600 global steps +
# 8 blocks x 2800 steps (which ends at ~554 s on 8 workers: global phase + slowest block):
#   blocks1600-SEED: a 1600-step global phase, then the 8 default blocks 5800 steps each;
#   blocks4800-SEED: a 4800-step global phase, then the 8 default blocks 1280 steps each;
# each chosen to end at about the same wall-clock on 8 workers.
# Run from the repository root after writing the town (see ../bounded/run.sh).
# Usage: sh docs/benchmark/town-256-t10/split/run.sh blocks1600-seed1 [blocks4800-seed1 ...]
set -e
D=docs/benchmark/town-256-t10/split
R=outputs/bench-town256-t10-split/runs
mkdir -p $R
for NAME in "$@"; do
    SEED=${NAME#blocks*-}
    G=${NAME%%-*}
    G=${G#blocks}
    python -m scalar_nerfstudio.benchmarking.runner $D/global$G-$SEED.spec.json > $R/global$G-$SEED.log 2>&1
    CKPT=$(ls $R/global$G-$SEED/*/scalar-nerf/*/nerfstudio_models/step-$(printf %09d $((G - 1))).ckpt | tail -1)
    sed "s#GLOBAL_CHECKPOINT#$CKPT#" $D/$NAME.spec.json > $R/$NAME.spec.json
    python -m scalar_nerfstudio.benchmarking.runner $R/$NAME.spec.json > $R/$NAME.log 2>&1
    echo "$NAME done $(date +%H:%M:%S)"
done
