#!/bin/sh
# castle-P30 (downscale 4, one model, seed 42; the *-seed1 specs seed 1) with and without a scene bound, and with the random
# or grey training background. Each name is a runner spec in this folder; run from the repository
# root with ../shared beside it. A 2000-step run takes 4-6 min on 2 cores, a 500-step one 1-1.5 min.
# Usage: sh docs/benchmark/castle-P30-bound/run.sh unbounded radius6 [radius20 radius6-grey ...]
set -e
D=docs/benchmark/castle-P30-bound
for NAME in "$@"; do
    mkdir -p outputs/bench-castle-bound/runs
    python -m scalar_nerfstudio.benchmarking.runner $D/$NAME.spec.json > outputs/bench-castle-bound/runs/$NAME.log 2>&1
    python -c "import json,sys; r=json.load(open(json.load(open(sys.argv[1]))['result'])); print(sys.argv[2], r['steps'], 'steps', round(r['final']['psnr'], 2), 'dB', round(r['final']['ssim'], 3), round(r['train_s']), 's')" \
        $D/$NAME.spec.json $NAME
done
