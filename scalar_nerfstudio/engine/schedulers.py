"""Learning-rate schedule of the paper (Sec. 4): linear warm-up, then exponential decay.

Lengths are fractions of the run, so a short CPU run warms up and decays like the paper's 200k
iterations. The multiplier is computed in plain Python floats: nerfstudio's own
``ExponentialDecayScheduler`` returns numpy scalars, which end up in checkpoints and make
``torch.load(weights_only=True)`` (torch >= 2.6's default) refuse them (nerfstudio #3683).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional, Type

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
    restart_fraction: float = 0.0
    """0: one warm-up and decay over ``max_steps``. Otherwise the schedule holds its rate after the
    warm-up for this share of ``max_steps``, then warms up again to ``restart_factor`` x lr and decays
    over the rest (a run of one model following the global-then-block schedule of a run with blocks)."""
    restart_factor: float = 1.0
    """Learning rate after the restart, relative to the initial one."""
    warmup_steps: Optional[int] = None
    """Steps of the warm-up; None: ``warmup_fraction`` of ``max_steps``. Set by the trainer when a time
    budget's plan changes the length of a phase that has started, so that its warm-up stays as it was."""


def warmup_exponential_decay_factor(
    step: int, max_steps: int, *, warmup_fraction: float, final_factor: float, warmup_steps: Optional[int] = None
) -> float:
    """Multiplier of the initial learning rate at ``step`` (a Python float in (0, 1]); ``warmup_steps``
    None: ``warmup_fraction`` of ``max_steps``."""
    if warmup_steps is None:
        warmup_steps = max(int(round(warmup_fraction * max_steps)), 0)
    warmup_steps = min(max(warmup_steps, 0), max_steps)
    if warmup_steps > 0 and step < warmup_steps:
        return max(step, 1) / warmup_steps
    decay_steps = max(max_steps - warmup_steps, 1)
    progress = min(max((step - warmup_steps) / decay_steps, 0.0), 1.0)
    return math.exp(math.log(final_factor) * progress)


def hold_then_restart_factor(
    step: int, max_steps: int, *, warmup_fraction: float, final_factor: float, restart_fraction: float, restart_factor: float,
    warmup_steps: Optional[int] = None,
) -> float:
    """Multiplier of the initial learning rate at ``step`` of a schedule that restarts once.

    Steps before ``round(restart_fraction * max_steps)`` warm up and then hold the rate (factor 1);
    from there the rest warms up again and decays to ``final_factor``, all scaled by ``restart_factor``
    (each part as :func:`warmup_exponential_decay_factor` over its own length). ``restart_fraction``
    0 (or a restart at step 0 or at the end) is the plain schedule. ``warmup_steps`` (None: the
    fraction) is the first warm-up's length.
    """
    restart = int(round(restart_fraction * max_steps))
    if restart <= 0 or restart >= max_steps:
        return warmup_exponential_decay_factor(step, max_steps, warmup_fraction=warmup_fraction, final_factor=final_factor,
                                               warmup_steps=warmup_steps)
    if step < restart:
        return warmup_exponential_decay_factor(step, restart, warmup_fraction=warmup_fraction, final_factor=1.0, warmup_steps=warmup_steps)
    return restart_factor * warmup_exponential_decay_factor(step - restart, max_steps - restart, warmup_fraction=warmup_fraction,
                                                            final_factor=final_factor)


def schedule_function(config: WarmupExponentialDecaySchedulerConfig) -> Callable[[int], float]:
    """The multiplier of the initial learning rate as a function of the run's step, for ``config``.

    Raises:
        ValueError: ``max_steps`` is unset, or the restart settings are out of range.
    """
    if config.max_steps is None:
        raise ValueError("WarmupExponentialDecaySchedulerConfig.max_steps is unset; the trainer fills it in.")
    max_steps, warmup, final, warmup_steps = config.max_steps, config.warmup_fraction, config.final_factor, config.warmup_steps
    start, restart, factor = config.start_step, config.restart_fraction, config.restart_factor
    if not 0.0 <= restart < 1.0 or not (math.isfinite(factor) and factor >= 0):
        raise ValueError(f"restart_fraction must lie in [0, 1) and restart_factor be finite and >= 0, got {restart} and {factor}")
    return lambda step: hold_then_restart_factor(step - start, max_steps, warmup_fraction=warmup, final_factor=final,
                                                 restart_fraction=restart, restart_factor=factor, warmup_steps=warmup_steps)


def warmup_steps_of(config: WarmupExponentialDecaySchedulerConfig) -> int:
    """The warm-up length, in steps, of the schedule ``config`` (its ``max_steps`` set)."""
    max_steps = int(config.max_steps or 0)
    if config.warmup_steps is not None:
        return min(max(config.warmup_steps, 0), max_steps)
    return max(int(round(config.warmup_fraction * max_steps)), 0)


def retarget(scheduler: lr_scheduler.LambdaLR, config: WarmupExponentialDecaySchedulerConfig) -> None:
    """Make ``scheduler`` (built from this module's config) follow ``config`` from its next step on,
    keeping its step count: a time budget's plan has changed the length of the phase it serves."""
    scheduler.lr_lambdas = [schedule_function(config) for _ in scheduler.lr_lambdas]


class WarmupExponentialDecayScheduler(Scheduler):
    """Builds the ``LambdaLR`` for :class:`WarmupExponentialDecaySchedulerConfig`."""

    config: WarmupExponentialDecaySchedulerConfig

    def get_scheduler(self, optimizer: Optimizer, lr_init: float) -> lr_scheduler.LRScheduler:
        return lr_scheduler.LambdaLR(optimizer, lr_lambda=schedule_function(self.config))
