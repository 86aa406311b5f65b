"""The thread governor (issue 18): the decision, the sampling schedule, and /proc/stat reading."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

import pytest

from scalar_nerfstudio.blocks.length import LengthSettings, TrainingLength
from scalar_nerfstudio.engine.contract import Phase
from scalar_nerfstudio.engine.threads import (
    CpuSample,
    ThreadGovernor,
    choose_threads,
    other_busy_cores,
    parse_proc_stat_busy,
    read_cpu_sample,
)

# ------------------------------------------------------------------------------------ choose_threads


def test_idle_machine_uses_every_thread() -> None:
    assert choose_threads(cores=2, other_busy_cores=0.0, current=2) == 2
    assert choose_threads(cores=2, other_busy_cores=0.05, current=1) == 2
    assert choose_threads(cores=8, other_busy_cores=0.1, current=3, max_threads=8) == 8


def test_busy_machine_drops_to_one_thread() -> None:
    assert choose_threads(cores=2, other_busy_cores=2.0, current=2) == 1  # another process wants both cores
    assert choose_threads(cores=2, other_busy_cores=1.9, current=2) == 1
    assert choose_threads(cores=2, other_busy_cores=1.0, current=2) == 1  # another training on 1 core
    assert choose_threads(cores=2, other_busy_cores=1.0, current=1) == 1
    assert choose_threads(cores=2, other_busy_cores=0.7, current=2) == 1  # it gets less than it wants
    assert choose_threads(cores=8, other_busy_cores=4.0, current=8) == 4


def test_bounds() -> None:
    assert choose_threads(cores=2, other_busy_cores=5.0, current=2) == 1  # never below 1
    assert choose_threads(cores=2, other_busy_cores=5.0, current=2, min_threads=0) == 1
    assert choose_threads(cores=4, other_busy_cores=4.0, current=4, min_threads=2) == 2
    assert choose_threads(cores=4, other_busy_cores=-1.0, current=1, max_threads=3) == 3  # never above max
    assert choose_threads(cores=4, other_busy_cores=0.0, current=4, max_threads=2) == 2
    assert choose_threads(cores=2, other_busy_cores=0.0, current=2) == 2  # max defaults to the cores


def test_hysteresis_band() -> None:
    """Down as soon as the rounded free cores fall below the count, up only 0.25 core past the boundary."""
    assert choose_threads(cores=2, other_busy_cores=0.45, current=2) == 2
    assert choose_threads(cores=2, other_busy_cores=0.55, current=2) == 1
    assert choose_threads(cores=2, other_busy_cores=0.45, current=1) == 1  # the same load, no way back up
    assert choose_threads(cores=2, other_busy_cores=0.3, current=1) == 1
    assert choose_threads(cores=2, other_busy_cores=0.2, current=1) == 2
    assert choose_threads(cores=2, other_busy_cores=0.2, current=1, up_margin=0.0) == 2
    assert choose_threads(cores=2, other_busy_cores=0.45, current=1, up_margin=0.0) == 2


def test_no_flapping_near_the_boundary() -> None:
    """A load that wanders around the 2 -> 1 boundary changes the count once, then stays put."""
    loads = [0.45, 0.55, 0.42, 0.58, 0.35, 0.6, 0.3, 0.5, 0.4, 0.55, 0.28]
    current, history = 2, []
    for load in loads:
        current = choose_threads(cores=2, other_busy_cores=load, current=current)
        history.append(current)
    assert history == [2] + [1] * (len(loads) - 1)


def test_symmetric_trainings_settle_on_one_thread_each() -> None:
    """Two trainings on 2 cores: each sees the other use what it leaves it, and neither goes back up."""
    a = b = 2
    for _ in range(6):
        # each process gets a share of the 2 cores proportional to its threads (the OS shares by thread)
        share_a, share_b = 2 * a / (a + b), 2 * b / (a + b)
        a, b = choose_threads(2, share_b, a), choose_threads(2, share_a, b)
    assert (a, b) == (1, 1)


# ----------------------------------------------------------------------------------- other_busy_cores


def test_other_busy_cores_subtracts_own_time() -> None:
    before = CpuSample(busy_s=100.0, own_s=10.0, cores=2)
    after = CpuSample(busy_s=110.0, own_s=15.0, cores=2)  # 10 s busy in 5 s, 5 of them ours
    assert other_busy_cores(before, after, 5.0) == pytest.approx(1.0)
    # tick rounding can make the machine look less busy than this process alone: never negative
    assert other_busy_cores(before, CpuSample(104.9, 15.0, 2), 5.0) == 0.0
    with pytest.raises(ValueError):
        other_busy_cores(before, after, 0.0)


# -------------------------------------------------------------------------------------- the governor


class FakeMachine:
    """A machine whose cumulative busy time and our own CPU time advance as the test says."""

    def __init__(self, cores: int = 2) -> None:
        self.cores, self.busy_s, self.own_s, self.reads = cores, 0.0, 0.0, 0

    def advance(self, seconds: float, own_cores: float, other_cores: float) -> None:
        self.busy_s += seconds * (own_cores + other_cores)
        self.own_s += seconds * own_cores

    def read(self) -> Optional[CpuSample]:
        self.reads += 1
        return CpuSample(busy_s=self.busy_s, own_s=self.own_s, cores=self.cores)


class FakeTorch:
    def __init__(self, threads: int) -> None:
        self.threads, self.calls = threads, []  # type: ignore[var-annotated]

    def get(self) -> int:
        return self.threads

    def set(self, threads: int) -> None:
        self.calls.append(threads)
        self.threads = threads


def make_governor(machine: FakeMachine, fake: FakeTorch, logs: List[str], environ: Optional[Dict[str, str]] = None,
                  **options: object) -> ThreadGovernor:
    return ThreadGovernor(read_sample=machine.read, get_threads=fake.get, set_threads=fake.set,
                          clock=lambda: pytest.fail("the test passes `now`"), log=logs.append,
                          environ={} if environ is None else environ, **options)  # type: ignore[arg-type]


def run_steps(governor: ThreadGovernor, machine: FakeMachine, fake: FakeTorch, *, start: float, seconds: float,
              step_s: float, other_cores: float) -> float:
    """Steps of ``step_s`` for ``seconds``; we use our thread count's cores as far as the others leave them."""
    now = start
    while now < start + seconds - 1e-9:
        governor.update(now=now)
        own = min(float(fake.threads), machine.cores - other_cores) if other_cores < machine.cores else 0.5
        machine.advance(step_s, own, other_cores)
        now += step_s
    return now


def test_governor_samples_only_when_due() -> None:
    machine, fake, logs = FakeMachine(), FakeTorch(2), []
    governor = make_governor(machine, fake, logs, every_seconds=5.0)
    for now in [0.0, 0.1, 1.0, 4.99]:
        governor.update(now=now)
    assert machine.reads == 1  # the first call takes the baseline, the others are not due
    governor.update(now=5.0)
    assert machine.reads == 2
    governor.update(now=9.9)
    assert machine.reads == 2
    governor.update(now=10.0)
    assert machine.reads == 3
    assert fake.calls == [] and logs == []


def test_governor_drops_then_restores_threads() -> None:
    machine, fake, logs = FakeMachine(), FakeTorch(2), []
    governor = make_governor(machine, fake, logs, every_seconds=5.0, confirmations=2)
    now = run_steps(governor, machine, fake, start=0.0, seconds=30.0, step_s=0.1, other_cores=0.0)  # alone
    assert fake.calls == []
    now = run_steps(governor, machine, fake, start=now, seconds=30.0, step_s=0.1, other_cores=1.0)  # another training starts
    assert fake.calls == [1]
    assert logs == ["threads: 2 -> 1 (other processes use 1.0 of 2 cores)"]
    assert governor.last_other_cores == pytest.approx(1.0)
    now = run_steps(governor, machine, fake, start=now, seconds=60.0, step_s=0.1, other_cores=1.0)  # it keeps running: no change
    assert fake.calls == [1]
    run_steps(governor, machine, fake, start=now, seconds=30.0, step_s=0.1, other_cores=0.0)  # it ended
    assert fake.calls == [1, 2]  # set only on change
    assert logs[-1] == "threads: 1 -> 2 (other processes use 0.0 of 2 cores)"


def test_governor_needs_confirmation() -> None:
    """One busy interval (a short burst of another process) does not change the count; two do."""
    machine, fake, logs = FakeMachine(), FakeTorch(2), []
    governor = make_governor(machine, fake, logs, every_seconds=5.0, confirmations=2)
    governor.update(now=0.0)
    machine.advance(5.0, 1.0, 1.0)
    governor.update(now=5.0)
    machine.advance(5.0, 2.0, 0.0)
    governor.update(now=10.0)
    machine.advance(5.0, 1.0, 1.0)
    governor.update(now=15.0)
    assert fake.calls == []
    machine.advance(5.0, 1.0, 1.0)
    governor.update(now=20.0)
    assert fake.calls == [1]


def test_governor_does_not_flap_under_a_wandering_load() -> None:
    machine, fake, logs = FakeMachine(), FakeTorch(2), []
    governor = make_governor(machine, fake, logs, every_seconds=5.0, confirmations=1)
    now = 0.0
    governor.update(now=now)
    for load in [0.6, 0.4, 0.55, 0.45, 0.35, 0.6, 0.3, 0.5]:
        machine.advance(5.0, min(float(fake.threads), 2.0 - load), load)
        now += 5.0
        governor.update(now=now)
    assert fake.calls == [1]


def test_governor_never_exceeds_torch_default_or_cores() -> None:
    machine, fake, logs = FakeMachine(cores=8), FakeTorch(4), []
    governor = make_governor(machine, fake, logs, confirmations=1)
    run_steps(governor, machine, fake, start=0.0, seconds=60.0, step_s=0.5, other_cores=0.0)
    assert fake.calls == []  # idle machine, 4 of 8: a lone run keeps torch's default
    fake.threads = 16
    governor = make_governor(machine, fake, logs, confirmations=1)
    run_steps(governor, machine, fake, start=0.0, seconds=12.0, step_s=0.5, other_cores=0.0)
    assert fake.calls == [8]  # not more threads than cores
    governor = make_governor(machine, fake, logs, confirmations=1, max_threads=3)
    run_steps(governor, machine, fake, start=0.0, seconds=12.0, step_s=0.5, other_cores=0.0)
    assert fake.calls == [8, 3]


def test_governor_respects_explicit_thread_count() -> None:
    machine, fake, logs = FakeMachine(), FakeTorch(2), []
    governor = make_governor(machine, fake, logs, environ={"OMP_NUM_THREADS": "2"}, confirmations=1)
    assert not governor.enabled
    run_steps(governor, machine, fake, start=0.0, seconds=30.0, step_s=0.1, other_cores=1.5)
    assert machine.reads == 0 and fake.calls == []
    governor = make_governor(machine, fake, logs, enabled=False, confirmations=1)
    run_steps(governor, machine, fake, start=0.0, seconds=30.0, step_s=0.1, other_cores=1.5)
    assert machine.reads == 0 and fake.calls == []
    governor = make_governor(machine, fake, logs, environ={"OMP_NUM_THREADS": ""}, confirmations=1)
    assert governor.enabled  # set but empty is no choice


def test_governor_without_proc_stat_does_nothing() -> None:
    fake, logs, reads = FakeTorch(2), [], []

    def unavailable() -> Optional[CpuSample]:
        reads.append(1)
        return None

    governor = ThreadGovernor(read_sample=unavailable, get_threads=fake.get, set_threads=fake.set, log=logs.append, environ={})
    for now in range(0, 60, 1):
        governor.update(now=float(now))
    assert len(reads) == 1 and not governor.enabled and fake.calls == []


# ----------------------------------------------------------------------------------------- /proc/stat

PROC_STAT_TEXT = """cpu  100 5 50 1000 20 3 2 1 7 0
cpu0 60 5 30 500 10 2 1 1 7 0
cpu1 40 0 20 500 10 1 1 0 0 0
intr 12345 0 0
ctxt 999
procs_running 3
"""


def test_parse_proc_stat() -> None:
    # user + nice + system + irq + softirq + steal; idle, iowait, guest, guest_nice left out
    assert parse_proc_stat_busy(PROC_STAT_TEXT) == 100 + 5 + 50 + 3 + 2 + 1
    assert parse_proc_stat_busy(PROC_STAT_TEXT, cpus={0}) == 60 + 5 + 30 + 2 + 1 + 1
    assert parse_proc_stat_busy(PROC_STAT_TEXT, cpus={0, 1}) == 161
    assert parse_proc_stat_busy(PROC_STAT_TEXT, cpus={5}) is None
    assert parse_proc_stat_busy("intr 1 2\n") is None


@pytest.mark.skipif(not sys.platform.startswith("linux") or not Path("/proc/stat").is_file(), reason="/proc/stat is Linux-only")
def test_real_proc_stat_is_sensible() -> None:
    first = read_cpu_sample()
    assert first is not None
    deadline = time.perf_counter() + 0.3
    while time.perf_counter() < deadline:  # burn some CPU so both clocks move
        sum(i * i for i in range(1000))
    second = read_cpu_sample()
    assert second is not None
    assert first.cores == second.cores >= 1
    assert 0 < first.busy_s <= second.busy_s
    assert 0 < first.own_s < second.own_s
    assert second.own_s - first.own_s <= 0.3 * first.cores + 0.05  # our CPU time cannot outrun the cores
    # the machine was busy at least while we were (up to tick rounding)
    assert second.busy_s - first.busy_s >= (second.own_s - first.own_s) - 0.1


# ------------------------------------------------------------------------------------ the trainer hook


class _OnePhasePipeline:
    """Just enough of a PhasedPipeline for ScalarTrainer.train_iteration (one phase of 100 steps)."""

    plan = None
    total_steps = 100
    phases = [Phase(None, 0, 100)]
    length = TrainingLength(100, 0, "given")
    num_blocks_following = 0

    def phase_at(self, step: int) -> Phase:
        return self.phases[0]

    def set_length(self, length: TrainingLength) -> None:
        self.length = length

    def length_settings(self) -> LengthSettings:
        return LengthSettings(global_steps=100, block_steps=0)

    def param_group_phases(self) -> dict:
        return {}

    holds_global_learning_rate = False
    global_restart_fraction = 0.0

    def plan_report(self) -> str:
        return ""

    def end_training_of(self, phase: object) -> None:
        pass

    def finish_phase(self, phase: object) -> None:
        pass

    def attach_run_dir(self, run_dir: object) -> None:
        pass


def _trainer(tmp_path: Path, device: str = "cpu", adapt: bool = True):
    from scalar_nerfstudio.engine.trainer import ScalarTrainer, ScalarTrainerConfig

    config = ScalarTrainerConfig(method_name="scalar-nerf", output_dir=tmp_path, adapt_threads=adapt, steps_per_preview=0)
    config.machine.device_type = device
    config.mixed_precision = False
    return ScalarTrainer(config)


def test_trainer_governs_threads_on_cpu_unless_told_not_to(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert _trainer(tmp_path).thread_governor.enabled
    assert not _trainer(tmp_path, adapt=False).thread_governor.enabled
    assert not _trainer(tmp_path, device="cuda").thread_governor.enabled
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    assert not _trainer(tmp_path).thread_governor.enabled


def test_trainer_updates_the_governor_once_per_step(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from nerfstudio.engine.trainer import Trainer

    trainer = _trainer(tmp_path)
    events: List[str] = []
    trainer.thread_governor = type("Governor", (), {"update": lambda self, now=None: events.append("update")})()
    monkeypatch.setattr(Trainer, "train_iteration", lambda self, step: events.append(f"step {step}") or step)
    trainer.pipeline = _OnePhasePipeline()  # type: ignore[assignment]
    trainer._total_steps = 100
    assert [trainer.train_iteration(step) for step in range(3)] == [0, 1, 2]
    assert events == ["update", "step 0", "update", "step 1", "update", "step 2"]


def test_the_trainer_ends_a_models_training_at_the_last_step_of_its_phase(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The run's last phase ends too (its model's occupancy grid is refreshed before the final
    checkpoint), once, at its last step; only phases before the last are finished (stored)."""
    from nerfstudio.engine.trainer import Trainer

    trainer = _trainer(tmp_path, adapt=False)
    events: List[str] = []
    pipeline = _OnePhasePipeline()
    pipeline.end_training_of = lambda phase: events.append(f"end {phase.end_step}")  # type: ignore[method-assign]
    pipeline.finish_phase = lambda phase: events.append("finish")  # type: ignore[method-assign]
    monkeypatch.setattr(Trainer, "train_iteration", lambda self, step: step)
    trainer.pipeline = pipeline  # type: ignore[assignment]
    trainer._total_steps = 100
    for step in range(95, 100):
        trainer.train_iteration(step)
    assert events == ["end 100"]
    events.clear()
    trainer._total_steps = 60  # the run's length (max_num_iterations) ends the phase early
    for step in range(55, 60):
        trainer.train_iteration(step)
    assert events == ["end 100"]
