"""Learning-rate schedule of the paper (Sec. 4): linear warm-up, then exponential decay.

Lengths are fractions of the run, so a short CPU run warms up and decays like the paper's 200k
iterations. The multiplier is computed in plain Python floats: nerfstudio's own
``ExponentialDecayScheduler`` returns numpy scalars, which end up in checkpoints and make
``torch.load(weights_only=True)`` (torch >= 2.6's default) refuse them (nerfstudio #3683).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional, Type

from nerfstudio.engine.schedulers import Scheduler, SchedulerConfig
from torch.optim import Optimizer, lr_scheduler


@dataclass
class WarmupExponentialDecaySchedulerConfig(SchedulerConfig):
    """Linear warm-up over ``warmup_fraction`` of the run, exponential decay to ``final_factor`` x lr."""

    _target: Type = field(default_factory=lambda: WarmupExponentialDecayScheduler)
    warmup_fraction: float = 0.025
    """Share of the run spent warming up (the paper: 5k of 200k iterations)."""
    final_factor: float = 0.1
    """Learning rate at the end of the run, relative to the initial one."""
    max_steps: Optional[int] = None
    """Length of the schedule in steps; None: filled in by the trainer (the length of the phase the
    parameter group trains in)."""
    start_step: int = 0
    """Global step at which the schedule starts (a block's phase starts after the global one)."""


def warmup_exponential_decay_factor(step: int, max_steps: int, warmup_fraction: float, final_factor: float) -> float:
    """Multiplier of the initial learning rate at ``step`` (a Python float in (0, 1])."""
    warmup_steps = max(int(round(warmup_fraction * max_steps)), 0)
    if warmup_steps > 0 and step < warmup_steps:
        return max(step, 1) / warmup_steps
    decay_steps = max(max_steps - warmup_steps, 1)
    progress = min(max((step - warmup_steps) / decay_steps, 0.0), 1.0)
    return math.exp(math.log(final_factor) * progress)


class WarmupExponentialDecayScheduler(Scheduler):
    """Builds the ``LambdaLR`` for :class:`WarmupExponentialDecaySchedulerConfig`."""

    config: WarmupExponentialDecaySchedulerConfig

    def get_scheduler(self, optimizer: Optimizer, lr_init: float) -> lr_scheduler.LRScheduler:
        if self.config.max_steps is None:
            raise ValueError("WarmupExponentialDecaySchedulerConfig.max_steps is unset; the trainer fills it in.")
        max_steps, warmup, final = self.config.max_steps, self.config.warmup_fraction, self.config.final_factor
        start = self.config.start_step
        return lr_scheduler.LambdaLR(
            optimizer, lr_lambda=lambda step: warmup_exponential_decay_factor(step - start, max_steps, warmup, final)
        )
