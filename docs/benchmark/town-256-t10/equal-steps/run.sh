#!/bin/sh
# Equal total steps on the bounded T = 10 town: the default global phase (3600 steps, the spec of
# ../bounded/), then the 8 default blocks 350 steps each, 3600 + 8 x 350 = 6400 steps in all, as many
# as NGP_10 trains in ../bounded/ngp10-*.json. Run from the repository root after writing the town
# (see ../bounded/run.sh).
# Usage: sh docs/benchmark/town-256-t10/equal-steps/run.sh blocks350-seed1 [blocks350-seed42]
set -e
D=docs/benchmark/town-256-t10/equal-steps
B=docs/benchmark/town-256-t10/bounded
R=outputs/bench-town256-t10-equal-steps/runs
mkdir -p $R
for NAME in "$@"; do
    SEED=${NAME#blocks350-}
    sed "s#outputs/bench-town256-t10-bounded/#outputs/bench-town256-t10-equal-steps/#g" $B/global-$SEED.spec.json > $R/global-$SEED.spec.json
    python -m scalar_nerfstudio.benchmarking.runner $R/global-$SEED.spec.json > $R/global-$SEED.log 2>&1
    CKPT=$(ls $R/global-$SEED/*/scalar-nerf/*/nerfstudio_models/step-000003599.ckpt | tail -1)
    sed "s#GLOBAL_CHECKPOINT#$CKPT#" $D/$NAME.spec.json > $R/$NAME.spec.json
    python -m scalar_nerfstudio.benchmarking.runner $R/$NAME.spec.json > $R/$NAME.log 2>&1
    echo "$NAME done $(date +%H:%M:%S)"
done
