"""One-off probe (issue 16): render every block and the global model on every eval view of a trained run once
and save the images, so that fusion rules can be scored offline (fusion_score.py, fusion_score2.py).

    python docs/benchmark/nearest-idw/fusion_probe.py RUN/config.yml renders.pt
"""
import sys, torch, json, itertools
from pathlib import Path
from nerfstudio.utils.eval_utils import eval_setup
from scalar_nerfstudio.metrics import psnr
cfg = Path(sys.argv[1]); out = Path(sys.argv[2])
_, pipeline, _, _ = eval_setup(cfg, test_mode="test")
pipeline.eval(); model = pipeline.model
K = model.split.num_blocks
pairs = list(pipeline.datamanager.fixed_indices_eval_dataloader)
gts, origins, renders = [], [], {m: [] for m in ["global-only"] + [f"block:{k}" for k in range(K)]}
with torch.no_grad():
    for camera, batch in pairs:
        gts.append(batch["image"][..., :3].float())
        origins.append(camera.camera_to_worlds.reshape(-1, 3, 4)[0, :3, 3].clone())
        for m in renders:
            model.set_fusion(m)
            renders[m].append(model.get_outputs_for_camera(camera=camera)["rgb"].clamp(0, 1).cpu())
torch.save({"gts": gts, "origins": origins, "renders": renders, "centres": model.block_centres.cpu(),
            "radii": model.block_radii.cpu()}, out)
print("saved", out)
