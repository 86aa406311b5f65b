"""Every nerfstudio verb on runs whose K was chosen automatically and that were trained at a downscale
factor (issue 19.1).

``ns-render dataset|camera-path`` set the pipeline up in "inference" mode, where nerfstudio parses
the cameras at full resolution: an automatic K decided again there differs from the trained one
(here 3 instead of 2, and 3 instead of 1). A run reads its shape back from its blocks.json instead.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Dict, List

import numpy as np
import pytest
from PIL import Image

from conftest import ns_eval, ns_train_command, run_dirs, viewer_page
from scalar_nerfstudio.blocks.plan import load_plan
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
    "--pipeline.global-steps", "20",
    "--pipeline.block-steps", "10",
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
        result = subprocess.run(command, capture_output=True, text=True, timeout=900)
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
        (run,) = run_dirs(output)
        assert f"automatic K = {EXPECTED_K[name]}" in result.stdout
        runs[name] = run
    return runs


def _run(command: List[str], timeout: int = 600) -> subprocess.CompletedProcess:
    result = subprocess.run(command, capture_output=True, text=True, timeout=timeout)
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


@pytest.mark.parametrize("verb", ["dataset", "camera-path", "interpolate", "spiral"])
@pytest.mark.parametrize("name", ["k1", "k2"])
def test_ns_render_verbs(auto_runs: Dict[str, Path], name: str, verb: str, tmp_path: Path) -> None:
    run = auto_runs[name]
    if verb == "dataset":
        rendered = _ns_render("dataset", run, tmp_path / "out", "--split", "test", "--rendered-output-names", "rgb")
        assert np.asarray(Image.open(rendered[0])).shape[:2] == (36, 48), "rendered at the trained resolution"
        return
    if shutil.which("ffmpeg") is None:
        pytest.skip("ns-render camera-path/interpolate/spiral need ffmpeg (tools/setup-tests.sh installs it)")
    extra = {
        "camera-path": ["--camera-path-filename", str(_camera_path(tmp_path / "camera_path.json"))],
        "interpolate": ["--interpolation-steps", "1", "--pose-source", "train", "--downscale-factor", "4"],
        "spiral": ["--seconds", "1", "--frame-rate", "2", "--downscale-factor", "4"],
    }[verb]
    _ns_render(verb, run, tmp_path / "out", "--output-format", "images", *extra)


@pytest.mark.parametrize("name", ["k1", "k2"])
def test_eval_and_fusion_commands(auto_runs: Dict[str, Path], name: str, tmp_path: Path) -> None:
    run = auto_runs[name]
    result = ns_eval(run, tmp_path / "eval.json")
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert 0.0 < json.loads((tmp_path / "eval.json").read_text())["results"]["psnr"] < 60.0
    _run(["scalar-nerf-render", "dataset", "--load-config", str(run / "config.yml"), "--fusion", "global-only",
          "--output-path", str(tmp_path / "render"), "--split", "test", "--rendered-output-names", "rgb"])
    assert _images(tmp_path / "render")
    _run(["scalar-nerf-eval-fusion", "--load-config", str(run / "config.yml"), "--output-dir", str(tmp_path / "fusion")])
    table = json.loads((tmp_path / "fusion" / "fusion.json").read_text())
    assert 0.0 < table["global-only"]["psnr"] < 60.0


@pytest.mark.parametrize("name", ["k1", "k2"])
def test_ns_viewer_loads_the_run(auto_runs: Dict[str, Path], name: str) -> None:
    assert "<html" in viewer_page(auto_runs[name] / "config.yml").lower()


@pytest.mark.parametrize("name", ["k1", "k2"])
def test_ns_export_pointcloud(auto_runs: Dict[str, Path], name: str, tmp_path: Path) -> None:
    """One merged point cloud of the fused model, with unit normals (where its points lie is checked
    on a longer run in test_export.py)."""
    import open3d as o3d

    _run([sys.executable, "-m", "nerfstudio.scripts.exporter", "pointcloud", "--load-config", str(auto_runs[name] / "config.yml"),
          "--output-dir", str(tmp_path), "--num-points", "300", "--remove-outliers", "False", "--num-rays-per-batch", "4096"])
    cloud = o3d.io.read_point_cloud(str(tmp_path / "point_cloud.ply"))
    points, normals = np.asarray(cloud.points), np.asarray(cloud.normals)
    assert len(points) > 0 and cloud.has_normals() and normals.shape == points.shape
    assert np.isfinite(points).all() and np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-3)
