#!/bin/bash
# The three seeds of the aerial 4x4 town, resumed with the wall-clock tries (one after another, nothing else running).
# Run 2026-11-28 05:45-06:48; seed 42 stopped in ngp21-wall-clock-2 and finished by the same command with --wall-clock-tries 2 (docs/notebook/town.md).
cd "$(git rev-parse --show-toplevel)"  # the repository root (outputs/ and the scene there)
COMMON="--data outputs/scenes/aerial-4x4-256 --downscale 1 --log2-table 10 --global-steps 900 --block-steps 175 --num-blocks 4 --parallel-block-steps 850 --eval-every 1600 --fusions nearest-guarded global-only --resume"
date; scalar-nerf-benchmark $COMMON --variants ngp19 auto-parallel --seed 2 --output-dir outputs/bench-aerial4x4-256-t10-seed2 2>&1 | grep -v Warning | tail -40
date; scalar-nerf-benchmark $COMMON --variants ngp19 auto-parallel --seed 1 --output-dir outputs/bench-aerial4x4-256-t10-seed1 2>&1 | grep -v Warning | tail -40
date; scalar-nerf-benchmark $COMMON --variants ngp19 ngp21 auto-parallel --output-dir outputs/bench-aerial4x4-256-t10 2>&1 | grep -v Warning | tail -40
date
