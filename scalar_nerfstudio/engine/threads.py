"""Torch's thread count, adapted to the cores that other processes leave free (issue 18).

Two CPU trainings started together on 2 cores, each with torch's default 2 OpenMP threads, each run
at about 0.2x of a lone run: libgomp's threads (torch's and the hash-grid kernel's, which uses
``at::get_num_threads()``) spin-wait at every barrier for a thread whose core the other process
holds. ``OMP_WAIT_POLICY`` cannot help: it is read when torch is imported, before this plugin loads.
A run on 1 thread beside another training keeps nearly its full per-core speed, so the trainer asks a
:class:`ThreadGovernor` once per step; every few seconds it measures how many cores other processes
kept busy and sets torch's thread count to the cores left free.

Measurement: over the interval since the last sample, the machine's busy CPU time (``/proc/stat``,
restricted to the CPUs this process may run on) minus this process's own CPU time (every thread of
it, so our own spinning threads never count as "others"), divided by the wall time: the cores used by
other processes. The decision itself is :func:`choose_threads`, a pure function.

Where ``/proc/stat`` cannot be read (macOS, Windows) the governor does nothing; an explicit
``OMP_NUM_THREADS`` in the environment is the user's choice and turns it off as well.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Collection, Mapping, Optional

import torch

PROC_STAT = Path("/proc/stat")

#: ``/proc/stat`` columns after the name that count as busy: user, nice, system, (idle, iowait skipped),
#: irq, softirq, steal. guest / guest_nice are already inside user / nice.
_BUSY_COLUMNS = (0, 1, 2, 5, 6, 7)


@dataclass(frozen=True)
class CpuSample:
    """Cumulative CPU times at one moment (all in seconds of CPU time, summed over cores)."""

    busy_s: float
    """Busy time of the usable CPUs since boot (every process on them, this one included)."""
    own_s: float
    """CPU time of this process so far (user + system, all its threads)."""
    cores: int
    """Number of CPUs this process may run on."""


def usable_cpus() -> Optional[frozenset[int]]:
    """The CPU ids this process may run on (its affinity mask); None where the OS does not say."""
    getaffinity = getattr(os, "sched_getaffinity", None)
    if getaffinity is None:
        return None
    return frozenset(getaffinity(0))


def parse_proc_stat_busy(text: str, cpus: Optional[Collection[int]] = None) -> Optional[int]:
    """Busy jiffies in the text of ``/proc/stat``: user + nice + system + irq + softirq + steal.

    Args:
        text: the file's contents.
        cpus: sum the per-CPU lines (``cpuN``) of these CPU ids; None: the machine's total (``cpu``).

    Returns:
        Busy jiffies since boot (ticks of ``SC_CLK_TCK`` per second), or None when the lines are missing.
    """
    total: Optional[int] = None
    wanted = None if cpus is None else set(cpus)
    for line in text.splitlines():
        if not line.startswith("cpu"):
            continue
        name, *columns = line.split()
        if wanted is None:
            if name != "cpu":
                continue
        elif name == "cpu" or int(name[3:]) not in wanted:
            continue
        values = [int(v) for v in columns]
        busy = sum(values[i] for i in _BUSY_COLUMNS if i < len(values))
        total = busy if total is None else total + busy
        if wanted is None:
            break
    return total


def read_cpu_sample(stat_path: Path = PROC_STAT) -> Optional[CpuSample]:
    """The machine's busy CPU time, this process's CPU time and the usable cores, now.

    Only the CPUs in this process's affinity mask are counted (a run pinned to 2 CPUs of a large
    machine measures those 2). Returns None where ``stat_path`` cannot be read or parsed (not Linux).
    """
    try:
        text = stat_path.read_text()
    except OSError:
        return None
    cpus = usable_cpus()
    machine_cpus = sum(1 for line in text.splitlines() if line.startswith("cpu") and line[3:4].isdigit())
    pinned = cpus is not None and len(cpus) < machine_cpus
    try:
        busy = parse_proc_stat_busy(text, cpus if pinned else None)
    except (ValueError, IndexError):
        return None
    if busy is None:
        return None
    cores = len(cpus) if cpus is not None else (os.cpu_count() or 1)
    ticks = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    return CpuSample(busy_s=busy / ticks, own_s=time.process_time(), cores=cores)


def other_busy_cores(before: CpuSample, after: CpuSample, elapsed_s: float) -> float:
    """Cores kept busy by other processes between two samples ``elapsed_s`` seconds of wall time apart.

    (machine busy - own CPU) / elapsed, at least 0 (``/proc/stat`` counts in whole ticks, so a short
    interval can come out slightly below this process's precise CPU time).
    """
    if elapsed_s <= 0:
        raise ValueError(f"elapsed_s must be > 0, not {elapsed_s}")
    others = (after.busy_s - before.busy_s) - (after.own_s - before.own_s)
    return max(others / elapsed_s, 0.0)


def choose_threads(cores: int, other_busy_cores: float, current: int, *, min_threads: int = 1,
                   max_threads: Optional[int] = None, up_margin: float = 0.25) -> int:
    """The thread count to use next, from the cores other processes keep busy.

    The target is the free cores, ``cores - other_busy_cores``, rounded to the nearest integer and
    clamped to [``min_threads``, ``max_threads``]. Going down happens as soon as the rounded target is
    below ``current`` (a thread without a core of its own makes every OpenMP barrier spin-wait, which
    costs far more than a missing thread); going up needs ``up_margin`` cores more than the rounding
    boundary, so a load hovering there does not make the count flip back and forth.

    Args:
        cores: CPUs this process may run on.
        other_busy_cores: cores other processes used over the last interval (>= 0, may be fractional).
        current: the thread count now.
        min_threads: never fewer threads (>= 1).
        max_threads: never more threads; None: ``cores``.
        up_margin: extra free cores (0..0.5) needed to add a thread.

    Returns:
        The thread count in [min_threads, max_threads] (``current`` when nothing should change).
    """
    low = max(1, min_threads)
    high = max(low, cores if max_threads is None else max_threads)
    free = cores - max(other_busy_cores, 0.0)
    down = min(max(math.floor(free + 0.5), low), high)
    if down < current:
        return down
    up = min(max(math.floor(free + 0.5 - up_margin), low), high)
    if up > current:
        return up
    return min(max(current, low), high)


def _explicit_thread_count(environ: Mapping[str, str]) -> bool:
    return bool(environ.get("OMP_NUM_THREADS", "").strip())


@dataclass
class ThreadGovernor:
    """Every ``every_seconds``, set torch's thread count to the cores that other processes leave free.

    Call :meth:`update` once per training step: when no sample is due it only compares two times.
    A change is applied when ``confirmations`` samples in a row ask for it (in the same direction),
    and logged in one line. Disabled (``update`` does nothing) when ``enabled`` is False, when the
    environment sets ``OMP_NUM_THREADS`` (the user chose), or where ``/proc/stat`` cannot be read.

    The readers, the setter, the clock and the log are arguments so that tests can replace them.
    """

    enabled: bool = True
    """False: never change the thread count."""
    every_seconds: float = 5.0
    """Seconds of wall time between samples."""
    min_threads: int = 1
    """Never fewer threads."""
    max_threads: Optional[int] = None
    """Never more threads; None: torch's thread count when the governor is made, at most the usable
    cores (so a lone run keeps torch's default, which is one thread per physical core)."""
    confirmations: int = 2
    """Samples in a row that must ask for a change before it is made."""
    up_margin: float = 0.25
    """Free cores beyond the rounding boundary needed to add a thread (:func:`choose_threads`)."""
    read_sample: Callable[[], Optional[CpuSample]] = read_cpu_sample
    """Reads the cumulative CPU times now (None: not available here)."""
    get_threads: Callable[[], int] = torch.get_num_threads
    """Torch's thread count now."""
    set_threads: Callable[[int], None] = torch.set_num_threads
    """Sets torch's thread count (called only when it changes)."""
    clock: Callable[[], float] = time.monotonic
    """Wall-clock seconds (any origin)."""
    log: Optional[Callable[[str], None]] = None
    """Where the one line per change goes; None: nerfstudio's console (``CONSOLE.log``)."""
    environ: Mapping[str, str] = field(default_factory=lambda: os.environ)
    """The environment that may hold ``OMP_NUM_THREADS``."""

    last_other_cores: Optional[float] = field(default=None, init=False)
    """Cores used by other processes over the latest interval (None before the second sample)."""
    _last: Optional[CpuSample] = field(default=None, init=False, repr=False)
    _last_time: float = field(default=0.0, init=False, repr=False)
    _due: Optional[float] = field(default=None, init=False, repr=False)
    _pending: Optional[int] = field(default=None, init=False, repr=False)
    _streak: int = field(default=0, init=False, repr=False)
    _ceiling: int = field(default=1, init=False, repr=False)

    def __post_init__(self) -> None:
        if _explicit_thread_count(self.environ):
            self.enabled = False
        self._ceiling = self.max_threads if self.max_threads is not None else max(self.get_threads(), self.min_threads)

    def update(self, now: Optional[float] = None) -> None:
        """Sample when due and change the thread count when the cores free for us changed.

        Args:
            now: the clock's time now (seconds); None: read ``clock``.
        """
        if not self.enabled:
            return
        now = self.clock() if now is None else now
        if self._due is not None and now < self._due:
            return
        self._due = now + self.every_seconds
        sample = self.read_sample()
        if sample is None:
            self.enabled = False  # no /proc/stat here: leave torch alone for good
            return
        previous, previous_time = self._last, self._last_time
        self._last, self._last_time = sample, now
        if previous is None or now <= previous_time:
            return
        others = other_busy_cores(previous, sample, now - previous_time)
        self.last_other_cores = others
        current = self.get_threads()
        high = self._ceiling if self.max_threads is not None else max(min(self._ceiling, sample.cores), self.min_threads)
        wanted = choose_threads(sample.cores, others, current, min_threads=self.min_threads, max_threads=high, up_margin=self.up_margin)
        if wanted == current:
            self._pending, self._streak = None, 0
            return
        if self._pending is not None and (self._pending > current) == (wanted > current):
            # same direction again: keep the smaller change of the two
            self._pending = min(self._pending, wanted) if wanted > current else max(self._pending, wanted)
            self._streak += 1
        else:
            self._pending, self._streak = wanted, 1
        if self._streak < self.confirmations:
            return
        target = self._pending
        self._pending, self._streak = None, 0
        self.set_threads(target)
        self._log(f"threads: {current} -> {target} (other processes use {others:.1f} of {sample.cores} cores)")

    def _log(self, message: str) -> None:
        if self.log is not None:
            self.log(message)
            return
        from nerfstudio.utils.rich_utils import CONSOLE

        CONSOLE.log(message)
