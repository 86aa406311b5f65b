"""Automatic block count and per-block capacity (blocks/capacity.py) and the model report."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import tiny_trainer
from hypothesis import given, settings, strategies as st
from prerequisites import CASTLE, FOX, SCENES, needs

from scalar_nerfstudio.blocks.capacity import auto_num_blocks, block_capacity, layout_scale
from scalar_nerfstudio.scenes.courtyard import look_at


def _orbit(num: int, radius: float, elevation_deg: float) -> np.ndarray:
    """[N, 4, 4] poses on a ring around the origin, all looking at it (an object capture)."""
    poses = []
    for angle in np.linspace(0.0, 2.0 * np.pi, num, endpoint=False):
        height = radius * np.tan(np.radians(elevation_deg))
        position = np.array([radius * np.cos(angle), radius * np.sin(angle), height])
        poses.append(look_at(position, np.zeros(3)))
    return np.stack(poses)


def _walk(num: int, length: float, seed: int = 0) -> np.ndarray:
    """[N, 4, 4] poses walking a street ``length`` long, each looking at the facade 5 units away."""
    rng = np.random.default_rng(seed)
    poses = []
    for x in np.linspace(0.0, length, num):
        position = np.array([x, 0.0, 1.6 + 0.1 * rng.random()])
        side = 1.0 if rng.random() < 0.5 else -1.0
        poses.append(look_at(position, position + np.array([0.3 * rng.standard_normal(), 5.0 * side, 0.5])))
    return np.stack(poses)


def _auto_k(poses: np.ndarray, focal: float, log2_t: int = 19) -> int:
    scale = layout_scale(poses[:, :3, 3], -poses[:, :3, 2], np.full(len(poses), focal))
    return auto_num_blocks(scale, log2_hashmap_size=log2_t, num_images=len(poses), min_images_per_block=6, max_blocks=8)


@pytest.mark.parametrize("elevation", [0.0, 30.0, 60.0])
@pytest.mark.parametrize("focal", [150.0, 300.0])
def test_object_capture_gets_one_block(elevation: float, focal: float) -> None:
    """Cameras all around an object, images up to ~600 pixels wide (fox: 270 x 480), stay one model."""
    assert _auto_k(_orbit(60, radius=3.0, elevation_deg=elevation), focal) == 1


def test_object_capture_at_very_high_resolution_is_split() -> None:
    """The rule is about pixels, not the kind of capture: a full orbit with ~3000-pixel images shows
    the object's surface at far more cells than a 2^19 table holds, so it gets blocks (arcs)."""
    assert _auto_k(_orbit(60, radius=3.0, elevation_deg=30.0), focal=1500.0) > 1


def test_spread_capture_gets_several_blocks_and_more_with_resolution() -> None:
    """A 200-unit street seen from 5 units needs several tables; fewer at a coarser resolution."""
    poses = _walk(80, length=200.0)
    fine, coarse = _auto_k(poses, focal=500.0), _auto_k(poses, focal=20.0)
    assert fine > 1
    assert coarse < fine
    assert _auto_k(poses, focal=500.0, log2_t=22) < fine, "a larger table needs fewer blocks"


def test_auto_k_is_bounded_by_images_and_max_blocks() -> None:
    poses = _walk(13, length=500.0)  # R^2 / T is huge; 13 images of at least 6 allow 2 blocks
    assert _auto_k(poses, focal=2000.0) == 2
    scale = layout_scale(poses[:, :3, 3], -poses[:, :3, 2], np.full(13, 2000.0))
    assert auto_num_blocks(scale, log2_hashmap_size=19, num_images=1000, min_images_per_block=1, max_blocks=3) == 3


def test_degenerate_layouts() -> None:
    """All cameras in one place, or all looking the same way, give finite scales and K >= 1."""
    same = np.repeat(_orbit(1, 3.0, 0.0), 10, axis=0)
    assert _auto_k(same, 500.0) == 1
    parallel = np.repeat(look_at(np.zeros(3), np.array([0.0, 1.0, 0.0]))[None], 20, axis=0)
    parallel[:, 0, 3] = np.linspace(0.0, 100.0, 20)
    scale = layout_scale(parallel[:, :3, 3], -parallel[:, :3, 2], np.full(20, 500.0))
    assert not scale.converged and scale.viewing_distance == pytest.approx(50.0)
    with pytest.raises(ValueError, match="finite"):
        layout_scale(np.full((3, 3), np.nan), np.ones((3, 3)), np.ones(3))


def test_a_street_rig_is_not_taken_for_converging_views() -> None:
    """A town's rig looks every way along the streets, and two cameras stand at each stop: their
    least-squares axis point lies in front of the cameras on average but in view of almost none, so
    the viewing distance falls back to half the extent (it was 0.66 m, giving K = 8 for any table)."""
    from scalar_nerfstudio.scenes.town import TownConfig, build_town, town_camera_poses

    config = TownConfig(num_images=300, width=128, height=96, blocks_x=2, blocks_y=2)
    poses = town_camera_poses(build_town(config))
    scale = layout_scale(poses[:, :3, 3], -poses[:, :3, 2], np.full(len(poses), config.focal_px))
    assert not scale.converged and scale.viewing_distance == pytest.approx(scale.extent / 2.0)
    # An inward ring looking at its centre still converges, at its radius.
    ring = _orbit(24, 3.0, 0.3)
    ring_scale = layout_scale(ring[:, :3, 3], -ring[:, :3, 2], np.full(24, 500.0))
    assert ring_scale.converged and ring_scale.viewing_distance == pytest.approx(3.0, rel=0.1)


def _parsed(scene: Path, downscale: int):
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    return NerfstudioDataParserConfig(data=scene, downscale_factor=downscale, eval_mode="interval", eval_interval=8).setup().get_dataparser_outputs("train")


@needs(f"castle-P30 and fox ({CASTLE.parent})", CASTLE.is_dir() and FOX.is_dir(), provided_by=SCENES)
def test_real_scenes_fox_one_block_castle_several() -> None:
    """The issue's examples, through nerfstudio's dataparser (the training frame and focal lengths)."""
    from scalar_nerfstudio.data.datamanager import parsed_layout_scale

    def k(scene: Path, downscale: int) -> int:
        parsed = _parsed(scene, downscale)
        return auto_num_blocks(parsed_layout_scale(parsed), log2_hashmap_size=19, num_images=len(parsed.image_filenames),
                               min_images_per_block=6, max_blocks=8)

    assert k(FOX, 1) == 1
    assert k(CASTLE, 1) == 4  # nerfstudio's default resolution for castle-P30 (768 x 512)
    assert k(CASTLE, 2) == 2
    assert k(CASTLE, 4) == 1  # 192 x 128 images: the courtyard is ~380 pixels across, one table holds it


@settings(max_examples=200, deadline=None)
@given(
    extent=st.floats(1e-6, 1e6),
    pixels=st.integers(1, 10**9),
    low=st.integers(1, 24),
    span=st.integers(0, 8),
    res_low=st.integers(1, 4096),
    res_span=st.integers(0, 4096),
)
def test_block_capacity_respects_bounds(*, extent: float, pixels: int, low: int, span: int, res_low: int, res_span: int) -> None:
    scale = layout_scale(np.array([[0.0, 0, 0], [10.0, 0, 0]]), np.array([[0.0, 1, 0], [0.0, 1, 0]]), np.array([500.0, 500.0]))
    capacity = block_capacity(scale, block_extent=extent, block_pixels=pixels, log2_hashmap_bounds=(low, low + span),
                              max_resolution_bounds=(res_low, res_low + res_span))
    assert low <= capacity.log2_hashmap_size <= low + span
    assert res_low <= capacity.max_resolution <= res_low + res_span


def test_block_capacity_grows_with_extent_and_is_capped_by_pixels() -> None:
    scale = layout_scale(np.array([[0.0, 0, 0], [10.0, 0, 0]]), np.array([[0.0, 1, 0], [0.0, 1, 0]]), np.array([100.0, 100.0]))
    small = block_capacity(scale, block_extent=1.0, block_pixels=10**9, log2_hashmap_bounds=(10, 24), max_resolution_bounds=(16, 8192))
    large = block_capacity(scale, block_extent=8.0, block_pixels=10**9, log2_hashmap_bounds=(10, 24), max_resolution_bounds=(16, 8192))
    assert large.log2_hashmap_size > small.log2_hashmap_size and large.max_resolution > small.max_resolution
    few_pixels = block_capacity(scale, block_extent=8.0, block_pixels=5000, log2_hashmap_bounds=(10, 24), max_resolution_bounds=(16, 8192))
    assert few_pixels.log2_hashmap_size == 13, "a table larger than the observed pixels cannot be filled"


# ----------------------------------------------------------------- through the pipeline / trainer


def _trainer(scene: Path, output_dir: Path, log2_hashmap_size: int = 14, **pipeline):
    """Tiny trainer: 6 global and 3 block steps, 256 rays; automatic K unless ``num_blocks`` is given."""
    settings = {"num_blocks": None, "global_steps": 6, "block_steps": 3, **pipeline}
    return tiny_trainer(scene, output_dir, log2_hashmap_size=log2_hashmap_size, rays_per_batch=256, **settings)


def _tables(trainer) -> dict:
    model = trainer.pipeline.model
    return {k: (b.field.config.log2_hashmap_size, b.field.config.max_resolution) for k, b in model.blocks.items()}


def test_pipeline_explicit_settings_win(scene: Path, tmp_path: Path) -> None:
    trainer = _trainer(scene, tmp_path, num_blocks=3, block_log2_hashmap_size=12, block_max_resolution=128, block_init="fresh")
    assert trainer.pipeline.auto_num_blocks is None and trainer.pipeline.split.num_blocks == 3
    assert _tables(trainer) == {"0": (12, 128), "1": (12, 128), "2": (12, 128)}
    for block in trainer.pipeline.model.blocks.values():
        encoder = block.field.encoder
        assert encoder.hashmap_size == 1 << 12 and max(encoder.resolutions) == 128
        assert encoder.table.shape[0] <= encoder.num_levels * (1 << 12)


@pytest.mark.slow  # trains
def test_pipeline_automatic_capacity_within_bounds_and_report(scene: Path, tmp_path: Path) -> None:
    """Automatic K and per-block tables; training ends with model_report.json naming every model."""
    trainer = _trainer(scene, tmp_path, num_blocks=2, block_log2_hashmap_bounds=(10, 13), block_max_resolution_bounds=(32, 200),
                       block_init="fresh")  # per-block capacities are those of fresh blocks (a copy has the global model's)
    tables = _tables(trainer)
    assert set(tables) == {"0", "1"}
    for log2_size, resolution in tables.values():
        assert 10 <= log2_size <= 13 and 32 <= resolution <= 200
    trainer.train()
    report = json.loads((trainer.base_dir / "model_report.json").read_text())
    names = [m["model"] for m in report["models"]]
    assert names == ["global", "block 0", "block 1"]
    params = {m["model"]: m["parameters"] for m in report["models"]}
    model = trainer.pipeline.model
    assert params["global"] == sum(p.numel() for p in model.global_model.parameters())
    assert params["block 1"] == sum(p.numel() for p in model.blocks["1"].parameters())
    assert report["total_parameters"] == sum(params.values())
    assert all(m["trained"] for m in report["models"])
    # Adam state is counted; the global model's and block 0's were released when their phases ended
    assert [m["optimizer_state_mib"] > 0 for m in report["models"]] == [False, False, True]
    assert report["peak_rss_mib"] > 100


def test_pipeline_auto_k(scene: Path, tmp_path: Path) -> None:
    """The tiny synthetic courtyard (96 px images, ~290 px across) against the global table size:
    2^19 rows hold it, so no block is allocated or trained; 2^14 rows do not, so it is split."""
    trainer = _trainer(scene, tmp_path, log2_hashmap_size=19)
    pipeline = trainer.pipeline
    assert pipeline.auto_num_blocks == 1
    assert [p.name for p in pipeline.phases] == ["global"]
    assert len(pipeline.model.blocks) == 0
    split = _trainer(scene, tmp_path / "small-table", log2_hashmap_size=14).pipeline
    assert split.auto_num_blocks == 3 == split.split.num_blocks, "ceil(291^2 / 2^14) = 6, at most 21 // 6 = 3 blocks"
    assert [p.name for p in split.phases] == ["global", "block 0", "block 1", "block 2"]
