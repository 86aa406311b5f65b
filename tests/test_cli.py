"""The commands a user runs: ns-train --help, ns-eval, ns-viewer, and the README's demo command."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import free_port, ns_eval, run_dirs, viewer_page
from scalar_nerfstudio.metrics import alexnet_weights_path


@pytest.mark.parametrize("method", ["scalar-nerf", "scalar-nerf-block"])
def test_ns_train_help(method: str) -> None:
    result = subprocess.run([sys.executable, "-m", "nerfstudio.scripts.train", method, "--help"], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "--pipeline.model.field.log2-hashmap-size" in result.stdout
    assert "nerfstudio-data" in result.stdout


@pytest.mark.slow
def test_ns_eval_reports_psnr_ssim_without_downloading(trained_castle_run: Path, tmp_path: Path) -> None:
    output = tmp_path / "eval.json"
    result = ns_eval(trained_castle_run, output)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    metrics = json.loads(output.read_text())["results"]
    assert 5.0 < metrics["psnr"] < 60.0 and 0.0 < metrics["ssim"] <= 1.0
    weights = alexnet_weights_path()
    if weights is None or not weights.is_file():
        assert "lpips" not in metrics
        assert "LPIPS skipped" in result.stdout + result.stderr


@pytest.mark.slow
def test_ns_viewer_serves_a_trained_run(trained_castle_run: Path) -> None:
    page = viewer_page(trained_castle_run / "config.yml")
    assert "<html" in page.lower()


@pytest.mark.slow
def test_demo_command_trains_on_the_builtin_scene(tmp_path: Path) -> None:
    result = subprocess.run(
        ["scalar-nerf-demo", "--scene-dir", str(tmp_path / "scene"), "--output-dir", str(tmp_path / "outputs"), "--max-num-iterations", "30",
         "--", "--viewer.websocket-port", str(free_port()), "--logging.local-writer.enable", "False"],
        capture_output=True, text=True, timeout=900, cwd=tmp_path,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    (run,) = run_dirs(tmp_path / "outputs")
    assert (run / "nerfstudio_models" / "step-000000029.ckpt").is_file()
    assert (run / "preview.png").is_file(), "a preview is written at the last step"
    assert f"ns-viewer --load-config {run / 'config.yml'}" in result.stdout, "the demo ends with the next commands"
    assert "Warning" not in result.stdout + result.stderr, "library warnings are not the user's business"


def test_ci_runs_the_readme_test_command() -> None:
    repo = Path(__file__).resolve().parents[1]
    script = (repo / ".ci" / "run").read_text()
    extraction = script.split("test_command=$(", 1)[1].split(")\n", 1)[0]
    extracted = subprocess.run(["bash", "-c", extraction], capture_output=True, text=True, cwd=repo, check=True).stdout.strip()
    readme = (repo / "README.md").read_text()
    assert "python -m pytest" in extracted
    assert extracted in readme.split("<!-- test command -->", 1)[1].split("```", 2)[1]


def test_ns_train_with_nerfstudio_default_step_log(scene: Path, tmp_path: Path) -> None:
    """Plain ``ns-train scalar-nerf`` with nerfstudio's step log on (its default; the other tests
    turn it off): the log's % done and ETA divide by the total steps, which only the phases know."""
    from conftest import TINY

    command = [
        sys.executable, "-m", "nerfstudio.scripts.train", "scalar-nerf", "--data", str(scene),
        "--output-dir", str(tmp_path), "--viewer.websocket-port", str(free_port()),
        "--viewer.quit-on-train-completion", "True", "--logging.steps-per-log", "5",
        *TINY, "--pipeline.global-steps", "12", "--pipeline.block-steps", "4",
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "ZeroDivisionError" not in result.stdout + result.stderr
    (run,) = run_dirs(tmp_path)
    assert sorted(p.name for p in (run / "nerfstudio_models").glob("step-*.ckpt"))[-1] == "step-000000019.ckpt"
