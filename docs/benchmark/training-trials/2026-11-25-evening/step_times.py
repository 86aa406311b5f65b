"""One-off (issue 18): the training benchmark's scalar-nerf run (bench_training.py's worker set-up: castle-P30
ds4, 4096 rays per step, every 8th image held out) with each step's wall-clock kept, so the run's time can be
split by phase. Writes the per-step seconds as JSON and prints seconds per phase, rays/s and held-out PSNR.

    python docs/benchmark/training-trials/2026-11-25-evening/step_times.py 1800 step_seconds.json
"""
import sys, time, json
from scalar_nerfstudio.engine.timing import time_train_iterations
from scalar_nerfstudio.benchmarking.runner import trainer_config
steps = int(sys.argv[1]); out = sys.argv[2]
sets = json.loads(sys.argv[3]) if len(sys.argv) > 3 else {}
overrides = {"machine.device_type": "cpu", "mixed_precision": False, "pipeline.datamanager.train_num_rays_per_batch": 4096, "max_num_iterations": steps}
overrides.update(sets)
config = trainer_config({"method": "scalar-nerf", "data": "../shared/data/castle-P30", "downscale": 4, "output_dir": "outputs/step_times", "overrides": overrides})
config.set_timestamp()
trainer = config.setup(local_rank=0, world_size=1); trainer.setup()
times = []
last = [None]
def after(step, result, clock):
    times.append(clock.wall_s)
clock = time_train_iterations(trainer, after)
trainer.train()
import numpy as np
t = np.array(times); d = np.diff(np.concatenate([[0], t]))
for a, b in [(0, 10), (10, 128), (128, 200), (200, 400), (400, 900), (900, 1300), (1300, 1800)]:
    if b <= len(d): print(f"steps {a}-{b}: {d[a:b].sum():.1f} s, {1000*d[a:b].mean():.0f} ms/step")
print("total", t[-1], "rays/s", len(t) * 4096 / t[-1])
pipeline = trainer.pipeline; pipeline.eval()
m = pipeline.get_average_eval_image_metrics(); print("psnr", m["psnr"], "ssim", m["ssim"])
json.dump(list(map(float, d)), open(out, "w"))
