"""``--pipeline.time-budget``: a run plans its steps to fit the budget at the pace it measures, records the
plan, and ``scalar-nerf-block`` runs train the steps it planned. Time is simulated (each step costs a fixed
number of seconds on the trainer's clock), so nothing here depends on the machine's speed."""

from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Dict, List

import pytest
from conftest import tiny_trainer

from scalar_nerfstudio.blocks.plan import load_plan
from scalar_nerfstudio.engine.pace import TrainingClock
from scalar_nerfstudio.runs import latest_checkpoint_step, load_run_config

#: Simulated seconds of one step: a block's cost more than the global model's (as measured on the towns), and
#: blocks differ (on Caliterra block 0's first steps ran at 8.0 steps/s, the others at 5.6-7.5).
GLOBAL_STEP_S, BLOCK_STEP_S = 0.2, {0: 0.3, 1: 0.45}


@pytest.mark.slow  # trains about 170 tiny steps
def test_a_time_budget_plans_the_steps_to_fit_it_and_records_them(scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                    capsys: pytest.CaptureFixture) -> None:
    trainer = tiny_trainer(scene, tmp_path, time_budget="40s", global_steps=None, block_steps=None)
    pipeline = trainer.pipeline
    assert not pipeline.length.measured and pipeline.length.source == "budget"
    simulated = {"t": 0.0}
    trainer.training_clock = TrainingClock(now=lambda: simulated["t"])
    per_phase: Dict[str, int] = {}
    train_loss = pipeline.get_train_loss_dict

    block_1_began = {}

    def costed(step: int):
        phase = pipeline.phase_at(step)
        if phase.block == 1:
            block_1_began.setdefault("t", simulated["t"])
        simulated["t"] += GLOBAL_STEP_S if phase.block is None else BLOCK_STEP_S[phase.block]
        per_phase[phase.name] = per_phase.get(phase.name, 0) + 1
        return train_loss(step)

    monkeypatch.setattr(pipeline, "get_train_loss_dict", costed)
    trainer.train()
    log = " ".join(capsys.readouterr().out.split())

    length = pipeline.length
    assert length.source == "budget" and length.measured and length.blocks_measured
    # The run ends on its budget (one step's cost of slack per re-plan), though block 1 is dearer than block 0 ...
    assert simulated["t"] == pytest.approx(40.0, abs=1.5)
    # ... it trained what it planned, the dearer block fewer steps (each planned again at its own pace) ...
    assert per_phase == {"global": length.global_steps, "block 0": length.steps_of_block(0), "block 1": length.steps_of_block(1)}
    assert length.finished_block_steps == (length.steps_of_block(0),) and length.steps_of_block(1) < length.steps_of_block(0)
    assert latest_checkpoint_step(trainer.checkpoint_dir) == length.total_steps(2) - 1
    # ... the global phase took its share of the capture's plan (2 : 1 per block, 2000 : 1000 here) ...
    assert length.global_steps * GLOBAL_STEP_S == pytest.approx(40.0 * 2 / 4, rel=0.1)
    # ... and the plan and its ETA were printed before the long work, and at every phase.
    assert "training length: global 2000 steps + 2 blocks x 1000 steps = 4000 steps for now" in log
    assert "planned for a budget of 40 s at" in log and "left (ends about" in log
    assert "phase block 1 starts (" in log and "steps/s in block 1" in log
    # At a block's start the time left is the budget's (its steps are planned again at its own pace), not the
    # steps left at the pace of the cheaper block before it.
    left = re.search(r"phase block 1 starts \(\d+ steps\); the run has about (\d+) s left \(ends about \d\d:\d\d\), the budget's end", log)
    assert left is not None, log[-2000:]
    assert abs(int(left.group(1)) - (40.0 - block_1_began["t"])) <= 1.0

    run = trainer.base_dir
    assert load_plan(run / "blocks.json").length == length  # a resumed run, ns-eval, the viewer read it back
    assert trainer.total_steps == length.total_steps(2)  # held by the trainer: config.yml keeps what was asked
    assert load_run_config(run).max_num_iterations == trainer.config.max_num_iterations == 0

    from scalar_nerfstudio.method_configs import scalar_nerf_block

    block_config = copy.deepcopy(scalar_nerf_block.config)
    block_config.global_run, block_config.block = run, 1
    block_config.adopt_global_run()
    assert block_config.pipeline.block_steps == length.steps_of_block(1)  # a block trained elsewhere trains the planned steps


@pytest.mark.slow  # trains about 60 tiny steps, twice
def test_a_resumed_budget_run_keeps_its_plan(scene: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Killed after its plan was measured, a run resumed from its checkpoint trains to the same planned end."""
    def one_model(**options) -> object:
        return tiny_trainer(scene, tmp_path, num_blocks=1, train_blocks=False, time_budget="20s", global_steps=None,
                            block_steps=None, **options)

    trainer = one_model()
    simulated = {"t": 0.0}
    trainer.training_clock = TrainingClock(now=lambda: simulated["t"])
    train_loss = trainer.pipeline.get_train_loss_dict
    steps: List[int] = []

    def costed(step: int):
        simulated["t"] += 0.25
        steps.append(step)
        if len(steps) == 50:
            trainer.stop_training = True  # as if killed after the checkpoint below
        return train_loss(step)

    monkeypatch.setattr(trainer.pipeline, "get_train_loss_dict", costed)
    trainer.config.steps_per_save = 25
    trainer.train()
    planned = load_plan(trainer.base_dir / "blocks.json").length
    assert planned.measured and planned.global_steps == pytest.approx(80, abs=2)  # 20 s at 4 steps/s
    assert latest_checkpoint_step(trainer.checkpoint_dir) is not None

    def resume(config) -> None:
        config.load_dir = trainer.checkpoint_dir
        config.timestamp = trainer.base_dir.name
        config.pipeline.run_plan = trainer.base_dir / "blocks.json"

    resumed = one_model(configure=resume)
    assert resumed.pipeline.length == planned
    resumed.train()
    assert latest_checkpoint_step(resumed.checkpoint_dir) == planned.global_steps - 1
