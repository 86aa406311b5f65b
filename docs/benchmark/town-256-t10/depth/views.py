"""One-off (issue 16, 2026-11-26): four views of a trained run, one row each: the true image, the
render, the true z-depth, the rendered depth (log scale to 80 m, white = far or unknown), the
accumulation (all white here: the renders are opaque).

    python docs/benchmark/town-256-t10/depth/views.py RUN/config.yml OUT.png eval|train
"""
import sys
import numpy as np, torch
from pathlib import Path
from PIL import Image
from nerfstudio.utils.eval_utils import eval_setup
from scalar_nerfstudio.scenes.town import read_depth_png
_, p, _, _ = eval_setup(Path(sys.argv[1]), test_mode="test")
scale = p.datamanager.train_dataparser_outputs.dataparser_scale
ds = p.datamanager.eval_dataset if sys.argv[3] == "eval" else p.datamanager.train_dataset
rows = []
for i in [0, 5, 10, 20]:
    cam = ds.cameras[i:i+1]
    with torch.no_grad(): out = p.model.get_outputs_for_camera(cam)
    d = out["depth"].squeeze(-1).numpy() / scale
    acc = out["accumulation"].squeeze(-1).numpy()
    z = read_depth_png(Path(str(ds._dataparser_outputs.image_filenames[i]).replace("/images/", "/depths/")))
    f = lambda x: np.clip(np.log1p(np.nan_to_num(x)) / np.log1p(80), 0, 1)
    gray = lambda x: np.repeat((x * 255).astype(np.uint8)[..., None], 3, -1)
    rgb = (out["rgb"].clamp(0,1).numpy()*255).astype(np.uint8)
    gt = (ds[i]["image"][..., :3].numpy()*255).astype(np.uint8)
    rows.append(np.concatenate([gt, rgb, gray(f(z)), gray(f(d)), gray(acc)], 1))
    print(i, "acc mean", acc.mean(), "acc<0.9", (acc<0.9).mean())
Image.fromarray(np.concatenate(rows, 0)).save(sys.argv[2])
