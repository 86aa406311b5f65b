"""The procedural town scene (scalar_nerfstudio/scenes/town/) and scalar-nerf-make-scene.

All sizes are tiny: no training, a few seconds in all.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path
from typing import List

import numpy as np
import pytest
from tiny_town import TINY, write_tiny_town

from scalar_nerfstudio.scenes.town import (
    DEPTH_PNG_MAX_M,
    GROUND,
    TownConfig,
    build_town,
    depth_suffix,
    intersect_town,
    load_town,
    points_inside_buildings,
    points_on_streets,
    read_depth,
    render_town_image,
    render_town_rays,
    town_boxes,
    town_camera_poses,
    write_town,
)


def _files(folder: Path) -> List[Path]:
    return sorted(p.relative_to(folder) for p in folder.rglob("*") if p.is_file())


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_town(tmp_path_factory.mktemp("town") / "scene")


# ------------------------------------------------------------------------------ determinism


def test_same_seed_writes_byte_identical_files(tiny_scene: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    write_town(again, TINY, progress=False)
    files = _files(tiny_scene)
    assert files == _files(again)
    assert len([f for f in files if f.parts[0] == "images"]) == TINY.num_images
    assert len([f for f in files if f.parts[0] == "depths"]) == TINY.num_images
    for name in files:
        assert (tiny_scene / name).read_bytes() == (again / name).read_bytes(), f"{name} differs between two writes with the same seed"


def test_the_town_leaves_malloc_alone_when_the_user_tuned_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The opt-out of engine/allocator.py holds for the scene generator too: with any of glibc's malloc
    variables set, writing a town never reaches mallopt."""
    from unittest import mock

    from scalar_nerfstudio.engine import allocator

    for name in allocator.GLIBC_MALLOC_ENV:
        monkeypatch.setenv(name, "1")
        assert not allocator.keep_render_temporaries() and not allocator.keep_freed_memory()
        monkeypatch.delenv(name)
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "1048576")
    with mock.patch.object(allocator, "_glibc", side_effect=AssertionError("mallopt reached")):
        write_town(tmp_path / "scene", dataclasses.replace(TINY, num_images=1), progress=False)


def test_other_seed_differs(tiny_scene: Path, tmp_path: Path) -> None:
    other = tmp_path / "other"
    write_town(other, dataclasses.replace(TINY, seed=4), progress=False)
    for name in ("transforms.json", "scene.json", "images/frame_00001.png"):
        assert (tiny_scene / name).read_bytes() != (other / name).read_bytes(), f"{name} is the same for seeds 3 and 4"


def test_workers_do_not_change_the_output(tiny_scene: Path, tmp_path: Path) -> None:
    parallel = tmp_path / "parallel"
    write_town(parallel, TINY, progress=False, workers=2)
    for name in _files(tiny_scene):
        assert (tiny_scene / name).read_bytes() == (parallel / name).read_bytes(), f"{name} differs with 2 workers"


def test_scene_json_records_options_and_geometry(tiny_scene: Path) -> None:
    content = json.loads((tiny_scene / "scene.json").read_text())
    assert TownConfig.from_json(content["config"]) == TINY
    town = load_town(tiny_scene)
    boxes = np.array([[box["lo"], box["hi"]] for box in content["boxes"]])
    np.testing.assert_array_equal(boxes, town_boxes(town))
    assert town.num_buildings > 10 and (boxes[:, 1, 2] > 5.0).all() and (boxes[:, 0, 2] == 0.0).all()


def test_config_rejects_bad_options() -> None:
    for bad, field in (({"width": 0}, "width"), ({"num_images": -1}, "num_images"), ({"blocks_x": 0}, "blocks_x"),
                       ({"block_size": -5.0}, "block_size"), ({"road_width": 20.0}, "road_width"), ({"fov_x_deg": 180.0}, "fov_x_deg"),
                       ({"capture": "drone"}, "capture"), ({"aerial_altitude": 0.0}, "aerial_altitude"), ({"aerial_altitude": float("inf")}, "aerial_altitude"), ({"rig_headings": ()}, "rig_headings"), ({"rig_headings": (float("nan"),)}, "rig_headings")):
        with pytest.raises(ValueError, match=field):
            TownConfig(**bad)


# ------------------------------------------------------------------------------- the capture


def test_rig_stops_take_one_frame_per_camera_at_its_headings() -> None:
    """The default capture: frames 2s and 2s+1 come from the same stop, 30 degrees left and right of
    the driving direction (a few degrees of jitter), level cameras on the streets."""
    config = TownConfig(num_images=41, width=16, height=12, blocks_x=2, blocks_y=2, seed=2)
    assert config.capture == "rig" and config.rig_headings == (30.0, -30.0)
    town = build_town(config)
    poses = town_camera_poses(town)
    assert poses.shape == (41, 4, 4)  # an odd count: the last stop keeps its first camera
    centres = poses[:, :3, 3]
    np.testing.assert_allclose(centres[0:40:2], centres[1:40:2])
    assert points_on_streets(centres, town).all()
    forward = -poses[:, :3, 2]
    yaw = np.degrees(np.arctan2(forward[:, 1], forward[:, 0]))
    between = (yaw[0:40:2] - yaw[1:40:2] + 180.0) % 360.0 - 180.0  # left camera minus right camera
    assert np.all(np.abs(between - 60.0) < 15.0), between
    steps = np.linalg.norm(np.diff(centres[0:40:2], axis=0), axis=1)
    # Evenly spaced along each street (the walk jumps where one street ends and the next begins).
    assert np.mean(np.abs(steps - np.median(steps)) < 0.05 * np.median(steps)) > 0.6, steps


def _nearest_like_training_frame(poses: np.ndarray, max_angle_deg: float = 10.0) -> np.ndarray:
    """[E] metres from each held-out frame (every 8th, as nerfstudio's --eval-interval 8) to the
    nearest training frame that looks within ``max_angle_deg`` of its direction (inf: none)."""
    forward = -poses[:, :3, 2]
    held_out = np.arange(len(poses)) % 8 == 0
    cos = forward[held_out] @ forward[~held_out].T  # [E, T]
    distance = np.linalg.norm(poses[held_out, :3, 3][:, None] - poses[~held_out, :3, 3][None], axis=-1)
    return np.where(cos > np.cos(np.radians(max_angle_deg)), distance, np.inf).min(axis=1)


def test_rig_puts_every_held_out_view_between_training_views_of_its_camera() -> None:
    """Why ``rig`` is the default: a held-out frame's camera took training frames at the stops next
    to it, so evaluation measures reconstruction, not a guess from other angles. The walk's random
    headings leave held-out views that no training view resembles (on 2026-11-23, 300 images of a
    2 x 2 town at 128 x 96: 18.4 dB held-out PSNR with the rig against 17.7 dB with the walk after
    1300 steps of one 2^14 model, docs/notebook/defaults.md)."""
    common = dict(num_images=200, width=16, height=12, blocks_x=2, blocks_y=2, seed=4)
    rig = build_town(TownConfig(**common))
    walk = build_town(TownConfig(capture="walk", **common))
    rig_poses, walk_poses = town_camera_poses(rig), town_camera_poses(walk)
    stop_spacing = np.median(np.linalg.norm(np.diff(rig_poses[0::2, :3, 3], axis=0), axis=1))
    near_rig = _nearest_like_training_frame(rig_poses)
    near_walk = _nearest_like_training_frame(walk_poses)
    # One stop away (two where the neighbouring stop turned into another street).
    assert (near_rig < 2.1 * stop_spacing).all() and np.median(near_rig) < 1.1 * stop_spacing, near_rig / stop_spacing
    assert (near_walk > 2.5 * stop_spacing).mean() > 0.4, near_walk / stop_spacing


def test_aerial_flight_covers_the_town_from_above_looking_down() -> None:
    """The ``aerial`` capture: every camera flies above the tallest roof, looks down 6-14 degrees
    forward of the vertical, an even number of flight lines (as many frames each way) cover the
    whole town (ring included) with side overlap, and a held-out frame lies a few metres from
    training frames that look the same way."""
    config = TownConfig(num_images=400, width=16, height=12, blocks_x=2, blocks_y=2, capture="aerial", seed=5)
    town = build_town(config)
    poses = town_camera_poses(town)
    assert poses.shape == (400, 4, 4)
    centres = poses[:, :3, 3]
    assert (centres[:, 2] >= town.hi[:, 2].max() + 2.0).all()
    assert (np.abs(centres[:, 2] - config.aerial_altitude) <= 0.5).all()
    down = poses[:, 2, 2]  # -(world z of the optical axis): the camera looks along its -z
    assert (down >= np.cos(np.radians(14.0)) - 1e-9).all() and (down <= np.cos(np.radians(6.0)) + 1e-9).all()
    # Each line's footprint across it (image width on the ground) overlaps its neighbours'.
    footprint = 2.0 * config.aerial_altitude * np.tan(np.radians(config.fov_x_deg) / 2.0)
    lines = np.unique(np.round(centres[:, 1], 6))
    assert len(lines) >= 4 and len(lines) % 2 == 0 and np.all(np.diff(lines) <= 0.5 * footprint + 1e-6), (lines, footprint)
    eastward = -poses[:, 0, 2] > 0
    assert abs(int(eastward.sum()) - int((~eastward).sum())) <= 1
    (sx, sy) = config.extent
    assert lines[0] - footprint / 2.0 <= -sy / 2.0 and lines[-1] + footprint / 2.0 >= sy / 2.0
    assert centres[:, 0].min() < -sx / 2.0 + 2.0 and centres[:, 0].max() > sx / 2.0 - 2.0
    near = _nearest_like_training_frame(poses, max_angle_deg=25.0)
    spacing = len(lines) * sx / len(poses)
    assert (near < 2.1 * spacing).all(), near / spacing


def test_aerial_frames_see_ground_and_roofs_only_within_the_depth_range(tmp_path: Path) -> None:
    """Looking down from the default altitude, no pixel sees the sky or lies beyond the depth PNGs'
    range (a zero there would read as sky), and the depth agrees with the flight height."""
    config = TownConfig(num_images=9, width=24, height=18, blocks_x=1, blocks_y=1, capture="aerial", seed=6)
    write_town(tmp_path / "scene", config, progress=False)
    town = build_town(config)
    for index, pose in enumerate(town_camera_poses(town)):
        depth = read_depth(tmp_path / "scene" / "depths" / f"frame_{index:05d}.png")
        assert (depth > 0).all() and depth.max() <= DEPTH_PNG_MAX_M
        half_height = np.tan(np.radians(config.fov_x_deg) / 2.0) * config.height / config.width
        deepest = pose[2, 3] / (np.cos(np.radians(14.0)) - half_height * np.sin(np.radians(14.0)))  # the ground at a far corner
        assert depth.max() <= deepest + 0.01
        # The tallest roof at the nearest; a ray's z-depth is its drop over at most sqrt(1 + half_height^2).
        assert depth.min() >= (pose[2, 3] - town.hi[:, 2].max()) / np.sqrt(1.0 + half_height**2) - 0.01


def test_a_flight_beyond_the_pngs_range_writes_its_depth_as_npy(tmp_path: Path) -> None:
    """At 90 m the ground lies beyond a 16-bit PNG's 65.535 m: the scene writes float32 ``.npy`` depth in the
    same millimetres, every ground pixel known (none written as 0), and nerfstudio's loader reads the same
    values. A flight at the default 55 m keeps its PNGs."""
    from nerfstudio.data.utils.data_utils import get_depth_image_from_path

    config = TownConfig(num_images=3, width=24, height=18, blocks_x=1, blocks_y=1, capture="aerial", aerial_altitude=90.0, seed=6)
    assert depth_suffix(config) == ".npy" and depth_suffix(dataclasses.replace(config, aerial_altitude=55.0)) == ".png"
    write_town(tmp_path / "scene", config, progress=False)
    frames = json.loads((tmp_path / "scene" / "transforms.json").read_text())["frames"]
    town = load_town(tmp_path / "scene")
    for frame in frames:
        assert frame["depth_file_path"].endswith(".npy")
        _, _, z_depth = render_town_image(town, np.array(frame["transform_matrix"]))
        depth = read_depth(tmp_path / "scene" / frame["depth_file_path"])
        assert np.isfinite(z_depth).all() and (depth > 0).all() and depth.max() > DEPTH_PNG_MAX_M
        np.testing.assert_allclose(depth, z_depth, rtol=1e-6)
        loaded = get_depth_image_from_path(tmp_path / "scene" / frame["depth_file_path"], config.height, config.width, 1e-3)[..., 0].numpy()
        np.testing.assert_allclose(loaded, depth, rtol=1e-6)
    assert not list((tmp_path / "scene" / "depths").glob("*.png"))


def test_nerfstudio_keeps_an_aerial_town_level(tmp_path: Path) -> None:
    """nerfstudio's default orientation (the cameras' mean "up" becomes +z) keeps the town level:
    the flight's cameras, at one altitude, stay within a few centimetres per 100 m of one height
    in the dataparser's frame (back-and-forth lines with no forward lean would tilt it)."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    config = TownConfig(num_images=120, width=16, height=12, blocks_x=2, blocks_y=2, capture="aerial", seed=7)
    write_town(tmp_path / "scene", config, progress=False)
    train = NerfstudioDataParserConfig(data=tmp_path / "scene", eval_mode="interval", eval_interval=8).setup().get_dataparser_outputs(split="train")
    centres = train.cameras.camera_to_worlds[:, :3, 3].double().numpy()
    spread = np.ptp(centres[:, :2], axis=0).max()
    assert spread > 0 and np.ptp(centres[:, 2]) < 0.03 * spread, (np.ptp(centres[:, 2]), spread)  # jitter: 1 m in 150 m


def test_aerial_and_rig_capture_is_the_drones_frames_then_the_rigs_and_stays_level(tmp_path: Path) -> None:
    """``aerial+rig``: the first half of the frames are the drone's survey, the rest the rig's drive, each as
    its own capture of that many frames would take them; nerfstudio's orientation keeps the street cameras
    (all at one height) level although half the cameras look down."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    common = dict(width=16, height=12, blocks_x=2, blocks_y=2, seed=7)
    mixed = TownConfig(num_images=121, capture="aerial+rig", **common)
    poses = town_camera_poses(build_town(mixed))
    aerial = town_camera_poses(build_town(TownConfig(num_images=61, capture="aerial", **common)))
    rig = town_camera_poses(build_town(TownConfig(num_images=60, capture="rig", **common)))
    assert poses.shape == (121, 4, 4) and np.array_equal(poses[:61], aerial) and np.array_equal(poses[61:], rig)
    write_town(tmp_path / "scene", mixed, progress=False)
    train = NerfstudioDataParserConfig(data=tmp_path / "scene", eval_mode="interval", eval_interval=8).setup().get_dataparser_outputs(split="train")
    centres = train.cameras.camera_to_worlds[:, :3, 3].double().numpy()
    street = np.array([int(Path(name).stem.split("_")[1]) >= 61 for name in train.image_filenames])
    spread = np.ptp(centres[:, :2], axis=0).max()
    assert street.sum() > 40 and np.ptp(centres[street, 2]) < 0.01 * spread, (np.ptp(centres[street, 2]), spread)


@pytest.mark.parametrize("altitude, fov, message", [(20.0, 45.0, "tallest roof"), (90.0, 160.0, "horizon")])
def test_an_aerial_altitude_that_cannot_be_flown_is_refused_before_writing(tmp_path: Path, altitude: float, fov: float, message: str) -> None:
    config = TownConfig(num_images=4, width=16, height=12, blocks_x=2, blocks_y=2, capture="aerial", aerial_altitude=altitude, fov_x_deg=fov, seed=5)
    with pytest.raises(ValueError, match=message):
        write_town(tmp_path / "scene", config, progress=False)
    assert not (tmp_path / "scene").exists()
    result = _cli("--output", str(tmp_path / "cli"), "--num-images", "4", "--width", "16", "--height", "12", "--blocks-x", "2", "--blocks-y", "2",
                  "--seed", "5", "--capture", "aerial", "--aerial-altitude", str(altitude), "--fov", str(fov))
    assert result.returncode == 2 and message in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and not (tmp_path / "cli").exists()


def test_a_version_1_scene_loads_as_the_walk_it_was(tiny_scene: Path, tmp_path: Path) -> None:
    """scene.json of generator version 1 has no capture key: its cameras walked."""
    content = json.loads((tiny_scene / "scene.json").read_text())
    del content["config"]["capture"], content["config"]["rig_headings"]
    content["version"] = 1
    (tmp_path / "scene.json").write_text(json.dumps(content))
    town = load_town(tmp_path)
    assert town.config.capture == "walk"
    assert town.num_buildings == load_town(tiny_scene).num_buildings


def test_cli_capture_options(tmp_path: Path) -> None:
    result = _cli("--output", str(tmp_path / "walk"), "--num-images", "3", "--width", "16", "--height", "12", "--blocks-x", "1", "--blocks-y", "1",
                  "--capture", "walk", "--quiet")
    assert result.returncode == 0, result.stderr
    assert json.loads((tmp_path / "walk" / "scene.json").read_text())["config"]["capture"] == "walk"
    result = _cli("--output", str(tmp_path / "rig"), "--num-images", "3", "--width", "16", "--height", "12", "--blocks-x", "1", "--blocks-y", "1",
                  "--rig-headings", "0", "90", "-90", "--quiet")
    assert result.returncode == 0, result.stderr
    assert json.loads((tmp_path / "rig" / "scene.json").read_text())["config"]["rig_headings"] == [0.0, 90.0, -90.0]


# -------------------------------------------------------------------------- depth and geometry


def _street_facing_box(town) -> int:
    """A building whose south face lies on the building line of an east-west street."""
    half = town.config.street_width / 2.0
    for b in range(town.num_buildings):
        on_line = np.isclose(town.lo[b, 1], town.street_y + half).any()
        if on_line and town.hi[b, 0] - town.lo[b, 0] > 4.0 and town.lo[b, 0] > town.street_x[0] and town.hi[b, 0] < town.street_x[-1]:
            return b
    raise AssertionError("no building on a street's building line")


def test_depth_of_a_known_wall() -> None:
    """A camera 8 m in front of a facade, looking straight at it: every pixel whose ray meets the
    facade rectangle sees that building at z-depth 8 m, the centre pixel at ray depth 8 m; the rays
    below its foot see the ground at their analytic distance."""
    config = TownConfig(num_images=4, width=33, height=25, blocks_x=2, blocks_y=2, seed=1)
    town = build_town(config)
    b = _street_facing_box(town)
    wall_y, distance = town.lo[b, 1], 8.0
    centre = np.array([(town.lo[b, 0] + town.hi[b, 0]) / 2.0, wall_y - distance, 1.7])
    assert points_on_streets(centre[None], town)[0] and not points_inside_buildings(centre[None], town)[0]
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = (1, 0, 0), (0, 0, 1), (0, -1, 0), centre  # OpenGL: looks along -z = +y
    rgb, ray_depth, z_depth = render_town_image(town, c2w)
    assert rgb.shape == (25, 33, 3) and ray_depth.shape == (25, 33)
    assert abs(ray_depth[12, 16] - distance) < 1e-9 and abs(z_depth[12, 16] - distance) < 1e-9

    # Analytic: the pixel rays' intersections with the facade plane y = wall_y.
    focal = config.focal_px
    u, v = np.meshgrid(np.arange(33) + 0.5, np.arange(25) + 0.5)
    directions = np.stack([(u - 16.5) / focal, np.ones_like(u), -(v - 12.5) / focal], axis=-1)  # world: x right, +y forward, z up
    on_plane = centre + directions * distance
    on_wall = (on_plane[..., 0] > town.lo[b, 0] + 1e-6) & (on_plane[..., 0] < town.hi[b, 0] - 1e-6) & (on_plane[..., 2] > 1e-6) & (on_plane[..., 2] < town.hi[b, 2])
    assert on_wall.sum() > 100
    np.testing.assert_allclose(z_depth[on_wall], distance, atol=1e-9)
    np.testing.assert_allclose(ray_depth[on_wall], distance * np.linalg.norm(directions[on_wall], axis=-1), atol=1e-9)
    hits = intersect_town(np.broadcast_to(centre, (int(on_wall.sum()), 3)), directions[on_wall], town)
    assert (hits.surface == b).all()
    np.testing.assert_array_equal(hits.normal, np.tile([0.0, -1.0, 0.0], (len(hits.depth), 1)))
    # Rays below the facade's foot hit the ground in front of it, at the analytic distance.
    ground = on_plane[..., 2] < -1e-6
    assert ground.any()
    t_ground = 1.7 / (-directions[ground][:, 2]) * np.linalg.norm(directions[ground], axis=-1)
    hits = intersect_town(np.broadcast_to(centre, (int(ground.sum()), 3)), directions[ground], town)
    assert (hits.surface == GROUND).all()
    np.testing.assert_allclose(hits.depth, t_ground, rtol=1e-12)


def test_intersection_matches_brute_force() -> None:
    """The cell-culled ray cast equals a plain slab test against every box and the ground, for
    street-level rays, rays from above the roofs (aerial views) and rays from outside the town."""
    town = build_town(TownConfig(num_images=300, width=16, height=12, blocks_x=3, blocks_y=2, seed=5))
    rng = np.random.default_rng(1)
    street = town_camera_poses(town)[:, :3, 3]
    aerial = np.column_stack([rng.uniform(-120, 120, 300), rng.uniform(-100, 100, 300), rng.uniform(60, 150, 300)])
    outside = np.column_stack([rng.uniform(-300, 300, 300), np.full(300, -250.0), rng.uniform(1, 40, 300)])
    repeat = 8
    origins = np.concatenate([street, aerial, outside]).repeat(repeat, axis=0)
    directions = rng.normal(size=(len(origins), 3))
    n = len(street) * repeat
    directions[:n, 2] = np.abs(directions[:n, 2]) * 0.3 * np.sign(rng.normal(size=n))  # near the horizon
    directions[n : 2 * n, 2] = -np.abs(directions[n : 2 * n, 2])  # aerial views look down
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    # Chunks of one origin (as for an image) and chunks mixing origins far apart.
    hits = intersect_town(origins, directions, town, chunk_rays=repeat)
    mixed = intersect_town(origins, directions, town, chunk_rays=1000)
    np.testing.assert_array_equal(hits.depth, mixed.depth)
    np.testing.assert_array_equal(hits.surface, mixed.surface)

    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (town.lo[None] - origins[:, None]) / directions[:, None]
        t1 = (town.hi[None] - origins[:, None]) / directions[:, None]
        near = np.nanmax(np.minimum(t0, t1), axis=2)
        far = np.nanmin(np.maximum(t0, t1), axis=2)
        t_box = np.where((far >= near) & (near > 1e-6), near, np.inf)
        t_ground = np.where(directions[:, 2] < 0, -origins[:, 2] / directions[:, 2], np.inf)
    expected = np.minimum(t_box.min(axis=1), t_ground)
    np.testing.assert_allclose(hits.depth, expected, rtol=1e-9)
    building = np.isfinite(expected) & (t_box.min(axis=1) < t_ground)
    np.testing.assert_array_equal(hits.surface[building], t_box.argmin(axis=1)[building])
    assert building.sum() > 1000 and (hits.surface == GROUND).sum() > 1000 and (~np.isfinite(hits.depth)).sum() > 100


def test_texture_is_multi_view_consistent() -> None:
    """The colour of a surface point does not depend on where it is seen from."""
    town = build_town(TownConfig(num_images=4, width=16, height=12, blocks_x=2, blocks_y=2, seed=1))
    b = _street_facing_box(town)
    rng = np.random.default_rng(0)
    targets = np.stack([rng.uniform(town.lo[b, 0] + 0.5, town.hi[b, 0] - 0.5, 50), np.full(50, town.lo[b, 1]), rng.uniform(0.3, town.hi[b, 2] - 0.5, 50)], axis=1)
    colours = []
    for eye in (np.array([0.0, -3.0, 0.1]), np.array([2.5, -5.5, 0.4]), np.array([-3.0, -2.0, -0.1])):  # in the street, in front of the facade
        origins = targets + eye
        rgb, depth = render_town_rays(origins, -np.broadcast_to(eye, origins.shape), town)
        np.testing.assert_allclose(depth, np.linalg.norm(eye), rtol=1e-9)
        colours.append(rgb)
    np.testing.assert_allclose(colours[0], colours[1], atol=1e-9)
    np.testing.assert_allclose(colours[0], colours[2], atol=1e-9)
    assert np.ptp(colours[0], axis=0).max() > 0.1, "the facade should carry texture, not one flat colour"


def test_depth_png_round_trips(tiny_scene: Path) -> None:
    """The 16-bit PNGs hold the exact z-depth within 1 mm (0 for the sky and beyond 65.535 m), and
    nerfstudio's depth loader reads the same values."""
    from nerfstudio.data.utils.data_utils import get_depth_image_from_path

    town = load_town(tiny_scene)
    frames = json.loads((tiny_scene / "transforms.json").read_text())["frames"]
    seen_sky = False
    for frame in frames[:6]:
        _, _, z_depth = render_town_image(town, np.array(frame["transform_matrix"]))
        png = read_depth(tiny_scene / frame["depth_file_path"])
        known = np.isfinite(z_depth) & (z_depth <= DEPTH_PNG_MAX_M)
        assert known.mean() > 0.3
        assert np.abs(png[known] - z_depth[known]).max() <= 0.5e-3 + 1e-9
        assert (png[~known] == 0).all()
        seen_sky |= bool((~np.isfinite(z_depth)).any())
        loaded = get_depth_image_from_path(tiny_scene / frame["depth_file_path"], TINY.height, TINY.width, 1e-3)[..., 0].numpy()
        np.testing.assert_allclose(loaded, png, atol=1e-6)
    assert seen_sky, "some frame should see the sky"


# ----------------------------------------------------------------------------- nerfstudio


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "scalar_nerfstudio.scripts.make_scene", *args], capture_output=True, text=True, timeout=300, check=False)


def test_cli_writes_a_town_and_a_courtyard(tmp_path: Path) -> None:
    result = _cli("--output", str(tmp_path / "town"), "--num-images", "3", "--width", "24", "--height", "16", "--blocks-x", "1", "--blocks-y", "1", "--seed", "2")
    assert result.returncode == 0, result.stderr
    assert "automatic K" in result.stdout
    content = json.loads((tmp_path / "town" / "transforms.json").read_text())
    assert len(content["frames"]) == 3 and content["w"] == 24 and content["h"] == 16
    assert json.loads((tmp_path / "town" / "scene.json").read_text())["config"]["seed"] == 2
    result = _cli("--scene", "courtyard", "--output", str(tmp_path / "courtyard"), "--num-images", "2", "--width", "16", "--height", "12", "--quiet")
    assert result.returncode == 0, result.stderr
    assert len(json.loads((tmp_path / "courtyard" / "transforms.json").read_text())["frames"]) == 2
    # --overwrite writes into the non-empty folder and leaves no stale frame behind.
    result = _cli("--output", str(tmp_path / "town"), "--num-images", "2", "--width", "24", "--height", "16", "--blocks-x", "1", "--blocks-y", "1", "--overwrite", "--quiet")
    assert result.returncode == 0, result.stderr
    assert len(list((tmp_path / "town" / "images").iterdir())) == 2


@pytest.mark.parametrize(
    "args, message",
    [
        (["--width", "0"], "--width"),
        (["--height", "-4"], "--height"),
        (["--num-images", "many"], "--num-images"),
        (["--blocks-x", "0"], "--blocks-x"),
        (["--extent", "100", "--blocks-x", "2"], "--extent"),
        (["--street-width", "3"], "--road-width"),
        (["--road-width", "13"], "--road-width"),
        (["--fov", "175"], "--fov"),
        (["--scene", "courtyard", "--blocks-x", "2"], "only for --scene town"),
        (["--scene", "courtyard", "--capture", "walk"], "only for --scene town"),
        (["--scene", "courtyard", "--aerial-altitude", "50"], "only for --scene town"),
        (["--scene", "facade", "--blocks-x", "2"], "only for --scene town"),
        (["--wall-length", "20"], "only for --scene facade"),
        (["--scene", "facade", "--wall-length", "0"], "--wall-length"),
        (["--aerial-altitude", "56"], "only with --capture aerial or aerial+rig"),
        (["--rig-headings", "200"], "--rig-headings"),
        (["--capture", "drone"], "--capture"),
        (["NON_EMPTY"], "not empty"),
        (["A_FILE"], "not a folder"),
        (["UNDER_A_FILE"], "cannot be created"),
    ],
)
def test_cli_rejects_bad_options_in_one_line(tmp_path: Path, args: List[str], message: str) -> None:
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("user data")
    (tmp_path / "file.txt").write_text("")
    output = {"NON_EMPTY": tmp_path / "full", "A_FILE": tmp_path / "file.txt", "UNDER_A_FILE": tmp_path / "file.txt" / "scene"}
    target = output.get(args[0], tmp_path / "new")
    options = [] if args[0] in output else args
    result = _cli("--output", str(target), "--num-images", "2", "--width", "16", "--height", "12", *options)
    # a malformed option is a usage error (2); an output folder that cannot be used, a bad input (1)
    assert result.returncode == (1 if args[0] in output else 2), result.stdout + result.stderr
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0] and message in lines[0], result.stderr
    assert (tmp_path / "full" / "keep.txt").read_text() == "user data"
    assert not (tmp_path / "new").exists() or not any((tmp_path / "new").iterdir())
