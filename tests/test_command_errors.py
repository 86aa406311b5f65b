"""Every ``scalar-nerf-*`` command on the bad inputs users meet, through its console entry point: a
missing or foreign run folder, an unfinished global run, a block run of another split, an unknown
fusion, an unreadable mesh, an output folder that is in use. Each ends with exit status 1 and one
line naming the problem, no traceback, and nothing written or changed."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from importlib.metadata import entry_points
from pathlib import Path
from typing import Dict, List, Tuple

import pytest
import torch
from cli_driver import DRIVER
from fake_runs import fake_run, foreign_run

#: Each case runs the console script's entry point as pip installed it (cli_driver.py: one process imports
#: the commands once, each case runs in a forked child). test_a_command_started_afresh_prints_one_line runs
#: one as a process of its own, with what its imports print.

#: name: (command, its arguments, what its one line must say). Paths are relative to the work folder
#: that the ``work`` fixture fills; ``out/NAME`` is where a case would write, were it not refused.
CASES: Dict[str, Tuple[str, List[str], str]] = {
    "render-missing-run": ("scalar-nerf-render", ["dataset", "--load-config", "runs/none/config.yml", "--output-path", "out/a"], "no config.yml"),
    "render-foreign-run": ("scalar-nerf-render", ["dataset", "--load-config", "runs/foreign/config.yml", "--fusion", "idw", "--output-path", "out/b"], "nerfacto, not of scalar-nerf"),
    "render-unfinished-run": ("scalar-nerf-render", ["dataset", "--load-config", "runs/unfinished/config.yml", "--output-path", "out/c"], "no checkpoint"),
    "render-unknown-fusion": ("scalar-nerf-render", ["dataset", "--load-config", "runs/global/config.yml", "--fusion", "nearest-ish", "--output-path", "out/d"], "unknown fusion mode 'nearest-ish'"),
    "eval-missing-run": ("scalar-nerf-eval-fusion", ["--load-config", "runs/none/config.yml", "--output-dir", "out/e"], "no config.yml"),
    "eval-foreign-run": ("scalar-nerf-eval-fusion", ["--load-config", "runs/foreign/config.yml", "--output-dir", "out/f"], "nerfacto, not of scalar-nerf"),
    "eval-unfinished-run": ("scalar-nerf-eval-fusion", ["--load-config", "runs/unfinished/config.yml", "--output-dir", "out/g"], "no checkpoint"),
    "eval-unknown-fusion": ("scalar-nerf-eval-fusion", ["--load-config", "runs/global/config.yml", "--modes", "idw", "blok:1", "--output-dir", "out/h"], "unknown fusion mode 'blok:1'"),
    "eval-output-is-a-file": ("scalar-nerf-eval-fusion", ["--load-config", "runs/global/config.yml", "--output-dir", "a_file"], "is a file"),
    "assemble-missing-run": ("scalar-nerf-assemble", ["--global-run", "runs/none", "--block-runs", "runs/block1", "--output-dir", "out/i"], "no config.yml"),
    "assemble-block-of-another-split": ("scalar-nerf-assemble", ["--global-run", "runs/global", "--block-runs", "runs/other-split", "--output-dir", "out/j"], "split differently"),
    "assemble-foreign-block-run": ("scalar-nerf-assemble", ["--global-run", "runs/global", "--block-runs", "runs/foreign", "--output-dir", "out/k"], "not a scalar-nerf-block run"),
    "assemble-unfinished-global": ("scalar-nerf-assemble", ["--global-run", "runs/unfinished", "--block-runs", "runs/block1", "--output-dir", "out/l"], "no checkpoint"),
    "train-blocks-missing-run": ("scalar-nerf-train-blocks", ["runs/none", "--output-dir", "out/m"], "no config.yml"),
    "train-blocks-foreign-run": ("scalar-nerf-train-blocks", ["runs/foreign", "--output-dir", "out/n"], "not a scalar-nerf run"),
    "train-blocks-unfinished-global": ("scalar-nerf-train-blocks", ["runs/unfinished", "--output-dir", "out/o"], "is not finished (0 steps checkpointed)"),
    "export-frame-missing-run": ("scalar-nerf-export-frame", ["--load-config", "runs/none/config.yml", "--input", "mesh.ply", "--output", "out/p.ply"], "dataparser_transforms.json: not found"),
    "export-frame-unreadable-mesh": ("scalar-nerf-export-frame", ["--load-config", "runs/global/config.yml", "--input", "broken.ply", "--output", "out/q.ply"], "broken.ply: not a readable .ply"),
    "make-scene-output-in-use": ("scalar-nerf-make-scene", ["--output", "in_use", "--num-images", "2", "--width", "16", "--height", "12"], "is not empty"),
    "process-data-missing-photos": ("scalar-nerf-process-data", ["--images", "photos/none", "--output", "out/r"], "no such folder of photos"),
    "benchmark-missing-scene": ("scalar-nerf-benchmark", ["--data", "scenes/none", "--output-dir", "out/s"], "is not a scene folder"),
}


def _digests(root: Path) -> Dict[str, str]:
    """SHA-256 of every file and the name of every folder under ``root``."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "folder"
            for p in sorted(root.rglob("*"))}


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder the commands run in: runs of every kind, a broken mesh, a folder in use, a file."""
    root = tmp_path_factory.mktemp("commands")
    fake_run(root / "runs" / "global", {"_model.global_model.w": torch.ones(2), "_model.blocks_started": torch.tensor([False, False])})
    (root / "runs" / "global" / "dataparser_transforms.json").write_text(json.dumps({"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 1.0}))
    fake_run(root / "runs" / "block1", {"_model.blocks.1.t": torch.ones(3), "_model.blocks_started": torch.tensor([False, True])}, only_block=1)
    fake_run(root / "runs" / "other-split", {"_model.blocks.1.t": torch.ones(3)}, only_block=1, num_images=10)
    fake_run(root / "runs" / "unfinished", checkpoint=False)
    foreign_run(root / "runs" / "foreign")
    (root / "broken.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\nproperty float x\nend_header\n\x00\x01")
    (root / "in_use").mkdir()
    (root / "in_use" / "notes.txt").write_text("the user's")
    (root / "a_file").write_text("the user's")
    return root


@pytest.fixture(scope="module")
def results(work: Path, tmp_path_factory: pytest.TempPathFactory) -> Dict[str, dict]:
    """Every case run once through the driver: {case: {rc, stdout, stderr, changed}}."""
    logs = tmp_path_factory.mktemp("command_logs")
    before = _digests(work)
    jobs = [{"command": command, "args": args, "cwd": str(work), **{k: str(logs / f"{name}.{k}") for k in ("stdout", "stderr", "rc")}}
            for name, (command, args, _) in CASES.items()]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    driver = subprocess.run([sys.executable, "-c", DRIVER, json.dumps(jobs)], capture_output=True, text=True, timeout=600, env=env, check=False)
    assert driver.returncode == 0, driver.stderr[-3000:]
    after = _digests(work)
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    return {name: {"rc": int((logs / f"{name}.rc").read_text()), "stdout": (logs / f"{name}.stdout").read_text(),
                   "stderr": (logs / f"{name}.stderr").read_text(), "changed": changed} for name in CASES}


@pytest.mark.parametrize("case", list(CASES))
def test_the_command_refuses_in_one_line_and_writes_nothing(results: Dict[str, dict], case: str) -> None:
    command, _, message = CASES[case]
    result = results[case]
    output = result["stdout"] + result["stderr"]
    assert "Traceback" not in output, output[-3000:]
    assert result["rc"] == 1, output[-3000:]
    lines = [line for line in result["stderr"].splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(command) and message in lines[0], result["stderr"][-3000:]
    assert result["changed"] == [], f"written or changed by the refused commands: {result['changed']}"


def test_a_command_started_afresh_prints_one_line(work: Path) -> None:
    """As a user starts it: the imports' deprecation warnings of torch and nerfstudio are not shown."""
    result = subprocess.run(["scalar-nerf-assemble", "--global-run", "runs/none", "--block-runs", "runs/block1"],
                            capture_output=True, text=True, timeout=300, cwd=work, env={**os.environ, "OMP_NUM_THREADS": "1"}, check=False)
    assert result.returncode == 1 and result.stdout == ""
    assert result.stderr.strip().splitlines() == ["scalar-nerf-assemble: runs/none: no config.yml there (not a nerfstudio run folder)"], result.stderr


def test_every_command_is_covered() -> None:
    """Each console script of the package but the demo has its bad inputs above."""
    commands = {ep.name for ep in entry_points(group="console_scripts") if ep.value.startswith("scalar_nerfstudio.")}
    assert commands - {"scalar-nerf-demo"} == {command for command, _, _ in CASES.values()}
