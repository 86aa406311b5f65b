"""``scalar-nerf-eval-fusion``: the paper's Tab. 3 on a trained run: every fusion mode, one table.

For each fusion mode it renders every eval image of the run and reports PSNR, SSIM (LPIPS when its
weights are on disk) and render time in ms per image, as ``fusion.json`` (keys named as the modes)
and ``fusion.md``. It also measures what choosing blocks per ray does: ``global``, ``idw`` and
``surface`` rendered again with every block on every ray, their times and how much the images differ.

    scalar-nerf-eval-fusion --load-config RUN/config.yml --output-dir RUN/fusion_eval
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Literal, Optional, Tuple

import tyro
from nerfstudio.utils.eval_utils import eval_setup

from scalar_nerfstudio.atomic_io import atomic_write_text
from scalar_nerfstudio.fusion import FUSION_MODES, FusionModeError, parse_fusion_mode
from scalar_nerfstudio.fusion_eval import evaluate_fusion_modes, markdown_table
from scalar_nerfstudio.runs import RunError, check_trained_run

PROG = "scalar-nerf-eval-fusion"

__all__ = ["EvalFusionArgs", "entrypoint", "evaluate", "main", "markdown_table"]


@dataclass
class EvalFusionArgs:
    """Evaluate every fusion mode of a scalar-nerf run on its eval images."""

    load_config: Path
    """config.yml of a trained scalar-nerf run."""
    output_dir: Path = Path("fusion_eval")
    """Where fusion.json and fusion.md are written."""
    modes: Tuple[str, ...] = FUSION_MODES
    """Fusion modes to evaluate (global, surface, idw, nearest, nearest-guarded, nearest-idw, global-only, block:K)."""
    measure_selection: bool = True
    """Also render global, surface and idw with every block on every ray and compare."""
    blocks_per_ray: Optional[int] = None
    """Render with this many blocks per ray instead of the run's (0: every block)."""
    selection_depth: Optional[Literal["field", "grid"]] = None
    """Choose the blocks per ray from this depth instead of the run's (field or grid)."""
    max_images: Optional[int] = None
    """Evaluate only the first this many eval images (evenly spread), for a quick table."""


def _print_row(mode: str, row: Dict[str, float]) -> None:
    print(f"{mode:>12}: " + ", ".join(f"{k} {v:.4g}" for k, v in row.items()), flush=True)


def check_arguments(args: EvalFusionArgs) -> None:
    """Refuse bad options and a run that cannot be evaluated, in one line before anything is loaded
    or written (SystemExit, exit status 1)."""
    for mode in args.modes:
        try:
            parse_fusion_mode(mode)
        except FusionModeError as error:
            raise SystemExit(f"{PROG}: --modes: {error}") from None
    if not args.modes:
        raise SystemExit(f"{PROG}: --modes: give at least one fusion mode")
    if args.blocks_per_ray is not None and args.blocks_per_ray < 0:
        raise SystemExit(f"{PROG}: --blocks-per-ray {args.blocks_per_ray}: must be >= 0 (0: every block)")
    if args.max_images is not None and args.max_images < 1:
        raise SystemExit(f"{PROG}: --max-images {args.max_images}: must be >= 1")
    if args.output_dir.exists() and not args.output_dir.is_dir():
        raise SystemExit(f"{PROG}: --output-dir {args.output_dir} is a file, not a folder")
    try:
        check_trained_run(args.load_config, scalar_only=True)
    except RunError as error:
        raise SystemExit(f"{PROG}: {error}") from None


def evaluate(args: EvalFusionArgs) -> Dict[str, Dict[str, float]]:
    """Run the table; returns ``{mode: {"psnr", "ssim", ["lpips"], "ms_per_image", ...}}``."""
    check_arguments(args)
    from scalar_nerfstudio.pipeline import ScalarPipeline  # here: loading the run imports it anyway

    _, pipeline, _, _ = eval_setup(args.load_config, test_mode="test")
    if not isinstance(pipeline, ScalarPipeline):
        raise SystemExit(f"{PROG}: {args.load_config}: its pipeline is a {type(pipeline).__name__}, not scalar-nerf's")
    if args.blocks_per_ray is not None:
        pipeline.model.config.blocks_per_ray = args.blocks_per_ray
    if args.selection_depth is not None:
        pipeline.model.config.selection_depth = args.selection_depth
    return evaluate_fusion_modes(pipeline, args.modes, measure_selection=args.measure_selection, on_mode=_print_row,
                                 max_images=args.max_images)


def main(args: EvalFusionArgs) -> None:
    table = evaluate(args)
    args.output_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.output_dir / "fusion.json", json.dumps(table, indent=2))
    atomic_write_text(args.output_dir / "fusion.md", markdown_table(table))
    print(markdown_table(table))
    print(f"written: {args.output_dir / 'fusion.json'}, {args.output_dir / 'fusion.md'}")


def entrypoint() -> None:
    """Console script ``scalar-nerf-eval-fusion``."""
    main(tyro.cli(EvalFusionArgs))


if __name__ == "__main__":
    entrypoint()
