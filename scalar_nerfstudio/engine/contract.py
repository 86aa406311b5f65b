"""The contract between :class:`~scalar_nerfstudio.engine.trainer.ScalarTrainer` and its pipeline.

nerfstudio's trainer knows a pipeline only through ``get_train_loss_dict``, ``get_param_groups`` and
``get_training_callbacks``. Training in phases needs a little more, and this Protocol names it, so
the trainer asks for it once (``isinstance``) instead of guessing attributes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Protocol, Tuple, runtime_checkable


@dataclass(frozen=True)
class Phase:
    """A contiguous range of training steps that trains one model."""

    block: Optional[int]
    """None: the global model; k: block k's local model."""
    start_step: int
    num_steps: int

    @property
    def end_step(self) -> int:
        """First step after the phase."""
        return self.start_step + self.num_steps

    @property
    def name(self) -> str:
        return "global" if self.block is None else f"block {self.block}"


@runtime_checkable
class PhasedPipeline(Protocol):
    """A pipeline that trains in phases (ScalarPipeline)."""

    plan: Any
    """The run's block plan (``blocks/plan.py``: ``BlockPlan``), saved into the run folder."""
    phases: List[Phase]
    """The training phases, in order."""

    @property
    def length(self) -> Any:
        """How long the run trains (``blocks/length.py``: ``TrainingLength``)."""
        ...

    def set_length(self, length: Any) -> None:
        """Train for ``length`` (a time budget's measured plan) from now on: the phases follow it."""
        ...

    def length_settings(self) -> Any:
        """The options the run's length is planned from (``blocks/length.py``: ``LengthSettings``)."""
        ...

    @property
    def num_blocks_following(self) -> int:
        """Blocks that train after the global model, here or in scalar-nerf-block runs."""
        ...

    @property
    def total_steps(self) -> int:
        """Steps of all phases together."""
        ...

    def phase_at(self, step: int) -> Phase:
        """The phase that trains at ``step``."""
        ...

    def end_training_of(self, phase: Phase) -> None:
        """Called once when ``phase`` has trained its last step (the run's last phase included),
        before :meth:`finish_phase` and the checkpoint: its model finishes its training."""
        ...

    def finish_phase(self, phase: Phase) -> None:
        """Called once when a phase other than the run's last has trained its last step, after
        :meth:`end_training_of`, before the checkpoint written then."""
        ...

    def attach_run_dir(self, run_dir: Any) -> None:
        """The run folder the pipeline keeps its per-block files in."""
        ...

    def param_group_phases(self) -> Dict[str, Tuple[str, Optional[Phase]]]:
        """For each optimiser parameter group: (its template key in ``optimizers``, its phase)."""
        ...

    @property
    def holds_global_learning_rate(self) -> bool:
        """The global phase's groups keep their learning rate after the warm-up (blocks follow them)."""
        ...

    @property
    def global_restart_fraction(self) -> float:
        """Share of the global model's steps after which its rates restart at the block templates'
        (a run of one model); 0: no restart."""
        ...

    def plan_report(self) -> str:
        """The split, automatic K, block capacities and phases, for the training log."""
        ...
