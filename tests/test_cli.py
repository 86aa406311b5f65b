"""The commands a user runs: ns-train --help, ns-train's step log and the README's demo command (ns-eval,
ns-render, ns-viewer and ns-export on trained runs: test_verbs.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from conftest import TOTAL_STEPS, free_port, full_run_log, run_dirs


@pytest.mark.parametrize("method", ["scalar-nerf", "scalar-nerf-block"])
def test_ns_train_help(method: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """``ns-train METHOD --help`` (nerfstudio's entry point, in-process: every other ns-train of the
    suite starts the command itself) lists the field's options and the dataparsers."""
    from nerfstudio.scripts import train as ns_train

    monkeypatch.setattr(sys, "argv", ["ns-train", method, "--help"])
    with pytest.raises(SystemExit) as exit_info:
        ns_train.entrypoint()
    assert exit_info.value.code in (0, None)
    out = capsys.readouterr().out
    assert "--pipeline.model.field.log2-hashmap-size" in out
    assert "nerfstudio-data" in out


@pytest.mark.slow
def test_demo_command_trains_on_the_builtin_scene(tmp_path: Path) -> None:
    result = subprocess.run(
        ["scalar-nerf-demo", "--scene-dir", str(tmp_path / "scene"), "--output-dir", str(tmp_path / "outputs"), "--max-num-iterations", "30",
         "--", "--viewer.websocket-port", str(free_port()), "--logging.local-writer.enable", "False"],
        capture_output=True, text=True, timeout=900, cwd=tmp_path, check=False
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


@pytest.mark.slow
def test_ns_train_with_nerfstudio_default_step_log(full_run: Path) -> None:
    """``ns-train scalar-nerf`` with nerfstudio's step log on (its default; the other runs of the
    suite turn it off): the log's % done and ETA divide by the total steps, which only the phases know."""
    log = full_run_log(full_run)
    assert "ZeroDivisionError" not in log and "Traceback" not in log
    assert sorted(p.name for p in (full_run / "nerfstudio_models").glob("step-*.ckpt"))[-1] == f"step-{TOTAL_STEPS - 1:09d}.ckpt"
    assert "ETA" in log or "%" in log, log[-2000:]
