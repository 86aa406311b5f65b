"""One-off: where do the surfaces a block renders lie, relative to the block's camera box?"""
import json, sys
from pathlib import Path
import torch
from nerfstudio.utils.eval_utils import eval_setup
run = Path(sys.argv[1])
_, pipeline, _, _ = eval_setup(run / "config.yml", test_mode="test")
model = pipeline.model
blocks = json.load(open(run / "blocks.json"))["blocks"]
lo = torch.tensor([b["aabb_min"] for b in blocks]); hi = torch.tensor([b["aabb_max"] for b in blocks])
centre, half = (lo + hi) / 2, (hi - lo) / 2
cams = pipeline.datamanager.eval_dataset.cameras
scales = (1.2, 2.0, 3.0, 5.0)
inside = {s: 0.0 for s in scales}; total = 0.0; far = 0.0
for i in range(len(cams)):
    cam = cams[i:i+1]
    bundle = cam.generate_rays(camera_indices=0, keep_shape=False)
    o = bundle.origins.reshape(-1, 3)
    b = int(torch.argmin(((centre[:, :2] - o[0, :2]) ** 2).sum(-1)))
    with torch.no_grad():
        out = model.global_model.render_rays(bundle)
    p = o + bundle.directions.reshape(-1, 3) * out["depth"].reshape(-1, 1)
    acc = out["accumulation"].reshape(-1)
    d = (p[:, :2] - centre[b, :2]).abs()
    for s in scales:
        inside[s] += float(((d <= half[b, :2] * s).all(-1).float() * acc).sum())
    total += float(acc.sum())
print({s: round(inside[s] / total, 3) for s in scales}, "block half-extent xy mean", half[:, :2].mean(0).tolist(), "scene xy extent", (hi.max(0).values - lo.min(0).values)[:2].tolist())
