"""nerfstudio's pipeline, built without ``VanillaPipeline.__init__`` (``nerfstudio/pipelines/base_pipeline.py``
of nerfstudio 1.1.5).

``VanillaPipeline.__init__`` builds one datamanager and passes the model only nerfstudio's arguments;
a pipeline of phases builds its datamanager and model itself and keeps every other method of
``VanillaPipeline`` (evaluation, parameter groups, state dicts). What is relied on, each checked by
``tests/test_nerfstudio_seam.py``:

* ``Pipeline.__init__`` takes no argument (it is ``nn.Module``'s);
* ``VanillaPipeline``'s methods use the attributes its constructor sets: ``config``, ``test_mode``,
  ``world_size``, ``datamanager`` and the private ``_model`` (returned by its ``model`` property, saved
  under :data:`~scalar_nerfstudio.seam.PIPELINE_MODEL_KEY_PREFIX`).
"""

from __future__ import annotations

from typing import Literal

from nerfstudio.models.base_model import Model
from nerfstudio.pipelines.base_pipeline import Pipeline, VanillaPipeline, VanillaPipelineConfig

__all__ = ["PipelineBase"]


class PipelineBase(VanillaPipeline):
    """``VanillaPipeline`` whose subclass builds the datamanager (``self.datamanager = ...``) and the model
    (:meth:`set_model`) in its own constructor, after this one."""

    def __init__(self, config: VanillaPipelineConfig, *, test_mode: Literal["test", "val", "inference"] = "val",
                 world_size: int = 1, local_rank: int = 0) -> None:
        Pipeline.__init__(self)
        self.config = config
        self.test_mode = test_mode
        self.world_size = world_size
        self.local_rank = local_rank

    def set_model(self, model: Model) -> None:
        """Make ``model`` the pipeline's model (``self.model``, and its checkpoint's ``_model.*`` tensors)."""
        self._model = model
