"""One-off probe (issue 16): blocks by where the cameras look, with pixel masks.

The global model's depth at every training pixel gives its surface point; KMeans (K = 8) on the
surface points (x, y) gives regions; a region's box is its points' AABB (x, y) scaled by 1.2, z the
scene's. Block k trains on the pixels whose surface lies in its box (sky pixels: in every block)
of the images with at least 5 % of their pixels in it.
"""
import copy, json, sys
from pathlib import Path
import numpy as np
import torch
from PIL import Image
from sklearn.cluster import KMeans
from nerfstudio.utils.eval_utils import eval_setup

run = Path(sys.argv[1]); plan_template = Path(sys.argv[2]); out = Path(sys.argv[3])
K, SCALE, MIN_SHARE = 8, 1.2, 0.05
_, pipeline, _, _ = eval_setup(run / "config.yml", test_mode="inference")
model = pipeline.model.global_model
dataset = pipeline.datamanager.train_dataset
cams = dataset.cameras
names = [str(Path(f).relative_to(Path(f).parent.parent)) for f in dataset._dataparser_outputs.image_filenames]
points, hits, shapes = [], [], []
for i in range(len(cams)):
    bundle = cams[i:i+1].generate_rays(camera_indices=0, keep_shape=True)
    h, w = bundle.origins.shape[:2]
    flat = bundle.reshape((-1,))
    with torch.no_grad():
        o = model.render_depth_only(flat)
    p = flat.origins + flat.directions * o["depth"]
    points.append(p.numpy()); hits.append((o["accumulation"][:, 0] > 0.5).numpy()); shapes.append((h, w))
cc = cams.camera_to_worlds[:, :2, 3].numpy()
c_lo, c_hi = cc.min(0), cc.max(0); c_mid, c_half = (c_lo + c_hi) / 2, (c_hi - c_lo) / 2 * 1.5
hits = [h & (np.abs(p[:, :2] - c_mid) <= c_half).all(-1) for p, h in zip(points, hits)]
print("near region", c_mid - c_half, c_mid + c_half)
allp = np.concatenate(points); allh = np.concatenate(hits)
print("share of pixels with a near surface", allh.mean())
sel = allp[allh][::7, :2]
km = KMeans(n_clusters=K, n_init=4, random_state=0).fit(sel)
z_lo, z_hi = float(allp[allh, 2].min()), float(allp[allh, 2].max())
boxes = []
for k in range(K):
    q = sel[km.labels_ == k]
    lo, hi = np.percentile(q, 1, axis=0), np.percentile(q, 99, axis=0)
    c, half = (lo + hi) / 2, (hi - lo) / 2 * SCALE
    boxes.append((c - half, c + half))
plan = json.load(open(plan_template))
blocks = []
mask_paths = {}
for k, (lo, hi) in enumerate(boxes):
    (out / f"masks-{k}").mkdir(parents=True, exist_ok=True)
    idx = []
    for i, (p, hit, (h, w)) in enumerate(zip(points, hits, shapes)):
        inside = hit & (p[:, 0] >= lo[0]) & (p[:, 0] <= hi[0]) & (p[:, 1] >= lo[1]) & (p[:, 1] <= hi[1])
        if inside.mean() >= MIN_SHARE:
            idx.append(i)
        mask = (inside | ~hit).reshape(h, w).astype(np.uint8) * 255
        path = out / f"masks-{k}" / Path(names[i]).name
        Image.fromarray(mask).save(path)
        mask_paths.setdefault(k, []).append(str(path.resolve()))
    c = [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (z_lo + z_hi) / 2]
    blocks.append({"index": k, "num_images": len(idx), "image_indices": idx, "image_names": [plan["image_names"][i] for i in idx],
                   "aabb_min": [float(lo[0]), float(lo[1]), z_lo], "aabb_max": [float(hi[0]), float(hi[1]), z_hi], "centre": c})
    print(k, len(idx), "box", np.round(lo, 2), np.round(hi, 2), "pixel share in its images", round(float(np.mean([ (np.array(Image.open(mask_paths[k][i]))>0).mean() for i in idx])), 2))
assert plan["image_names"] == names, (plan["image_names"][:3], names[:3])
plan["blocks"] = blocks
(out / "plan").mkdir(exist_ok=True)
json.dump(plan, open(out / "plan" / "blocks.json", "w"), indent=1)
json.dump(mask_paths, open(out / "mask_paths.json", "w"))
