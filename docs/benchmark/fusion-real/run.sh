#!/bin/bash
# every fusion mode on trained real-capture runs: the runs of docs/benchmark/caliterra/1000x750-seed1 (auto-parallel),
# docs/benchmark/kitti-1 and docs/benchmark/caliterra/fresh-clone (paths as they were on the machine that ran it)
set -u
MODES="nearest-guarded nearest nearest-idw idw global global-only"
OUT=/work/bench-logs/fusion-real
for pair in \
  "caliterra-1000x750-seed1-parallel /work/bench-caliterra-1000x750-seed1/runs/auto-parallel/caliterra/scalar-nerf/2026-11-28_223114/config.yml" \
  "kitti-1 /work/kitti-run/kitti-1/scalar-nerf/2026-11-28_225400/config.yml" \
  "caliterra-500x375-default /work/e2e-caliterra/outputs/scene/scalar-nerf/2026-11-28_212223/config.yml" ; do
  set -- $pair
  echo "== $1 $(date +%T)"
  /usr/bin/time -f "%e s, %M kB" scalar-nerf-eval-fusion --load-config $2 --modes $MODES --no-measure-selection --output-dir $OUT/$1 > $OUT/$1.log 2>&1
  tail -3 $OUT/$1.log
done
echo "== done $(date +%T)"
