"""``scalar-nerf-assemble``: one renderable run from a global run and blocks trained on their own.

Blocks trained with ``ns-train scalar-nerf-block --global-run G --block k`` live in folders of their
own. This command writes a *new* run folder (method ``scalar-nerf``) whose checkpoint holds G's
global model and blocks and, for each given block run, that run's block k. ``ns-eval``,
``ns-viewer``, ``ns-render`` and ``scalar-nerf-render`` then work on it as on any scalar-nerf run.
Neither G nor the block runs are modified.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple

import tyro

from scalar_nerfstudio.assembly import AssembleError, assemble
from scalar_nerfstudio.runs import run_config_path

__all__ = ["AssembleArgs", "AssembleError", "assemble", "entrypoint", "main"]


@dataclass
class AssembleArgs:
    """Combine a scalar-nerf run and scalar-nerf-block runs into one run that renders with fusion."""

    global_run: Path
    """The scalar-nerf run the blocks were trained from (folder or config.yml)."""
    block_runs: Tuple[Path, ...]
    """scalar-nerf-block run folders (one per block; blocks not given keep the global run's)."""
    output_dir: Optional[Path] = None
    """Root of the new run (default: the global run's output root)."""


def main(args: AssembleArgs) -> None:
    try:
        run_dir = assemble(args.global_run, list(args.block_runs), args.output_dir)
    except AssembleError as error:
        raise SystemExit(f"scalar-nerf-assemble: {error}") from None
    print(f"assembled run: {run_dir}\n  ns-eval --load-config {run_config_path(run_dir)} --output-path eval.json")


def entrypoint() -> None:
    """Console script ``scalar-nerf-assemble``."""
    main(tyro.cli(AssembleArgs))


if __name__ == "__main__":
    entrypoint()
