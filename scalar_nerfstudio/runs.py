"""Run folders: the one module that knows their layout (standard library and PyYAML; torch only to save).

A run folder (``OUTPUT/EXPERIMENT/METHOD/TIMESTAMP``) holds

* ``config.yml``: the trainer config (nerfstudio's, YAML with Python tags);
* ``blocks.json``: the run's block plan (``blocks/plan.py``), written once when training starts;
* ``nerfstudio_models/step-NNNNNNNNN.ckpt``: checkpoints (nerfstudio's names), written atomically;
* ``dataparser_transforms.json``, ``model_report.json`` and, for an assembled run, ``assembled_from.json``.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Dict, Optional

import yaml

from scalar_nerfstudio.atomic_io import atomic_write_text

CONFIG_NAME = "config.yml"
BLOCKS_JSON_NAME = "blocks.json"
REPORT_NAME = "model_report.json"
ASSEMBLED_FROM_NAME = "assembled_from.json"
CHECKPOINT_PATTERN = re.compile(r"^step-(\d{9})\.ckpt$")
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


def latest_checkpoint(run_dir: Path, config: Any) -> Path:
    """The newest checkpoint of a run, given its folder and config."""
    checkpoint_dir = Path(run_dir) / config.relative_model_dir
    step = latest_checkpoint_step(checkpoint_dir)
    if step is None:
        raise RunError(f"{run_dir}: no checkpoint in {checkpoint_dir}")
    return checkpoint_dir / checkpoint_name(step)


def report_path(run_dir: Path) -> Path:
    """Where a run keeps its model report (parameters, table sizes, memory)."""
    return Path(run_dir) / REPORT_NAME
