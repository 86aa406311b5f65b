"""NGP_12 on the aerial 4 x 4 town, seed 42 (2026-11-28), added to the runs of drive.py (docs/notebook/town.md).

    python docs/benchmark/aerial-4x4-256/t10/drive_ngp12.py

Trains the benchmark's ``ngp21`` variant (here 2^12: --log2-table 10 + 2) and, when it ends before the
blocks' wall-clock, ``ngp21-wall-clock``, with the benchmark's own functions and the same config as
drive.py; then rewrites the report from every run of outputs/bench-aerial4x4-256-t10/runs."""
import json, subprocess, sys, time
from pathlib import Path
from scalar_nerfstudio.benchmarking.variants import BenchmarkConfig, plan, wall_clock_variants
from scalar_nerfstudio.benchmarking.schedule import variant_spec, with_base_phase
from scalar_nerfstudio.benchmarking.report import write_report
from scalar_nerfstudio.benchmarking.machine import hash_grid_speed

config = BenchmarkConfig(data=Path("outputs/scenes/aerial-4x4-256"), downscale=1, log2_table=10, global_steps=900, block_steps=175, num_blocks=4,
    parallel_block_steps=850, eval_every=1600, variants=("ngp19", "ngp21", "auto-parallel"), output_dir=Path("outputs/bench-aerial4x4-256-t10"))
runs = config.output_dir / "runs"
variants, notes = plan(config)
probe_before = hash_grid_speed()
print("probe before", probe_before, time.strftime("%H:%M:%S"), flush=True)
results = {name: json.loads((runs / f"{name}.json").read_text()) for name in ("global", "ngp19", "auto-parallel", "ngp19-wall-clock")}
results["auto-parallel"] = with_base_phase(results["auto-parallel"], results["global"])
def run(variant):
    spec = variant_spec(config, variant, runs, results)
    path = runs / f"{variant.name}.spec.json"
    path.write_text(json.dumps(spec, indent=2))
    t = time.time()
    subprocess.run([sys.executable, "-m", "scalar_nerfstudio.benchmarking.runner", str(path)], check=True,
                   stdout=open(runs / f"{variant.name}.log", "w"), stderr=subprocess.STDOUT)
    print(variant.name, "done in", round(time.time() - t), "s", time.strftime("%H:%M:%S"), flush=True)
    results[variant.name] = json.loads(Path(spec["result"]).read_text())
run({v.name: v for v in variants}["ngp21"])
for variant, note in wall_clock_variants(config, variants, results):
    if variant.name.startswith("ngp19"):  # trained by drive.py already
        notes[variant.name] = note.replace(" trained again", " trained again (drive.py)")
        continue
    run(variant)
    notes[variant.name] = note
probe = {"before": probe_before, "after": hash_grid_speed()}
command = ("scalar-nerf-benchmark --data outputs/scenes/aerial-4x4-256 --downscale 1 --log2-table 10 --global-steps 900 --block-steps 175 "
           "--num-blocks 4 --parallel-block-steps 850 --eval-every 1600 --variants ngp19 ngp21 auto-parallel (stopped after ngp19; then "
           "docs/benchmark/aerial-4x4-256/t10/drive.py: auto-parallel with fusions nearest-guarded and global-only, and ngp19-wall-clock; "
           "then drive_ngp12.py: ngp21 and ngp21-wall-clock)")
write_report(config, results, notes, command, time.time(), probe)
print(open(config.output_dir / "results.md").read().split("\n![")[0])
