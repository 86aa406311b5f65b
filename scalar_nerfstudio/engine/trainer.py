"""Trainer for SCALAR-NeRF: nerfstudio's trainer with atomic checkpoints and run-scaled schedules."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, Literal, Optional, Type

import torch
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils.rich_utils import CONSOLE

from scalar_nerfstudio.engine.schedulers import WarmupExponentialDecaySchedulerConfig

CHECKPOINT_PATTERN = re.compile(r"^step-(\d{9})\.ckpt$")
PARTIAL_SUFFIX = ".ckpt.partial"


def atomic_torch_save(state: Dict[str, Any], path: Path) -> None:
    """Write ``state`` to ``path`` so that ``path`` is either absent or complete, never half-written.

    The bytes go to a hidden file in ``path``'s parent's parent (outside the checkpoint folder, whose
    every file nerfstudio's loaders parse as ``step-N.ckpt``), are fsynced, then renamed into place.
    """
    staging = path.parent.parent / f".{path.stem}{PARTIAL_SUFFIX}"
    with open(staging, "wb") as handle:
        torch.save(state, handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(staging, path)


def latest_checkpoint_step(checkpoint_dir: Path) -> Optional[int]:
    """Largest N among the ``step-N.ckpt`` files in ``checkpoint_dir`` (other files are ignored)."""
    if not checkpoint_dir.is_dir():
        return None
    steps = [int(m.group(1)) for m in map(CHECKPOINT_PATTERN.match, os.listdir(checkpoint_dir)) if m]
    return max(steps) if steps else None


@dataclass
class ScalarTrainerConfig(TrainerConfig):
    """nerfstudio's TrainerConfig; ``--load-dir RUN/nerfstudio_models`` resumes *in* RUN."""

    _target: Type = field(default_factory=lambda: ScalarTrainer)

    def set_timestamp(self) -> None:
        """Resume into the run folder that ``load_dir`` belongs to, instead of starting a new one."""
        run_dir = self._resumed_run_dir()
        if run_dir is not None and self.timestamp == "{timestamp}":
            self.output_dir = run_dir.parent.parent.parent
            self.experiment_name = run_dir.parent.parent.name
            self.timestamp = run_dir.name
        super().set_timestamp()

    def _resumed_run_dir(self) -> Optional[Path]:
        if self.load_dir is None:
            return None
        run_dir = Path(self.load_dir).resolve().parent
        is_run = (run_dir / "config.yml").is_file() and run_dir.parent.name == self.method_name
        return run_dir if is_run else None


class ScalarTrainer(Trainer):
    """Adds to nerfstudio's Trainer: atomic checkpoints, robust resume, schedules scaled to the run."""

    config: ScalarTrainerConfig

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        self._scale_schedules_to_run()
        super().setup(test_mode=test_mode)

    def _scale_schedules_to_run(self) -> None:
        for group, settings in self.config.optimizers.items():
            scheduler = settings.get("scheduler")
            if isinstance(scheduler, WarmupExponentialDecaySchedulerConfig) and scheduler.max_steps is None:
                scheduler.max_steps = self.config.max_num_iterations
                CONSOLE.log(f"lr schedule of '{group}' spans the run: {scheduler.max_steps} steps")

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
        self.step = max(self._start_step - 1, 0)
        self.config.max_num_iterations = max(total - self._start_step, 0)
        try:
            super().train()
        finally:
            self.config.max_num_iterations = total

    def save_checkpoint(self, step: int) -> None:
        """Save model, optimizers, schedulers and scaler atomically; keep only the latest if configured."""
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        ckpt_path = self.checkpoint_dir / f"step-{step:09d}.ckpt"
        pipeline = self.pipeline.module if hasattr(self.pipeline, "module") else self.pipeline
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
    """``scalar-nerf-block``: train one block from a trained global run (not built yet)."""

    block: int = 0
    """Index of the block (as listed in the global run's blocks.json) to train."""
    global_run: Optional[Path] = None
    """config.yml of the trained global run whose decoder and block split the block starts from."""

    def set_timestamp(self) -> None:
        """Called by ``ns-train`` before anything is written: refuse instead of pretending to train."""
        raise SystemExit(
            "scalar-nerf-block: training a single block on its own is not built yet. "
            "Train the global model with `ns-train scalar-nerf --data SCENE`; block training follows in a later release."
        )
