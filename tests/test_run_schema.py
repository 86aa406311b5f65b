"""Run schema versions: an older run is upgraded as it is loaded (``runs.upgrade_run_config``,
``runs.upgrade_blocks_json``) and keeps the behaviour it was trained with; a new run is written at the
current version and loads unchanged; a run newer than the code is refused by name."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
import yaml

from scalar_nerfstudio.blocks.plan import load_plan
from scalar_nerfstudio.blocks.split import BlockSplitError, load_blocks_json
from scalar_nerfstudio.method_configs import global_trainer_config
from scalar_nerfstudio.runs import RUN_SCHEMA_VERSION, RunSchemaError, load_run_config, save_run_config

OLD_RUN = Path(__file__).parent / "fixtures" / "old_run"
"""A run folder's config.yml and blocks.json as written before schema versions (see the files' heads)."""


def _without(text: str, *keys: str) -> str:
    """``text`` (a dumped config) less the lines of ``keys`` (scalars at any depth)."""
    for key in keys:
        text, count = re.subn(rf"(?m)^ *{key}: .*\n", "", text)
        assert count == 1, key
    return text


def test_an_old_run_loads_with_the_behaviour_it_was_trained_with() -> None:
    """The saved old run: fresh blocks, per-phase learning rates, no one-model restart, unbounded rays,
    block tables at the global table's rate; its blocks.json (version 1, no plan) still gives its split."""
    from scalar_nerfstudio.models.scalar_model import near_far_collider

    text = (OLD_RUN / "config.yml").read_text()
    assert not re.search(r"(?m)^ *(scalar_schema_version|block_init|lr_schedule|scene_radius|block_encoder):", text)
    for config in (load_run_config(OLD_RUN), yaml.load(text, Loader=yaml.Loader)):  # ours, and nerfstudio's eval_setup
        pipeline = config.pipeline
        assert pipeline.scalar_schema_version == RUN_SCHEMA_VERSION
        assert pipeline.block_init == "fresh" and pipeline.plan_settings().global_max_resolution is None
        assert pipeline.lr_schedule == "per-phase" and pipeline.one_model_restart == 0.0
        assert pipeline.scene_radius_from_depth is False and pipeline.model.scene_radius is None
        assert near_far_collider(pipeline.model, scene_radius=pipeline.model.scene_radius).scene_radius is None
        assert pipeline.run_plan is None and pipeline.num_blocks == 2  # what it has is kept
        optimizers = config.optimizers
        assert optimizers["block_encoder"]["optimizer"].lr == optimizers["encoder"]["optimizer"].lr == 1e-2
        assert optimizers["block_encoder"] is not optimizers["encoder"]
    split, names = load_blocks_json(OLD_RUN / "blocks.json")
    assert split.num_blocks == 2 and len(names) == 6
    with pytest.raises(BlockSplitError, match="no plan"):
        load_plan(OLD_RUN / "blocks.json")


def test_a_resumed_old_run_decides_its_plan_again_and_a_new_one_keeps_its_plan(tmp_path: Path) -> None:
    """Resuming adopts the run's blocks.json as its plan only when its config.yml records one."""
    config = global_trainer_config()
    config._adopt_run_plan(OLD_RUN)
    assert config.pipeline.run_plan is None
    run = tmp_path / "run"
    shutil.copytree(OLD_RUN, run)
    recorded = load_run_config(run)
    recorded.pipeline.run_plan = (run / "blocks.json").resolve()
    save_run_config(recorded, run)
    config._adopt_run_plan(run)
    assert config.pipeline.run_plan == (run / "blocks.json").resolve()


def test_a_new_run_is_written_at_the_current_version_and_loads_unchanged(tmp_path: Path) -> None:
    config = global_trainer_config()
    config.pipeline.block_init, config.pipeline.lr_schedule, config.pipeline.one_model_restart = "fitted", "per-phase", 0.25
    config.pipeline.model.scene_radius = 3.5
    path = save_run_config(config, tmp_path)
    assert f"scalar_schema_version: {RUN_SCHEMA_VERSION}\n" in path.read_text()
    loaded = load_run_config(tmp_path)
    assert loaded.pipeline == config.pipeline and loaded.optimizers == config.optimizers
    fresh = load_run_config(save_run_config(global_trainer_config(), tmp_path / "defaults"))
    assert (fresh.pipeline.block_init, fresh.pipeline.lr_schedule, fresh.pipeline.one_model_restart) == ("global", "restart", 0.5)
    assert fresh.pipeline.scene_radius_from_depth is True


def test_options_added_one_at_a_time_load_as_trained() -> None:
    """A config.yml written between two options has the first and lacks the second: what it has is
    kept, what it lacks loads as it was trained."""
    text = yaml.dump(global_trainer_config())
    no_version = ("scalar_schema_version",)
    before_restart = yaml.load(_without(text, *no_version, "one_model_restart"), Loader=yaml.Loader).pipeline
    assert before_restart.lr_schedule == "restart" and before_restart.one_model_restart == 0.0
    assert before_restart.block_init == "global"
    before_bound = yaml.load(_without(text, *no_version, "scene_radius", "scene_radius_from_depth"), Loader=yaml.Loader).pipeline
    assert before_bound.model.scene_radius is None and before_bound.scene_radius_from_depth is False
    assert before_bound.one_model_restart == 0.5
    before_block_init = yaml.load(_without(text, *no_version, "block_init"), Loader=yaml.Loader).pipeline
    assert before_block_init.block_init == "fresh" and before_block_init.lr_schedule == "restart"
    current = yaml.load(_without(text, "block_init"), Loader=yaml.Loader).pipeline  # a version-2 file: no upgrade
    assert current.block_init == "global"


def test_a_run_newer_than_this_code_is_refused_by_name(tmp_path: Path) -> None:
    newer = RUN_SCHEMA_VERSION + 1
    run = tmp_path / "run"
    run.mkdir()
    text = yaml.dump(global_trainer_config()).replace(f"scalar_schema_version: {RUN_SCHEMA_VERSION}\n", f"scalar_schema_version: {newer}\n")
    (run / "config.yml").write_text(text)
    with pytest.raises(RunSchemaError, match=rf"{re.escape(str(run / 'config.yml'))}: .*newer scalar-nerfstudio \(schema version {newer}"):
        load_run_config(run)
    with pytest.raises(RunSchemaError, match="newer"):  # as ns-eval, ns-render, ns-viewer and ns-export load it
        yaml.load(text, Loader=yaml.Loader)
    content = json.loads((OLD_RUN / "blocks.json").read_text())
    content["version"] = newer
    (run / "blocks.json").write_text(json.dumps(content))
    with pytest.raises(BlockSplitError, match=rf"blocks.json was written by a newer scalar-nerfstudio \(schema version {newer}"):
        load_blocks_json(run / "blocks.json")
