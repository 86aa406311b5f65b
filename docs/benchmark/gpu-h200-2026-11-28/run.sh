#!/usr/bin/env bash
# One device call on a lent GPU (issue "fast on the machines users have", GPU part), in a fixed
# time budget (DEADLINE_S, default 530 s from the start of this script):
#   0. the machine; the C++ and CUDA extensions built once, up front (both at once);
#   1. training on castle-P30 (downscale 4), each run alone on the GPU, BENCH_MINUTES each:
#      scalar-nerf at 32768 rays per step and nerfacto at its default (4096), in one benchmark run;
#      scalar-nerf at 4096 rays per step (its default); nerfacto at 32768;
#   2. render time of an 800 x 600 view of the trained scalar-nerf run, per render chunk size;
#   3. the test suite with the GPU visible (pytest-xdist, one worker per core): the quick tests, then the
#      slow ones (those that train) in the time left.
# Needs the project installed (docs/benchmark/gpu-h200-2026-11-28/README.md says how) and
# ../shared/data beside the checkout. Writes at most 8 files to $OUT (the device tool's limit).
#
#     OUT=/tmp/out bash docs/benchmark/gpu-h200-2026-11-28/run.sh
#     DEVICE=cpu BENCH_MINUTES=0.05 STAGES="1 2" OUT=/tmp/out bash docs/benchmark/gpu-h200-2026-11-28/run.sh   # a dry run on a CPU
set -uo pipefail
cd "$(dirname "$0")/../../.."
out=${OUT:-outputs/gpu-round}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
start=$(date +%s)
deadline=$(( start + ${DEADLINE_S:-530} ))
left() { echo $(( deadline - $(date +%s) )); }
stage() { echo; echo "=== $(date +%H:%M:%S) (+$(( $(date +%s) - start )) s) $*"; }
wanted() { [[ " ${STAGES:-1 2 3} " == *" $1 "* ]]; }
device=${DEVICE:-cuda}
minutes=${BENCH_MINUTES:-0.3}
data=${SCALAR_CHECK_DATA:-../shared/data/castle-P30}
work=/tmp/gpu-round
rm -rf "$work"; mkdir -p "$work"

stage "0. machine, extensions"
{ nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv 2>&1
  python -c "import torch; print('torch', torch.__version__, 'CUDA', torch.version.cuda, torch.cuda.get_device_name() if torch.cuda.is_available() else 'no GPU', 'cpus', torch.get_num_threads())"
  grep -m1 "model name" /proc/cpuinfo; grep -o -m1 -w "avx512_bf16\|amx_bf16" /proc/cpuinfo | sort -u | tr '\n' ' '; echo; } 2>&1 | tee "$out/machine.txt"
export MAX_JOBS=$(nproc)
python -c "from scalar_nerfstudio.encodings import _cpp; print('C++ kernels:', _cpp.CPU_KERNELS.available(), _cpp.CPU_KERNELS.error())" &
if [ "$device" = cuda ]; then
    python -c "from scalar_nerfstudio.encodings import _cpp; print('CUDA kernels:', _cpp.CUDA_HASH_GRID.available(), _cpp.CUDA_HASH_GRID.error())" &
fi
wait

bench() {  # name, then bench_training.py arguments
    local name=$1; shift
    timeout "$(( $(left) - 30 ))" python benchmarks/bench_training.py --device "$device" --data "$data" --minutes "$minutes" \
        --workdir "$work/$name" --json "$out/bench-$name.json" "$@" 2>&1 | grep --line-buffered -v "Warning\|warn(\|@custom\|^\s*$"
}
if wanted 1; then
stage "1. training, castle-P30, $minutes min per run, each alone"
{ bench default --methods scalar-nerf nerfacto --scalar-set pipeline.datamanager.train_num_rays_per_batch=32768
  bench rays4096 --methods scalar-nerf --rays-per-batch 4096
  bench nerfacto-rays32768 --methods nerfacto --rays-per-batch 32768; } 2>&1 | tee "$out/bench.log"
fi

if wanted 2; then
stage "2. render time of an 800 x 600 view"
config=$(find "$work/default" -name config.yml -path "*scalar-nerf*" | head -1)
timeout "$(( $(left) - 20 ))" python benchmarks/bench_render.py --load-config "$config" --size 800x600 --rounds 3 --json "$out/render.json" \
    --model-setting eval_num_rays_per_chunk=16384 eval_num_rays_per_chunk=65536 eval_num_rays_per_chunk=262144 eval_num_rays_per_chunk=524288 \
    2>&1 | grep --line-buffered -v "Warning\|warn(\|@custom\|^\s*$"
fi

if wanted 3; then
stage "3a. the quick tests with the GPU visible, $(( $(left) - 10 )) s left"
suite=(python -m pytest -n "$(nproc)" --dist loadfile -p no:cacheprovider -q -rfEs --tb=line --durations=10)
timeout "$(( $(left) - 10 ))" "${suite[@]}" -m "not slow" > "$out/suite-quick.log" 2>&1
echo "pytest exit $? (124: stopped by the time limit)"
grep -E "passed|failed|^FAILED|^ERROR" "$out/suite-quick.log" | tail -30
stage "3b. the slow tests (those that train), $(( $(left) - 5 )) s left"
timeout "$(( $(left) - 5 ))" "${suite[@]}" -m slow > "$out/suite-slow.log" 2>&1
echo "pytest exit $? (124: stopped by the time limit)"
grep -E "passed|failed|^FAILED|^ERROR" "$out/suite-slow.log" | tail -30
fi
stage "done"
