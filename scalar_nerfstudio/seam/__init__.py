"""The seam with nerfstudio: every use of its private or undocumented internals, and nowhere else.

The rest of the package uses nerfstudio's public classes (``Trainer``, ``VanillaPipeline``, ``Model``,
``ViewerControl``, the dataparsers and datamanagers, ``ns-render``'s commands) through their public
methods, plus what this package offers. Each hook below says what of nerfstudio 1.1.5 it relies on,
and ``tests/test_nerfstudio_seam.py`` fails, naming the hook, when the installed nerfstudio no longer
has it. The hooks are split by the nerfstudio module they touch, so that importing one does not
import the others (nerfstudio's viewer and ``ns-render`` take seconds to import):

* :mod:`.trainer` (``nerfstudio.engine.trainer``, ``nerfstudio.utils.writer``):
  :class:`~.trainer.TrainerBase` gives ``Trainer.__init__`` the resolved device and mixed precision
  without writing them into the config, bounds ``Trainer.train``'s loop without leaving the bound in
  ``config.max_num_iterations``, and splits the private ``Trainer._load_checkpoint`` into a choice of
  step and a hook after loading; :func:`~.trainer.start_step` reads the private ``Trainer._start_step``;
  :func:`~.trainer.set_progress_total` writes the step log's total (``writer.GLOBAL_BUFFER["max_iter"]``).
* :mod:`.pipeline` (``nerfstudio.pipelines.base_pipeline``): :class:`~.pipeline.PipelineBase` is
  ``VanillaPipeline`` without its constructor body (a pipeline that builds its datamanager and model its
  own way), and puts the model where nerfstudio keeps it (the private ``_model``:
  :data:`PIPELINE_MODEL_KEY_PREFIX` in checkpoints).
* :mod:`.data` (``nerfstudio.data.datasets.base_dataset``, ``nerfstudio.data.datamanagers.base_datamanager``):
  :func:`~.data.dataparser_outputs` reads a dataset's private ``_dataparser_outputs``;
  :func:`~.data.loader_options` gives ``VanillaDataManager.setup_train`` / ``setup_eval`` other image
  sampling options than its config's, for the loader they build.
* :mod:`.viewer` (``nerfstudio.viewer.viewer_elements``, ``nerfstudio.viewer.viewer``):
  :class:`~.viewer.ViewerHook` is a ``ViewerControl`` told when the viewer has set it up (the
  "internal use only" ``ViewerControl._setup``), with the viewer's undocumented attributes (its
  trainer, its pause buttons, its step, its scene scale) read through small functions.
* :mod:`.render_state` (``nerfstudio.viewer.render_state_machine``):
  :class:`~.render_state.RenderStateMachineBase` is nerfstudio's per-client render thread with its
  private steps (``_calculate_image_res``, ``_render_img``, ``_send_output_to_viewer``) as public
  methods to extend; :class:`~.render_state.SwappingMachines` makes a viewer build its render threads
  of another class (``Viewer.render_statemachines``).
* :mod:`.render_command` (``nerfstudio.scripts.render``): :func:`~.render_command.after_each_load`
  hands every run that ``ns-render``'s commands load to a function first (their module's
  ``eval_setup``).
* :mod:`.method_list` (``nerfstudio.configs.external_methods``):
  :func:`~.method_list.list_methods_without_reading_sources` gives nerfstudio's list of external methods
  an ``inspect.stack`` that reads no source file (seconds of every ``ns-*`` command's start).

This module itself imports nothing (the checkpoint layout below is read by modules that must not
import nerfstudio's pipelines).
"""

from __future__ import annotations

PIPELINE_MODEL_KEY_PREFIX = "_model."
"""Where a nerfstudio pipeline's checkpoint (``state_dict``) keeps its model's tensors: nerfstudio's
``Pipeline`` holds the model as ``_model`` (``Pipeline.load_state_dict`` strips this prefix)."""
