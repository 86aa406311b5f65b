"""The training clock: how long a run has trained, how fast it steps, and when it will end.

:class:`TrainingClock` counts the wall-clock of training (everything between the run's first step and
its latest: steps, callbacks, previews, checkpoints), less what a caller does inside a ``paused()``
block (a benchmark's evaluations). It keeps the time of every recent step, so that the pace is read
over the latest steps, after the first ones (slower: the occupancy grid has not yet learnt where the
scene is empty). A time budget is planned from :meth:`TrainingClock.pace` once :func:`pace_is_due`
says enough steps were seen; the ETA lines of the training log come from :func:`eta_line`.
"""

from __future__ import annotations

import time
from collections import deque
from contextlib import contextmanager
from typing import Callable, Deque, Iterator, Optional, Tuple

from scalar_nerfstudio.blocks.length import format_duration

__all__ = [
    "BLOCK_CALIBRATION_STEPS", "CALIBRATION_SKIP_STEPS", "CALIBRATION_STEPS", "REPLAN_AT", "TrainingClock", "calibration_start",
    "eta_line", "pace_is_due",
]

#: The pace is not read over a run's first steps: the occupancy grid warms up for 128 steps and
#: prunes empty space over its first updates, and steps then get faster.
CALIBRATION_SKIP_STEPS = 160
#: Steps after those over which the pace is measured.
CALIBRATION_STEPS = 80
#: Shares of a time budget at which a global phase (or a run of blocks only, in its first phase) is planned
#: again from the pace of its latest steps: steps get dearer as the model learns where the scene is.
REPLAN_AT = (0.25, 0.5, 0.75)
#: A time budget's blocks are planned once more after the first block has trained this many steps (or a
#: third of its steps), at that block's own pace.
BLOCK_CALIBRATION_STEPS = 60


class TrainingClock:
    """Training wall-clock with pauses, and the times of the latest steps."""

    def __init__(self, *, now: Callable[[], float] = time.perf_counter, history: int = 512) -> None:
        self._now = now
        self._start: Optional[float] = None
        self._before_s: Optional[float] = None
        self._start_steps = 0
        self._paused_s = 0.0
        self._pause_started: Optional[float] = None
        self._marks: Deque[Tuple[int, float]] = deque(maxlen=history)
        """(steps done, training seconds) after each recent step."""

    def start(self, steps_done: int = 0, trained_s: Optional[float] = None) -> None:
        """Start counting: the first step of this process begins now, ``steps_done`` steps were trained
        before, in ``trained_s`` seconds of training (a resumed run's, from its checkpoint; None: not known,
        and :meth:`elapsed_s` counts this process only)."""
        self._start = self._now()
        self._before_s = trained_s
        self._start_steps = steps_done
        self._marks.clear()
        self._marks.append((steps_done, self.elapsed_s()))

    @property
    def knows_earlier_time(self) -> bool:
        """Whether :meth:`elapsed_s` includes the training time of the steps before :meth:`start`."""
        return self._before_s is not None

    @property
    def started(self) -> bool:
        return self._start is not None

    def elapsed_s(self) -> float:
        """Training seconds since :meth:`start`, less paused time, plus those before it when known."""
        if self._start is None:
            return 0.0
        paused = self._paused_s + (self._now() - self._pause_started if self._pause_started is not None else 0.0)
        return (self._before_s or 0.0) + self._now() - self._start - paused

    @contextmanager
    def paused(self) -> Iterator[None]:
        """What runs inside does not count as training time."""
        if self._pause_started is not None:  # nested: the outer pause counts
            yield
            return
        self._pause_started = self._now()
        try:
            yield
        finally:
            self._paused_s += self._now() - self._pause_started
            self._pause_started = None

    def mark(self, steps_done: int) -> None:
        """Record that ``steps_done`` steps (of the whole run) are done now."""
        if self._start is None:
            self.start(max(steps_done - 1, 0))
        self._marks.append((steps_done, self.elapsed_s()))

    @property
    def steps_seen(self) -> int:
        """Steps trained since :meth:`start` (not only those whose times are kept)."""
        return self._marks[-1][0] - self._start_steps if self._marks else 0

    def pace(self, *, last_steps: Optional[int] = None, since_steps: Optional[int] = None) -> Optional[float]:
        """Steps per second over the latest ``last_steps`` steps, or since the run had done ``since_steps``
        (the oldest step kept if earlier; all kept steps by default). None before two marks."""
        marks = list(self._marks)
        if len(marks) < 2:
            return None
        first = 0
        if since_steps is not None:
            first = next((i for i, (steps, _) in enumerate(marks) if steps >= since_steps), len(marks) - 2)
        if last_steps is not None:
            first = max(first, len(marks) - 1 - last_steps)
        first = min(first, len(marks) - 2)
        steps = marks[-1][0] - marks[first][0]
        seconds = marks[-1][1] - marks[first][1]
        return steps / seconds if seconds > 0 and steps > 0 else None


def pace_is_due(steps_seen: int, elapsed_s: float, budget_s: Optional[float]) -> bool:
    """Whether enough of this process's steps were seen to read the pace: :data:`CALIBRATION_SKIP_STEPS`
    + :data:`CALIBRATION_STEPS`, or (a short budget) a tenth of the budget and 20 steps."""
    if steps_seen >= CALIBRATION_SKIP_STEPS + CALIBRATION_STEPS:
        return True
    return budget_s is not None and elapsed_s >= 0.1 * budget_s and steps_seen >= 20


def calibration_start(steps_seen: int) -> int:
    """How many of the seen steps to leave out of the pace: the first :data:`CALIBRATION_SKIP_STEPS`,
    or the first half of a short calibration."""
    return CALIBRATION_SKIP_STEPS if steps_seen >= CALIBRATION_SKIP_STEPS + CALIBRATION_STEPS else steps_seen // 2


def eta_line(steps_left: int, pace_steps_per_s: Optional[float], *, now: Callable[[], float] = time.time) -> str:
    """``about 12 min 05 s left (ends about 22:41)`` for ``steps_left`` steps at ``pace_steps_per_s``."""
    if pace_steps_per_s is None or pace_steps_per_s <= 0:
        return f"{steps_left} steps left"
    return time_left_line(steps_left / pace_steps_per_s, now=now)


def time_left_line(seconds: float, *, now: Callable[[], float] = time.time) -> str:
    """``about 12 min 05 s left (ends about 22:41)`` for ``seconds`` left."""
    end = time.strftime("%H:%M", time.localtime(now() + seconds))
    return f"about {format_duration(seconds)} left (ends about {end})"
