"""nerfstudio method specifications: ``scalar-nerf`` and ``scalar-nerf-block``.

Registered through the ``nerfstudio.method_configs`` entry points in ``pyproject.toml``. Only nerfstudio
and the command lines (``scripts/``) import this module: it sits above the rest of the package.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Type

import torch
from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.plugins.types import MethodSpecification

from scalar_nerfstudio.data.datamanager import ScalarDataManagerConfig
from scalar_nerfstudio.engine.block_trainer import ScalarBlockTrainerConfig
from scalar_nerfstudio.engine.device import AutoMachineConfig
from scalar_nerfstudio.engine.schedulers import WarmupExponentialDecaySchedulerConfig
from scalar_nerfstudio.engine.trainer import ScalarTrainerConfig
from scalar_nerfstudio.models.scene_model import ScalarSceneModelConfig
from scalar_nerfstudio.pipeline import ScalarPipelineConfig
from scalar_nerfstudio.seam.method_list import list_methods_without_reading_sources

# nerfstudio imports this module (its entry point) while it builds its list of methods, before it lists the
# external ones: that listing then skips reading source files (seconds of every ns-* command's start).
list_methods_without_reading_sources()


@dataclass
class FusedAdamOptimizerConfig(AdamOptimizerConfig):
    """Adam with torch's fused kernel (CPU and CUDA): ~8x faster steps over a large hash table."""

    _target: Type = torch.optim.Adam
    fused: bool = True
    """Use the fused multi-tensor kernel."""


def _adam(lr: float, eps: float = 1e-15) -> dict:
    return {"optimizer": FusedAdamOptimizerConfig(lr=lr, eps=eps), "scheduler": WarmupExponentialDecaySchedulerConfig()}


def global_trainer_config(method_name: str = "scalar-nerf", config_class: Type[ScalarTrainerConfig] = ScalarTrainerConfig) -> ScalarTrainerConfig:
    """Trainer config: global phase, then the blocks (paper Sec. 4 hyper-parameters, CPU-sized phases)."""
    return config_class(
        method_name=method_name,
        max_num_iterations=0,
        steps_per_save=250,
        steps_per_eval_batch=500,
        steps_per_eval_image=500,
        steps_per_eval_all_images=100000,
        mixed_precision=True,  # on CUDA only: the device is chosen when training starts
        machine=AutoMachineConfig(),
        pipeline=ScalarPipelineConfig(
            datamanager=ScalarDataManagerConfig(
                dataparser=NerfstudioDataParserConfig(eval_mode="interval", eval_interval=8),
            ),
            model=ScalarSceneModelConfig(),  # rays per render chunk: by device (device_sizes)
        ),
        # Templates: a block's table uses "block_encoder", its appearance "appearance", its fine-tuned
        # decoder "block_decoder" (the paper's 5e-5). Each schedule spans the phase its group trains in.
        optimizers={
            # Hash tables at 1e-2, as Instant-NGP and nerfacto train them: the paper's 1e-3 serves 200k
            # iterations, and at CPU run lengths (a few thousand steps) 1e-2 generalises better.
            "encoder": _adam(1e-2),
            # A block's table at 4e-2: blocks start from the global model's trained table and underfit
            # their views within a block phase at the global table's rate.
            "block_encoder": _adam(4e-2),
            "decoder": _adam(1e-3),
            "appearance": _adam(1e-3),
            "block_decoder": _adam(5e-5),
            # Pose corrections (--pipeline.model.camera-optimizer.mode SO3xR3), learnt in the global phase
            # only, with one decay over it: nerfacto's rate.
            "camera_opt": _adam(1e-3),
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 14),
        vis="viewer",
    )


scalar_nerf = MethodSpecification(
    config=global_trainer_config(),
    description="SCALAR-NeRF: coarse global hash-grid model, then K overlapping blocks, fused by the global model.",
)

scalar_nerf_block = MethodSpecification(
    config=global_trainer_config("scalar-nerf-block", ScalarBlockTrainerConfig),
    description="SCALAR-NeRF: train one block of a trained scalar-nerf run (--global-run RUN --block K), in its own folder.",
)
