"""Render every block and the global model on every eval view of a run; save tensors."""
import sys, time, torch
from pathlib import Path
from nerfstudio.utils.eval_utils import eval_setup
cfg = Path(sys.argv[1]); out = Path(sys.argv[2])
_, pipeline, _, _ = eval_setup(cfg, test_mode="test")
model = pipeline.model
K = model.split.num_blocks
pairs = list(pipeline.datamanager.fixed_indices_eval_dataloader)
rec = {"gt": [], "origin": [], "global": [], "blocks": []}
t0 = time.time()
for camera, batch in pairs:
    rec["gt"].append(batch["image"][..., :3].clone())
    rec["origin"].append(camera.camera_to_worlds[..., :3, 3].reshape(3).clone())
    model.set_fusion("global-only"); o = model.get_outputs_for_camera(camera=camera)
    rec["global"].append(o["rgb"].clone())
    block_rgb = []
    for k in range(K):
        model.set_fusion(f"block:{k}"); o = model.get_outputs_for_camera(camera=camera)
        block_rgb.append(o["rgb"].clone())
    rec["blocks"].append(torch.stack(block_rgb))  # [K, H, W, 3]
    print(len(rec["gt"]), f"{time.time()-t0:.0f}s", flush=True)
rec["centres"] = model.block_centres.clone()
torch.save(rec, out)
