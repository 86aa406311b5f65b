"""SCALAR-NeRF pipeline: nerfstudio's VanillaPipeline, the place where training phases attach."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig


@dataclass
class ScalarPipelineConfig(VanillaPipelineConfig):
    """Pipeline of the global model (data: all training images)."""

    _target: Type = field(default_factory=lambda: ScalarPipeline)


class ScalarPipeline(VanillaPipeline):
    """Global-model pipeline: datamanager over all training images -> :class:`ScalarModel`."""

    config: ScalarPipelineConfig
