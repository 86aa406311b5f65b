"""Mean PSNR and accumulation over every third training view of trained runs."""
import sys, torch
from pathlib import Path
from nerfstudio.utils.eval_utils import eval_setup
from scalar_nerfstudio.metrics import psnr
for cfg in sys.argv[1:]:
    _, p, _, _ = eval_setup(Path(cfg), test_mode="test")
    ds = p.datamanager.train_dataset; cams = ds.cameras
    ps = []; accs = []
    for i in range(0, len(cams), 3):
        with torch.no_grad():
            out = p.model.get_outputs_for_camera(cams[i:i+1].to(p.device))
        gt = ds[i]["image"][..., :3].float()
        ps.append(float(psnr(out["rgb"].clamp(0, 1), gt)))
        accs.append(float(out["accumulation"].mean()))
    print(cfg.split('/')[4], "train-view PSNR mean %.2f" % (sum(ps)/len(ps)), "acc %.3f" % (sum(accs)/len(accs)))
