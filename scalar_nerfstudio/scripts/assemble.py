"""``scalar-nerf-assemble``: one renderable run from a global run and blocks trained on their own.

Blocks trained with ``ns-train scalar-nerf-block --global-run G --block k`` live in folders of their
own. This command writes a *new* run folder (method ``scalar-nerf``) whose checkpoint holds G's
global model and blocks and, for each given block run, that run's block k. ``ns-eval``,
``ns-viewer``, ``ns-render`` and ``scalar-nerf-render`` then work on it as on any scalar-nerf run.
Neither G nor the block runs are modified.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import torch
import tyro

from scalar_nerfstudio.atomic_io import atomic_write_text
from scalar_nerfstudio.blocks.split import BlockSplitError, load_blocks_json
from scalar_nerfstudio.runs import (
    ASSEMBLED_FROM_NAME,
    BLOCKS_JSON_NAME,
    RunError,
    atomic_torch_save,
    blocks_json_path,
    checkpoint_name,
    latest_checkpoint,
    load_run_config,
    run_config_path,
    save_run_config,
)

MODEL_PREFIX = "_model."


class AssembleError(RuntimeError):
    """The runs cannot be combined (named in the message)."""


def load_run(run: Path) -> Tuple[Path, object, Path]:
    """(run folder, its config, its newest checkpoint) for a run folder or its config.yml."""
    config_path = run_config_path(run)
    try:
        config = load_run_config(config_path)
        return config_path.parent, config, latest_checkpoint(config_path.parent, config)
    except RunError as error:
        raise AssembleError(str(error)) from None


def _split_of(run_dir: Path) -> Tuple[List[str], List[Tuple[int, ...]]]:
    """(training image names, each block's image indices) of a run's blocks.json."""
    try:
        split, names = load_blocks_json(blocks_json_path(run_dir))
    except BlockSplitError as error:
        raise AssembleError(f"{run_dir}: {error}") from None
    return names, [block.image_indices for block in split.blocks]


def merge_block_states(global_state: Dict[str, torch.Tensor], block_states: Dict[int, Dict[str, torch.Tensor]]) -> Dict[str, torch.Tensor]:
    """The global run's pipeline state with block k's weights taken from ``block_states[k]``.

    Every block given is marked as started (it will be fused); a block not given keeps what the
    global run has for it (trained there, or not started and so not fused).
    """
    merged = dict(global_state)
    started = merged[f"{MODEL_PREFIX}blocks_started"].clone()
    for block, state in block_states.items():
        prefix = f"{MODEL_PREFIX}blocks.{block}."
        weights = {k: v for k, v in state.items() if k.startswith(prefix)}
        if not weights:
            raise AssembleError(f"block {block}: the block run's checkpoint holds no weights for it")
        missing = {k for k in merged if k.startswith(prefix)} - set(weights)
        if missing:
            raise AssembleError(f"block {block}: the block run lacks {len(missing)} tensors, e.g. {sorted(missing)[0]}")
        for key, value in weights.items():
            if key in merged and merged[key].shape != value.shape:
                raise AssembleError(f"block {block}: {key} has shape {list(value.shape)}, the global run {list(merged[key].shape)}")
            merged[key] = value
        started[block] = True
    merged[f"{MODEL_PREFIX}blocks_started"] = started
    return merged


def assemble(global_run: Path, block_runs: List[Path], output_dir: Optional[Path] = None) -> Path:
    """Write the combined run; returns its folder."""
    global_dir, global_config, global_checkpoint = load_run(global_run)
    split = _split_of(global_dir)
    block_states: Dict[int, Dict[str, torch.Tensor]] = {}
    sources: Dict[int, Path] = {}
    for block_run in block_runs:
        run_dir, config, checkpoint = load_run(block_run)
        block = getattr(config.pipeline, "only_block", None)
        if block is None:
            raise AssembleError(f"{run_dir} is not a scalar-nerf-block run")
        if _split_of(run_dir) != split:
            raise AssembleError(f"{run_dir} was split differently from {global_dir} (its blocks.json differs)")
        if block in sources:
            raise AssembleError(f"block {block} is given twice: {sources[block]} and {run_dir}")
        block_states[block] = torch.load(checkpoint, map_location="cpu", weights_only=True)["pipeline"]
        sources[block] = run_dir
    state = torch.load(global_checkpoint, map_location="cpu", weights_only=True)
    merged = merge_block_states(state["pipeline"], block_states)

    timestamp = datetime.now().strftime("%Y-%m-%d_%H%M%S") + "-assembled"
    root = Path(output_dir) if output_dir is not None else Path(global_config.output_dir)
    run_dir = root / global_config.experiment_name / global_config.method_name / timestamp
    global_config.output_dir = root
    global_config.timestamp = timestamp
    global_config.load_dir = None
    model_dir = run_dir / global_config.relative_model_dir
    model_dir.mkdir(parents=True)
    for name in (BLOCKS_JSON_NAME, "dataparser_transforms.json"):
        if (global_dir / name).is_file():
            shutil.copy2(global_dir / name, run_dir / name)
    if getattr(global_config.pipeline, "run_plan", None) is not None:
        global_config.pipeline.run_plan = blocks_json_path(run_dir).resolve()  # the copy: the new run is self-contained
    atomic_torch_save({"step": state["step"], "pipeline": merged}, model_dir / checkpoint_name(state["step"]))
    save_run_config(global_config, run_dir)
    atomic_write_text(
        run_dir / ASSEMBLED_FROM_NAME,
        json.dumps({"global_run": str(global_dir), "blocks": {str(k): str(v) for k, v in sorted(sources.items())}}, indent=2),
    )
    return run_dir


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
    print(f"assembled run: {run_dir}\n  ns-eval --load-config {run_dir / 'config.yml'} --output-path eval.json")


def entrypoint() -> None:
    """Console script ``scalar-nerf-assemble``."""
    main(tyro.cli(AssembleArgs))


if __name__ == "__main__":
    entrypoint()
