#!/bin/sh
# nearest-guarded against nearest and the global model alone on trained runs (docs/notebook/defaults.md, "Fusion: nearest-guarded").
# Usage, from the repository root: sh docs/benchmark/nearest-guarded/eval.sh LABEL=RUN/config.yml ...
# Each run's table goes to docs/benchmark/nearest-guarded/LABEL/fusion.{json,md}; summary.py (in raw.tar.xz) prints them side by side.
set -e
D=docs/benchmark/nearest-guarded
for PAIR in "$@"; do
    LABEL=${PAIR%%=*}
    CONFIG=${PAIR#*=}
    scalar-nerf-eval-fusion --load-config "$CONFIG" --output-dir $D/$LABEL \
        --modes nearest nearest-guarded global-only --no-measure-selection > $D/$LABEL.log 2>&1
    echo "$LABEL done $(date +%H:%M:%S)"
done
