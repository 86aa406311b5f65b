import sys, torch
from pathlib import Path
from nerfstudio.utils.eval_utils import eval_setup
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
        mse = ((out["rgb"].clamp(0,1) - gt) ** 2).mean()
        ps.append(float(-10 * torch.log10(mse)))
    print("radius", radius, "colliders", len(colliders(m)), ["%.2f" % x for x in ps])
