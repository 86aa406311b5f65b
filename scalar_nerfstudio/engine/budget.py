"""Following the clock while a run trains: the ETA lines, and a time budget's plan made again as the pace is known.

:class:`ClockFollower` is told of every step (:meth:`ClockFollower.after_step`). Once the pace is known
(:func:`.pace.pace_is_due`) it prints the ETA, and again at :data:`.pace.REPLAN_AT` of the global phase and at
each phase's start; with a time budget (``--pipeline.time-budget``) it plans the steps then, again at
:data:`.pace.REPLAN_AT` of the budget while the global phase trains (the pace changes as the occupancy grid
learns where the scene is empty), the blocks' steps from the time left when the global phase ends, and each
block's again once its own pace is known (:meth:`ClockFollower.plan_blocks_in`). The plan itself is set by
the trainer's ``replan`` (phases, learning-rate schedules, the recorded plan follow it).
"""

from __future__ import annotations

from typing import Callable, Dict, Optional, Set, Tuple

from nerfstudio.utils.rich_utils import CONSOLE

from scalar_nerfstudio.blocks.length import (
    TrainingLength,
    blocks_from_remaining_time,
    format_duration,
    length_from_budget,
)
from scalar_nerfstudio.engine.contract import Phase, PhasedPipeline
from scalar_nerfstudio.engine.pace import (
    BLOCK_CALIBRATION_STEPS,
    REPLAN_AT,
    TrainingClock,
    calibration_start,
    eta_line,
    pace_is_due,
    time_left_line,
)
from scalar_nerfstudio.pipeline_text import format_length

__all__ = ["ClockFollower"]

#: Set the run's length from now on: ``replan(length, started_through)``, ``started_through`` the last step done.
Replan = Callable[[TrainingLength, int], None]


class ClockFollower:
    """The ETA and a time budget's plan of one training process."""

    def __init__(self, clock: TrainingClock, *, replan: Replan, total_steps: Callable[[], int]) -> None:
        self.clock = clock
        self._replan = replan
        self._total_steps = total_steps
        self._pace_reported = False
        self._replans_done: Set[float] = set()
        self._block_replans_done: Set[Tuple[int, str]] = set()
        self._blocks_began: Optional[Tuple[int, float]] = None
        """(steps done, training seconds) when the global phase ended in this process: the blocks' pace is read since."""

    def _steps_left(self, step: int) -> int:
        return self._total_steps() - step - 1

    def after_step(self, pipeline: PhasedPipeline, step: int) -> None:
        """After ``step``: the ETA once the pace is known, a time budget's plan when it is due, and at each
        phase's start the ETA."""
        clock = self.clock
        clock.mark(step + 1)
        length = pipeline.length
        budget = length.budget_s if length.source == "budget" else None
        phase = pipeline.phase_at(step)
        in_global = phase.block is None and step + 1 < phase.end_step
        if not self._pace_reported and pace_is_due(clock.steps_seen, clock.elapsed_s(), budget):
            self._pace_reported = True
            first = step + 1 - clock.steps_seen + calibration_start(clock.steps_seen)
            pace = clock.pace(since_steps=first)
            if budget is not None and not length.measured and pace is not None:
                self._replan_from_pace(pipeline, step, budget, pace)
            CONSOLE.print(f"step {step + 1}: {pace or 0.0:.2f} steps/s over steps {first}-{step + 1} (early steps are the "
                          f"slowest); {format_length(pipeline.length, pipeline.phases)}; {eta_line(self._steps_left(step), pace)}")
            if budget is None:  # the global phase's shares already passed need no ETA of their own after this one
                self._replans_done.update(share for share in REPLAN_AT if step + 1 - phase.start_step >= share * phase.num_steps)
        elif budget is None and in_global and self._pace_reported:
            self._eta_in_global_phase(phase, step)
        elif budget is not None and length.measured and (in_global or phase.block is not None and phase.start_step == 0):
            pace = clock.pace(last_steps=200)
            spent = self.budget_spent_s(step + 1, pace or 0.0)
            due = [share for share in REPLAN_AT if share not in self._replans_done and spent >= share * budget]
            if due and pace is not None:
                self._replans_done.update(due)
                self._replan_from_pace(pipeline, step, budget, pace)
                CONSOLE.print(f"step {step + 1}: {pace:.2f} steps/s over the last steps, {due[-1]:.0%} of the budget spent; "
                              f"{format_length(pipeline.length, pipeline.phases)}; {eta_line(self._steps_left(step), pace)}")
        phase = pipeline.phase_at(step)
        if budget is not None and phase.block is not None and phase.start_step > 0:
            self.plan_blocks_in(pipeline, phase, step, budget)
        if budget is not None and phase.block is None and step + 1 == phase.end_step and not pipeline.length.blocks_measured:
            pace = clock.pace(last_steps=200) or pipeline.length.pace_steps_per_s or 0.0
            remaining = budget - self.budget_spent_s(step + 1, pace)
            self._replan(blocks_from_remaining_time(pipeline.length, pipeline.length_settings(),
                                                    num_blocks_trained=pipeline.num_blocks_following, remaining_s=remaining,
                                                    pace_steps_per_s=pace), step)
            self._blocks_began = (step + 1, clock.elapsed_s())
            CONSOLE.print(f"step {step + 1}: the global phase took {format_duration(clock.elapsed_s())}; "
                          f"{format_duration(max(remaining, 0))} "
                          f"of the budget left: {format_length(pipeline.length, pipeline.phases)}")
        upcoming = pipeline.phase_at(step + 1)
        if self._pace_reported and step + 1 == upcoming.start_step and step + 1 < self._total_steps():
            pace = clock.pace(last_steps=200)
            left = eta_line(self._steps_left(step), pace)
            if budget is not None and upcoming.block is not None and pipeline.length_settings().block_workers <= 1:
                # the blocks are planned again at their own pace to end on the budget: the last block's pace misleads
                left = time_left_line(max(budget - self.budget_spent_s(step + 1, pace or 0.0), 0.0)) + ", the budget's end"
            CONSOLE.print(f"step {step + 1}: phase {upcoming.name} starts ({upcoming.num_steps} steps); the run has {left}")

    def _eta_in_global_phase(self, phase: Phase, step: int) -> None:
        """Without a budget: the ETA again at :data:`.pace.REPLAN_AT` of the global phase's steps, from the pace
        of the latest steps (the first ETA comes from the slowest steps, before the occupancy grid has pruned)."""
        done = step + 1 - phase.start_step
        due = [share for share in REPLAN_AT if share not in self._replans_done and done >= share * phase.num_steps]
        pace = self.clock.pace(last_steps=200)
        if due and pace is not None:
            self._replans_done.update(due)
            CONSOLE.print(f"step {step + 1}: {pace:.2f} steps/s over the last steps, {due[-1]:.0%} of the global phase done; "
                          f"the run has {eta_line(self._steps_left(step), pace)}")

    def plan_blocks_in(self, pipeline: PhasedPipeline, phase: Phase, step: int, budget: float) -> None:
        """In a block phase of a budget run, after ``step``: plan its steps and those of the blocks after it again
        from the time left, once it has trained :data:`.pace.BLOCK_CALIBRATION_STEPS` (or a third) of them, and on
        one machine again at its half (blocks differ in cost: a plan at the first block's pace alone overran). The
        rest of this block is costed at its own pace, the blocks after it at the pace of all blocks so far. On
        K workers only the first block is planned again (each block stands for one worker's)."""
        settings = pipeline.length_settings()
        blocks = [p for p in pipeline.phases if p.block is not None]
        index = blocks.index(phase)
        one_machine = settings.block_workers <= 1
        if index > 0 and not one_machine:
            return
        done = step + 1 - phase.start_step
        points: Dict[str, int] = {"start": min(BLOCK_CALIBRATION_STEPS, max(phase.num_steps // 3, 1))}
        if one_machine:
            points["half"] = phase.num_steps // 2
        due = [name for name, at in points.items() if done >= at and (index, name) not in self._block_replans_done]
        if not due or phase.num_steps - done <= 1:
            return
        self._block_replans_done.update((index, name) for name in due)
        clock = self.clock
        pace = clock.pace(since_steps=phase.start_step + min(10, done // 2)) or 0.0
        blocks_pace = pace
        if self._blocks_began is not None and index > 0:
            began_steps, began_s = self._blocks_began
            spent_in_blocks = clock.elapsed_s() - began_s
            blocks_pace = (step + 1 - began_steps) / spent_in_blocks if spent_in_blocks > 0 else pace
        remaining = budget - self.budget_spent_s(step + 1, pace)
        self._replan(blocks_from_remaining_time(
            pipeline.length, settings, num_blocks_trained=pipeline.num_blocks_following, remaining_s=remaining, pace_steps_per_s=pace,
            later_blocks_pace_steps_per_s=blocks_pace, current_block_steps_done=done,
            finished_block_steps=[p.num_steps for p in blocks[:index]] if one_machine else ()), step)
        CONSOLE.print(f"step {step + 1}: {pace:.2f} steps/s in {phase.name} ({blocks_pace:.2f} over the blocks so far); "
                      f"{format_length(pipeline.length, pipeline.phases)}; {eta_line(self._steps_left(step), pace)}")

    def _replan_from_pace(self, pipeline: PhasedPipeline, step: int, budget: float, pace: float) -> None:
        """Plan the steps so that those done after ``step`` plus those that fit the budget's time left at ``pace``
        make the run (the phase that trains keeps at least the steps it has done)."""
        remaining = max(budget - self.budget_spent_s(step + 1, pace), 0.0)
        effective = (step + 1 + remaining * pace) / budget  # steps per second of budget: those done and those that fit
        length = length_from_budget(pipeline.length, pipeline.length_settings(), num_blocks_trained=pipeline.num_blocks_following,
                                    pace_steps_per_s=effective, steps_done=step + 1)
        self._replan(length, step)

    def budget_spent_s(self, steps_done: int, pace: float) -> float:
        """Training seconds of the budget spent after ``steps_done`` steps: the clock's (a resumed run's earlier
        training time is in its checkpoint), or, resumed from a checkpoint without it, its earlier steps at ``pace``."""
        if self.clock.knows_earlier_time:
            return self.clock.elapsed_s()
        earlier = steps_done - self.clock.steps_seen
        return self.clock.elapsed_s() + (earlier / pace if pace > 0 and earlier > 0 else 0.0)
