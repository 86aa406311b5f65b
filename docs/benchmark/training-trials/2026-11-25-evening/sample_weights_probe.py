"""One-off (issue 18): on a trained checkpoint, one training batch: samples per ray that the field evaluates
without gradients (candidates), that it keeps for the pass with gradients, why the others are dropped
(behind the surface or too transparent), and the rendering weights of the kept samples.

    python docs/benchmark/training-trials/2026-11-25-evening/sample_weights_probe.py RUN/config.yml
"""
import sys, torch
from pathlib import Path
from nerfstudio.utils.eval_utils import eval_setup
from scalar_nerfstudio.models import scalar_model as sm
cfg = Path(sys.argv[1])
_, pipeline, _, step = eval_setup(cfg, test_mode="val")
model = pipeline.model
gm = getattr(model, "global_model", model)
gm.train(); gm.occupancy._warming_up = False
print("step", step, "pruning", gm.occupancy.pruning if hasattr(gm.occupancy, "pruning") else None)
ray_bundle, batch = pipeline.datamanager.next_train(step)
rb = gm.collider(ray_bundle)
samples = gm._ray_samples(rb, jitter=True)
deltas = samples.t_ends - samples.t_starts
cand = gm._worth_evaluating(samples.unit_positions, deltas.reshape(-1))
print("rays", deltas.shape, "candidates/ray", float(cand.sum()) / deltas.shape[0])
ids, enc = gm._visible_samples(samples.unit_positions, deltas)
print("kept/ray", ids.numel() / deltas.shape[0])
with torch.no_grad():
    out = gm.get_outputs(rb)
# recompute weights of kept samples
with torch.no_grad():
    density, geo = gm.field.density_at_unit(samples.unit_positions[ids])
    R, S = deltas.shape
    dens = torch.zeros(R * S); dens[ids] = density.float()
    w, _ = sm.render_weights(dens.reshape(R, S), deltas)
    wk = w.reshape(-1)[ids]
for eps in [1e-5, 1e-4, 1e-3, 3e-3, 1e-2]:
    m = wk < eps
    print(f"kept samples with weight < {eps}: {float(m.float().mean()):.3f}, their weight sum per ray {float(wk[m].sum())/R:.5f}")
with torch.no_grad():
    cid = torch.nonzero(cand).squeeze(-1)
    d2, _ = gm.field.density_at_unit(samples.unit_positions[cid])
    dd = torch.zeros(R * S); dd[cid] = d2.float()
    alphas = sm.alphas_from_densities(dd.reshape(R, S), deltas)
    _, trans = sm.weights_from_alphas(alphas)
    Tc = trans.reshape(-1)[cid]; Ac = alphas.reshape(-1)[cid]
    print("candidates behind surface (T<=1e-3):", float((Tc <= 1e-3).float().mean()), " low alpha but visible:", float(((Tc > 1e-3) & (Ac <= 0.01)).float().mean()))
    # position along ray of candidates: fraction in each quarter
    pos = cid % S
    for q in range(4):
        sel = (pos >= q * S // 4) & (pos < (q + 1) * S // 4)
        print(f"quarter {q}: candidates {float(sel.float().mean()):.3f}, behind-surface share {float((Tc[sel] <= 1e-3).float().mean()):.3f}")
