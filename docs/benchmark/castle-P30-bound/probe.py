"""Accumulation, depth and distance from the centre of the surfaces in the top, middle and bottom thirds of held-out view 0."""
import sys, torch
from pathlib import Path
from nerfstudio.utils.eval_utils import eval_setup
for cfg in sys.argv[1:]:
    _, p, _, _ = eval_setup(Path(cfg), test_mode="test")
    cams = p.datamanager.eval_dataset.cameras
    with torch.no_grad():
        out = p.model.get_outputs_for_camera(cams[0:1].to(p.device))
    rays = cams[0:1].generate_rays(camera_indices=0, keep_shape=True)
    pts = rays.origins + rays.directions * out["depth"]
    r = pts.norm(dim=-1)
    H = r.shape[0]
    for name, sl in (("top", slice(0, H//3)), ("mid", slice(H//3, 2*H//3)), ("bottom", slice(2*H//3, H))):
        print(cfg.split('/')[3], name, "acc %.2f" % out["accumulation"][sl].mean().item(), "depth med %.2f" % out["depth"][sl].median().item(), "r med %.2f  r>6 %.2f" % (r[sl].median().item(), (r[sl] > 6).float().mean().item()))
    print("cam origin", rays.origins[0, 0].tolist(), "radius", p.model.global_model.config.scene_radius)
