"""Render time of a trained run's held-out views (issue 18: a 192x128 view of a global model in <= 0.3 s).

Loads ``RUN/config.yml`` as ``ns-eval`` does, renders every eval view once to warm up (kernel builds,
the allocator's first growth), then renders them ``--rounds`` more times per fusion mode and prints
the median and fastest time per view (and the median per pixel), and the held-out PSNR of the last round. Each mode is timed
in alternating rounds, so a slow moment of the machine does not fall on one mode only.

    python benchmarks/bench_render.py --load-config outputs/bench_training/runs/castle-P30/scalar-nerf/<ts>/config.yml
    python benchmarks/bench_render.py --load-config RUN/config.yml --fusion nearest global-only --json out.json
    python benchmarks/bench_render.py --load-config RUN/config.yml --model-setting grid_alpha_skip=False grid_alpha_skip=True
    python benchmarks/bench_render.py --load-config RUN/config.yml --size 800x600 --model-setting eval_num_rays_per_chunk=16384 eval_num_rays_per_chunk=262144

``--model-setting NAME=VALUE ...`` times each setting of the models' config (the run's model, the global
model's and every block in memory) as a variant of its own, in the same alternating rounds.

The cameras are moved to the model's device before rendering, as nerfstudio's viewer does, and on
CUDA each time ends after ``torch.cuda.synchronize()``. ``--size WxH`` renders the eval views' poses at
that size instead (the same horizontal field of view, centred principal point); no PSNR is printed then.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Dict, List, Tuple


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--load-config", type=Path, required=True, help="RUN/config.yml of a trained scalar-nerf run")
    parser.add_argument("--fusion", nargs="+", default=["global-only"], help="fusion modes to time (a run with K = 1 has global-only)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--model-setting", nargs="+", default=[], metavar="NAME=VALUE",
                        help="model config settings to compare, each a variant (e.g. grid_alpha_skip=False grid_alpha_skip=True)")
    parser.add_argument("--size", type=parse_size, default=None, metavar="WxH", help="render the eval poses at this size (e.g. 800x600)")
    args = parser.parse_args()

    import torch
    from nerfstudio.utils.eval_utils import eval_setup

    from scalar_nerfstudio.metrics import psnr

    _, pipeline, _, _ = eval_setup(args.load_config, test_mode="test")
    model = pipeline.model
    dataset = pipeline.datamanager.eval_dataset
    cameras = dataset.cameras if args.size is None else _resized(dataset.cameras, *args.size)
    cameras = cameras.to(model.device)
    targets = [dataset[i]["image"][..., :3] for i in range(len(cameras))] if args.size is None else None
    synchronize = torch.cuda.synchronize if model.device.type == "cuda" else (lambda: None)
    settings = [_parse_setting(text) for text in args.model_setting] or [None]
    variants = [(mode, setting) for mode in args.fusion for setting in settings]
    times: Dict[Tuple[str, object], List[float]] = {variant: [] for variant in variants}
    scores: Dict[Tuple[str, object], List[float]] = {}
    with torch.no_grad():
        for round_index in range(args.rounds + 1):  # round 0 warms up and is not counted
            for variant in variants:
                mode, setting = variant
                model.set_fusion(mode)
                _apply_setting(model, setting)
                scores[variant] = []
                for index in range(len(cameras)):
                    synchronize()
                    start = time.perf_counter()
                    outputs = model.get_outputs_for_camera(cameras[index : index + 1])
                    synchronize()
                    if round_index > 0:
                        times[variant].append(time.perf_counter() - start)
                    if targets is not None:
                        scores[variant].append(float(psnr(outputs["rgb"].clamp(0.0, 1.0), targets[index].to(outputs["rgb"]))))
    height, width = int(cameras.height[0]), int(cameras.width[0])
    results = []
    device = torch.cuda.get_device_name() if model.device.type == "cuda" else f"cpu, {torch.get_num_threads()} threads"
    print(f"{args.load_config}: {len(cameras)} eval views of {width}x{height}, {device}, {args.rounds} rounds")
    for variant in variants:
        mode, setting = variant
        setting_text = None if setting is None else f"{setting[0]}={setting[1]}"
        label = mode if setting_text is None else f"{mode} {setting_text}"
        row = {"fusion": mode, "setting": setting_text,
               "median_ms": 1000 * statistics.median(times[variant]), "min_ms": 1000 * min(times[variant]),
               "median_us_per_pixel": 1e6 * statistics.median(times[variant]) / (width * height),
               "psnr": sum(scores[variant]) / len(scores[variant]) if scores[variant] else None,
               "views": len(cameras), "width": width, "height": height}
        results.append(row)
        score = f", held-out PSNR {row['psnr']:.2f} dB" if row["psnr"] is not None else ""
        print(f"{label:<12} median {row['median_ms']:.1f} ms / view ({row['median_us_per_pixel']:.2f} us / pixel), "
              f"fastest {row['min_ms']:.1f} ms{score}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"config": str(args.load_config), "device": device, "rounds": args.rounds, "results": results}, indent=2))


def parse_size(text: str) -> Tuple[int, int]:
    """"800x600" -> (800, 600)."""
    width, separator, height = text.lower().partition("x")
    if not separator or not width.isdigit() or not height.isdigit() or int(width) < 1 or int(height) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected WIDTHxHEIGHT, e.g. 800x600")
    return int(width), int(height)


def _resized(cameras, width: int, height: int):
    """``cameras`` (pinhole) at ``width`` x ``height``: the same poses and horizontal field of view, the
    principal point at the centre."""
    from nerfstudio.cameras.cameras import Cameras

    scale = width / cameras.width.float()
    return Cameras(camera_to_worlds=cameras.camera_to_worlds, fx=cameras.fx * scale, fy=cameras.fy * scale,
                   cx=width / 2.0, cy=height / 2.0, width=width, height=height, camera_type=cameras.camera_type)


def _parse_setting(text: str) -> Tuple[str, object]:
    """"NAME=VALUE" -> (NAME, VALUE as a Python literal, or the string itself)."""
    import ast

    name, separator, value = text.partition("=")
    if not separator or not name:
        raise SystemExit(f"--model-setting {text!r}: expected NAME=VALUE")
    try:
        return name, ast.literal_eval(value)
    except (ValueError, SyntaxError):
        return name, value


def _apply_setting(model, setting) -> None:
    """Set ``setting`` (NAME, VALUE) on the config of every ScalarModel inside ``model``."""
    from scalar_nerfstudio.models.scalar_model import ScalarModel

    if setting is None:
        return
    name, value = setting
    models = [model] + [module for module in model.modules() if isinstance(module, ScalarModel) and module is not model]
    for each in models:
        if not hasattr(each.config, name):
            raise SystemExit(f"--model-setting: the model config has no {name!r}")
        setattr(each.config, name, value)


if __name__ == "__main__":
    main()
