"""The capture frame's geometry (``process.geo``, ``process.align``) and ``scalar-nerf-export-frame``: WGS84 and
east-north-up, similarity fits, levelling, and exported geometry moved back into the capture's frame."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest
import torch

from scalar_nerfstudio.process import geo
from scalar_nerfstudio.process.align import capture_frame
from scalar_nerfstudio.process.errors import ProcessDataError
from scalar_nerfstudio.process.export_frame import DataparserTransform, map_file, read_transform
from scalar_nerfstudio.scenes.courtyard import look_at
from scalar_nerfstudio.scripts import export_frame as export_frame_cli

HAS_PYCOLMAP = importlib.util.find_spec("pycolmap") is not None

#: A place on Earth for the east-north-up frame (lat, lon in degrees, altitude in m).
GPS_ORIGIN = np.array([46.5197, 6.6323, 372.0])


def test_enu_round_trip_and_agreement_with_pycolmap() -> None:
    enu = np.random.default_rng(0).uniform(-2000.0, 2000.0, size=(20, 3))
    lla = geo.enu_to_wgs84(enu, GPS_ORIGIN)
    assert np.allclose(geo.wgs84_to_enu(lla, GPS_ORIGIN), enu, atol=1e-6)
    if HAS_PYCOLMAP:
        import pycolmap

        transform = pycolmap.GPSTransform(pycolmap.GPSTransformEllipsoid.WGS84)
        assert np.allclose(transform.ellipsoid_to_enu(lla, *GPS_ORIGIN), enu, atol=1e-6)


def _random_similarity(seed: int) -> geo.Similarity:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    return geo.Similarity(float(rng.uniform(0.1, 10.0)), q, rng.normal(size=3) * 100.0)


def test_umeyama_recovers_a_similarity_and_drops_a_jumped_fix() -> None:
    truth = _random_similarity(1)
    points = np.random.default_rng(2).normal(size=(30, 3))
    target = truth.apply(points)
    fitted = geo.umeyama(points, target)
    assert np.isclose(fitted.scale, truth.scale) and np.allclose(fitted.rotation, truth.rotation) and np.allclose(fitted.translation, truth.translation)
    noisy = target + np.random.default_rng(3).normal(scale=0.01, size=target.shape)
    noisy[5] += 50.0
    robust, keep = geo.robust_umeyama(points, noisy)
    assert not keep[5] and keep.sum() >= 25 and np.allclose(robust.rotation, truth.rotation, atol=1e-2)
    assert np.allclose(fitted.inverse().apply(target), points)
    with pytest.raises(ValueError, match="collinear"):
        geo.umeyama(np.outer(np.arange(5.0), [1.0, 2.0, 3.0]), np.outer(np.arange(5.0), [1.0, 0.0, 0.0]))


def _level_cameras(count: int = 12, seed: int = 0) -> np.ndarray:
    """[N, 4, 4] OpenCV poses of cameras with level image rows (a drone's nadir and oblique views)
    over a 100 m x 60 m area, in the world (z up)."""
    rng = np.random.default_rng(seed)
    poses = np.stack([np.eye(4)] * count)
    for k in range(count):
        position = np.array([rng.uniform(-50, 50), rng.uniform(-30, 30), rng.uniform(48, 52)])
        heading = rng.uniform(-np.pi, np.pi)
        target = position + np.array([0.3 * np.cos(heading), 0.3 * np.sin(heading), -1.0])
        poses[k] = look_at(position, target) @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL -> OpenCV axes
    return poses


def test_capture_frame_without_complete_gps_levels_the_cameras() -> None:
    world = _level_cameras()
    tilt = _random_similarity(4)
    colmap = geo.Similarity(0.37, tilt.rotation, tilt.translation).apply_to_poses(world)
    names = [f"{k}.jpg" for k in range(len(world))]
    frame = capture_frame(names, colmap, {"0.jpg": GPS_ORIGIN})
    assert frame.kind == "up" and "1.jpg" in frame.note and "level" in frame.note
    moved = frame.scene_from_colmap.apply_to_poses(colmap)
    assert np.allclose(moved[:, :3, 3].mean(axis=0), 0.0, atol=1e-9)
    assert np.allclose(moved[:, 2, 0], 0.0, atol=1e-9) and np.all(moved[:, 2, 2] < -0.9)  # rows level, looking down


def test_gps_altitude_drift_leaves_up_to_the_cameras_level() -> None:
    """GPS whose altitude drifts 100 m over the flight (as a consumer camera's does) but whose
    horizontal position is right to 2 m: the frame stays level, in metres, north up."""
    world = _level_cameras(count=30, seed=1)
    rng = np.random.default_rng(2)
    enu = world[:, :3, 3] + np.c_[rng.normal(0.0, 2.0, (30, 2)), np.linspace(-50.0, 50.0, 30)]
    gps = dict(zip([f"{k}.jpg" for k in range(30)], geo.enu_to_wgs84(enu, GPS_ORIGIN)))
    tilt = _random_similarity(5)
    colmap = geo.Similarity(0.37, tilt.rotation, tilt.translation).apply_to_poses(world)
    frame = capture_frame(list(gps), colmap, gps)
    assert frame.kind == "enu-level" and "disagree" in frame.note, frame.describe()
    moved = frame.scene_from_colmap.apply_to_poses(colmap)
    origin_offset = geo.wgs84_to_enu(GPS_ORIGIN[None], frame.gps_origin)[0]
    assert np.allclose(moved[:, 2, 0], 0.0, atol=1e-9)  # level
    sim = geo.umeyama(moved[:, :3, 3], world[:, :3, 3])
    assert abs(sim.scale - 1.0) < 0.02 and geo.rotation_angle_deg(sim.rotation[None], np.eye(3)[None])[0] < 1.0
    assert np.allclose(sim.translation[:2], -origin_offset[:2], atol=2.0)


def _dataparser_transform(seed: int) -> DataparserTransform:
    sim = _random_similarity(seed)
    return DataparserTransform(np.hstack([sim.rotation, sim.translation[:, None]]), sim.scale)


def test_export_frame_round_trip_ply_and_obj_agrees_with_nerfstudio(tmp_path) -> None:
    """Capture-frame points -> the model frame (dataparser transform) -> written as ns-export would
    (.ply with normals, .obj) -> scalar-nerf-export-frame -> the original points and normals."""
    from nerfstudio.data.dataparsers.base_dataparser import transform_poses_to_original_space
    from plyfile import PlyData, PlyElement

    transform = _dataparser_transform(5)
    rng = np.random.default_rng(6)
    points = rng.uniform(-50.0, 50.0, size=(40, 3))
    normals = rng.normal(size=(40, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    model_points = transform.to_model(points)
    model_normals = normals @ transform.rotation.T
    poses = torch.from_numpy(np.concatenate([np.tile(np.eye(3), (40, 1, 1)), model_points[:, :, None]], axis=2))
    nerfstudio_back = transform_poses_to_original_space(poses, torch.from_numpy(transform.transform), transform.scale)[:, :3, 3].numpy()
    assert np.allclose(nerfstudio_back, points, atol=1e-9)

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yml").write_text("")
    (run / "dataparser_transforms.json").write_text(json.dumps({"transform": transform.transform.tolist(), "scale": transform.scale}))
    vertex = np.empty(40, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"), ("red", "u1")])
    for k, axis in enumerate("xyz"):
        vertex[axis] = model_points[:, k]
        vertex["n" + axis] = model_normals[:, k]
    vertex["red"] = np.arange(40)
    faces = np.array([([0, 1, 2],)], dtype=[("vertex_indices", "i4", (3,))])
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(faces, "face")], text=False).write(str(tmp_path / "mesh.ply"))
    obj = "".join(f"v {float(x)!r} {float(y)!r} {float(z)!r} 0.5 0.5 0.5\n" for x, y, z in model_points)
    obj += "".join(f"vn {float(x)!r} {float(y)!r} {float(z)!r}\n" for x, y, z in model_normals) + "f 1//1 2//2 3//3\n"
    (tmp_path / "mesh.obj").write_text(obj)

    for name in ("mesh.ply", "mesh.obj"):
        code = export_frame_cli.main(["--load-config", str(run / "config.yml"), "--input", str(tmp_path / name), "--output", str(tmp_path / f"world_{name}")])
        assert code == 0
    ply = PlyData.read(str(tmp_path / "world_mesh.ply"))
    back = np.stack([ply["vertex"][a] for a in "xyz"], axis=1)
    back_normals = np.stack([ply["vertex"]["n" + a] for a in "xyz"], axis=1)
    assert np.allclose(back, points, atol=1e-9) and np.allclose(back_normals, normals, atol=1e-5)
    assert ply["vertex"]["red"].tolist() == list(range(40)) and ply["face"]["vertex_indices"][0].tolist() == [0, 1, 2]
    lines = (tmp_path / "world_mesh.obj").read_text().splitlines()
    obj_points = np.array([[float(v) for v in line.split()[1:4]] for line in lines if line.startswith("v ")])
    obj_normals = np.array([[float(v) for v in line.split()[1:4]] for line in lines if line.startswith("vn ")])
    assert np.allclose(obj_points, points, atol=1e-6) and np.allclose(obj_normals, normals, atol=1e-6)
    assert lines[0].endswith(" 0.5 0.5 0.5") and lines[-1] == "f 1//1 2//2 3//3"


def test_export_frame_errors(tmp_path) -> None:
    (tmp_path / "run").mkdir()
    (tmp_path / "mesh.ply").write_text("not a ply")
    assert export_frame_cli.main(["--load-config", str(tmp_path / "run" / "config.yml"), "--input", str(tmp_path / "mesh.ply"), "--output", str(tmp_path / "o.ply")]) == 1
    (tmp_path / "run" / "dataparser_transforms.json").write_text(json.dumps({"transform": np.eye(4)[:3].tolist(), "scale": 2.0}))
    with pytest.raises(ProcessDataError, match="not a readable .ply"):
        map_file(tmp_path / "mesh.ply", tmp_path / "o.ply", read_transform(tmp_path / "run" / "dataparser_transforms.json"))
    with pytest.raises(ProcessDataError, match="must end in .ply"):
        map_file(tmp_path / "mesh.ply", tmp_path / "o.obj", read_transform(tmp_path / "run" / "dataparser_transforms.json"))
