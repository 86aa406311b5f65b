"""The aerial 4 x 4 town's benchmark of 2026-11-27, cut to fit the session (docs/notebook/town.md).

    scalar-nerf-benchmark --data outputs/scenes/aerial-4x4-256 --downscale 1 --log2-table 10 --global-steps 900 \
        --block-steps 175 --num-blocks 4 --parallel-block-steps 850 --eval-every 1600 \
        --variants ngp19 ngp21 auto-parallel --output-dir outputs/bench-aerial4x4-256-t10
    # stopped once runs/ngp19.json was written (before ngp21), then:
    python docs/benchmark/aerial-4x4-256/t10/drive.py

It trains the default blocks (auto-parallel, evaluated with nearest-guarded and global-only only) from
the benchmark's global phase, then NGP_10 again for the blocks' wall-clock, and writes the report, all
with the benchmark's own functions. (In the session the auto-parallel spec was written by the same
lines, run by hand before this script.)"""
import json, subprocess, sys, time
from pathlib import Path
from scalar_nerfstudio.benchmarking.variants import BenchmarkConfig, plan, wall_clock_variants
from scalar_nerfstudio.benchmarking.schedule import variant_spec, with_base_phase
from scalar_nerfstudio.benchmarking.report import write_report
from scalar_nerfstudio.benchmarking.machine import hash_grid_speed

config = BenchmarkConfig(data=Path("outputs/scenes/aerial-4x4-256"), downscale=1, log2_table=10, global_steps=900, block_steps=175, num_blocks=4,
    parallel_block_steps=850, eval_every=1600, variants=("ngp19", "auto-parallel"), output_dir=Path("outputs/bench-aerial4x4-256-t10"))
runs = config.output_dir / "runs"
variants, notes = plan(config)
probe_before = hash_grid_speed()
print("probe before", probe_before, flush=True)
results = {}
for name in ("global", "ngp19"):
    results[name] = json.loads((runs / f"{name}.json").read_text())
def run(spec_path):
    t = time.time()
    subprocess.run([sys.executable, "-m", "scalar_nerfstudio.benchmarking.runner", str(spec_path)], check=True,
                   stdout=open(str(spec_path).replace(".spec.json", ".log"), "w"), stderr=subprocess.STDOUT)
    print(spec_path, "done in", round(time.time() - t), "s", time.strftime("%H:%M:%S"), flush=True)
spec_path = runs / "auto-parallel-two-fusions.spec.json"
if not spec_path.is_file():  # the benchmark's auto-parallel spec, with two of its four fusions
    results["global"]["checkpoint"] = str(sorted((Path(results["global"]["run_dir"]) / "nerfstudio_models").glob("step-*.ckpt"))[-1])
    blocks = {v.name: v for v in variants}["auto-parallel"]
    blocks.fusions = ["nearest-guarded", "global-only"]
    spec_path.write_text(json.dumps(variant_spec(config, blocks, runs, results), indent=2))
if not (runs / "auto-parallel.json").is_file():
    run(spec_path)
results["auto-parallel"] = with_base_phase(json.loads((runs / "auto-parallel.json").read_text()), results["global"])
print("blocks wall-clock", results["auto-parallel"]["parallel_train_s"], flush=True)
for variant, note in wall_clock_variants(config, variants, results):
    spec = variant_spec(config, variant, runs, results)
    path = runs / f"{variant.name}.spec.json"
    path.write_text(json.dumps(spec, indent=2))
    run(path)
    results[variant.name] = json.loads(Path(spec["result"]).read_text())
    notes[variant.name] = note
probe = {"before": probe_before, "after": hash_grid_speed()}
command = ("scalar-nerf-benchmark --data outputs/scenes/aerial-4x4-256 --downscale 1 --log2-table 10 --global-steps 900 --block-steps 175 "
           "--num-blocks 4 --parallel-block-steps 850 --eval-every 1600 --variants ngp19 ngp21 auto-parallel (stopped after ngp19; then "
           "docs/benchmark/aerial-4x4-256/t10/drive.py: auto-parallel with fusions nearest-guarded and global-only, and ngp19-wall-clock)")
write_report(config, results, notes, command, time.time(), probe)
print(open(config.output_dir / "results.md").read().split("\n![")[0])
