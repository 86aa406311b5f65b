"""How long a run trains (blocks/length.py) and the training clock (engine/pace.py): pure, no training."""

from __future__ import annotations

import math
from pathlib import Path
from typing import List

import pytest

from scalar_nerfstudio.blocks.length import (
    LengthError,
    LengthSettings,
    TrainingLength,
    blocks_from_remaining_time,
    format_duration,
    length_from_budget,
    length_from_capture,
    length_from_json,
    length_to_json,
    parse_duration,
    plan_length,
)
from scalar_nerfstudio.engine.contract import Phase
from scalar_nerfstudio.engine.pace import TrainingClock, calibration_start, eta_line, pace_is_due


@pytest.mark.parametrize("text, seconds", [
    ("90s", 90.0), ("45m", 2700.0), ("2h", 7200.0), ("1h30m", 5400.0), ("1.5h", 5400.0), ("3600", 3600.0),
    ("1h 5m 10s", 3910.0), ("2H", 7200.0), ("1d", 86400.0),
])
def test_a_budget_is_read_as_the_user_writes_it(text: str, seconds: float) -> None:
    assert parse_duration(text) == pytest.approx(seconds)


@pytest.mark.parametrize("text", ["", "h", "abc", "10x", "0s", "0", "-5m", "1h-5m", "nan", "5 minutes"])
def test_a_budget_that_is_no_duration_is_refused_with_the_text_named(text: str) -> None:
    with pytest.raises(LengthError, match="duration|longer than 0"):
        parse_duration(text)


def test_durations_print_as_a_person_reads_them() -> None:
    assert format_duration(45) == "45 s"
    assert format_duration(725) == "12 min 05 s"
    assert format_duration(3 * 3600 + 20 * 60) == "3 h 20 min"
    assert format_duration(math.inf) == "unknown"


def test_the_capture_plans_more_steps_for_more_pixels() -> None:
    settings = LengthSettings(rays_per_batch=2048, rays_per_pixel=0.5, block_rays_per_pixel=1.0)
    small = length_from_capture(settings, train_pixels=10 * 640 * 480, block_pixels=[3 * 640 * 480] * 2)
    assert (small.global_steps, small.block_steps, small.source) == (2000, 1000, "capture")  # the floors
    large = length_from_capture(settings, train_pixels=3000 * 512 * 384, block_pixels=[300 * 512 * 384] * 10)
    assert large.global_steps == math.ceil(0.5 * 3000 * 512 * 384 / 2048)
    assert large.block_steps == math.ceil(300 * 512 * 384 / 2048)
    huge = length_from_capture(settings, train_pixels=10**12, block_pixels=[10**12])
    assert huge.global_steps == huge.block_steps == settings.max_steps


def test_given_steps_stay_as_given() -> None:
    both = length_from_capture(LengthSettings(global_steps=7, block_steps=3), 10**9, [10**9])
    assert (both.global_steps, both.block_steps, both.source) == (7, 3, "given")
    one = length_from_capture(LengthSettings(global_steps=7), 10**9, [10**9])
    assert one.global_steps == 7 and one.block_steps > 1000 and one.source == "capture"


def test_a_budget_scales_the_capture_plan_to_fit_its_time() -> None:
    settings = LengthSettings(time_budget_s=3600.0, rays_per_batch=2048)
    capture = TrainingLength(2000, 1000, "capture")
    length = length_from_budget(capture, settings, num_blocks_trained=4, pace_steps_per_s=10.0)
    assert length.source == "budget" and length.measured and not length.blocks_measured
    assert length.global_steps + 4 * length.block_steps == pytest.approx(36000, abs=5)
    assert length.global_steps / length.block_steps == pytest.approx(2.0, rel=1e-3)
    again = length_from_budget(length, settings, num_blocks_trained=4, pace_steps_per_s=10.0)  # a plan passed again
    assert again.global_steps / again.block_steps == pytest.approx(2.0, rel=1e-3)


def test_blocks_on_workers_get_the_time_of_the_waves() -> None:
    capture = TrainingLength(2000, 1000, "capture")
    one = length_from_budget(capture, LengthSettings(time_budget_s=600.0), num_blocks_trained=8, pace_steps_per_s=10.0)
    four = length_from_budget(capture, LengthSettings(time_budget_s=600.0, block_workers=4), num_blocks_trained=8, pace_steps_per_s=10.0)
    assert four.global_steps + 2 * four.block_steps == pytest.approx(6000, abs=3)  # 8 blocks on 4 workers: 2 waves
    assert four.block_steps == pytest.approx(2.5 * one.block_steps, rel=0.01)  # the same time over 2 + 2 shares, not 2 + 8


def test_a_budget_beside_given_steps_fills_the_rest() -> None:
    capture = TrainingLength(500, 1000, "capture")
    length = length_from_budget(capture, LengthSettings(global_steps=500, time_budget_s=100.0), num_blocks_trained=2, pace_steps_per_s=20.0)
    assert length.global_steps == 500 and length.block_steps == (2000 - 500) // 2
    with pytest.raises(LengthError, match="not all three"):
        length_from_budget(capture, LengthSettings(global_steps=500, block_steps=10, time_budget_s=100.0), num_blocks_trained=2,
                           pace_steps_per_s=20.0)


def test_a_budget_waits_for_its_pace_and_never_plans_the_past() -> None:
    settings = LengthSettings(time_budget_s=60.0)
    provisional = plan_length(settings, train_pixels=10**6, block_pixels=[10**6])
    assert not provisional.measured and provisional.source == "budget" and provisional.budget_s == 60.0
    assert (provisional.global_steps, provisional.block_steps) == (2000, 1000)  # the capture's plan, for now
    slow = length_from_budget(provisional, settings, num_blocks_trained=1, pace_steps_per_s=1.0, steps_done=300)
    assert slow.global_steps == 301  # 60 steps fit, but 300 are done: the phase keeps them and ends next step
    blocks_only = length_from_budget(provisional, LengthSettings(global_steps=0, time_budget_s=60.0), num_blocks_trained=1,
                                     pace_steps_per_s=1.0, steps_done=300)
    assert blocks_only.block_steps == 301 and blocks_only.blocks_measured


def test_the_blocks_are_planned_from_the_time_left_and_the_first_blocks_pace() -> None:
    length = TrainingLength(1000, 500, "budget", budget_s=600.0, pace_steps_per_s=5.0, blocks_measured=False)
    planned = blocks_from_remaining_time(length, LengthSettings(time_budget_s=600.0), num_blocks_trained=3, remaining_s=300.0,
                                         pace_steps_per_s=4.0)
    assert planned.block_steps == 400 and planned.blocks_measured and planned.global_steps == 1000
    # 60 steps of block 0 done, 100 s left at 3 steps/s: 300 more steps for the three blocks' 3B - 60
    again = blocks_from_remaining_time(planned, LengthSettings(time_budget_s=600.0), num_blocks_trained=3, remaining_s=100.0,
                                       pace_steps_per_s=3.0, current_block_steps_done=60)
    assert again.block_steps == 120
    spent = blocks_from_remaining_time(planned, LengthSettings(time_budget_s=600.0), num_blocks_trained=3, remaining_s=-50.0,
                                       pace_steps_per_s=3.0, current_block_steps_done=60)
    assert spent.block_steps == 61  # out of time: block 0 ends at its next step, the others train as long



def test_on_one_machine_the_blocks_after_a_finished_one_share_the_time_left_at_their_own_pace() -> None:
    length = TrainingLength(1000, 400, "budget", budget_s=600.0, pace_steps_per_s=5.0)
    settings = LengthSettings(time_budget_s=600.0)
    # Block 0 trained 400 steps; block 1 has done 30 at 2 steps/s, 3 blocks in all have trained at 3 steps/s:
    # B - 30 steps at 2/s and B more at 3/s in 200 s: B (1/2 + 1/3) = 200 + 15, B = 258.
    planned = blocks_from_remaining_time(length, settings, num_blocks_trained=3, remaining_s=200.0, pace_steps_per_s=2.0,
                                         later_blocks_pace_steps_per_s=3.0, current_block_steps_done=30, finished_block_steps=[400])
    assert (planned.finished_block_steps, planned.block_steps) == ((400,), 258)
    assert [planned.steps_of_block(i) for i in range(3)] == [400, 258, 258] and planned.total_steps(3) == 1000 + 400 + 2 * 258
    assert length_from_json(length_to_json(planned)) == planned
    with pytest.raises(LengthError, match="one after another on one machine"):  # K workers: every block gets the same time
        blocks_from_remaining_time(length, LengthSettings(time_budget_s=600.0, block_workers=3), num_blocks_trained=3,
                                   remaining_s=200.0, pace_steps_per_s=2.0, finished_block_steps=[400])

def test_a_length_survives_its_json_and_a_broken_one_is_named() -> None:
    length = TrainingLength(1234, 567, "budget", budget_s=3600.0, pace_steps_per_s=9.5, measured=True, blocks_measured=False)
    assert length_from_json(length_to_json(length)) == length
    for broken in ({"global_steps": 1}, {**length_to_json(length), "source": "guess"}, {**length_to_json(length), "block_steps": -1}):
        with pytest.raises(LengthError, match="malformed training length"):
            length_from_json(broken)


def test_the_plan_file_keeps_the_length(tmp_path: Path) -> None:
    import numpy as np

    from scalar_nerfstudio.blocks.plan import PlanSettings, load_plan, plan_blocks, save_plan

    centres = np.stack([np.linspace(0, 10, 12), np.zeros(12), np.zeros(12)], axis=1)
    plan = plan_blocks(centres, np.tile([0.0, 1.0, 0.0], (12, 1)), np.full(12, 100.0), image_pixels=[100 * 100] * 12,
                       image_names=[f"{i}.png" for i in range(12)], settings=PlanSettings(num_blocks=2))
    from dataclasses import replace

    measured = replace(plan, length=TrainingLength(900, 300, "budget", budget_s=120.0, pace_steps_per_s=10.0))
    save_plan(measured, tmp_path / "blocks.json")
    assert load_plan(tmp_path / "blocks.json") == measured
    save_plan(plan, tmp_path / "old.json")  # a plan from before lengths: none read back
    assert load_plan(tmp_path / "old.json").length is None


class _FakeTime:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_the_clock_counts_training_time_only_and_reads_the_latest_pace() -> None:
    now = _FakeTime()
    clock = TrainingClock(now=now)
    clock.start(0)
    for step in range(1, 101):  # 100 steps at 0.5 s, then 100 at 0.25 s
        now.t += 0.5 if step <= 100 else 0.25
        clock.mark(step)
    with clock.paused():  # an evaluation
        now.t += 30.0
    for step in range(101, 201):
        now.t += 0.25
        clock.mark(step)
    assert clock.elapsed_s() == pytest.approx(75.0)
    assert clock.steps_seen == 200
    assert clock.pace(last_steps=50) == pytest.approx(4.0)
    assert clock.pace(since_steps=0) == pytest.approx(200 / 75.0)
    assert clock.pace(since_steps=100) == pytest.approx(4.0)


def test_the_clock_counts_every_step_beyond_the_times_it_keeps() -> None:
    """A run of more steps than the clock keeps times of still counts them all, and a new run has trained 0 s before:
    (a clock that lost count added the dropped steps' time again, and ended a 4-minute budget at 200 s)."""
    now = _FakeTime()
    clock = TrainingClock(now=now, history=16)
    clock.start(0, 0.0)
    for step in range(1, 101):
        now.t += 1.0
        clock.mark(step)
    assert clock.steps_seen == 100 and clock.elapsed_s() == pytest.approx(100.0) and clock.knows_earlier_time
    assert clock.pace(last_steps=10) == pytest.approx(1.0)


def test_a_resumed_clock_counts_from_its_first_step() -> None:
    now = _FakeTime()
    clock = TrainingClock(now=now)
    clock.start(500)
    now.t += 10.0
    clock.mark(520)
    assert clock.steps_seen == 20 and clock.pace() == pytest.approx(2.0)


def test_the_pace_is_read_after_the_first_steps_or_a_tenth_of_a_short_budget() -> None:
    assert not pace_is_due(100, 1000.0, None)
    assert pace_is_due(240, 10.0, None)
    assert pace_is_due(30, 7.0, 60.0) and not pace_is_due(30, 5.0, 60.0) and not pace_is_due(10, 7.0, 60.0)
    assert calibration_start(240) == 160 and calibration_start(30) == 15


def test_the_eta_says_how_long_and_until_when() -> None:
    line = eta_line(600, 2.0, now=lambda: 0.0)
    assert line.startswith("about 5 min 00 s left (ends about ")
    assert eta_line(600, None) == "600 steps left"


def test_a_bad_budget_option_is_refused_before_anything_is_written() -> None:
    from scalar_nerfstudio.config_checks import OptionError, check_pipeline_options
    from scalar_nerfstudio.pipeline import ScalarPipelineConfig

    bad: List[tuple] = [
        ({"time_budget": "soon"}, "--pipeline.time-budget soon"),
        ({"time_budget": "1h", "global_steps": 10, "block_steps": 5}, "leave one of the step counts out"),
        ({"rays_per_pixel": 0.0}, "--pipeline.rays-per-pixel 0"),
        ({"block_workers": 0}, "--pipeline.block-workers 0"),
    ]
    for options, message in bad:
        pipeline = ScalarPipelineConfig()
        for key, value in options.items():
            setattr(pipeline, key, value)
        with pytest.raises(OptionError, match=message):
            check_pipeline_options(pipeline)
    good = ScalarPipelineConfig()
    good.time_budget, good.global_steps = "15m", 100
    check_pipeline_options(good)


class _PhasesOnly:
    """The part of a pipeline the ETA lines read: a plan from the capture, a global phase and two blocks."""

    def __init__(self, global_steps: int, block_steps: int) -> None:
        self.length = TrainingLength(global_steps, block_steps, "capture")
        self.phases = [Phase(None, 0, global_steps), Phase(0, global_steps, block_steps), Phase(1, global_steps + block_steps, block_steps)]

    def phase_at(self, step: int) -> Phase:
        return next((p for p in self.phases if p.start_step <= step < p.end_step), self.phases[-1])


def test_without_a_budget_the_eta_follows_the_pace_through_the_global_phase(capsys: pytest.CaptureFixture[str]) -> None:
    """The first ETA comes from the slowest steps (before the occupancy grid has pruned): the ETA is printed
    again at 25, 50 and 75 % of the global phase from the latest steps' pace, and at each block's start."""
    from scalar_nerfstudio.engine.budget import ClockFollower

    now = _FakeTime()
    clock = TrainingClock(now=now)
    pipeline = _PhasesOnly(global_steps=2000, block_steps=1000)
    follower = ClockFollower(clock, replan=lambda *_: pytest.fail("a plan from the capture is never planned again"),
                             total_steps=lambda: 4000)
    clock.start(0)
    lines = {}
    for step in range(4000):
        now.t += 0.5 if step < 600 else 0.1  # 2 steps/s until the grid prunes, then 10
        follower.after_step(pipeline, step)  # type: ignore[arg-type]  # the fake has what the ETA reads
        out = capsys.readouterr().out
        if out:
            lines[step + 1] = " ".join(out.split())
    assert "2.00 steps/s over steps 160-240 (early steps are the slowest)" in lines[240]
    assert "about 31 min 20 s left" in lines[240]  # 3760 steps at the first pace
    for step, share, left in [(500, "25%", "about 29 min 10 s left"), (1000, "50%", "about 5 min 00 s left"),
                              (1500, "75%", "about 4 min 10 s left")]:
        assert f"{share} of the global phase done" in lines[step] and left in lines[step], lines[step]
    assert "phase block 0 starts (1000 steps); the run has about 3 min 20 s left" in lines[2000]
    assert sorted(lines) == [240, 500, 1000, 1500, 2000, 3000], sorted(lines)


def test_a_short_global_phase_gets_one_eta_line_where_its_shares_passed_before_the_pace_was_known(
        capsys: pytest.CaptureFixture[str]) -> None:
    from scalar_nerfstudio.engine.budget import ClockFollower

    now = _FakeTime()
    clock = TrainingClock(now=now)
    pipeline = _PhasesOnly(global_steps=400, block_steps=100)
    follower = ClockFollower(clock, replan=lambda *_: None, total_steps=lambda: 600)
    clock.start(0)
    printed = []
    for step in range(400):
        now.t += 0.1
        follower.after_step(pipeline, step)  # type: ignore[arg-type]  # the fake has what the ETA reads
        if capsys.readouterr().out:
            printed.append(step + 1)
    assert printed == [240, 300, 400], printed  # the first ETA (25 % and 50 % had passed), 75 %, block 0 starts
