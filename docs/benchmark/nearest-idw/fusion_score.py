"""One-off probe (issue 16): held-out PSNR of fusion rules applied offline to fusion_probe.py's renders:
nearest, the best single block per view (an oracle), means of the m nearest blocks, inverse-distance
weighting over every block or the m nearest, for several exponents.

    python docs/benchmark/nearest-idw/fusion_score.py renders.pt
"""
import sys, torch
from scalar_nerfstudio.metrics import psnr
d = torch.load(sys.argv[1]); gts, origins, R, C = d["gts"], d["origins"], d["renders"], d["centres"]
K = C.shape[0]; n = len(gts)
B = torch.stack([torch.stack(R[f"block:{k}"]) for k in range(K)])  # [K, n, H, W, 3]
G = torch.stack(R["global-only"]); T = torch.stack(gts); O = torch.stack(origins)
dist = torch.cdist(O, C)  # [n, K]
def score(imgs): return sum(float(psnr(imgs[i], T[i])) for i in range(n)) / n
print("global-only", round(score(G), 3))
order = dist.argsort(dim=1)
near = B[order[:, 0], torch.arange(n)]
print("nearest", round(score(near), 3))
per_block = torch.tensor([[float(psnr(B[k, i], T[i])) for k in range(K)] for i in range(n)])
print("oracle best block per view", round(float(per_block.max(1).values.mean()), 3))
print("rank of nearest among blocks: mean psnr of r-th nearest", [round(float(per_block.gather(1, order[:, r:r+1]).mean()), 2) for r in range(K)])
for m in [2, 3, 4]:
    avg = torch.stack([B[order[:, r], torch.arange(n)] for r in range(m)]).mean(0)
    print(f"mean of {m} nearest", round(score(avg), 3))
for g in [1, 2, 4, 8, 16]:
    w = dist.clamp_min(1e-6) ** -g; w = w / w.sum(1, keepdim=True)  # [n, K]
    img = torch.einsum("nk,knhwc->nhwc", w, B)
    print(f"idw gamma {g}", round(score(img), 3))
for m in [2, 3]:
    for g in [1, 2, 4]:
        w = torch.zeros_like(dist); idx = order[:, :m]
        w.scatter_(1, idx, dist.gather(1, idx).clamp_min(1e-6) ** -g); w = w / w.sum(1, keepdim=True)
        print(f"idw top{m} gamma {g}", round(score(torch.einsum("nk,knhwc->nhwc", w, B)), 3))
allavg = B.mean(0); print("mean of all blocks", round(score(allavg), 3))
print("mean of nearest + global", round(score((near + G) / 2), 3))
