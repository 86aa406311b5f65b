"""The town through nerfstudio: its dataparser's cameras walk the streets, held-out images carry the true
depth, and a run is bounded by the scene's depth. All sizes are tiny."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny_town import TINY, write_tiny_town

from scalar_nerfstudio.scenes.town import (
    DEPTH_PNG_MAX_M,
    TownConfig,
    build_town,
    load_town,
    points_inside_buildings,
    points_on_streets,
    read_depth,
    render_town_rays,
    town_camera_poses,
)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_town(tmp_path_factory.mktemp("town") / "scene")


def _rays_in_town_frame(rays, outputs) -> tuple:
    """nerfstudio's rays (dataparser frame) -> ([N, 3] origins, [N, 3] directions) in the written town's
    metres, undoing the dataparser's orientation, centring and scaling (``outputs``: its outputs)."""
    transform = outputs.dataparser_transform.double().numpy()
    scale = float(outputs.dataparser_scale)
    origins = (rays.origins.reshape(-1, 3).double().numpy() / scale - transform[:, 3]) @ transform[:, :3]
    directions = rays.directions.reshape(-1, 3).double().numpy() @ transform[:, :3]
    return origins, directions


def _datamanager(scene: Path, **options):
    """The datamanager ns-train builds for ``scene`` (every 8th frame held out), set up for evaluation."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from scalar_nerfstudio.data.datamanager import ScalarDataManagerConfig

    config = ScalarDataManagerConfig(data=scene, dataparser=NerfstudioDataParserConfig(eval_mode="interval", eval_interval=8), **options)
    return config.setup(device="cpu", test_mode="test")


def test_nerfstudio_parses_the_scene_and_cameras_walk_the_streets(tiny_scene: Path) -> None:
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    parser = NerfstudioDataParserConfig(data=tiny_scene, eval_mode="interval", eval_interval=8).setup()
    train = parser.get_dataparser_outputs(split="train")
    val = parser.get_dataparser_outputs(split="val")
    assert [p.name for p in val.image_filenames] == ["frame_00000.png", "frame_00008.png", "frame_00016.png"]
    assert len(train.image_filenames) == TINY.num_images - 3
    assert [p.name for p in train.metadata["depth_filenames"]] == [p.name for p in train.image_filenames]
    assert train.cameras.width[0].item() == TINY.width and abs(train.cameras.fx[0].item() - TINY.focal_px) < 1e-3

    # Undo nerfstudio's orientation, centring and scaling: the centres are the written ones.
    transform = train.dataparser_transform.double().numpy()
    scale = float(train.dataparser_scale)
    centres = (val.cameras.camera_to_worlds[:, :3, 3].double().numpy() / scale - transform[:, 3]) @ transform[:, :3]
    frames = json.loads((tiny_scene / "transforms.json").read_text())["frames"]
    written = np.array([f["transform_matrix"] for f in frames])[:, :3, 3]
    np.testing.assert_allclose(centres, written[[0, 8, 16]], atol=1e-4)

    town = load_town(tiny_scene)
    assert points_on_streets(written, town).all()
    assert not points_inside_buildings(written, town, margin=1.0).any()
    low, high = TINY.camera_height
    assert ((written[:, 2] >= low) & (written[:, 2] <= high)).all()

    # nerfstudio's own rays for an eval frame, mapped back to the town, see the written depth.
    origins, directions = _rays_in_town_frame(val.cameras.generate_rays(camera_indices=1), train)
    _, depth = render_town_rays(origins, directions, town)
    cos = -(directions / np.linalg.norm(directions, axis=1, keepdims=True)) @ np.array(frames[8]["transform_matrix"])[:3, 2]
    png = read_depth(tiny_scene / frames[8]["depth_file_path"]).reshape(-1)
    known = png > 0
    assert known.mean() > 0.3
    assert np.median(np.abs(depth[known] * cos[known] - png[known])) < 2e-3


def test_eval_images_carry_the_true_ray_depth_and_training_images_do_not(tiny_scene: Path) -> None:
    """The datamanager gives each eval image its true distance along every pixel's ray, in the
    model's units (what evaluation scores the rendered depth against): the generator's exact ray
    depth, within the PNG's millimetre, 0 for the sky. Training batches carry no depth."""
    datamanager = _datamanager(tiny_scene, train_num_rays_per_batch=64)
    assert datamanager.eval_dataset.load_ray_depth and not datamanager.train_dataset.load_ray_depth
    _, train_batch = datamanager.next_train(0)
    assert "ray_depth" not in train_batch

    outputs = datamanager.eval_dataset._dataparser_outputs
    scale = float(outputs.dataparser_scale)
    town = load_town(tiny_scene)

    def check(camera, ray_depth: torch.Tensor) -> bool:
        """ray_depth [H, W, 1] against the generator's exact depth along nerfstudio's rays of ``camera``;
        whether the image sees the sky."""
        assert ray_depth.shape == (TINY.height, TINY.width, 1) and ray_depth.dtype == torch.float32
        origins, directions = _rays_in_town_frame(camera.generate_rays(camera_indices=0, keep_shape=True), outputs)
        _, exact = render_town_rays(origins, directions, town)  # [H * W] metres along the ray, inf: sky
        loaded = ray_depth.reshape(-1).double().numpy() / scale
        known = loaded > 0
        assert known.mean() > 0.3, "ground and walls"
        assert (~np.isfinite(exact[~known]) | (exact[~known] > DEPTH_PNG_MAX_M)).all(), "unknown only where the PNG holds no depth"
        np.testing.assert_allclose(loaded[known], exact[known], atol=2e-3, rtol=1e-4)
        return bool((~known).any())

    for camera, batch in datamanager.fixed_indices_eval_dataloader:  # what evaluation reads
        check(camera, batch["ray_depth"])
    train = datamanager.train_dataset  # more views, some with sky: the same conversion
    assert any([check(train.cameras[i : i + 1], train.ray_depth(i)) for i in range(6)]), "some frame should see the sky"


def test_missing_depth_files_skip_the_depth_metrics_with_a_message(tiny_scene: Path, tmp_path: Path, capsys) -> None:
    """A scene whose depth files are not all there (a downscaled load looks for depths_N/) still
    evaluates: without depth, and saying why, instead of failing in the middle of ns-eval."""
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    (scene / "depths" / "frame_00008.png").unlink()  # an eval frame's
    datamanager = _datamanager(scene)
    assert not datamanager.eval_dataset.load_ray_depth
    assert all("ray_depth" not in batch for _, batch in datamanager.fixed_indices_eval_dataloader)
    log = " ".join(capsys.readouterr().out.split())
    assert "depth metrics skipped: 1 of the eval images' depth files are missing" in log and "frame_00008.png" in log


def test_an_unreadable_depth_file_is_named(tiny_scene: Path, tmp_path: Path) -> None:
    """An eval image's depth file that exists but cannot be read stops evaluation with its name."""
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    (scene / "depths" / "frame_00000.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match=r"frame_00000\.png: cannot read this depth image"):
        _datamanager(scene)  # nerfstudio reads the eval images while setting up


def _train_outputs(scene: Path):
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    return NerfstudioDataParserConfig(data=scene, eval_mode="interval", eval_interval=8).setup().get_dataparser_outputs(split="train")


def test_the_scene_radius_from_depth_is_that_of_the_farthest_true_surface(tiny_scene: Path) -> None:
    """With every pixel and no margin, the bound is the distance from the centre of the farthest
    surface point the generator put in front of a training camera (within the PNG's millimetre);
    the default (99.9 % of the points, twice that radius) holds every one of them."""
    from scalar_nerfstudio.data.depth import scene_radius_from_depth

    outputs = _train_outputs(tiny_scene)
    scale = float(outputs.dataparser_scale)
    town = load_town(tiny_scene)
    farthest = 0.0
    for i in range(len(outputs.image_filenames)):
        rays = outputs.cameras[i : i + 1].generate_rays(camera_indices=0)
        origins, directions = _rays_in_town_frame(rays, outputs)
        _, exact = render_town_rays(origins, directions, town)  # metres along the ray, inf: sky
        known = np.isfinite(exact) & (exact <= DEPTH_PNG_MAX_M)
        points = rays.origins.reshape(-1, 3).double().numpy() + rays.directions.reshape(-1, 3).double().numpy() * (exact * scale)[:, None]
        farthest = max(farthest, float(np.linalg.norm(points[known], axis=1).max()))
    tight = scene_radius_from_depth(outputs, quantile=1.0, margin=1.0)
    assert tight == pytest.approx(farthest, abs=2e-3 * scale + 1e-5)
    assert scene_radius_from_depth(outputs) >= tight
    half = scene_radius_from_depth(outputs, max_images=2, quantile=1.0, margin=1.0)  # the first and last image only
    assert half <= tight


def test_a_scene_without_all_its_depth_files_is_not_bounded(tiny_scene: Path, tmp_path: Path) -> None:
    from scalar_nerfstudio.data.depth import scene_radius_from_depth

    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    (scene / "depths" / "frame_00001.png").unlink()
    assert scene_radius_from_depth(_train_outputs(scene)) is None
    (scene / "depths" / "frame_00001.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match=r"frame_00001\.png: cannot read this depth image"):
        scene_radius_from_depth(_train_outputs(scene))
    transforms = json.loads((scene / "transforms.json").read_text())
    for frame in transforms["frames"]:
        del frame["depth_file_path"]
    (scene / "transforms.json").write_text(json.dumps(transforms))
    assert scene_radius_from_depth(_train_outputs(scene)) is None


def test_all_cameras_on_streets_for_the_default_town() -> None:
    town = build_town(TownConfig())
    centres = town_camera_poses(town)[:, :3, 3]
    assert points_on_streets(centres, town).all()
    assert not points_inside_buildings(centres, town, margin=1.0).any()


def test_default_town_gets_more_than_one_automatic_block() -> None:
    """scalar-nerf's capacity rule (T = 2^19, 6 images per block, at most 8) splits the default town."""
    from scalar_nerfstudio.blocks.capacity import auto_num_blocks, layout_scale

    config = TownConfig()
    poses = town_camera_poses(build_town(config))
    train = poses[np.arange(len(poses)) % 8 != 0]
    scale = layout_scale(train[:, :3, 3], -train[:, :3, 2], np.full(len(train), config.focal_px))
    assert auto_num_blocks(scale, log2_hashmap_size=19, num_images=len(train), min_images_per_block=6, max_blocks=8) > 1


def test_check_scene_accepts_the_town(tiny_scene: Path) -> None:
    from scalar_nerfstudio.data.validation import check_scene

    assert check_scene(tiny_scene, eval_interval=8) == TINY.num_images


# ------------------------------------------------------------------------------------- CLI


@pytest.mark.parametrize("scene_name, from_depth", [("town", True), ("town", False), ("courtyard", True)])
def test_a_new_run_is_bounded_by_the_scenes_depth_and_records_it(scene_name: str, from_depth: bool, tiny_scene: Path,
                                                                   scene: Path, tmp_path: Path) -> None:
    """ns-train on a scene with depth images bounds every model (global and blocks) by them and
    records the radius in the run's blocks.json (config.yml keeps the option as given), so that every
    later load renders as trained; a scene without depth, or --pipeline.scene-radius-from-depth False,
    leaves rays unbounded."""
    import yaml
    from conftest import tiny_trainer

    from scalar_nerfstudio.blocks.plan import SceneBound, load_plan
    from scalar_nerfstudio.data.depth import scene_radius_from_depth

    data = tiny_scene if scene_name == "town" else scene
    trainer = tiny_trainer(data, tmp_path, num_blocks=2, scene_radius_from_depth=from_depth)
    expected = scene_radius_from_depth(trainer.pipeline.datamanager.train_dataparser_outputs) if from_depth else None
    assert (expected is not None) == (scene_name == "town" and from_depth)
    model = trainer.pipeline.model
    assert len(model.blocks) == 2
    assert trainer.pipeline.scene_radius == expected
    for collider in [model.collider] + [block.collider for block in model.blocks.values()]:
        assert collider.scene_radius == expected
    saved = yaml.load((trainer.base_dir / "config.yml").read_text(), Loader=yaml.Loader)
    assert saved.pipeline.model.scene_radius is None and saved.pipeline.run_plan is not None
    assert load_plan(saved.pipeline.run_plan).scene_bound == SceneBound(expected)


def _differences(saved: object, asked: object, path: str = "config") -> list:
    """The dotted paths at which two configs (dataclasses, dicts, values) differ."""
    import dataclasses

    if dataclasses.is_dataclass(saved) and not isinstance(saved, type) and type(saved) is type(asked):
        return [d for f in dataclasses.fields(saved)
                for d in _differences(getattr(saved, f.name), getattr(asked, f.name), f"{path}.{f.name}")]
    if isinstance(saved, dict) and isinstance(asked, dict) and saved.keys() == asked.keys():
        return [d for key in saved for d in _differences(saved[key], asked[key], f"{path}[{key!r}]")]
    return [] if saved == asked else [f"{path}: {saved!r} in config.yml, {asked!r} asked"]


def test_a_trained_runs_config_is_as_asked_and_its_loads_keep_the_derived_values(tiny_scene: Path,
                                                                                  tmp_path: Path) -> None:
    """The config.yml of a short run (global phase and 2 blocks) is the config it was given, nothing derived
    written in (steps, device, mixed precision, scene radius, collider); ns-eval's loading of the run
    (nerfstudio's eval_setup) still bounds every model by the radius the run fitted to its depth images."""
    import copy

    from conftest import tiny_trainer
    from nerfstudio.utils.eval_utils import eval_setup

    from scalar_nerfstudio.runs import load_run_config

    asked: list = []

    def configure(config) -> None:
        config.pipeline.model.render_occupancy_resolution = 16  # a cheap render grid at each phase's end
        asked.append(copy.deepcopy(config))

    trainer = tiny_trainer(tiny_scene, tmp_path, num_blocks=2, global_steps=6, block_steps=3, configure=configure)
    trainer.train()
    radius = trainer.pipeline.scene_radius
    assert radius is not None and trainer.total_steps == 12
    run = trainer.base_dir
    saved = load_run_config(run)
    assert saved.pipeline.run_plan == (run / "blocks.json").resolve()  # the link to what the run derived
    (expected,) = asked
    for name in ("timestamp", "experiment_name"):  # set by nerfstudio's set_timestamp and save_config
        setattr(expected, name, getattr(saved, name))
    expected.pipeline.run_plan = saved.pipeline.run_plan
    # nerfstudio's datamanager writes --data into its dataparser's config, in every method's run
    expected.pipeline.datamanager.dataparser.data = saved.pipeline.datamanager.dataparser.data
    assert _differences(saved, expected) == []
    assert (saved.max_num_iterations, saved.machine.device_type, saved.pipeline.model.scene_radius) == (0, "auto", None)

    _, pipeline, _, step = eval_setup(run / "config.yml", test_mode="test")
    assert step == 11 and pipeline.scene_radius == radius
    model = pipeline.model
    for collider in [model.collider, model.global_model.collider] + [block.collider for block in model.blocks.values()]:
        assert collider.scene_radius == radius
