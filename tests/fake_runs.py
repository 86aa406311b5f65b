"""Run folders written without training: what a command reads of a run (config.yml, blocks.json, one
checkpoint), for tests of how commands combine or refuse runs."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch
import yaml

from scalar_nerfstudio.atomic_io import atomic_torch_save
from scalar_nerfstudio.blocks.split import save_blocks_json, split_cameras
from scalar_nerfstudio.method_configs import scalar_nerf
from scalar_nerfstudio.runs import save_run_config


def fake_run(folder: Path, state: Optional[Dict[str, torch.Tensor]] = None, only_block: Optional[int] = None,
             *, num_images: int = 8, checkpoint: bool = True) -> Path:
    """A scalar-nerf run folder (a scalar-nerf-block run with ``only_block``): config.yml, a 2-block
    split of ``num_images`` images in a row (another ``num_images``: another split) and, with
    ``checkpoint``, step 27 holding ``state``."""
    config = copy.deepcopy(scalar_nerf.config)
    config.output_dir, config.experiment_name, config.pipeline.only_block = folder.parent, "scene", only_block
    if only_block is not None:
        config.method_name = "scalar-nerf-block"
    (folder / "nerfstudio_models").mkdir(parents=True)
    centres = np.stack([np.linspace(-1, 1, num_images), np.zeros(num_images), np.zeros(num_images)], axis=1)
    save_blocks_json(split_cameras(centres, 2, aabb_scale=(1.2, 1.2, 1.2)), folder / "blocks.json", [f"{i}.png" for i in range(num_images)])
    config.pipeline.run_plan = (folder / "blocks.json").resolve() if only_block is None else None
    save_run_config(config, folder)
    if checkpoint:
        atomic_torch_save({"step": 27, "pipeline": state or {}}, folder / "nerfstudio_models" / "step-000000027.ckpt")
    return folder


def foreign_run(folder: Path) -> Path:
    """A nerfacto run folder: its config.yml as nerfstudio writes it and a checkpoint file."""
    from nerfstudio.configs.method_configs import method_configs

    config = copy.deepcopy(method_configs["nerfacto"])
    (folder / "nerfstudio_models").mkdir(parents=True)
    (folder / "config.yml").write_text(yaml.dump(config))
    atomic_torch_save({"step": 10, "pipeline": {}}, folder / "nerfstudio_models" / "step-000000010.ckpt")
    return folder
