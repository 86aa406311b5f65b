"""Trainer for SCALAR-NeRF: nerfstudio's trainer with atomic checkpoints and run-scaled schedules."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Dict, List, Literal, Optional, Type

from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils import writer
from nerfstudio.utils.rich_utils import CONSOLE

from scalar_nerfstudio.atomic_io import atomic_torch_save
from scalar_nerfstudio.blocks.plan import save_plan
from scalar_nerfstudio.blocks.split import BlockSplitError, load_blocks_json
from scalar_nerfstudio.config_checks import OptionError, check_block_counts, check_block_plan, check_options, check_output_dir
from scalar_nerfstudio.data.validation import SceneError, scan_scene
from scalar_nerfstudio.engine.contract import PhasedPipeline
from scalar_nerfstudio.engine.device import limit_onednn_kernel_cache, resolve_machine
from scalar_nerfstudio.engine.preview import write_preview
from scalar_nerfstudio.engine.report import format_report, scene_model_report, write_report
from scalar_nerfstudio.engine.schedulers import WarmupExponentialDecaySchedulerConfig
from scalar_nerfstudio.engine.threads import ThreadGovernor
from scalar_nerfstudio.runs import (
    RunError,
    RunSchemaError,
    blocks_json_path,
    checkpoint_name,
    latest_checkpoint_step,
    load_run_config,
    report_path,
    run_config_path,
    save_run_config,
    upgrade_run_config,
)

#: The template whose rate a global group restarts at in a run of one model (``global_restart_fraction``):
#: the rate a block's group starts with.
RESTART_TEMPLATES: Dict[str, str] = {"encoder": "block_encoder", "decoder": "block_decoder"}


@dataclass
class ScalarTrainerConfig(TrainerConfig):
    """nerfstudio's TrainerConfig; ``--load-dir RUN/nerfstudio_models`` resumes *in* RUN."""

    _target: Type = field(default_factory=lambda: ScalarTrainer)
    max_num_iterations: int = 0
    """Stop after this many steps in total; 0: train every phase (global steps + blocks x block steps)."""
    steps_per_preview: int = 500
    """Every this many steps and at the last, render the first eval view beside its ground truth into
    RUN/preview.png and RUN/previews/, and log its PSNR; 0: never."""
    preview_max_size: int = 512
    """Longest side of the preview in pixels: a larger eval view is rendered smaller, so a preview of
    a full-resolution photo costs seconds, not minutes; 0: the eval image's size."""
    adapt_threads: bool = True
    """CPU training: every few seconds, use as many threads as there are cores not busy with other
    processes; off, or OMP_NUM_THREADS set: torch's thread count is left alone."""

    def __setstate__(self, state: Dict[str, Any]) -> None:
        """Built from config.yml (YAML, as every nerfstudio command loads a run) or unpickled: a run
        written by an older version is upgraded first (``runs.upgrade_run_config``)."""
        self.__dict__.update(upgrade_run_config(state))

    def set_timestamp(self) -> None:
        """Check the options and the scene, then resume into the run folder that ``load_dir`` belongs
        to (if any), then check that the run folder can be written.

        ``ns-train`` calls this before it writes anything, so a bad scene, option or output folder
        ends here with one clear message and no run folder.
        """
        self._check_scene()
        run_dir = self._resumed_run_dir()
        if run_dir is not None and self.timestamp == "{timestamp}":
            self.output_dir = run_dir.parent.parent.parent
            self.experiment_name = run_dir.parent.parent.name
            self.timestamp = run_dir.name
        if run_dir is not None and self.pipeline.run_plan is None:
            self._adopt_run_plan(run_dir)
        super().set_timestamp()
        self._check_output_dir()

    # ------------------------------------------------ up-front checks (config_checks.py, data/validation.py)
    def _check_scene(self) -> None:
        """Options, then the scene (every image decoded), then the options that depend on the scene
        (number of blocks vs training images, the block split): each ends in one paragraph, no traceback."""
        self._exit_on_option_error(check_options, self)
        dataparser = self.pipeline.datamanager.dataparser
        if not isinstance(dataparser, NerfstudioDataParserConfig):
            return
        data = Path(self.data if self.data is not None else getattr(self.pipeline.datamanager, "data", None) or dataparser.data)
        try:
            scene = scan_scene(data, eval_interval=dataparser.eval_interval, eval_mode=dataparser.eval_mode,
                               train_fraction=dataparser.train_split_fraction, downscale_factor=dataparser.downscale_factor)
        except SceneError as error:
            raise SystemExit(f"{self.method_name}: bad scene: {error}") from None
        note = scene.conversion_note(self.pipeline.datamanager.alpha_background)
        if note is not None:
            CONSOLE.print(f"{self.method_name}: {note}", soft_wrap=True, markup=False, highlight=False)
        self._exit_on_option_error(check_block_counts, self.pipeline, scene.num_train, scene.num_frames)
        if self.load_dir is None:
            self._exit_on_option_error(check_block_plan, self.pipeline, data)

    def _exit_on_option_error(self, check: Callable[..., None], *args: Any) -> None:
        try:
            check(*args)
        except OptionError as error:
            raise SystemExit(f"{self.method_name}: bad option: {error}") from None

    def _check_output_dir(self) -> None:
        try:
            check_output_dir(self.get_base_dir())
        except OptionError as error:
            raise SystemExit(f"{self.method_name}: cannot write the run: {error}") from None
    # ------------------------------------------------------------------------------------------------

    def _adopt_run_plan(self, run_dir: Path) -> None:
        """A resumed run keeps the shape it was planned with (its blocks.json), whatever the options
        say, once its config.yml records a plan (a run stopped before its plan was recorded, or
        written before plans were, has its shape decided again, as it was then)."""
        try:
            recorded = load_run_config(run_dir).pipeline.run_plan
        except RunError as error:
            raise SystemExit(f"{self.method_name}: cannot resume {run_dir}: {error}") from None
        if recorded is not None:
            self.pipeline.run_plan = blocks_json_path(run_dir).resolve()

    def _resumed_run_dir(self) -> Optional[Path]:
        if self.load_dir is None:
            return None
        run_dir = Path(self.load_dir).resolve().parent
        is_run = run_config_path(run_dir).is_file() and run_dir.parent.name == self.method_name
        return run_dir if is_run else None


class ScalarTrainer(Trainer):
    """Adds to nerfstudio's Trainer: atomic checkpoints, robust resume, schedules scaled to the run."""

    config: ScalarTrainerConfig

    def __init__(self, config: ScalarTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        resolve_machine(config)  # device "auto" and mixed precision (CUDA only), before nerfstudio reads them
        limit_onednn_kernel_cache()  # before the first CPU kernel: memory must not grow with the steps
        super().__init__(config, local_rank, world_size)
        self.thread_governor = ThreadGovernor(enabled=config.adapt_threads and config.machine.device_type == "cpu")

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        super().setup(test_mode=test_mode)
        pipeline = self.phased_pipeline
        pipeline.attach_run_dir(self.base_dir)
        if self.config.max_num_iterations <= 0:
            self.config.max_num_iterations = pipeline.total_steps
        # nerfstudio's step log (ETA, % done) was set up in Trainer.__init__, before the phases were
        # known, with max_num_iterations 0 (= every phase): give it the real total.
        writer.GLOBAL_BUFFER["max_iter"] = self.config.max_num_iterations
        if test_mode == "val":
            self._record_plan(pipeline)
            CONSOLE.print(pipeline.plan_report())
            CONSOLE.print(f"split saved to {blocks_json_path(self.base_dir)}")

    @property
    def phased_pipeline(self) -> PhasedPipeline:
        """The pipeline, checked against the trainer's contract (engine/contract.py)."""
        pipeline = self.pipeline
        if not isinstance(pipeline, PhasedPipeline):
            raise TypeError(f"{type(self).__name__} trains a pipeline that trains in phases (ScalarPipeline), not {type(pipeline).__name__}")
        return pipeline

    def _record_plan(self, pipeline: PhasedPipeline) -> None:
        """Save the run's block plan as blocks.json and name it in config.yml (once), so that every
        later load of the run builds the model that was trained (K, split, block capacities)."""
        path = blocks_json_path(self.base_dir)
        if self.config.pipeline.run_plan is not None and Path(self.config.pipeline.run_plan).resolve() == path.resolve():
            return
        save_plan(pipeline.plan, path)
        self.config.pipeline.run_plan = path.resolve()
        save_run_config(self.config, self.base_dir)

    def setup_optimizers(self) -> Optimizers:
        """One optimiser per parameter group, from the template in ``optimizers`` that fits the group.

        A block's groups (``block{k}.encoder`` ...) use the ``block_encoder`` / ``appearance`` templates
        and ``block_decoder`` for a fine-tuned decoder; each schedule spans the phase its group trains in.
        The global model's rate is held after its warm-up when the pipeline says so
        (``holds_global_learning_rate``: blocks follow, ``--pipeline.lr-schedule restart``); in a run of
        one model it is held and then restarts at the rate of the group's :data:`RESTART_TEMPLATES`
        template (``global_restart_fraction``, ``--pipeline.one-model-restart``).
        """
        pipeline = self.phased_pipeline
        param_groups = pipeline.get_param_groups()
        phases = pipeline.param_group_phases()
        config: Dict[str, Any] = {}
        for group in param_groups:
            template, phase = phases.get(group, (group, None))
            template = self._optimizer_template(group, template)
            settings = dict(self.config.optimizers[template])
            scheduler = settings.get("scheduler")
            if isinstance(scheduler, WarmupExponentialDecaySchedulerConfig):
                start, length = (phase.start_step, phase.num_steps) if phase is not None else (0, self.config.max_num_iterations)
                is_global = phase is not None and phase.block is None
                held = is_global and pipeline.holds_global_learning_rate
                restart = pipeline.global_restart_fraction if is_global else 0.0
                restart_factor = 1.0
                if restart > 0:  # one model: restart at the rate a block's group starts with
                    restart_template = self._optimizer_template(group, RESTART_TEMPLATES.get(template, template))
                    base_lr = float(settings["optimizer"].lr)  # 0: a frozen group stays frozen
                    restart_factor = float(self.config.optimizers[restart_template]["optimizer"].lr) / base_lr if base_lr > 0 else 1.0
                settings["scheduler"] = replace(scheduler, start_step=start, max_steps=scheduler.max_steps or max(length, 1),
                                                final_factor=1.0 if held else scheduler.final_factor,
                                                restart_fraction=restart, restart_factor=restart_factor)
            config[group] = settings
        return Optimizers(config, param_groups)

    def _optimizer_template(self, group: str, template: str) -> str:
        """``template``, checked to be in ``optimizers``."""
        if template not in self.config.optimizers:
            raise KeyError(f"no optimizer settings for parameter group {group!r} (looked for --optimizers.{template})")
        return template

    def train_iteration(self, step: int):
        """One step; a checkpoint is also written at the end of every phase, a preview every
        ``steps_per_preview`` steps and at the last step. Torch's thread count follows the free cores
        (``adapt_threads``)."""
        self.thread_governor.update()
        result = super().train_iteration(step)
        every = self.config.steps_per_preview
        if every > 0 and ((step + 1) % every == 0 or step + 1 == self._total_steps):
            path, psnr = write_preview(self.pipeline, self.base_dir, step, self.config.preview_max_size)
            CONSOLE.print(f"step {step + 1}: preview (render | ground truth, eval view 0, {psnr:.2f} dB) written to {path}")
        phase = self.phased_pipeline.phase_at(step)
        if step + 1 == min(phase.end_step, self._total_steps):  # a run may end before its phase's planned end
            self.phased_pipeline.end_training_of(phase)  # its render grid from the final field
        if step + 1 == phase.end_step and step + 1 < self._total_steps:
            self.release_finished_optimizer_state(step + 1)
            self.phased_pipeline.finish_phase(phase)  # a block's weights to their own file, out of memory
            self.save_checkpoint(step)
        return result

    def release_finished_optimizer_state(self, steps_done: int) -> List[str]:
        """Drop the Adam moments of the parameter groups whose phase has ended after ``steps_done``
        steps (the global model's once the blocks train, each finished block's): they never train
        again, and their moments (2x their parameters) would stay in memory and in every later
        checkpoint. Returns the groups released."""
        released = []
        for group, (_, phase) in self.phased_pipeline.param_group_phases().items():
            optimizer = self.optimizers.optimizers.get(group)
            if phase is not None and phase.end_step <= steps_done and optimizer is not None and optimizer.state:
                optimizer.state.clear()
                released.append(group)
        return released

    def _load_checkpoint(self) -> None:
        """Resume from the newest complete checkpoint; ignores anything that is not ``step-N.ckpt``."""
        if self.config.load_dir is not None and self.config.load_step is None:
            load_dir = Path(self.config.load_dir)
            step = latest_checkpoint_step(load_dir)
            if step is None:
                raise FileNotFoundError(f"--load-dir {load_dir}: no step-N.ckpt checkpoint in that folder.")
            self.config.load_step = step
        super()._load_checkpoint()

    def train(self) -> None:
        """Train up to ``max_num_iterations`` steps in total.

        nerfstudio trains ``max_num_iterations`` *more* steps after a resume, which would run the
        learning-rate schedule past its end; here a resumed run trains only the remaining steps.
        """
        total = self.config.max_num_iterations
        self._total_steps = total
        self.step = max(self._start_step - 1, 0)
        self.release_finished_optimizer_state(self._start_step)  # a resumed run's finished phases
        self.config.max_num_iterations = max(total - self._start_step, 0)
        try:
            super().train()
        finally:
            self.config.max_num_iterations = total
        self._report_models()

    def _report_models(self) -> None:
        """Print and save (model_report.json) every model's parameters, table size and memory."""
        pipeline = self.phased_pipeline
        report = scene_model_report(pipeline.model, self.optimizers.optimizers.values(), self.device)
        path = report_path(self.base_dir)
        write_report(report, path, {"auto_num_blocks": pipeline.plan.auto_num_blocks})
        CONSOLE.print(format_report(report))
        CONSOLE.print(f"model report saved to {path}")

    def save_checkpoint(self, step: int) -> None:
        """Save model, optimizers, schedulers and scaler atomically; keep only the latest if configured."""
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        ckpt_path = self.checkpoint_dir / checkpoint_name(step)
        pipeline = self.pipeline
        state = {
            "step": step,
            "pipeline": pipeline.state_dict(),
            "optimizers": {k: v.state_dict() for (k, v) in self.optimizers.optimizers.items()},
            "schedulers": {k: v.state_dict() for (k, v) in self.optimizers.schedulers.items()},
            "scalers": self.grad_scaler.state_dict(),
        }
        atomic_torch_save(state, ckpt_path)
        if self.config.save_only_latest_checkpoint:
            for old in self.checkpoint_dir.glob("step-*.ckpt"):
                if old != ckpt_path:
                    old.unlink()


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
        if not hasattr(global_pipeline, "global_steps"):
            raise RunError(f"{config_path} is not a scalar-nerf run.")
        blocks_json = blocks_json_path(run_dir)
        if not blocks_json.is_file():
            raise RunError(f"{blocks_json} is missing; was {run_dir} trained with scalar-nerf?")
        checkpoint_dir = run_dir / global_config.relative_model_dir
        step = latest_checkpoint_step(checkpoint_dir)
        if step is None or step + 1 < global_pipeline.global_steps:
            done = 0 if step is None else step + 1
            raise RunError(
                f"the global phase of {run_dir} is not finished "
                f"({done} of {global_pipeline.global_steps} steps checkpointed); train it first."
            )
        try:
            num_blocks = load_blocks_json(blocks_json)[0].num_blocks
        except BlockSplitError as error:
            raise RunError(str(error)) from None
        if not 0 <= self.block < num_blocks:
            raise RunError(f"--block {self.block} does not exist; {blocks_json} has blocks 0..{num_blocks - 1}.")
        pipeline = self.pipeline
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
        for name in ("block_steps", "decoder_mode"):
            if getattr(pipeline, name) == getattr(defaults, name):
                setattr(pipeline, name, getattr(global_pipeline, name))
        if pipeline.datamanager.train_num_rays_per_batch == defaults.datamanager.train_num_rays_per_batch:
            pipeline.datamanager.train_num_rays_per_batch = global_pipeline.datamanager.train_num_rays_per_batch
        pipeline.only_block = self.block
        pipeline.blocks_json = blocks_json.resolve()
        pipeline.global_checkpoint = (checkpoint_dir / checkpoint_name(step)).resolve()
        self.data = global_pipeline.datamanager.data
        if self.experiment_name is None:
            self.experiment_name = global_config.experiment_name
