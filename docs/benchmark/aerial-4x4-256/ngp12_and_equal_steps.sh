#!/bin/bash
# Run 2026-11-28 08:10-10:39: equal total steps (auto) on all seeds, NGP_12 on seeds 1 and 2; each resumed, one after another, nothing else heavy running.
cd "$(git rev-parse --show-toplevel)"  # the repository root (outputs/ and the scene there)
COMMON="--data outputs/scenes/aerial-4x4-256 --downscale 1 --log2-table 10 --global-steps 900 --block-steps 175 --num-blocks 4 --parallel-block-steps 850 --eval-every 1600 --fusions nearest-guarded global-only --resume"
echo "probe $(python -c 'from scalar_nerfstudio.benchmarking.machine import hash_grid_speed; print(hash_grid_speed())' 2>/dev/null)"
date; scalar-nerf-benchmark $COMMON --variants ngp19 ngp21 auto auto-parallel --output-dir outputs/bench-aerial4x4-256-t10 2>&1 | grep -v Warning | tail -40
date; scalar-nerf-benchmark $COMMON --variants ngp19 ngp21 auto auto-parallel --seed 1 --output-dir outputs/bench-aerial4x4-256-t10-seed1 2>&1 | grep -v Warning | tail -40
date; scalar-nerf-benchmark $COMMON --variants ngp19 ngp21 auto auto-parallel --seed 2 --output-dir outputs/bench-aerial4x4-256-t10-seed2 2>&1 | grep -v Warning | tail -40
date
echo "probe $(python -c 'from scalar_nerfstudio.benchmarking.machine import hash_grid_speed; print(hash_grid_speed())' 2>/dev/null)"
# Then, after commit 939d986 (the equal wall-clock table's fix), seed 42's and seed 1's commands again: every run reused, the reports rewritten.
