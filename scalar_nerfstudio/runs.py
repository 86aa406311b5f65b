"""Run folders: the one module that knows their layout and upgrades older runs (standard library and
PyYAML only; it knows nothing of the model: assembling block runs is ``assembly.py``).

A run folder (``OUTPUT/EXPERIMENT/METHOD/TIMESTAMP``) holds

* ``config.yml``: the trainer config (nerfstudio's, YAML with Python tags);
* ``blocks.json``: the run's block plan (``blocks/plan.py``), written once when training starts;
* ``nerfstudio_models/step-NNNNNNNNN.ckpt``: checkpoints (nerfstudio's names), written atomically:
  the global model and the block that trains (or last trained); a finished block's tensors are
  empty there, its weights are in
* ``block_models/block-NNNN.ckpt``: one file per finished block, written atomically when its phase
  ends (so memory and checkpoints do not grow with the number of blocks);
* ``dataparser_transforms.json``, ``model_report.json`` and, for an assembled run, ``assembled_from.json``.

config.yml and blocks.json carry the run's schema version (:data:`RUN_SCHEMA_VERSION`): a run
written by an older version is upgraded when it is loaded (:func:`upgrade_run_config`,
:func:`upgrade_blocks_json`), one written by a newer version is refused (:class:`RunSchemaError`).
"""

from __future__ import annotations

import copy
import os
import re
from pathlib import Path
from typing import Any, Dict, Mapping, Optional

import yaml

from scalar_nerfstudio.atomic_io import atomic_write_text

CONFIG_NAME = "config.yml"
BLOCKS_JSON_NAME = "blocks.json"
REPORT_NAME = "model_report.json"
ASSEMBLED_FROM_NAME = "assembled_from.json"
BLOCK_MODELS_DIR = "block_models"
CHECKPOINT_PATTERN = re.compile(r"^step-(\d{9})\.ckpt$")
MODEL_DIR_NAME = "nerfstudio_models"
"""nerfstudio's default ``relative_model_dir`` (the benchmark's runs keep it)."""


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


def run_config_path(run: Path) -> Path:
    """``config.yml`` of a run given as the file itself or its folder."""
    path = Path(run)
    return path if path.suffix in (".yml", ".yaml") else path / CONFIG_NAME


def load_run_config(run: Path) -> Any:
    """The trainer config of a run (folder or config.yml), upgraded to :data:`RUN_SCHEMA_VERSION`
    (``ScalarTrainerConfig`` calls :func:`upgrade_run_config` as YAML builds it).

    Raises:
        RunError: there is no config.yml.
        RunSchemaError: the run was written by a newer version (the message names the file).
    """
    path = run_config_path(run)
    if not path.is_file():
        raise RunError(f"{run}: no {CONFIG_NAME} there (not a nerfstudio run folder)")
    try:
        return yaml.load(path.read_text(encoding="utf-8"), Loader=yaml.Loader)
    except RunSchemaError as error:
        raise RunSchemaError(f"{path}: {error}") from None
    except (yaml.YAMLError, UnicodeDecodeError, AttributeError, TypeError, ImportError) as error:
        # not YAML, or it names a class this installation lacks (another plugin's run, a broken file)
        first_line = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise RunError(f"{path} cannot be read as a nerfstudio run config ({first_line})") from None


#: The methods whose runs hold a global model and blocks (an assembled run is a scalar-nerf run).
SCALAR_METHODS = ("scalar-nerf", "scalar-nerf-block")


def check_trained_run(run: Path, *, scalar_only: bool) -> Path:
    """The config.yml of a run that ns-* verbs can load: it is there, it reads, it has a checkpoint
    and, with ``scalar_only``, it is a scalar-nerf run; checked before anything is loaded or written.

    Raises:
        RunError: what is wrong, naming the file.
    """
    path = run_config_path(run)
    config = load_run_config(path)
    method = getattr(config, "method_name", None)
    if scalar_only and method not in SCALAR_METHODS:
        raise RunError(f"{path} is a run of {method or 'no known method'}, not of scalar-nerf")
    if not hasattr(config, "relative_model_dir"):
        raise RunError(f"{path} is not a nerfstudio trainer config")
    latest_checkpoint(path.parent, config)
    return path


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


# ------------------------------------------------------------------ schema versions and migration
RUN_SCHEMA_VERSION = 3
"""Version of the run files this code writes: ``pipeline.scalar_schema_version`` in config.yml and
``version`` in blocks.json. Version 1: every run written before the versions were recorded. Version 2:
config.yml holds the options as given plus the values the run derived (the scene radius fitted to the
depth images in ``model.scene_radius``, the planned steps in ``max_num_iterations``, the device). Version 3:
config.yml holds the options as given; the run's derived values are in its blocks.json (the scene radius
as ``plan.scene_radius``) or are derived again (the steps from the plan's length, the device)."""
SCHEMA_FIELD = "scalar_schema_version"
"""The pipeline config's field that holds the version of config.yml."""

#: What a version-1 config.yml may lack, with the value it was trained with: pipeline options ...
_V1_PIPELINE = {
    "block_init": "fresh",  # blocks started from an empty table of their own
    "lr_schedule": "per-phase",  # every phase, the global one too, warmed up and decayed
    "one_model_restart": 0.0,  # one model decayed over its whole run, without a restart
    "scene_radius_from_depth": False,  # rays ran to the far plane
}
#: ... model options ...
_V1_MODEL = {"scene_radius": None}  # unbounded rays
#: ... and optimiser templates, with the template that trained those groups then.
_V1_OPTIMIZERS = {"block_encoder": "encoder"}  # block tables at the global table's rate


class RunSchemaError(RunError):
    """A run file was written by a newer version of scalar-nerfstudio than this one (or its version is not a number)."""


def _check_version(version: Any, what: str) -> int:
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise RunSchemaError(f"{what} has schema version {version!r}, not a whole number >= 1")
    if version > RUN_SCHEMA_VERSION:
        raise RunSchemaError(f"{what} was written by a newer scalar-nerfstudio (schema version {version}; this one reads "
                             f"versions up to {RUN_SCHEMA_VERSION}): load it with that version")
    return version


def upgrade_run_config(state: Dict[str, Any]) -> Dict[str, Any]:
    """A run's trainer config, as YAML (or pickle) hands it over (the attributes of a
    ``ScalarTrainerConfig``, its pipeline already built), brought to :data:`RUN_SCHEMA_VERSION`.

    Version 1 (no ``scalar_schema_version``): every option it lacks is set to the value it was
    trained with (``_V1_*``; options it has are kept), so it loads and resumes as it was trained.
    Version 2: kept as it is: its ``model.scene_radius`` may be the radius the run fitted to its depth
    images (its blocks.json records none), which the model then reads as a given radius, so the run
    loads with the bound it was trained with; its ``max_num_iterations`` may be the steps it planned,
    which its phases also give. A config whose pipeline is not scalar-nerf's is returned unchanged.

    Raises:
        RunSchemaError: the config was written by a newer version.
    """
    pipeline = state.get("pipeline")
    if not hasattr(type(pipeline), SCHEMA_FIELD):
        return state
    fields = vars(pipeline)
    version = _check_version(fields.get(SCHEMA_FIELD, 1), "config.yml")
    if version < 2:
        for name, value in _V1_PIPELINE.items():
            fields.setdefault(name, value)
        model = fields.get("model")
        if model is not None:
            for name, value in _V1_MODEL.items():
                vars(model).setdefault(name, value)
        optimizers = state.get("optimizers")
        if isinstance(optimizers, dict):
            for name, template in _V1_OPTIMIZERS.items():
                if name not in optimizers and template in optimizers:
                    optimizers[name] = copy.deepcopy(optimizers[template])
    fields[SCHEMA_FIELD] = RUN_SCHEMA_VERSION
    return state


def upgrade_blocks_json(content: Mapping[str, Any], path: Path) -> Dict[str, Any]:
    """A blocks.json's ``content`` brought to :data:`RUN_SCHEMA_VERSION` (versions 1 and 2 have the same
    layout: the split, and the plan when a run wrote it, so only its version changes; their plan has no
    ``scene_radius``: such a run's config.yml gives its radius, if it has one).

    Raises:
        RunSchemaError: the file was written by a newer version (the message names ``path``).
    """
    upgraded = dict(content)
    _check_version(upgraded.get("version", 1), str(path))
    upgraded["version"] = RUN_SCHEMA_VERSION
    return upgraded
