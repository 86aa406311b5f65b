"""``scalar-nerf-block``'s trainer config: one block of a trained ``scalar-nerf`` run, in a folder of its own."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from scalar_nerfstudio.blocks.length import TrainingLength
from scalar_nerfstudio.blocks.plan import load_plan
from scalar_nerfstudio.blocks.split import BlockSplitError, load_blocks_json
from scalar_nerfstudio.engine.trainer import ScalarTrainerConfig
from scalar_nerfstudio.pipeline import ScalarPipelineConfig
from scalar_nerfstudio.runs import (
    RunError,
    RunSchemaError,
    blocks_json_path,
    checkpoint_name,
    latest_checkpoint_step,
    load_run_config,
    run_config_path,
)


@dataclass
class ScalarBlockTrainerConfig(ScalarTrainerConfig):
    """``scalar-nerf-block``: train one block of a trained ``scalar-nerf`` run, in a folder of its own.

    The scene, the split (the global run's blocks.json) and the model hyper-parameters come from the
    global run; the global model's weights are read from its newest checkpoint. Nothing is written
    into the global run, so several blocks can train at once (other processes or machines).
    """

    block: int = 0
    """Index of the block (as listed in the global run's blocks.json) to train."""
    global_run: Optional[Path] = None
    """The trained scalar-nerf run to start from: its folder (or its config.yml)."""

    def set_timestamp(self) -> None:
        """Called by ``ns-train`` before anything is written: adopt the global run's scene and split.

        The run folder is named ``TIMESTAMP-blockK``, so blocks started in the same second (several
        processes at once) never share a folder.
        """
        try:
            self.adopt_global_run()
        except RunError as error:
            raise SystemExit(f"scalar-nerf-block: {error}") from None
        fresh = self.timestamp == "{timestamp}" and self._resumed_run_dir() is None
        super().set_timestamp()
        if fresh:
            self.timestamp = f"{self.timestamp}-block{self.block}"

    def adopt_global_run(self) -> None:
        """Take the scene, split, model settings and global checkpoint from ``global_run`` (``ns-train``
        does this first; ``scalar-nerf-train-blocks`` to check a global run without training).

        Raises:
            RunError: ``global_run`` is not a scalar-nerf run whose global phase is finished (one line).
        """
        if self.global_run is None:
            raise RunError("--global-run is required (the folder of a trained `ns-train scalar-nerf` run).")
        config_path = run_config_path(self.global_run)
        try:
            global_config = load_run_config(config_path)
        except RunSchemaError:
            raise
        except RunError:
            raise RunError(f"the global run {self.global_run}: no config.yml there (not a scalar-nerf run folder).") from None
        run_dir = config_path.parent
        global_pipeline = getattr(global_config, "pipeline", None)
        if not isinstance(global_pipeline, ScalarPipelineConfig):
            raise RunError(f"{config_path} is not a scalar-nerf run.")
        blocks_json = blocks_json_path(run_dir)
        if not blocks_json.is_file():
            raise RunError(f"{blocks_json} is missing; was {run_dir} trained with scalar-nerf?")
        checkpoint_dir = run_dir / global_config.relative_model_dir
        step = latest_checkpoint_step(checkpoint_dir)
        global_length = _recorded_length(blocks_json)
        global_steps = global_length.global_steps if global_length is not None else global_pipeline.global_steps
        if global_length is not None and not global_length.measured:
            raise RunError(f"the global phase of {run_dir} is not finished (its time budget's steps are not planned yet); train it first.")
        if step is None or global_steps is None or step + 1 < global_steps:
            done = 0 if step is None else step + 1
            planned = "" if global_steps is None else f" of {global_steps}"
            raise RunError(f"the global phase of {run_dir} is not finished ({done}{planned} steps checkpointed); train it first.")
        try:
            num_blocks = load_blocks_json(blocks_json)[0].num_blocks
        except BlockSplitError as error:
            raise RunError(str(error)) from None
        if not 0 <= self.block < num_blocks:
            raise RunError(f"--block {self.block} does not exist; {blocks_json} has blocks 0..{num_blocks - 1}.")
        pipeline = self.scalar_pipeline
        pipeline.datamanager.data = global_pipeline.datamanager.data
        pipeline.datamanager.dataparser = global_pipeline.datamanager.dataparser
        pipeline.model = global_pipeline.model
        pipeline.num_blocks, pipeline.aabb_scale = global_pipeline.num_blocks, global_pipeline.aabb_scale
        pipeline.split_seed = global_pipeline.split_seed
        pipeline.min_overlap_images = global_pipeline.min_overlap_images
        for name in ("block_log2_hashmap_size", "block_log2_hashmap_bounds", "block_max_resolution", "block_max_resolution_bounds"):
            setattr(pipeline, name, getattr(global_pipeline, name))
        # Block settings left at their defaults follow the global run (an explicit value wins).
        defaults = type(pipeline)()
        if pipeline.decoder_mode == defaults.decoder_mode:
            pipeline.decoder_mode = global_pipeline.decoder_mode
        if pipeline.block_steps is None and pipeline.time_budget is None:  # the steps the global run planned for its blocks
            pipeline.block_steps = global_length.steps_of_block(self.block) if global_length is not None else global_pipeline.block_steps
        if pipeline.datamanager.train_num_rays_per_batch == defaults.datamanager.train_num_rays_per_batch:
            pipeline.datamanager.train_num_rays_per_batch = global_pipeline.datamanager.train_num_rays_per_batch
        pipeline.only_block = self.block
        pipeline.blocks_json = blocks_json.resolve()
        pipeline.global_checkpoint = (checkpoint_dir / checkpoint_name(step)).resolve()
        self.data = global_pipeline.datamanager.data
        if self.experiment_name is None:
            self.experiment_name = global_config.experiment_name


def _recorded_length(blocks_json: Path) -> Optional[TrainingLength]:
    """The length a run recorded in its blocks.json (None: a run from before lengths were planned, whose
    config.yml has the steps)."""
    try:
        return load_plan(blocks_json).length
    except BlockSplitError:
        return None
