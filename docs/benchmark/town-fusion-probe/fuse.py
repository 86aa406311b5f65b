import sys, torch
from scalar_nerfstudio.metrics import psnr as project_psnr
r = torch.load(sys.argv[1])
C = r["centres"]; n = len(r["gt"])
def psnr(a, b): return float(project_psnr(a.clamp(0, 1), b))
res = {}
def add(name, f):
    res[name] = sum(psnr(f(i), r["gt"][i]) for i in range(n)) / n
distances = [torch.linalg.vector_norm(C - r["origin"][i], dim=-1) for i in range(n)]  # [K] per view
orders = [torch.argsort(d) for d in distances]
def dist(i): return distances[i]
def order(i): return orders[i]
add("global-only", lambda i: r["global"][i])
add("nearest", lambda i: r["blocks"][i][order(i)[0]])
for m in (2, 3, 4, 8):
    add(f"mean of {m} nearest", lambda i, m=m: r["blocks"][i][order(i)[:m]].mean(0))
for g in (1, 2, 4, 8):
    def f(i, g=g):
        w = dist(i) ** -g; w = w / w.sum(); return (w[:, None, None, None] * r["blocks"][i]).sum(0)
    add(f"idw gamma {g} all", f)
for m in (2, 3):
    for g in (1, 2, 4):
        def f(i, g=g, m=m):
            o = order(i)[:m]; w = dist(i)[o] ** -g; w = w / w.sum(); return (w[:, None, None, None] * r["blocks"][i][o]).sum(0)
        add(f"idw gamma {g} over {m} nearest", f)
add("(nearest + global)/2", lambda i: 0.5 * (r["blocks"][i][order(i)[0]] + r["global"][i]))
add("median of all blocks", lambda i: r["blocks"][i].median(0).values)
# per image, each block's PSNR: the oracle (best block per image) and that block's rank by distance
block_psnr = [torch.tensor([psnr(r["blocks"][i][k], r["gt"][i]) for k in range(len(C))]) for i in range(n)]
res["oracle best block per image"] = sum(float(p.max()) for p in block_psnr) / n
ranks = [int((order(i) == int(block_psnr[i].argmax())).nonzero()) for i in range(n)]
print("rank (by distance) of the best block per image:", ranks)
for k, v in sorted(res.items(), key=lambda kv: -kv[1]): print(f"{v:7.3f}  {k}")
