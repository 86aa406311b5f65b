#!/bin/sh
# The seed-42 default blocks (auto-parallel) with the far plane at 4 units: global phase, then the
# 8 blocks from its checkpoint. Run from the repository root after writing the town:
#   scalar-nerf-make-scene --scene town --output outputs/scenes/town-2x2-rig-256 --blocks-x 2 --blocks-y 2 \
#       --num-images 300 --width 256 --height 192
set -e
D=docs/benchmark/town-256-t10/depth/far-plane
R=outputs/bench-town256-t10-far4-seed42/runs
mkdir -p $R
cp $D/blocks-seed42-global.spec.json $R/global.spec.json
python -m scalar_nerfstudio.benchmarking.runner $R/global.spec.json > $R/global.log 2>&1
CKPT=$(ls $R/global/*/scalar-nerf/*/nerfstudio_models/step-000003599.ckpt | tail -1)
sed "s#\"pipeline.global_checkpoint\": \"[^\"]*\"#\"pipeline.global_checkpoint\": \"$CKPT\"#" \
    $D/blocks-seed42-auto-parallel.spec.json > $R/auto-parallel.spec.json
python -m scalar_nerfstudio.benchmarking.runner $R/auto-parallel.spec.json > $R/auto-parallel.log 2>&1
