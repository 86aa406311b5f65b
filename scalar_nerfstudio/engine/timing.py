"""Timing for benchmarks: training steps of a running trainer, and repeated calls of a function.

Used by ``scalar-nerf-benchmark`` (its runner) and the scripts in ``benchmarks/``, so that every
benchmark measures time the same way.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from typing import Any, Callable, Optional


@dataclass
class StepClock:
    """Training time of the steps run so far (:func:`time_train_iterations`)."""

    steps: int = 0
    """Steps run."""
    busy_s: float = 0.0
    """Seconds spent inside the steps (``train_iteration``) only."""
    wall_s: float = 0.0
    """Seconds from the start of the first step to the end of the latest one: the steps and everything
    the trainer does between them (callbacks such as occupancy-grid updates, logging)."""


def time_train_iterations(trainer: Any, after_step: Optional[Callable[[int, Any, StepClock], None]] = None) -> StepClock:
    """Time every step of ``trainer`` (a nerfstudio ``Trainer``) from now on.

    Wraps ``trainer.train_iteration``. ``after_step(step, result, clock)`` runs after each step, once
    the clock has been updated and outside the timed span (evaluating there is not training time); it
    may end training with ``trainer.stop_training = True``.

    Returns:
        The clock, updated in place as the trainer trains.
    """
    clock = StepClock()
    iteration = trainer.train_iteration
    first_start: Optional[float] = None

    def timed_iteration(step: int):
        nonlocal first_start
        start = time.perf_counter()
        if first_start is None:
            first_start = start
        result = iteration(step)
        end = time.perf_counter()
        clock.busy_s += end - start
        clock.wall_s = end - first_start
        clock.steps += 1
        if after_step is not None:
            after_step(step, result, clock)
        return result

    trainer.train_iteration = timed_iteration
    return clock


def median_seconds(call: Callable[[], Any], repeats: int, warmup: int = 0) -> float:
    """Median wall time of ``call()`` over ``repeats`` timed calls, after ``warmup`` untimed ones."""
    for _ in range(warmup):
        call()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return statistics.median(times)
