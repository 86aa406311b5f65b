"""Every nerfstudio verb on runs whose K was chosen automatically and that were trained at a downscale
factor (issue 19.1).

``ns-render dataset|camera-path`` set the pipeline up in "inference" mode, where nerfstudio parses
the cameras at full resolution: an automatic K decided again there differs from the trained one
(here 3 instead of 2, and 3 instead of 1). A run reads its shape back from its blocks.json instead.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Dict, List

import numpy as np
import pytest
import torch
from conftest import ns_eval, ns_train_command, run_dirs, viewer_image
from PIL import Image
from prerequisites import has_tool, need
from quality import (
    FUSION_TOLERANCE_DB,
    TRAINED_MARGIN_DB,
    eval_renders,
    image_difference,
    load_pipeline,
    untrained_psnr,
)

from scalar_nerfstudio.blocks.plan import load_plan
from scalar_nerfstudio.metrics import alexnet_weights_path
from scalar_nerfstudio.scenes.courtyard import write_scene

pytestmark = pytest.mark.slow

# Courtyard of 24 images (21 training) at 96x72, trained at downscale 2 (48x36): the layout is
# ~145 training pixels across (~290 at full resolution). T = 2^14 gives K = ceil(145^2 / 2^14) = 2
# when trained, 3 at full resolution; T = 2^15 gives K = 1 when trained, 3 at full resolution.
TABLES = {"k1": 15, "k2": 14}
EXPECTED_K = {"k1": 1, "k2": 2}
TINY_AUTO = [
    "--pipeline.model.field.max-resolution", "128",
    "--pipeline.model.num-samples-per-ray", "24",
    "--pipeline.datamanager.train-num-rays-per-batch", "256",
    "--pipeline.model.occupancy-warmup-steps", "8",
    "--pipeline.block-log2-hashmap-bounds", "10", "12",
    "--pipeline.global-steps", "100",  # ~+3.4 dB over step 0 (20 steps: +0.6); the time goes into starting ns-train
    "--pipeline.block-steps", "30",
]


def _downscaled_scene(folder: Path) -> Path:
    write_scene(folder, num_images=24, width=96, height=72)
    (folder / "images_2").mkdir()
    for image in sorted((folder / "images").glob("*.png")):
        Image.open(image).resize((48, 36), Image.LANCZOS).save(folder / "images_2" / image.name)
    return folder


@pytest.fixture(scope="module")
def auto_runs(tmp_path_factory: pytest.TempPathFactory) -> Dict[str, Path]:
    """Two runs with automatic K trained at --downscale-factor 2: K = 1 and K = 2."""
    scene = _downscaled_scene(tmp_path_factory.mktemp("scene_ds2"))
    runs = {}
    for name, log2_t in TABLES.items():
        output = tmp_path_factory.mktemp(f"auto_{name}")
        command = ns_train_command(
            scene, output, "--pipeline.model.field.log2-hashmap-size", str(log2_t), *TINY_AUTO,
            "nerfstudio-data", "--downscale-factor", "2",
        )
        result = subprocess.run(command, capture_output=True, text=True, timeout=900, check=False)
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
        (run,) = run_dirs(output)
        assert f"automatic K = {EXPECTED_K[name]}" in result.stdout
        runs[name] = run
    return runs


def _run(command: List[str], timeout: int = 600) -> subprocess.CompletedProcess:
    result = subprocess.run(command, capture_output=True, text=True, timeout=timeout, check=False)
    assert result.returncode == 0, " ".join(command) + "\n" + result.stdout[-3000:] + result.stderr[-3000:]
    assert "size mismatch" not in result.stdout + result.stderr
    return result


def _images(folder: Path) -> List[Path]:
    return sorted(folder.rglob("*.png")) + sorted(folder.rglob("*.jpg"))


def _ns_render(verb: str, run: Path, output: Path, *extra: str) -> List[Path]:
    _run([sys.executable, "-m", "nerfstudio.scripts.render", verb, "--load-config", str(run / "config.yml"),
          "--output-path", str(output), *extra])
    images = _images(output)
    assert images, f"ns-render {verb} wrote no image under {output}"
    return images


@pytest.mark.parametrize("name", ["k1", "k2"])
def test_the_run_records_its_own_plan(auto_runs: Dict[str, Path], name: str) -> None:
    run = auto_runs[name]
    plan = load_plan(run / "blocks.json")
    assert plan.auto_num_blocks == EXPECTED_K[name]
    assert len(plan.held_blocks) == (0 if EXPECTED_K[name] == 1 else EXPECTED_K[name])
    assert "run_plan" in (run / "config.yml").read_text()


def _camera_path(path: Path) -> Path:
    """A camera path as the viewer's Render tab writes it: one pose in the dataparser's frame."""
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.0, 0.2]
    path.write_text(json.dumps({
        "render_height": 36, "render_width": 48, "seconds": 1.0, "camera_type": "perspective",
        "camera_path": [{"camera_to_world": pose.reshape(-1).tolist(), "fov": 60.0, "aspect": 48 / 36}],
    }))
    return path


def _camera_path_render(pipeline, camera_path: Path) -> np.ndarray:
    """The run's own render ``[H, W, 3]`` of the camera path's first camera, as ns-render frames it."""
    from nerfstudio.cameras.camera_paths import get_path_from_json

    cameras = get_path_from_json(json.loads(camera_path.read_text())).to(pipeline.device)
    with torch.no_grad():
        outputs = pipeline.model.get_outputs_for_camera(cameras[0:1])
    return outputs["rgb"].clamp(0, 1).cpu().numpy()


@pytest.mark.parametrize("name", ["k1", "k2"])
def test_ns_render_dataset_and_camera_path_write_the_runs_own_renders(auto_runs: Dict[str, Path], name: str, tmp_path: Path) -> None:
    """``ns-render dataset`` and ``ns-render camera-path`` write, at the trained resolution, what the
    run renders in-process for the same cameras (to the 8-bit level)."""
    run = auto_runs[name]
    pipeline = load_pipeline(run)
    _, renders = eval_renders(pipeline)
    names = [Path(f).stem for f in pipeline.datamanager.eval_dataset.image_filenames]
    rendered = _ns_render("dataset", run, tmp_path / "dataset", "--split", "test", "--rendered-output-names", "rgb", "--image-format", "png")
    assert sorted(p.stem for p in rendered) == sorted(names)
    for stem, render in zip(names, renders):
        (path,) = [p for p in rendered if p.stem == stem]
        assert render.shape[:2] == (36, 48), "rendered at the trained resolution"
        assert image_difference(path, render) < 1.0, f"{path.name} is not the run's render of that camera"
    need("ffmpeg (ns-render camera-path)", has_tool("ffmpeg"))
    camera_path = _camera_path(tmp_path / "camera_path.json")
    (frame,) = _ns_render("camera-path", run, tmp_path / "path", "--output-format", "images", "--image-format", "png",
                          "--camera-path-filename", str(camera_path))
    assert image_difference(frame, _camera_path_render(pipeline, camera_path)) < 1.0, "the frame is not the run's render of the path's camera"


@pytest.mark.parametrize(("name", "verb"), [("k1", "interpolate"), ("k2", "spiral")])
def test_ns_render_interpolate_and_spiral_write_their_frames(auto_runs: Dict[str, Path], name: str, verb: str, tmp_path: Path) -> None:
    """The trajectory verbs (the same frame writer as camera-path, checked against the run's render
    above): every frame of the trajectory at the asked size, not blank."""
    need("ffmpeg (ns-render interpolate/spiral)", has_tool("ffmpeg"))
    extra = {
        "interpolate": ["--interpolation-steps", "1", "--pose-source", "train", "--downscale-factor", "4"],
        "spiral": ["--seconds", "1", "--frame-rate", "2", "--downscale-factor", "4"],
    }[verb]
    frames = _ns_render(verb, auto_runs[name], tmp_path / "out", "--output-format", "images", "--image-format", "png", *extra)
    expected = {"interpolate": 20, "spiral": 2}[verb]  # interpolate: one frame per training camera but the last
    assert len(frames) == expected, [p.name for p in frames]
    for frame in frames:
        image = np.asarray(Image.open(frame).convert("RGB"), dtype=np.float32)
        assert image.shape[:2] == (9, 12) and image.std() > 1.0, f"{frame.name}: {image.shape}, std {image.std():.2f}"


@pytest.mark.parametrize("name", ["k1", "k2"])
def test_ns_eval_scores_the_run_above_its_untrained_model_and_fused_at_least_its_global_model(
        auto_runs: Dict[str, Path], name: str, tmp_path: Path) -> None:
    """``ns-eval`` on each run: PSNR beats the run's own untrained model by TRAINED_MARGIN_DB, without
    downloading LPIPS weights. K = 2: the fused score is at least the global model alone's (within
    FUSION_TOLERANCE_DB). K = 1: ``scalar-nerf-eval-fusion`` reports the same score for its global model."""
    run = auto_runs[name]
    result = ns_eval(run, tmp_path / "eval.json")
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    metrics = json.loads((tmp_path / "eval.json").read_text())["results"]
    log = " ".join((result.stdout + result.stderr).split())
    assert "eval image 1/" in log and "s per image, about" in log and "s per image, done in" in log  # images done, time left
    step_0 = untrained_psnr(run)
    assert metrics["psnr"] > step_0 + TRAINED_MARGIN_DB, (metrics["psnr"], step_0)
    assert 0.0 < metrics["ssim"] <= 1.0
    weights = alexnet_weights_path()
    if weights is None or not weights.is_file():
        assert "lpips" not in metrics and "LPIPS skipped" in result.stdout + result.stderr
    if name == "k2":
        global_only = eval_renders(load_pipeline(run), "global-only")[0]["psnr"]
        assert metrics["psnr"] >= global_only - FUSION_TOLERANCE_DB, (metrics["psnr"], global_only)
    else:
        _run(["scalar-nerf-eval-fusion", "--load-config", str(run / "config.yml"), "--output-dir", str(tmp_path / "fusion")])
        table = json.loads((tmp_path / "fusion" / "fusion.json").read_text())
        assert table["global-only"]["psnr"] == pytest.approx(metrics["psnr"], abs=1e-3)


def _psnr_8bit(image: np.ndarray, reference: np.ndarray) -> float:
    mse = float(np.mean((image.astype(np.float64) - reference.astype(np.float64)) ** 2))
    return 10.0 * math.log10(255.0**2 / max(mse, 1e-12))


def test_ns_viewer_shows_the_run_of_one_model_through_the_camera_a_browser_sends(auto_runs: Dict[str, Path]) -> None:
    """``ns-viewer`` renders a run of one model for the camera a browser sends over its websocket: the image it
    sends back is the run's own render through that camera (JPEG aside), not its render through another
    training camera. The blocks' run is shown in a real browser in test_viewer.py."""
    from nerfstudio.cameras.cameras import CameraType
    from nerfstudio.viewer.utils import CameraState, get_camera

    run = auto_runs["k1"]
    pipeline = load_pipeline(run)
    cameras = pipeline.datamanager.train_dataset.cameras
    height, width = int(cameras.height[0]), int(cameras.width[0])
    fov, aspect = 2.0 * math.atan(height / (2.0 * float(cameras.fy[0]))), width / height
    poses = {"asked": cameras.camera_to_worlds[len(cameras) // 2], "another": cameras.camera_to_worlds[0]}

    shown = viewer_image(run / "config.yml", c2w=poses["asked"], fov=fov, aspect=aspect)
    assert shown.std() > 5.0, "the viewer sent a blank image"

    def render(c2w: torch.Tensor) -> np.ndarray:
        state = CameraState(fov=fov, aspect=aspect, c2w=c2w, camera_type=CameraType.PERSPECTIVE)
        with torch.no_grad():
            outputs = pipeline.model.get_outputs_for_camera(get_camera(state, shown.shape[0], shown.shape[1]).to(pipeline.device))
        return (outputs["rgb"].clamp(0, 1).cpu().numpy() * 255.0).round()

    own, other = _psnr_8bit(shown, render(poses["asked"])), _psnr_8bit(shown, render(poses["another"]))
    assert own > 30.0 and own > other + 5.0, f"PSNR against the run's render through the camera sent {own:.1f} dB, through another {other:.1f} dB"


EXPORTS = {  # nerfstudio's exporter on a small budget: its file, and the options that keep it to seconds
    "pointcloud": ("point_cloud.ply", ["--num-points", "300", "--remove-outliers", "False", "--num-rays-per-batch", "4096"]),
    "tsdf": ("tsdf_mesh.ply", ["--resolution", "32", "--batch-size", "4", "--downscale-factor", "4", "--texture-method", "tsdf"]),
    "poisson": ("poisson_mesh.ply", ["--num-points", "2000", "--remove-outliers", "False", "--num-rays-per-batch", "4096",
                                     "--texture-method", "point_cloud"]),
}


@pytest.mark.parametrize("name, verb", [("k1", "pointcloud"), ("k2", "tsdf"), ("k2", "poisson")])
def test_ns_export_writes_the_runs_cloud_or_mesh(auto_runs: Dict[str, Path], name: str, verb: str, tmp_path: Path) -> None:
    """``ns-export pointcloud`` (one merged cloud of the fused model, with unit normals; where its points lie is
    checked on a longer run in test_export.py), ``tsdf`` (the rendered depths fused into a mesh) and ``poisson``
    (a mesh from the cloud and the model's normals): each writes a non-empty, finite result."""
    import open3d as o3d

    filename, options = EXPORTS[verb]
    _run([sys.executable, "-m", "nerfstudio.scripts.exporter", verb, "--load-config", str(auto_runs[name] / "config.yml"),
          "--output-dir", str(tmp_path), *options])
    if verb == "pointcloud":
        cloud = o3d.io.read_point_cloud(str(tmp_path / filename))
        points, normals = np.asarray(cloud.points), np.asarray(cloud.normals)
        assert len(points) > 0 and cloud.has_normals() and normals.shape == points.shape
        assert np.isfinite(points).all() and np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-3)
        return
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / filename))
    vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    assert len(vertices) > 0 and len(triangles) > 0 and np.isfinite(vertices).all()
    assert triangles.min() >= 0 and triangles.max() < len(vertices)
