"""PSNR on training views against held-out views, for one or more trained runs.

A model whose held-out PSNR stalls while its training-view PSNR keeps rising is limited by how well
the views constrain the scene, not by its capacity; one whose training views are no better than its
held-out ones is short of capacity (or of steps). Issue 16 asks whether a scene is "too large for
one hash table"; this tells the two apart for a trained NGP_T, NGP_{T+2} or SCALAR-NeRF run.

Each run renders every ``--every``-th training image and every held-out image through the same
path (``get_outputs_for_camera``, the run's fusion), on the CPU, one process, and prints one row
per run: mean PSNR on each, and the difference.

    python benchmarks/train_vs_heldout.py --load-config RUN_A/config.yml RUN_B/config.yml --every 10
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Dict, List


def view_psnrs(pipeline, dataset, indices: List[int]) -> List[float]:
    """PSNR in dB of each view ``indices`` of ``dataset`` rendered by the pipeline's model (eval mode)."""
    import torch

    from scalar_nerfstudio.metrics import psnr

    model = pipeline.model
    model.eval()
    scores = []
    with torch.no_grad():
        for index in indices:
            camera = dataset.cameras[index : index + 1].to(pipeline.device)
            rendered = model.get_outputs_for_camera(camera)["rgb"].float().cpu().clamp(0, 1)  # [H, W, 3]
            truth = dataset[index]["image"].float()[..., :3]  # [H, W, 3]
            if truth.shape != rendered.shape:
                raise SystemExit(f"view {index}: rendered {tuple(rendered.shape)} but the image is {tuple(truth.shape)}")
            scores.append(float(psnr(rendered, truth)))
    return scores


def measure(config: Path, every: int) -> Dict[str, float]:
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    datamanager = pipeline.datamanager
    train, held_out = datamanager.train_dataset, datamanager.eval_dataset
    train_indices = list(range(0, len(train), every))
    train_scores = view_psnrs(pipeline, train, train_indices)
    held_out_scores = view_psnrs(pipeline, held_out, list(range(len(held_out))))
    mean_train, mean_held_out = sum(train_scores) / len(train_scores), sum(held_out_scores) / len(held_out_scores)
    return {"train_psnr": mean_train, "train_views": len(train_scores), "held_out_psnr": mean_held_out,
            "held_out_views": len(held_out_scores), "gap_db": mean_train - mean_held_out}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--load-config", type=Path, nargs="+", required=True, help="config.yml of each trained run")
    parser.add_argument("--every", type=int, default=10, help="render every this many training images")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args()
    if args.every < 1:
        raise SystemExit(f"--every {args.every}: must be >= 1")
    missing = [str(c) for c in args.load_config if not c.is_file()]
    if missing:
        raise SystemExit(f"no such config.yml: {', '.join(missing)}")
    rows = {}
    for config in args.load_config:
        rows[str(config)] = row = measure(config, args.every)
        print(f"{config}: training views {row['train_psnr']:.2f} dB ({row['train_views']}), held out "
              f"{row['held_out_psnr']:.2f} dB ({row['held_out_views']}), gap {row['gap_db']:+.2f} dB", flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
