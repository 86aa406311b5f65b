"""One-off (issue 18): the same run for N steps, timing the hash table's gradient (the C++ backward, which
allocates and zeroes the [rows, F] gradient) and counting minor page faults per step and inside it.

    python docs/benchmark/training-trials/2026-11-25-evening/table_gradient_faults.py 400
"""
import sys, time, resource, json
from scalar_nerfstudio.engine.timing import time_train_iterations
from scalar_nerfstudio.benchmarking.runner import trainer_config
import scalar_nerfstudio.encodings.hash_grid as hg
steps = int(sys.argv[1])
overrides = {"machine.device_type": "cpu", "mixed_precision": False, "pipeline.datamanager.train_num_rays_per_batch": 4096, "max_num_iterations": steps}
config = trainer_config({"method": "scalar-nerf", "data": "../shared/data/castle-P30", "downscale": 4, "output_dir": "outputs/step_times", "overrides": overrides})
config.set_timestamp()
trainer = config.setup(local_rank=0, world_size=1); trainer.setup()
orig = hg._cpp_table_gradient
bw = []
def timed(*a, **k):
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt; t = time.perf_counter()
    r = orig(*a, **k)
    bw.append((time.perf_counter() - t, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)); return r
hg._cpp_table_gradient = timed
rows = []
last = [resource.getrusage(resource.RUSAGE_SELF).ru_minflt, 0.0]
def after(step, result, clock):
    f = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    rows.append((clock.wall_s - last[1], f - last[0])); last[0] = f; last[1] = clock.wall_s
time_train_iterations(trainer, after)
trainer.train()
import numpy as np
r = np.array(rows); b = np.array(bw)
for a, z in [(0, 128), (128, 200), (200, 300), (300, steps)]:
    print(f"steps {a}-{z}: {1000*r[a:z,0].mean():.0f} ms/step, {r[a:z,1].mean():.0f} minor faults/step; table backward {1000*b[a:z,0].mean():.1f} ms, {b[a:z,1].mean():.0f} faults")
