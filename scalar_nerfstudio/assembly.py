"""Assembling block runs into one run: a global ``scalar-nerf`` run plus ``scalar-nerf-block`` runs
become a new run folder whose checkpoint holds the global model and every block (``scalar-nerf-assemble``,
``scalar-nerf-train-blocks``).

The run-folder layout comes from ``runs.py``; the checkpoint's key names (which tensors are the global
model's, which are block k's) from :class:`~scalar_nerfstudio.models.scene_model.ScalarSceneModel`.
Neither the global run nor the block runs are modified.
"""

from __future__ import annotations

import json
import shutil
from datetime import datetime
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import torch

from scalar_nerfstudio.atomic_io import atomic_torch_save, atomic_write_text
from scalar_nerfstudio.blocks.split import BlockSplitError, load_blocks_json
from scalar_nerfstudio.models.block_memory import save_block_file
from scalar_nerfstudio.models.scene_model import ScalarSceneModel
from scalar_nerfstudio.runs import (
    ASSEMBLED_FROM_NAME,
    BLOCKS_JSON_NAME,
    RunError,
    block_model_path,
    block_models_dir,
    blocks_json_path,
    checkpoint_name,
    latest_checkpoint,
    load_run_config,
    run_config_path,
    save_run_config,
)

__all__ = ["AssembleError", "assemble", "load_run", "merge_block_states"]


class AssembleError(RuntimeError):
    """The runs cannot be combined (named in the message)."""


def load_run(run: Path) -> Tuple[Path, Any, Path]:
    """(run folder, its config, its newest checkpoint) for a run folder or its config.yml."""
    config_path = run_config_path(run)
    try:
        config = load_run_config(run)
        return config_path.parent, config, latest_checkpoint(config_path.parent, config)
    except RunError as error:
        raise AssembleError(str(error)) from None


def _load_checkpoint(path: Path) -> Dict[str, Any]:
    return torch.load(path, map_location="cpu", weights_only=True)


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
    global run has for it (trained there, or not started and so not fused). A tensor the global run
    holds empty (a block kept in its file, or never started) takes the block run's shape.
    """
    merged = dict(global_state)
    started_key = ScalarSceneModel.started_key()
    started = merged[started_key].clone()
    for block, state in block_states.items():
        weights = {k: state[k] for k in ScalarSceneModel.block_keys(state, block)}
        if not weights:
            raise AssembleError(f"block {block}: the block run's checkpoint holds no weights for it")
        missing = set(ScalarSceneModel.block_keys(merged, block)) - set(weights)
        if missing:
            raise AssembleError(f"block {block}: the block run lacks {len(missing)} tensors, e.g. {sorted(missing)[0]}")
        for key, value in weights.items():
            if key in merged and merged[key].numel() > 0 and merged[key].shape != value.shape:
                raise AssembleError(f"block {block}: {key} has shape {list(value.shape)}, the global run {list(merged[key].shape)}")
            merged[key] = value
        started[block] = True
    merged[started_key] = started
    return merged


def _move_blocks_to_files(merged: Dict[str, torch.Tensor], global_dir: Path, run_dir: Path) -> None:
    """Every started block of the assembled run goes to its own file in ``run_dir``'s block_models/
    (its tensors in ``merged`` become empty), so loading the run holds a bounded number of blocks in
    memory: weights present in ``merged`` are written out, and the global run's block files are copied."""
    started = merged[ScalarSceneModel.started_key()].tolist()
    for block, is_started in enumerate(started):
        if not is_started:
            continue
        keys = ScalarSceneModel.block_keys(merged, block)
        target = block_model_path(block_models_dir(run_dir), block)
        if keys and any(merged[k].numel() > 0 for k in keys):
            head = f"{ScalarSceneModel.PIPELINE_KEY_PREFIX}blocks.{block}."
            save_block_file(target, block, {k[len(head):]: merged[k] for k in keys})
            for key in keys:
                merged[key] = merged[key].new_empty(0)
        else:
            source = block_model_path(block_models_dir(global_dir), block)
            if not source.is_file():
                raise AssembleError(f"block {block}: {global_dir} says it trained, but {source} is missing")
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)


def assemble(global_run: Path, block_runs: List[Path], output_dir: Optional[Path] = None) -> Path:
    """Write the combined run of ``global_run`` and ``block_runs`` (folders or config.yml files) under
    ``output_dir`` (default: the global run's output root); returns its folder.

    Raises:
        AssembleError: a run is missing or malformed, is not a block run of ``global_run``'s split, or
            a block is given twice (nothing is written then).
    """
    global_dir, global_config, global_checkpoint = load_run(global_run)
    split = _split_of(global_dir)
    block_states: Dict[int, Dict[str, torch.Tensor]] = {}
    sources: Dict[int, Path] = {}
    for block_run in block_runs:
        run_dir, config, checkpoint = load_run(block_run)
        block = getattr(config.pipeline, "only_block", None)  # None also for a run of another method
        if block is None:
            raise AssembleError(f"{run_dir} is not a scalar-nerf-block run")
        if _split_of(run_dir) != split:
            raise AssembleError(f"{run_dir} was split differently from {global_dir} (its blocks.json differs)")
        if block in sources:
            raise AssembleError(f"block {block} is given twice: {sources[block]} and {run_dir}")
        block_states[block] = _load_checkpoint(checkpoint)["pipeline"]
        sources[block] = run_dir
    state = _load_checkpoint(global_checkpoint)
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
    if global_config.pipeline.run_plan is not None:
        global_config.pipeline.run_plan = blocks_json_path(run_dir).resolve()  # the copy: the new run is self-contained
    _move_blocks_to_files(merged, global_dir, run_dir)
    atomic_torch_save({"step": state["step"], "pipeline": merged}, model_dir / checkpoint_name(state["step"]))
    save_run_config(global_config, run_dir)
    atomic_write_text(
        run_dir / ASSEMBLED_FROM_NAME,
        json.dumps({"global_run": str(global_dir), "blocks": {str(k): str(v) for k, v in sorted(sources.items())}}, indent=2),
    )
    return run_dir
