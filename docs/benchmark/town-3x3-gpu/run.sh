#!/usr/bin/env bash
# The 3 x 3 town on one GPU with many more rays than the 2-core CPU allows (the dated town.md, section
# "The 3 x 3 town on a GPU"; docs/notebook/defaults.md, "The dated logs"). Every run starts at once and shares the GPU:
#   - one model with a 2^T, a 2^(T+2) and a 2^(T+4) table, STEPS steps each (the benchmark's
#     one-model runs: its runner, its specs);
#   - the global phase (GLOBAL_STEPS steps, 2^T, automatic K), then its blocks trained at once by
#     `scalar-nerf-train-blocks --gpus-per-block 1/BLOCKS_PER_GPU` (8 by default; STEPS - GLOBAL_STEPS steps each: the equal
#     wall-clock budget on K workers, counted in steps), then `scalar-nerf-eval-fusion` on the
#     assembled run.
# Held-out views: every 8th image, as in the benchmark. Results go to $OUT (seven files: each run's
# JSON, fusion.json, run.log, logs.tgz with every process's log).
#
#     OUT=outputs/town3x3-gpu bash docs/benchmark/town-3x3-gpu/run.sh
# ONE_MODEL_TABLES (default "T T+2 T+4") and MODES (the fusions evaluated) trim the work to a short
# device call.
#     STEPS=40 GLOBAL_STEPS=20 EVAL_EVERY=20 RAYS=256 OUT=/tmp/dry bash docs/benchmark/town-3x3-gpu/run.sh  # a dry run
set -uo pipefail
cd "$(dirname "$0")/../../.."
data=${DATA:-outputs/scenes/town-3x3-rig}
out=${OUT:-outputs/town3x3-gpu}
work=${WORK:-/tmp/town3x3-gpu}
steps=${STEPS:-6000}
global_steps=${GLOBAL_STEPS:-3000}
block_steps=$((steps - global_steps))
rays=${RAYS:-4096}
t=${T:-12}
eval_every=${EVAL_EVERY:-$((steps / 4))}
blocks_per_gpu=${BLOCKS_PER_GPU:-8}
one_model_tables=(${ONE_MODEL_TABLES:-$t $((t + 2)) $((t + 4))})   # log2 table sizes of the one-model runs
fusion_modes=(${MODES:-nearest nearest-idw global global-only})
mkdir -p "$out" "$work"
export PYTHONUNBUFFERED=1
say() { echo "=== $(date +%H:%M:%S) $*" | tee -a "$out/run.log"; }

spec() {  # NAME LOG2_TABLE GLOBAL_STEPS NUM_BLOCKS(null: automatic) EVAL_EVERY
    python - "$@" <<PY
import json, sys
name, log2, global_steps, num_blocks, eval_every = sys.argv[1:]
spec = {
    "name": name, "method": "scalar-nerf", "data": "$data", "downscale": 1,
    "overrides": {
        "machine.seed": 42,
        "pipeline.datamanager.train_num_rays_per_batch": $rays,
        "pipeline.model.field.log2_hashmap_size": int(log2),
        "pipeline.num_blocks": None if num_blocks == "null" else int(num_blocks),
        "pipeline.train_blocks": False,
        "pipeline.global_steps": int(global_steps),
        "pipeline.block_steps": $block_steps,
    },
    "eval_every": int(eval_every), "time_limit_s": 0.0, "fusions": ["global"],
    "output_dir": "$work/runs/" + name, "result": "$out/" + name + ".json",
}
with open("$work/" + name + ".spec.json", "w") as f:
    json.dump(spec, f, indent=2)
PY
}

say "machine"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>&1 | tee -a "$out/run.log"
python -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())" 2>&1 | tee -a "$out/run.log"
say "build the CUDA hash grid once (the runs would wait on its lock)"
python -c "from scalar_nerfstudio.encodings._cpp import CUDA_HASH_GRID as k; import torch; print('CUDA hash grid:', k.load() is not None if torch.cuda.is_available() else 'no GPU')" 2>&1 | tail -1 | tee -a "$out/run.log"

for log2 in "${one_model_tables[@]}"; do spec "ngp$log2" "$log2" "$steps" 1 "$eval_every"; done
spec "global$t" "$t" "$global_steps" null "$global_steps"

pids=()
for log2 in "${one_model_tables[@]}"; do
    name="ngp$log2"
    say "start $name ($steps steps of $rays rays)"
    OMP_NUM_THREADS=2 python -m scalar_nerfstudio.benchmarking.runner "$work/$name.spec.json" > "$work/$name.log" 2>&1 &
    pids+=($!)
done

(
    say "start global$t ($global_steps steps)"
    OMP_NUM_THREADS=2 python -m scalar_nerfstudio.benchmarking.runner "$work/global$t.spec.json" > "$work/global$t.log" 2>&1 \
        || { say "global$t failed"; tail -30 "$work/global$t.log"; exit 1; }
    run=$(dirname "$(find "$work/runs/global$t" -name config.yml | head -1)")
    say "global$t done: $run; its blocks, $blocks_per_gpu per GPU, $block_steps steps each"
    share=$(python -c "print(1 / $blocks_per_gpu)")
    gpus=(); python -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" && gpus=(--gpus-per-block "$share")
    scalar-nerf-train-blocks "$run" --output-dir "$work/blocks" --block-steps "$block_steps" --cpus-per-block 1 "${gpus[@]}" \
        > "$work/train-blocks.log" 2>&1 || { say "train-blocks failed"; tail -40 "$work/train-blocks.log"; exit 1; }
    say "blocks done"
    tail -25 "$work/train-blocks.log" | tee -a "$out/run.log"
    assembled=$(grep -o "[^ ]*/config.yml" "$work/train-blocks.log" | tail -1)
    [ -n "$assembled" ] || assembled=$(find "$work/blocks" -path "*assembled*" -name config.yml | head -1)
    say "eval-fusion on $assembled"
    scalar-nerf-eval-fusion --load-config "$assembled" --output-dir "$work/fusion" --modes "${fusion_modes[@]}" \
        --no-measure-selection > "$work/eval-fusion.log" 2>&1 || { say "eval-fusion failed"; tail -30 "$work/eval-fusion.log"; exit 1; }
    cp "$work/fusion/fusion.json" "$out/fusion.json"
    say "eval-fusion done"
) &
pids+=($!)

while sleep 30; do
    alive=0; for p in "${pids[@]}"; do kill -0 "$p" 2>/dev/null && alive=1; done
    line=$(for f in "$work"/*.log; do printf '%s %s | ' "$(basename "$f" .log)" "$(grep -o 'PROGRESS [0-9]* [0-9]*' "$f" | tail -1 | cut -d' ' -f2-)"; done)
    say "progress: $line"
    nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>/dev/null | tee -a "$out/run.log"
    [ "$alive" = 1 ] || break
done
wait
say "done"
for f in "$out"/ngp*.json "$out"/global*.json; do
    python -c "import json,sys; d=json.load(open('$f')); print(d['name'], d['steps'], 'steps', round(d['train_s']), 's', round(d['train_rays_per_s']), 'rays/s', 'final', {k: round(v, 3) for k, v in d['final'].items() if k != 'step'}); [print('   ', c['step'], round(c['train_s']), round(c['psnr'], 2), round(c.get('depth_delta1', -1), 3)) for c in d['curve']]" 2>&1 | tee -a "$out/run.log"
done
cat "$work/fusion/fusion.md" 2>/dev/null | tee -a "$out/run.log"
tar czf "$out/logs.tgz" -C "$work" $(cd "$work" && ls *.log *.spec.json) blocks/train_blocks.json 2>/dev/null
