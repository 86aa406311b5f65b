"""Trainer for SCALAR-NeRF: nerfstudio's trainer with atomic checkpoints and run-scaled schedules."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Dict, List, Literal, Optional, Type

import torch
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine.optimizers import Optimizers
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.utils.rich_utils import CONSOLE
from torch.optim import lr_scheduler

from scalar_nerfstudio.atomic_io import atomic_torch_save
from scalar_nerfstudio.blocks.length import TrainingLength
from scalar_nerfstudio.blocks.plan import save_plan
from scalar_nerfstudio.config_checks import (
    OptionError,
    check_block_counts,
    check_block_plan,
    check_options,
    check_output_dir,
)
from scalar_nerfstudio.data.validation import SceneError, scan_scene
from scalar_nerfstudio.engine.budget import ClockFollower
from scalar_nerfstudio.engine.contract import PhasedPipeline
from scalar_nerfstudio.engine.device import resolve_device_type
from scalar_nerfstudio.engine.pace import TrainingClock
from scalar_nerfstudio.engine.preview import write_preview
from scalar_nerfstudio.engine.process_settings import apply_process_settings
from scalar_nerfstudio.engine.report import format_report, scene_model_report, write_report
from scalar_nerfstudio.engine.schedulers import WarmupExponentialDecaySchedulerConfig, retarget, warmup_steps_of
from scalar_nerfstudio.engine.threads import ThreadGovernor
from scalar_nerfstudio.pipeline import ScalarPipelineConfig
from scalar_nerfstudio.runs import (
    RunError,
    blocks_json_path,
    checkpoint_name,
    latest_checkpoint_step,
    load_run_config,
    report_path,
    run_config_path,
    save_run_config,
    upgrade_run_config,
)
from scalar_nerfstudio.seam.trainer import TrainerBase, set_progress_total, start_step

#: The template whose rate a global group restarts at in a run of one model (``global_restart_fraction``):
#: the rate a block's group starts with.
RESTART_TEMPLATES: Dict[str, str] = {"encoder": "block_encoder", "decoder": "block_decoder"}
#: Templates of global groups that decay once over the global phase, neither held nor restarted: the pose
#: corrections, which the blocks use as they are and do not follow.
ONE_DECAY_TEMPLATES = frozenset({"camera_opt"})


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

    @property
    def scalar_pipeline(self) -> ScalarPipelineConfig:
        """``pipeline`` (nerfstudio types it as its base class), checked to be a :class:`ScalarPipelineConfig`."""
        if not isinstance(self.pipeline, ScalarPipelineConfig):
            raise TypeError(f"{type(self).__name__} needs a ScalarPipelineConfig pipeline, "
                            f"not {type(self.pipeline).__name__}")
        return self.pipeline

    def setup(self, **kwargs: Any) -> Any:
        """The trainer, built after the process-wide settings for its device (``engine/process_settings.py``)."""
        apply_process_settings(resolve_device_type(self.machine.device_type))
        return super().setup(**kwargs)

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
        if run_dir is not None and self.scalar_pipeline.run_plan is None:
            self._adopt_run_plan(run_dir)
        super().set_timestamp()
        self._check_output_dir()

    # ------------------------------------------------ up-front checks (config_checks.py, data/validation.py)
    def _check_scene(self) -> None:
        """Options, then the scene (every image decoded), then the options that depend on the scene
        (number of blocks vs training images, the block split): each ends in one paragraph, no traceback."""
        self._exit_on_option_error(check_options, self)
        pipeline = self.scalar_pipeline
        dataparser = pipeline.datamanager.dataparser
        if not isinstance(dataparser, NerfstudioDataParserConfig):
            return
        data = Path(self.data if self.data is not None else getattr(pipeline.datamanager, "data", None) or dataparser.data)
        try:
            scene = scan_scene(data, eval_interval=dataparser.eval_interval, eval_mode=dataparser.eval_mode,
                               train_fraction=dataparser.train_split_fraction, downscale_factor=dataparser.downscale_factor)
        except SceneError as error:
            raise SystemExit(f"{self.method_name}: bad scene: {error}") from None
        note = scene.conversion_note(pipeline.datamanager.alpha_background)
        if note is not None:
            CONSOLE.print(f"{self.method_name}: {note}", soft_wrap=True, markup=False, highlight=False)
        self._exit_on_option_error(check_block_counts, pipeline, scene.num_train, scene.num_frames)
        if self.load_dir is None:
            self._exit_on_option_error(check_block_plan, pipeline, data)

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
            self.scalar_pipeline.run_plan = blocks_json_path(run_dir).resolve()

    def _resumed_run_dir(self) -> Optional[Path]:
        if self.load_dir is None:
            return None
        run_dir = Path(self.load_dir).resolve().parent
        is_run = run_config_path(run_dir).is_file() and run_dir.parent.name == self.method_name
        return run_dir if is_run else None


class ScalarTrainer(TrainerBase):
    """Adds to nerfstudio's Trainer: atomic checkpoints, robust resume, schedules scaled to the run.

    Its config stays as it was given (and as config.yml records it): the device it trains on ("auto":
    CUDA when there is one), whether it uses mixed precision (on CUDA only) and the steps it trains
    (:attr:`total_steps`) are held by the trainer.
    """

    config: ScalarTrainerConfig

    def __init__(self, config: ScalarTrainerConfig, local_rank: int = 0, world_size: int = 1) -> None:
        device = resolve_device_type(config.machine.device_type)  # "auto": CUDA when this process has it
        super().__init__(config, local_rank, world_size, device_type=device,
                         mixed_precision=bool(config.mixed_precision) and device == "cuda")
        self.thread_governor = ThreadGovernor(enabled=config.adapt_threads and device == "cpu")
        self._schedules: Dict[str, WarmupExponentialDecaySchedulerConfig] = {}
        self._total_steps = 0
        self.clock_follower = ClockFollower(TrainingClock(), replan=self._replan, total_steps=lambda: self._total_steps)
        """The ETA lines, and a time budget's plan made again as the pace is known (engine/budget.py)."""
        self._trained_s_before: Optional[float] = None

    @property
    def training_clock(self) -> TrainingClock:
        """Training wall-clock and pace: the ETA lines and a time budget's plan (a benchmark pauses it while it evaluates)."""
        return self.clock_follower.clock

    @training_clock.setter
    def training_clock(self, clock: TrainingClock) -> None:
        self.clock_follower.clock = clock

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        super().setup(test_mode=test_mode)
        pipeline = self.phased_pipeline
        pipeline.attach_run_dir(self.base_dir)
        self._total_steps = self._planned_total(pipeline)
        # nerfstudio's step log (ETA, % done) was set up in Trainer.setup, before the phases were
        # known, with max_num_iterations 0 (= every phase): give it the real total.
        set_progress_total(self._total_steps)
        if test_mode == "val":
            self._record_plan(pipeline)
            CONSOLE.print(pipeline.plan_report())
            CONSOLE.print(f"split saved to {blocks_json_path(self.base_dir)}")

    @property
    def total_steps(self) -> int:
        """Steps of the run once set up: ``--max-num-iterations`` when given, else every phase's (a time
        budget's as planned so far)."""
        return self._total_steps

    @property
    def _total_from_plan(self) -> bool:
        """The run trains every phase (``--max-num-iterations 0``)."""
        return self.config.max_num_iterations <= 0

    @property
    def phased_pipeline(self) -> PhasedPipeline:
        """The pipeline, checked against the trainer's contract (engine/contract.py)."""
        pipeline = self.pipeline
        if not isinstance(pipeline, PhasedPipeline):
            raise TypeError(f"{type(self).__name__} trains a pipeline that trains in phases (ScalarPipeline), not {type(pipeline).__name__}")
        return pipeline

    def _record_plan(self, pipeline: PhasedPipeline, again: bool = False) -> None:
        """Save the run's block plan as blocks.json and name it in config.yml (once; ``again``: a time budget's
        plan was measured), so that every later load of the run builds the model that was trained (K, split,
        block capacities) and trains the steps it planned."""
        path = blocks_json_path(self.base_dir)
        run_plan = self.config.scalar_pipeline.run_plan
        if not again and run_plan is not None and Path(run_plan).resolve() == path.resolve():
            return
        save_plan(pipeline.plan, path)
        self.config.scalar_pipeline.run_plan = path.resolve()
        save_run_config(self.config, self.base_dir)

    def setup_optimizers(self) -> Optimizers:
        """One optimiser per parameter group, from the template in ``optimizers`` that fits the group.

        A block's groups (``block{k}.encoder`` ...) use the ``block_encoder`` / ``appearance`` templates
        and ``block_decoder`` for a fine-tuned decoder; each schedule spans the phase its group trains in.
        The global model's rate is held after its warm-up when the pipeline says so
        (``holds_global_learning_rate``: blocks follow, ``--pipeline.lr-schedule restart``); in a run of
        one model it is held and then restarts at the rate of the group's :data:`RESTART_TEMPLATES`
        template (``global_restart_fraction``, ``--pipeline.one-model-restart``). The pose corrections
        (:data:`ONE_DECAY_TEMPLATES`) decay once over the global phase.
        """
        _ = self.phased_pipeline  # checked against the contract before nerfstudio's groups are read
        param_groups = self.pipeline.get_param_groups()
        config: Dict[str, Any] = {}
        self._schedules = {}
        for group in param_groups:
            settings = dict(self.config.optimizers[self._group_template(group)])
            schedule = self._schedule_of(group)
            if schedule is not None:
                settings["scheduler"] = self._schedules[group] = schedule
            config[group] = settings
        return Optimizers(config, param_groups)

    def _group_template(self, group: str) -> str:
        template, _ = self.phased_pipeline.param_group_phases().get(group, (group, None))
        return self._optimizer_template(group, template)

    def _schedule_of(self, group: str, warmup_steps: Optional[int] = None) -> Optional[WarmupExponentialDecaySchedulerConfig]:
        """The schedule of ``group``'s learning rate over the phase it trains in (None: its template has
        another kind of scheduler). ``warmup_steps``: keep this warm-up (a phase whose length changed)."""
        pipeline = self.phased_pipeline
        template, phase = pipeline.param_group_phases().get(group, (group, None))
        template = self._optimizer_template(group, template)
        settings = self.config.optimizers[template]
        scheduler = settings.get("scheduler")
        if not isinstance(scheduler, WarmupExponentialDecaySchedulerConfig):
            return None
        start, length = (phase.start_step, phase.num_steps) if phase is not None else (0, self._planned_total(pipeline))
        is_global = phase is not None and phase.block is None
        follows_global = is_global and template not in ONE_DECAY_TEMPLATES
        held = follows_global and pipeline.holds_global_learning_rate
        restart = pipeline.global_restart_fraction if follows_global else 0.0
        restart_factor = 1.0
        if restart > 0:  # one model: restart at the rate a block's group starts with
            restart_template = self._optimizer_template(group, RESTART_TEMPLATES.get(template, template))
            base_lr = float(settings["optimizer"].lr)  # 0: a frozen group stays frozen
            restart_factor = float(self.config.optimizers[restart_template]["optimizer"].lr) / base_lr if base_lr > 0 else 1.0
        return replace(scheduler, start_step=start, max_steps=scheduler.max_steps or max(length, 1),
                       final_factor=1.0 if held else scheduler.final_factor, restart_fraction=restart,
                       restart_factor=restart_factor, warmup_steps=warmup_steps if warmup_steps is not None else scheduler.warmup_steps)

    def _planned_total(self, pipeline: PhasedPipeline) -> int:
        """Steps of the run: ``--max-num-iterations`` when given, else every phase's."""
        return pipeline.total_steps if self._total_from_plan else self.config.max_num_iterations

    def _replan(self, length: TrainingLength, started_through: int) -> None:
        """Train for ``length`` from now on: the phases, the learning-rate schedules (a phase that has started
        keeps its warm-up), the run's total and its recorded plan follow it."""
        pipeline = self.phased_pipeline
        pipeline.set_length(length)
        for group, scheduler in self.optimizers.schedulers.items():
            old = self._schedules.get(group)
            if old is None or not isinstance(scheduler, lr_scheduler.LambdaLR):
                continue
            started = old.start_step <= started_through
            new = self._schedule_of(group, warmup_steps=warmup_steps_of(old) if started else None)
            if new is not None and new != old:
                retarget(scheduler, new)
                self._schedules[group] = new
        self._total_steps = self._planned_total(pipeline)
        set_progress_total(self._total_steps)
        self._record_plan(pipeline, again=True)

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
        self.clock_follower.after_step(self.phased_pipeline, step)
        if step + 1 >= self._total_steps:
            self.stop_training = True  # a time budget's loop runs to its longest possible plan
        every = self.config.steps_per_preview
        if every > 0 and ((step + 1) % every == 0 or step + 1 == self._total_steps):
            path, psnr = write_preview(self.pipeline, self.base_dir, step=step, max_size=self.config.preview_max_size)
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

    def resume_step(self, load_dir: Path) -> Optional[int]:
        """Resume from the newest complete checkpoint; ignores anything that is not ``step-N.ckpt``."""
        step = latest_checkpoint_step(load_dir)
        if step is None:
            raise FileNotFoundError(f"--load-dir {load_dir}: no step-N.ckpt checkpoint in that folder.")
        return step

    def checkpoint_loaded(self, step: Optional[int]) -> None:
        """Read the training time the resumed run had spent (its checkpoint's ``training_s``)."""
        if self.config.load_dir is not None and step is not None:
            path = Path(self.config.load_dir) / checkpoint_name(step)
            trained = torch.load(path, map_location="cpu", weights_only=True, mmap=True).get("training_s")
            self._trained_s_before = None if trained is None else float(trained)

    def train(self) -> None:
        """Train up to :attr:`total_steps` steps in total.

        nerfstudio trains ``max_num_iterations`` *more* steps after a resume, which would run the
        learning-rate schedule past its end; here a resumed run trains only the remaining steps.
        """
        total = self._planned_total(self.phased_pipeline)
        self._total_steps = total
        first = start_step(self)
        self.step = max(first - 1, 0)
        self.release_finished_optimizer_state(first)  # a resumed run's finished phases
        # a new run has trained for 0 s; a resumed one for what its checkpoint says (None: a checkpoint without it)
        self.training_clock.start(first, self._trained_s_before if first > 0 else 0.0)
        # A time budget waiting for its pace may train up to its longest plan; train_iteration stops it at the planned end.
        self.train_for(max(self._loop_bound(total) - first, 0))
        self._report_models()

    def _report_models(self) -> None:
        """Print and save (model_report.json) every model's parameters, table size and memory."""
        pipeline = self.phased_pipeline
        report = scene_model_report(self.pipeline.model, self.optimizers.optimizers.values(), self.device)
        path = report_path(self.base_dir)
        write_report(report, path, {"auto_num_blocks": pipeline.plan.auto_num_blocks})
        CONSOLE.print(format_report(report))
        CONSOLE.print(f"model report saved to {path}")

    def _loop_bound(self, total: int) -> int:
        """The steps nerfstudio's loop may run: ``total``, or, while a time budget's plan is not measured, its
        longest plan (every phase at the most steps a phase may have)."""
        length = self.phased_pipeline.length
        if length.final or not self._total_from_plan:
            return total
        most = self.phased_pipeline.length_settings().max_steps
        return max(total, most * (1 + self.phased_pipeline.num_blocks_following))

    def save_checkpoint(self, step: int) -> None:
        """Save model, optimizers, schedulers and scaler atomically; keep only the latest if configured.
        A run stopped at its planned end (nerfstudio then names the step after its last) is saved as its last step."""
        total = self._total_steps
        if self.stop_training and step >= total > 0:
            step = total - 1
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        ckpt_path = self.checkpoint_dir / checkpoint_name(step)
        pipeline = self.pipeline
        state = {
            "step": step,
            "pipeline": pipeline.state_dict(),
            "optimizers": {k: v.state_dict() for (k, v) in self.optimizers.optimizers.items()},
            "schedulers": {k: v.state_dict() for (k, v) in self.optimizers.schedulers.items()},
            "scalers": self.grad_scaler.state_dict(),
            "training_s": self.training_clock.elapsed_s(),  # a resumed time budget counts what was spent
        }
        atomic_torch_save(state, ckpt_path)
        if self.config.save_only_latest_checkpoint:
            for old in self.checkpoint_dir.glob("step-*.ckpt"):
                if old != ckpt_path:
                    old.unlink()
