"""Memory, checkpoint size and render time of ``ns-train scalar-nerf`` against the number of blocks K.

    python benchmarks/bench_scale.py [--blocks 4 16 64] [--images 640] [--block-log2 19] [--out FILE.json]

On one generated town (``scalar-nerf-make-scene``'s, ``--images`` views of ``--size`` pixels), each K
trains a run with tables of the same size for every block (``--block-log2``, equal block size) and
tiny steps (``--global-steps``, ``--block-steps``), through every phase, as a user runs it. Printed per K:

* peak RSS of the training process (a fresh process per K: ``getrusage`` of its children);
* bytes of the newest checkpoint, of the largest block file and of all block files together;
* per-view render time of held-out views with the default fusion (first render, blocks loaded from
  their files as needed; and the same view again) and with ``global-only`` (one model), the ratios,
  the blocks a view uses, and peak RSS of the rendering process (a fresh one per K).

Run nothing else meanwhile: the times are wall-clock on the shared cores.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List


def run_measured(command: List[str]) -> Dict[str, Any]:
    """Run ``command`` in a child: its output (stdout and stderr), its own peak RSS (``wait4``: not the largest of
    every child so far) and seconds. A child that fails ends this script with its output's tail."""
    start = time.perf_counter()
    with tempfile.TemporaryFile("w+") as log:
        child = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, text=True)
        _, status, usage = os.wait4(child.pid, 0)
        child.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait for it again
        log.seek(0)
        output = log.read()
    if child.returncode != 0:
        raise SystemExit(f"{' '.join(command[:6])} ... failed:\n{output[-6000:]}")
    return {"output": output, "peak_rss_mib": round(usage.ru_maxrss / 1024), "seconds": round(time.perf_counter() - start, 1)}


def train_command(scene: Path, output: Path, args: argparse.Namespace, num_blocks: int) -> List[str]:
    return [
        sys.executable, "-m", "nerfstudio.scripts.train", "scalar-nerf",
        "--data", str(scene), "--output-dir", str(output), "--vis", "tensorboard",
        "--logging.local-writer.enable", "False", "--steps-per-save", "100000",
        "--steps-per-eval-image", "100000", "--steps-per-eval-batch", "100000", "--steps-per-eval-all-images", "100000",
        "--steps-per-preview", "0",
        "--pipeline.num-blocks", str(num_blocks),
        "--pipeline.global-steps", str(args.global_steps), "--pipeline.block-steps", str(args.block_steps),
        "--pipeline.block-log2-hashmap-size", str(args.block_log2), "--pipeline.block-max-resolution", str(args.block_max_resolution),
        "--pipeline.model.field.log2-hashmap-size", str(args.global_log2),
        "--pipeline.datamanager.train-num-rays-per-batch", str(args.rays),
        "nerfstudio-data", "--eval-mode", "interval", "--eval-interval", "8",
    ]


def render_views(config: Path, num_views: int) -> Dict[str, Any]:
    """In this process: load the run and time ``num_views`` held-out views, default fusion and global-only."""
    import torch
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    model = pipeline.model
    cameras = pipeline.datamanager.eval_dataset.cameras
    fusion = str(model.fusion_mode)
    times: Dict[str, List[float]] = {fusion: [], "global-only": [], "again": []}
    blocks_per_view: List[int] = []
    with torch.no_grad():
        for mode in (fusion, "global-only"):
            model.set_fusion(mode)
            for index in range(min(num_views, len(cameras)) + 1):  # the first view warms up (not timed)
                camera = cameras[index % len(cameras):index % len(cameras) + 1]
                start = time.perf_counter()
                model.get_outputs_for_camera(camera)
                if index > 0:
                    times[mode].append(time.perf_counter() - start)
                if mode == fusion and index > 0:
                    blocks_per_view.append(len([b for b in model.rendered_models if b != "global"]))
                    start = time.perf_counter()  # the same view again: its blocks are loaded if they fit
                    model.get_outputs_for_camera(camera)
                    times["again"].append(time.perf_counter() - start)
    fused_ms, global_ms, again_ms = (1000 * statistics.median(times[m]) for m in (fusion, "global-only", "again"))
    return {
        "fusion": fusion, "render_ms": round(fused_ms, 1), "render_again_ms": round(again_ms, 1),
        "global_only_ms": round(global_ms, 1), "render_ratio": round(fused_ms / global_ms, 2),
        "render_again_ratio": round(again_ms / global_ms, 2), "blocks_per_view": statistics.median(blocks_per_view),
        "max_resident_blocks": model.config.max_resident_blocks,
        "render_peak_rss_mib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
    }


def measure(scene: Path, work: Path, args: argparse.Namespace, num_blocks: int) -> Dict[str, Any]:
    output = work / f"K{num_blocks}"
    trained = run_measured(train_command(scene, output, args, num_blocks))
    (run,) = sorted(p.parent for p in output.glob("*/scalar-nerf/*/config.yml"))
    checkpoint = max((run / "nerfstudio_models").glob("step-*.ckpt"))
    block_files = sorted((run / "block_models").glob("block-*.ckpt"))
    render = subprocess.run([sys.executable, __file__, "--render", str(run / "config.yml"), "--views", str(args.views)],
                            capture_output=True, text=True, check=False)
    if render.returncode != 0:
        raise SystemExit(render.stdout[-3000:] + render.stderr[-3000:])
    return {
        "blocks": num_blocks, "train_peak_rss_mib": trained["peak_rss_mib"], "train_s": trained["seconds"],
        "checkpoint_mib": round(checkpoint.stat().st_size / 2**20, 1),
        "largest_block_file_mib": round(max((f.stat().st_size for f in block_files), default=0) / 2**20, 1),
        "block_files": len(block_files), "block_files_mib": round(sum(f.stat().st_size for f in block_files) / 2**20, 1),
        **json.loads(render.stdout.strip().splitlines()[-1]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--blocks", type=int, nargs="+", default=[4, 16, 64])
    parser.add_argument("--images", type=int, default=640, help="views of the generated town (every 8th held out)")
    parser.add_argument("--size", type=int, nargs=2, default=[64, 48], metavar=("W", "H"))
    parser.add_argument("--block-log2", type=int, default=19, help="log2 table rows of every block (equal block size)")
    parser.add_argument("--block-max-resolution", type=int, default=2048)
    parser.add_argument("--global-log2", type=int, default=19)
    parser.add_argument("--global-steps", type=int, default=60)
    parser.add_argument("--block-steps", type=int, default=2)
    parser.add_argument("--rays", type=int, default=1024)
    parser.add_argument("--views", type=int, default=4, help="held-out views timed per K")
    parser.add_argument("--out", type=Path, default=None, help="write the rows as JSON here")
    parser.add_argument("--render", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.render:
        print(json.dumps(render_views(args.render, args.views)))
        return

    from scalar_nerfstudio.scenes.town import TownConfig, write_town

    work = Path(tempfile.mkdtemp(prefix="bench-scale-"))
    scene = work / "town"
    # The walk capture, as when docs/benchmark/scale/bench_scale.json was measured (generator version 1); memory and
    # checkpoint sizes do not depend on where the cameras look.
    write_town(scene, TownConfig(num_images=args.images, width=args.size[0], height=args.size[1], capture="walk"), progress=False)
    header = (f"{'K':>3} {'train RSS MiB':>13} {'train s':>7} {'ckpt MiB':>8} {'block file MiB':>14} {'files MiB':>9} "
              f"{'render ms':>9} {'again ms':>8} {'1 model ms':>10} {'ratio':>5} {'again':>5} {'blocks/view':>11} {'render RSS MiB':>14}")
    print(f"town: {args.images} views of {args.size[0]}x{args.size[1]}, block tables 2^{args.block_log2}, "
          f"{args.global_steps} global + K x {args.block_steps} block steps, {args.rays} rays; work folder {work}")
    print(header)
    rows = []
    for num_blocks in args.blocks:
        row = measure(scene, work, args, num_blocks)
        rows.append(row)
        print(f"{row['blocks']:>3} {row['train_peak_rss_mib']:>13} {row['train_s']:>7} {row['checkpoint_mib']:>8} "
              f"{row['largest_block_file_mib']:>14} {row['block_files_mib']:>9} {row['render_ms']:>9} {row['render_again_ms']:>8} "
              f"{row['global_only_ms']:>10} {row['render_ratio']:>5} {row['render_again_ratio']:>5} {row['blocks_per_view']:>11} "
              f"{row['render_peak_rss_mib']:>14}", flush=True)
    first, last = rows[0], rows[-1]
    print(f"K {first['blocks']} -> {last['blocks']}: train peak RSS x{last['train_peak_rss_mib'] / first['train_peak_rss_mib']:.2f}, "
          f"checkpoint x{last['checkpoint_mib'] / first['checkpoint_mib']:.2f}, render time x{last['render_ms'] / first['render_ms']:.2f}")
    if args.out:
        args.out.write_text(json.dumps({"settings": {k: v for k, v in vars(args).items() if k not in ("out", "render")}, "rows": rows},
                                       indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
