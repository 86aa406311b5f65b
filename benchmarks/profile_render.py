"""Where one camera render's time goes, and the render's speed levers side by side with an earlier commit's code.

Loads ``RUN/config.yml`` as ``ns-eval`` does and renders one eval view (``--view``, at its own size or
``--size WxH``) for every variant, in alternating rounds after a warm-up render, so that a slow moment of
the machine does not fall on one variant only. Per variant it prints the median time, microseconds per
pixel, the sample funnel per pixel (bins -> grid candidates -> density evaluations -> kept) and the largest
8-bit difference from the first variant's image. A variant is

- ``--group G``: the candidates per ray of one front-to-back round (``visibility.RENDER_GROUP``);
- ``--decoder fused|onednn``: the float32 decoder without autograd through the AVX2 tile kernels or
  through oneDNN layer by layer (the decoder's ``float32_cpu_inference``; bfloat16 decoders ignore it);
- ``--chunk N``: rays per chunk;
- ``--march kernels|torch``: the rounds' bookkeeping and the volume rendering through the C++ march kernels
  (``csrc/march.cpp``) or through the torch code they replaced (the code before them, in the same run);
- ``--baseline-ref REF`` adds ``baseline``: the visibility pass of the commit REF (read with ``git show``)
  with the oneDNN decoder: the code before the cuts, timed in the same run.

    python benchmarks/profile_render.py --load-config RUN/config.yml --baseline-ref a7fb8f9 --group 4 --decoder fused onednn
    python benchmarks/profile_render.py --load-config RUN/config.yml --march torch kernels --rounds 5
    python benchmarks/profile_render.py --load-config RUN/config.yml --size 2000x1500 --rounds 1 --profile
"""

from __future__ import annotations

import argparse
import collections
import itertools
import json
import statistics
import subprocess
import sys
import time
import types
from pathlib import Path
from typing import Any, Dict, List

import torch

STATS: collections.Counter = collections.Counter()
VISIBILITY_PATH = "scalar_nerfstudio/model_components/visibility.py"


def install_probes() -> None:
    """Class-level wrappers that count the funnel and label the stages for torch.profiler."""
    from scalar_nerfstudio.fields.scalar_field import ScalarField
    from scalar_nerfstudio.model_components.visibility import VisibilitySampler

    def wrap(owner, name, label, count=None):
        original = getattr(owner, name)

        def wrapper(*args, **kwargs):
            with torch.profiler.record_function(label):
                result = original(*args, **kwargs)
            if count is not None:
                count(args, result)
            return result

        setattr(owner, name, wrapper)

    from scalar_nerfstudio.models import scalar_model
    from scalar_nerfstudio.models.fused_render import FusedRenderer

    wrap(VisibilitySampler, "worth_evaluating", "grid test", lambda a, r: STATS.update(candidates=int(r.sum())))
    wrap(VisibilitySampler, "visible_with_features", "visibility (rounds, with the density)")
    wrap(scalar_model.ScalarModel, "_ray_samples", "sampling")
    wrap(scalar_model.ScalarModel, "render_rays", "one model's render")
    wrap(scalar_model, "render_kept_samples", "volume rendering")  # a module global used by get_outputs
    wrap(FusedRenderer, "render", "fused render (all models, fusion)")
    wrap(FusedRenderer, "select_rays", "block selection")
    wrap(FusedRenderer, "_guard_transparent_blocks", "guard (the global model's rays)")
    wrap(ScalarField, "density_at_unit", "field.density", lambda a, r: STATS.update(density_evals=a[1].shape[0]))
    wrap(ScalarField, "colour", "field.colour", lambda a, r: STATS.update(colour_evals=a[1].shape[0]))


def baseline_visibility(ref: str):
    """``VisibilitySampler.visible_with_features`` of commit ``ref`` (its module executed apart, with its own constants)."""
    repo = Path(__file__).resolve().parents[1]
    source = subprocess.run(["git", "-C", str(repo), "show", f"{ref}:{VISIBILITY_PATH}"], capture_output=True, text=True, check=True).stdout
    module = types.ModuleType(f"visibility_at_{ref}")
    sys.modules[module.__name__] = module  # its dataclasses look their module up
    exec(compile(source, f"{ref}:{VISIBILITY_PATH}", "exec"), module.__dict__)  # noqa: S102 (the project's own history)
    return module.VisibilitySampler.visible_with_features


def to_8bit(rgb: torch.Tensor) -> torch.Tensor:
    return (rgb.float().clamp(0.0, 1.0) * 255.0).round().to(torch.int16)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--load-config", type=Path, required=True)
    parser.add_argument("--fusion", default=None, help="fusion mode (default: the run's; global-only for a run of one model)")
    parser.add_argument("--size", default=None, help="WxH (default: the eval view's own size)")
    parser.add_argument("--view", type=int, default=0, help="index into the eval views")
    parser.add_argument("--group", type=int, nargs="+", default=[4], help="candidates per ray per round")
    parser.add_argument("--decoder", nargs="+", choices=["fused", "onednn"], default=["fused"])
    parser.add_argument("--chunk", type=int, nargs="+", default=[None], help="rays per chunk (default: the run's)")
    parser.add_argument("--march", nargs="+", choices=["kernels", "torch"], default=["kernels"],
                        help="the render march through the C++ kernels or the torch code (the first listed is the reference image)")
    parser.add_argument("--baseline-ref", default=None, help="add the variant of this commit's visibility pass with the oneDNN decoder")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--profile", action="store_true", help="torch.profiler table of one render of the first variant")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    from bench_render import _resized  # same directory
    from nerfstudio.utils.eval_utils import eval_setup

    from scalar_nerfstudio.encodings import _cpp
    from scalar_nerfstudio.fields.scalar_field import Decoder
    from scalar_nerfstudio.model_components import visibility

    _, pipeline, _, _ = eval_setup(args.load_config, test_mode="test")
    model = pipeline.model
    if args.fusion is not None:
        model.set_fusion(args.fusion)
    cameras = pipeline.datamanager.eval_dataset.cameras
    if args.size:
        cameras = _resized(cameras, *(int(v) for v in args.size.lower().split("x")))
    camera = cameras[args.view : args.view + 1].to(model.device)
    pixels = int(camera.height[0]) * int(camera.width[0])
    current = visibility.VisibilitySampler.visible_with_features
    install_probes()
    chunk_default = model.config.eval_num_rays_per_chunk

    variants: List[Dict[str, Any]] = []
    if args.baseline_ref:
        variants.append({"name": f"baseline {args.baseline_ref}", "pass": baseline_visibility(args.baseline_ref), "group": None,
                         "decoder": "onednn", "chunk": args.chunk[0], "march": "torch"})
    for march, group, decoder, chunk in itertools.product(args.march, args.group, args.decoder, args.chunk):
        variants.append({"name": f"march {march} group {group} decoder {decoder} chunk {chunk or chunk_default}", "pass": current,
                         "group": group, "decoder": decoder, "chunk": chunk, "march": march})
    march_ops = _cpp.march_ops

    def render(variant: Dict[str, Any]) -> torch.Tensor:
        visibility.VisibilitySampler.visible_with_features = variant["pass"]
        _cpp.march_ops = march_ops if variant["march"] == "kernels" else (lambda: None)
        if variant["group"] is not None:
            visibility.RENDER_GROUP = variant["group"]
        for module in model.modules():
            if isinstance(module, Decoder):
                module.float32_cpu_inference = variant["decoder"] == "fused" and module.float32_cpu_training
        model.config.eval_num_rays_per_chunk = variant["chunk"] or chunk_default
        return model.get_outputs_for_camera(camera)["rgb"]

    times: Dict[str, List[float]] = {v["name"]: [] for v in variants}
    funnels: Dict[str, Dict[str, int]] = {}
    images: Dict[str, torch.Tensor] = {}
    with torch.no_grad():
        render(variants[0])  # warm-up: kernel builds, the allocator's growth
        for _ in range(args.rounds):
            for variant in variants:
                STATS.clear()
                start = time.perf_counter()
                images[variant["name"]] = render(variant)
                times[variant["name"]].append(time.perf_counter() - start)
                funnels[variant["name"]] = dict(STATS)
    first = images[variants[0]["name"]]
    print(f"{args.load_config}: view {args.view}, {camera.width.item()} x {camera.height.item()} ({pixels} px), "
          f"fusion {model.fusion_mode}, {torch.get_num_threads()} threads")
    rows = []
    for variant in variants:
        name = variant["name"]
        median = statistics.median(times[name])
        per_px = {k: v / pixels for k, v in funnels[name].items()}
        diff = int((to_8bit(images[name]) - to_8bit(first)).abs().max())
        rows.append({"variant": name, "median_s": median, "us_per_px": 1e6 * median / pixels, "per_px": per_px, "max_8bit_diff": diff})
        print(f"{name:<55} {median:7.3f} s {1e6 * median / pixels:7.2f} us/px ({median / statistics.median(times[variants[0]['name']]):.2f}x the first); "
              f"per px: candidates {per_px.get('candidates', 0):.2f}, density evals {per_px.get('density_evals', 0):.2f}, "
              f"colour {per_px.get('colour_evals', 0):.2f}; max 8-bit diff vs the first {diff}")
    if args.json is not None:
        args.json.write_text(json.dumps({"config": str(args.load_config), "pixels": pixels, "rows": rows}, indent=1))
    if args.profile:
        with torch.no_grad(), torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as profile:
            render(variants[0])
        averages = profile.key_averages()
        print(averages.table(sort_by="self_cpu_time_total", row_limit=25))
        for event in sorted((e for e in averages if not e.key.startswith(("aten::", "scalar_nerf", "mkldnn"))), key=lambda e: -e.cpu_time_total):
            print(f"{event.key:<40} {event.count:>6} calls {event.cpu_time_total / 1e3:>10.1f} ms (with what it calls)")


if __name__ == "__main__":
    main()
