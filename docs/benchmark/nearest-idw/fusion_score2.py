"""One-off probe (issue 16): the two nearest blocks blended only where their colours agree within tau
(nearest elsewhere), on fusion_probe.py's renders.

    python docs/benchmark/nearest-idw/fusion_score2.py renders.pt
"""
import sys, torch
from scalar_nerfstudio.metrics import psnr
d = torch.load(sys.argv[1]); gts, origins, R, C = d["gts"], d["origins"], d["renders"], d["centres"]
K = C.shape[0]; n = len(gts)
B = torch.stack([torch.stack(R[f"block:{k}"]) for k in range(K)]); T = torch.stack(gts); O = torch.stack(origins)
dist = torch.cdist(O, C); order = dist.argsort(1); ar = torch.arange(n)
def score(imgs): return sum(float(psnr(imgs[i], T[i])) for i in range(n)) / n
c1, c2 = B[order[:, 0], ar], B[order[:, 1], ar]
d1, d2 = dist.gather(1, order[:, :1]), dist.gather(1, order[:, 1:2])
for g in [2, 4]:
    w1 = d1 ** -g / (d1 ** -g + d2 ** -g); w1 = w1[:, :, None, None]
    blend = w1 * c1 + (1 - w1) * c2
    line = [f"gamma {g} blend {score(blend):.3f}"]
    for tau in [0.03, 0.05, 0.1, 0.2]:
        agree = ((c1 - c2).norm(dim=-1, keepdim=True) < tau)
        line.append(f"tau {tau}: {score(torch.where(agree, blend, c1)):.3f}")
    print(" | ".join(line))
print("dist ratio d2/d1 per view:", [round(float(x), 2) for x in (d2 / d1).flatten()][:40])
