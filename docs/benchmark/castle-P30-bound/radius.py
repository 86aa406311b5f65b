"""Radius a sparse point cloud would give: surface points of a trained run's training views (accumulation > 0.9)."""
import sys, torch
from pathlib import Path
from nerfstudio.utils.eval_utils import eval_setup
config = Path(sys.argv[1])
_, pipeline, _, _ = eval_setup(config, test_mode="test")
dm = pipeline.datamanager
cams = dm.train_dataset.cameras
pts = []
with torch.no_grad():
    for i in range(0, len(cams), 2):
        out = pipeline.model.get_outputs_for_camera(cams[i:i+1].to(pipeline.device))
        rays = cams[i:i+1].generate_rays(camera_indices=0, keep_shape=True)
        d = out["depth"].reshape(-1); a = out["accumulation"].reshape(-1)
        keep = a > 0.9
        p = rays.origins.reshape(-1, 3)[keep] + rays.directions.reshape(-1, 3)[keep] * d[keep, None]
        pts.append(p[::20])
pts = torch.cat(pts); r = pts.norm(dim=-1)
cam_r = cams.camera_to_worlds[:, :, 3].norm(dim=-1).max()
print("points", pts.shape[0], "cam max r", float(cam_r))
for q in (0.5, 0.9, 0.99, 0.999): print(q, float(torch.quantile(r.double(), q)))
print("RADIUS", 2 * float(torch.quantile(r.double(), 0.999)))
