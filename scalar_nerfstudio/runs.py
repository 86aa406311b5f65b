"""Run folders: the one module that knows their layout (standard library and PyYAML; torch only to
save, load and assemble checkpoints).

A run folder (``OUTPUT/EXPERIMENT/METHOD/TIMESTAMP``) holds

* ``config.yml``: the trainer config (nerfstudio's, YAML with Python tags);
* ``blocks.json``: the run's block plan (``blocks/plan.py``), written once when training starts;
* ``nerfstudio_models/step-NNNNNNNNN.ckpt``: checkpoints (nerfstudio's names), written atomically:
  the global model and the block that trains (or last trained); a finished block's tensors are
  empty there, its weights are in
* ``block_models/block-NNNN.ckpt``: one file per finished block, written atomically when its phase
  ends (so memory and checkpoints do not grow with the number of blocks);
* ``dataparser_transforms.json``, ``model_report.json`` and, for an assembled run, ``assembled_from.json``.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Tuple

import yaml

from scalar_nerfstudio.atomic_io import atomic_write_text

if TYPE_CHECKING:
    import torch

CONFIG_NAME = "config.yml"
BLOCKS_JSON_NAME = "blocks.json"
REPORT_NAME = "model_report.json"
ASSEMBLED_FROM_NAME = "assembled_from.json"
BLOCK_MODELS_DIR = "block_models"
CHECKPOINT_PATTERN = re.compile(r"^step-(\d{9})\.ckpt$")
MODEL_DIR_NAME = "nerfstudio_models"
"""nerfstudio's default ``relative_model_dir`` (the benchmark's runs keep it)."""
PARTIAL_SUFFIX = ".ckpt.partial"


class RunError(ValueError):
    """A folder is not the run it was given as (the message says what is missing)."""


def checkpoint_name(step: int) -> str:
    """nerfstudio's checkpoint file name for ``step``."""
    return f"step-{step:09d}.ckpt"


def latest_checkpoint_step(checkpoint_dir: Path) -> Optional[int]:
    """Largest N among the ``step-N.ckpt`` files in ``checkpoint_dir`` (other files are ignored)."""
    if not Path(checkpoint_dir).is_dir():
        return None
    steps = [int(m.group(1)) for m in map(CHECKPOINT_PATTERN.match, os.listdir(checkpoint_dir)) if m]
    return max(steps) if steps else None


def atomic_torch_save(state: Dict[str, Any], path: Path) -> None:
    """Write ``state`` to ``path`` so that ``path`` is either absent or complete, never half-written.

    The bytes go to a hidden file in ``path``'s parent's parent (outside the checkpoint folder, whose
    every file nerfstudio's loaders parse as ``step-N.ckpt``), are fsynced, then renamed into place.
    """
    import torch  # here, not at import: light processes (Ray workers) read run folders without torch

    path = Path(path)
    staging = path.parent.parent / f".{path.stem}{PARTIAL_SUFFIX}"
    with open(staging, "wb") as handle:
        torch.save(state, handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(staging, path)


def run_config_path(run: Path) -> Path:
    """``config.yml`` of a run given as the file itself or its folder."""
    path = Path(run)
    return path if path.suffix in (".yml", ".yaml") else path / CONFIG_NAME


def load_run_config(run: Path) -> Any:
    """The trainer config of a run (folder or config.yml)."""
    path = run_config_path(run)
    if not path.is_file():
        raise RunError(f"{run}: no {CONFIG_NAME} there (not a nerfstudio run folder)")
    return yaml.load(path.read_text(encoding="utf-8"), Loader=yaml.Loader)


def save_run_config(config: Any, run_dir: Path) -> Path:
    """Write ``config`` as ``run_dir/config.yml`` atomically; returns the path."""
    path = Path(run_dir) / CONFIG_NAME
    atomic_write_text(path, yaml.dump(config))
    return path


def blocks_json_path(run_dir: Path) -> Path:
    """Where a run keeps its block plan."""
    return Path(run_dir) / BLOCKS_JSON_NAME


def block_models_dir(run_dir: Path) -> Path:
    """Where a run keeps its finished blocks' weights, one file per block."""
    return Path(run_dir) / BLOCK_MODELS_DIR


def block_model_path(block_dir: Path, block: int) -> Path:
    """Block ``block``'s file in a run's :func:`block_models_dir`."""
    return Path(block_dir) / f"block-{block:04d}.ckpt"


def newest_checkpoint(checkpoint_dir: Path) -> Optional[Path]:
    """The ``step-N.ckpt`` file of largest N in ``checkpoint_dir`` (a run's ``nerfstudio_models``), or None."""
    step = latest_checkpoint_step(checkpoint_dir)
    return None if step is None else Path(checkpoint_dir) / checkpoint_name(step)


def latest_checkpoint(run_dir: Path, config: Any) -> Path:
    """The newest checkpoint of a run, given its folder and config."""
    checkpoint_dir = Path(run_dir) / config.relative_model_dir
    path = newest_checkpoint(checkpoint_dir)
    if path is None:
        raise RunError(f"{run_dir}: no checkpoint in {checkpoint_dir}")
    return path


def report_path(run_dir: Path) -> Path:
    """Where a run keeps its model report (parameters, table sizes, memory)."""
    return Path(run_dir) / REPORT_NAME


def _load_checkpoint(path: Path) -> Dict[str, Any]:
    import torch

    return torch.load(path, map_location="cpu", weights_only=True)


# ------------------------------------------------------------------ assembling block runs into one run
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
    from scalar_nerfstudio.blocks.split import BlockSplitError, load_blocks_json  # numpy and sklearn: only here

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
    from scalar_nerfstudio.models.scene_model import ScalarSceneModel

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
    from scalar_nerfstudio.models.block_memory import save_block_file
    from scalar_nerfstudio.models.scene_model import ScalarSceneModel

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
    if getattr(global_config.pipeline, "run_plan", None) is not None:
        global_config.pipeline.run_plan = blocks_json_path(run_dir).resolve()  # the copy: the new run is self-contained
    _move_blocks_to_files(merged, global_dir, run_dir)
    atomic_torch_save({"step": state["step"], "pipeline": merged}, model_dir / checkpoint_name(state["step"]))
    save_run_config(global_config, run_dir)
    atomic_write_text(
        run_dir / ASSEMBLED_FROM_NAME,
        json.dumps({"global_run": str(global_dir), "blocks": {str(k): str(v) for k, v in sorted(sources.items())}}, indent=2),
    )
    return run_dir
