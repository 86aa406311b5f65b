"""The block plan (blocks/plan.py): decided once from the cameras, saved with the split, read back whole."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from scalar_nerfstudio.blocks.plan import PlanSettings, load_plan, plan_blocks, save_plan
from scalar_nerfstudio.blocks.split import BlockSplitError, load_blocks_json, save_blocks_json
from scalar_nerfstudio.scenes.courtyard import look_at


def _walk(num: int = 24, length: float = 20.0) -> np.ndarray:
    """[N, 4, 4] poses along a street, each looking at a facade 5 units to the side."""
    poses = []
    for i, x in enumerate(np.linspace(0.0, length, num)):
        position = np.array([x, 0.0, 1.6])
        side = 1.0 if i % 2 else -1.0
        poses.append(look_at(position, position + np.array([0.0, 5.0 * side, 0.5])))
    return np.stack(poses)


def _plan(focal: float, settings: PlanSettings, poses: np.ndarray | None = None):
    poses = _walk() if poses is None else poses
    n = len(poses)
    return plan_blocks(
        centres=poses[:, :3, 3], directions=-poses[:, :3, 2], focal_px=np.full(n, focal),
        image_pixels=[640 * 480] * n, image_names=[f"images/{i:03d}.png" for i in range(n)], settings=settings,
    )


def test_save_and_load_give_the_same_plan(tmp_path: Path) -> None:
    plan = _plan(2000.0, PlanSettings(log2_hashmap_size=14, block_log2_hashmap_bounds=(12, 16)))
    assert plan.auto_num_blocks is not None and plan.auto_num_blocks > 1
    assert plan.held_blocks == tuple(range(plan.split.num_blocks)) and set(plan.capacities) == set(plan.held_blocks)
    save_plan(plan, tmp_path / "blocks.json")
    assert load_plan(tmp_path / "blocks.json") == plan
    split, names = load_blocks_json(tmp_path / "blocks.json")  # still a blocks.json for older readers
    assert split == plan.split and tuple(names) == plan.image_names


def test_a_loaded_plan_does_not_depend_on_the_cameras_parsed_later(tmp_path: Path) -> None:
    """What ns-render's inference mode did: the same cameras at 4x the focal length decide another K."""
    trained = _plan(200.0, PlanSettings(log2_hashmap_size=16))
    full_resolution = _plan(800.0, PlanSettings(log2_hashmap_size=16))
    assert trained.auto_num_blocks != full_resolution.auto_num_blocks
    save_plan(trained, tmp_path / "blocks.json")
    assert load_plan(tmp_path / "blocks.json").auto_num_blocks == trained.auto_num_blocks


def test_automatic_k_of_one_holds_no_block() -> None:
    plan = _plan(50.0, PlanSettings(log2_hashmap_size=19))
    assert plan.auto_num_blocks == 1 and plan.single_model
    assert plan.held_blocks == () and plan.capacities == {}


def test_explicit_settings_win_and_one_block_runs_hold_one() -> None:
    plan = _plan(2000.0, PlanSettings(num_blocks=3, block_log2_hashmap_size=11, block_max_resolution=99))
    assert plan.auto_num_blocks is None and plan.split.num_blocks == 3
    assert {c.log2_hashmap_size for c in plan.capacities.values()} == {11}
    assert {c.max_resolution for c in plan.capacities.values()} == {99}
    one = plan_blocks(
        centres=_walk()[:, :3, 3], directions=-_walk()[:, :3, 2], focal_px=np.full(24, 2000.0), image_pixels=[1] * 24,
        image_names=[str(i) for i in range(24)], settings=PlanSettings(only_block=2), given_split=plan.split,
    )
    assert one.held_blocks == (2,) and one.split == plan.split
    with pytest.raises(BlockSplitError, match="block 5 does not exist"):
        plan_blocks(centres=_walk()[:, :3, 3], directions=-_walk()[:, :3, 2], focal_px=np.full(24, 2000.0),
                    image_pixels=[1] * 24, image_names=[str(i) for i in range(24)], settings=PlanSettings(only_block=5),
                    given_split=plan.split)


def test_older_and_damaged_blocks_json_are_refused_by_name(tmp_path: Path) -> None:
    plan = _plan(2000.0, PlanSettings(num_blocks=2))
    save_blocks_json(plan.split, tmp_path / "old.json", plan.image_names)  # a split without a plan
    with pytest.raises(BlockSplitError, match="no plan"):
        load_plan(tmp_path / "old.json")
    save_plan(plan, tmp_path / "bad.json")
    content = json.loads((tmp_path / "bad.json").read_text())
    content["plan"]["held_blocks"] = [0, 7]
    (tmp_path / "bad.json").write_text(json.dumps(content))
    with pytest.raises(BlockSplitError, match="malformed plan"):
        load_plan(tmp_path / "bad.json")
