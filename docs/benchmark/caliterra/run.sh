#!/usr/bin/env bash
# The real drone capture (OpenDroneMap's Caliterra, 75 photos of 4000 x 3000 with GPS) end to end:
# photos -> poses (pycolmap) -> the benchmark at 500 x 375 (images_8), where automatic K = 2 with 2^19
# tables. Usage: docs/benchmark/caliterra/run.sh PATH/TO/odm_data_caliterra SCENE OUTPUT [SEED]
# (clone https://github.com/OpenDroneMap/odm_data_caliterra first; the photos are never committed).
set -euo pipefail
repo=$1 scene=$2 output=$3 seed=${4:-42}
[ -f "$scene/transforms.json" ] || tools/make_caliterra_scene.sh "$repo" "$scene"
scalar-nerf-benchmark --data "$scene" --downscale 8 --log2-table 19 \
    --global-steps 1000 --block-steps 500 --num-blocks 2 --eval-every 1000 \
    --variants ngp-t ngp-t-decay ngp-t2 ngp-t2-decay auto auto-parallel \
    --fusions nearest-guarded nearest nearest-idw idw global-only \
    --seed "$seed" --resume --output-dir "$output"
