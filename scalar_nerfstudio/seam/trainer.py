"""nerfstudio's trainer, where scalar-nerf reaches past its public methods (``nerfstudio/engine/trainer.py``
and ``nerfstudio/utils/writer.py`` of nerfstudio 1.1.5).

What is relied on, each checked by ``tests/test_nerfstudio_seam.py``:

* ``Trainer.__init__`` reads ``config.machine.device_type`` and ``config.mixed_precision``, and no other
  method of ``Trainer`` reads them;
* ``Trainer.train`` reads its loop's length from ``config.max_num_iterations`` once, as it starts, and
  runs ``range(self._start_step, self._start_step + length)``, calling ``train_iteration`` once a step;
* ``Trainer.setup`` calls the private ``Trainer._load_checkpoint``, which loads
  ``load_dir/step-{load_step:09d}.ckpt`` (the largest step there when ``load_step`` is None) and sets the
  private ``_start_step`` to the step after it;
* nerfstudio's step log (ETA, % done) takes the run's total steps from ``writer.GLOBAL_BUFFER["max_iter"]``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.utils import writer

__all__ = ["TrainerBase", "set_progress_total", "start_step"]

#: The key of the run's total steps in nerfstudio's writer buffer.
PROGRESS_TOTAL_KEY = "max_iter"


def set_progress_total(steps: int) -> None:
    """Make nerfstudio's step log (its ETA and % done) count to ``steps``: it was given the total when the
    trainer was set up (``writer.setup_local_writer``), before a run's phases or time budget were planned."""
    writer.GLOBAL_BUFFER[PROGRESS_TOTAL_KEY] = steps


def start_step(trainer: Trainer) -> int:
    """The step ``trainer`` trains first: 0, or the step after the checkpoint it resumed from."""
    return int(trainer._start_step)


class TrainerBase(Trainer):
    """nerfstudio's ``Trainer``, with the parts scalar-nerf changes as arguments and methods of their own.

    * built with the device and mixed precision it trains with (``device_type``, ``mixed_precision``),
      while its config keeps what was asked (``auto``, say);
    * :meth:`train_for` runs nerfstudio's training loop for a number of steps, while the config keeps
      its ``max_num_iterations``;
    * :meth:`resume_step` chooses the checkpoint ``--load-dir`` resumes from, :meth:`checkpoint_loaded`
      is told which one was loaded.
    """

    def __init__(self, config: TrainerConfig, local_rank: int = 0, world_size: int = 1, *, device_type: str,
                 mixed_precision: bool) -> None:
        asked = (config.machine.device_type, config.mixed_precision)
        config.machine.device_type, config.mixed_precision = device_type, mixed_precision  # type: ignore[assignment]
        try:
            super().__init__(config, local_rank, world_size)
        finally:  # nerfstudio read them in its __init__ only
            config.machine.device_type, config.mixed_precision = asked
        self._asked_iterations: Optional[int] = None

    # ------------------------------------------------------------------- the training loop's length
    def train_for(self, num_iterations: int) -> None:
        """nerfstudio's ``Trainer.train``, its loop ``num_iterations`` steps long from :func:`start_step`
        (it may stop earlier: ``stop_training``). nerfstudio reads the length from
        ``config.max_num_iterations`` as its loop starts: the config holds ``num_iterations`` until the
        first step (or the loop's end), then its own value again."""
        self._asked_iterations = self.config.max_num_iterations
        self.config.max_num_iterations = num_iterations
        try:
            Trainer.train(self)
        finally:
            self._restore_iterations()

    def train_iteration(self, step: int) -> Any:
        """nerfstudio's step (the first puts back the config's ``max_num_iterations``: :meth:`train_for`)."""
        self._restore_iterations()
        return super().train_iteration(step)

    def _restore_iterations(self) -> None:
        if self._asked_iterations is not None:
            self.config.max_num_iterations, self._asked_iterations = self._asked_iterations, None

    # ------------------------------------------------------------------------------ resuming
    def resume_step(self, load_dir: Path) -> Optional[int]:
        """The step of the checkpoint in ``load_dir`` that ``--load-dir`` resumes from when ``--load-step``
        is not given; None: nerfstudio's choice (the largest step of any file there)."""
        return None

    def checkpoint_loaded(self, step: Optional[int]) -> None:
        """Called once nerfstudio has loaded the checkpoint: ``step``, that of the ``--load-dir`` checkpoint
        it loaded (None: none was loaded from ``--load-dir``, or nerfstudio chose which)."""

    def _load_checkpoint(self) -> None:
        """nerfstudio's private step of ``Trainer.setup``, between :meth:`resume_step` and
        :meth:`checkpoint_loaded`; ``config.load_step`` is the chosen step only while nerfstudio loads it."""
        load_dir, asked = self.config.load_dir, self.config.load_step
        step = asked
        if load_dir is not None and asked is None:
            step = self.resume_step(Path(load_dir))
        self.config.load_step = step
        try:
            super()._load_checkpoint()
        finally:
            self.config.load_step = asked
        self.checkpoint_loaded(step if load_dir is not None else None)
