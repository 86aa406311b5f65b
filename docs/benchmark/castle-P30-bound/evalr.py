"""PSNR per held-out view of a trained run, rendered unbounded and with the scene bound at 20 and 6 units."""
import sys, torch
from pathlib import Path
from nerfstudio.utils.eval_utils import eval_setup
from scalar_nerfstudio.metrics import psnr
from scalar_nerfstudio.models.scalar_model import BoundedNearFarCollider
_, p, _, _ = eval_setup(Path(sys.argv[1]), test_mode="test")
m = p.model
def colliders(mod):
    return [x for x in mod.modules() if isinstance(x, BoundedNearFarCollider)]
for radius in (None, 20.0, 6.0):
    for c in colliders(m): c.scene_radius = radius
    cams = p.datamanager.eval_dataset.cameras
    ps = []
    for i in range(len(cams)):
        with torch.no_grad():
            out = m.get_outputs_for_camera(cams[i:i+1].to(p.device))
        gt = p.datamanager.eval_dataset[i]["image"][..., :3].float()
        ps.append(float(psnr(out["rgb"].clamp(0, 1), gt)))
    print("radius", radius, "colliders", len(colliders(m)), ["%.2f" % x for x in ps])
