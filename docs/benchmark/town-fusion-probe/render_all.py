"""Render every block and the global model on every eval view of a run; save tensors."""
import sys, time, torch
from pathlib import Path
from nerfstudio.utils.eval_utils import eval_setup
cfg = Path(sys.argv[1]); out = Path(sys.argv[2])
_, pipeline, _, _ = eval_setup(cfg, test_mode="test")
model = pipeline.model
K = model.split.num_blocks
pairs = list(pipeline.datamanager.fixed_indices_eval_dataloader)
rec = {"gt": [], "origin": [], "global": [], "blocks": [], "gdepth": [], "bdepth": [], "bacc": []}
t0 = time.time()
for camera, batch in pairs:
    rec["gt"].append(batch["image"][..., :3].clone())
    rec["origin"].append(camera.camera_to_worlds[..., :3, 3].reshape(3).clone())
    model.set_fusion("global-only"); o = model.get_outputs_for_camera(camera=camera)
    rec["global"].append(o["rgb"].clone()); rec["gdepth"].append(o["depth"].clone())
    bs, ds, accs = [], [], []
    for k in range(K):
        model.set_fusion(f"block:{k}"); o = model.get_outputs_for_camera(camera=camera)
        bs.append(o["rgb"].clone()); ds.append(o["depth"].clone()); accs.append(o["accumulation"].clone())
    rec["blocks"].append(torch.stack(bs)); rec["bdepth"].append(torch.stack(ds)); rec["bacc"].append(torch.stack(accs))
    print(len(rec["gt"]), f"{time.time()-t0:.0f}s", flush=True)
rec["centres"] = model.block_centres.clone(); rec["radii"] = model.block_radii.clone()
torch.save(rec, out)
