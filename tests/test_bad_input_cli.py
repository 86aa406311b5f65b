"""``ns-train`` on bad scenes and options, end to end: one clear paragraph, a non-zero exit, no
traceback and nothing written; grayscale and RGBA scenes train."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import pytest
from bad_scenes import CASES, broken_copy, truncated_jpeg
from cli_driver import DRIVER
from conftest import ns_train_command, run_dirs

from scalar_nerfstudio.data.validation import SceneError, scan_scene

# ------------------------------------------------------------------------- ns-train, end to end

# Every case runs nerfstudio's real `ns-train` entry point, in one process that imported it once (cli_driver.py).

#: A guard, so that a case the checks miss trains one step and ends instead of hanging in the viewer.
_GUARD = ["--max-num-iterations", "1", "--vis", "tensorboard", "--viewer.quit-on-train-completion", "True"]

#: Option cases run through ns-train on the good scene: name -> (extra arguments, message fragment).
CLI_OPTION_CASES: Dict[str, Tuple[List[str], str]] = {
    "num-blocks 0": (["--pipeline.num-blocks", "0"], "bad option: --pipeline.num-blocks 0: must be at least 1"),
    "num-blocks 50": (["--pipeline.num-blocks", "50"], "bad option: --pipeline.num-blocks 50: the scene has only 5 training images"),
    "aabb-scale -1": (["--pipeline.aabb-scale", "-1", "-1", "-1"], "bad option: --pipeline.aabb-scale -1 -1 -1"),
    "global-steps -1": (["--pipeline.global-steps", "-1"], "bad option: --pipeline.global-steps -1"),
    "log2 bounds reversed": (["--pipeline.block-log2-hashmap-bounds", "19", "14"], "bad option: --pipeline.block-log2-hashmap-bounds 19 14"),
    "eval-interval 0": (["nerfstudio-data", "--eval-interval", "0"], "bad option: --eval-interval 0"),
    "block split too small": (["--pipeline.num-blocks", "5", "--pipeline.aabb-scale", "1", "1", "1", "--pipeline.min-overlap-images", "0"],
                              "bad option: the block split with --pipeline.num-blocks 5"),
}
#: Scene cases run through ns-train.
CLI_SCENE_CASES = ["missing image", "truncated transforms", "nan pose", "empty folder", "no training image", "image size differs from w/h",
                   "3x4 and 4x4 poses", "identical camera centres", "truncated jpeg"]


def _read_only_mount_works(folder: Path) -> bool:
    """Whether this machine lets us mount a read-only tmpfs in a private mount namespace (root, unshare)."""
    if shutil.which("unshare") is None:
        return False
    folder.mkdir(parents=True, exist_ok=True)
    probe = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o ro tmpfs '{folder}' && ! touch '{folder}/x' 2>/dev/null"],
                           capture_output=True, timeout=30, check=False)
    return probe.returncode == 0


@pytest.fixture(scope="module")
def ns_train_results(good_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Dict[str, dict]:
    """Every CLI case through ns-train in one process: name -> {rc, output, outputs folder, earlier file}."""
    root = tmp_path_factory.mktemp("cli")
    jobs, results = [], {}

    def add(name: str, scene: Path, extra: List[str], outputs: Optional[Path] = None) -> None:
        folder = root / f"case{len(jobs)}"
        folder.mkdir()
        if outputs is None:
            outputs = folder / "outputs"
            outputs.mkdir()
            (outputs / "earlier-run.txt").write_text("an earlier run's file")
        args = ["scalar-nerf", "--data", str(scene), "--output-dir", str(outputs), *_GUARD, *extra]  # a dataparser comes last
        jobs.append({"command": "ns-train", "args": args, "stdout": str(folder / "out"), "stderr": str(folder / "err"), "rc": str(folder / "rc")})
        results[name] = {"folder": folder, "outputs": outputs}

    for case in CLI_SCENE_CASES:
        scene = root / f"scene-{len(jobs)}"
        shutil.copytree(good_scene, scene)
        CASES[case][0](scene)
        add(case, scene, [])
    for case, (extra, _) in CLI_OPTION_CASES.items():
        add(case, good_scene, extra)
    file_output = root / "a-file"
    file_output.write_text("not a folder")
    add("output under a file", good_scene, [], outputs=file_output / "outputs")
    read_only = root / "read-only"
    command = [sys.executable, "-c", DRIVER]
    if _read_only_mount_works(read_only):
        add("read-only output", good_scene, [], outputs=read_only / "outputs")
        driver = f"mount -t tmpfs -o ro tmpfs '{read_only}' && exec \"$@\""
        command = ["unshare", "-m", "sh", "-c", driver, "sh", *command]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([*command, json.dumps(jobs)], capture_output=True, text=True, timeout=600, env=env, check=False)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    for name, result in results.items():
        folder = result["folder"]
        result["rc"] = int((folder / "rc").read_text())
        result["output"] = (folder / "out").read_text() + (folder / "err").read_text()
    return results


def _assert_stopped_cleanly(result: dict, message: str, earlier: bool = True) -> None:
    output = result["output"]
    assert result["rc"] != 0, output[-3000:]
    assert "Traceback" not in output, output[-3000:]
    assert message in " ".join(output.split()), output[-3000:]
    outputs: Path = result["outputs"]
    if earlier:
        assert sorted(p.name for p in outputs.rglob("*")) == ["earlier-run.txt"]
        assert (outputs / "earlier-run.txt").read_text() == "an earlier run's file"
    else:
        assert not outputs.exists()


@pytest.mark.parametrize("case", CLI_SCENE_CASES)
def test_ns_train_stops_cleanly_and_writes_nothing(ns_train_results: Dict[str, dict], case: str) -> None:
    _assert_stopped_cleanly(ns_train_results[case], "bad scene")
    _assert_stopped_cleanly(ns_train_results[case], CASES[case][1])


@pytest.mark.parametrize("case", list(CLI_OPTION_CASES))
def test_ns_train_bad_option_stops_before_writing(ns_train_results: Dict[str, dict], case: str) -> None:
    _assert_stopped_cleanly(ns_train_results[case], CLI_OPTION_CASES[case][1])


def test_ns_train_output_under_a_file(ns_train_results: Dict[str, dict]) -> None:
    result = ns_train_results["output under a file"]
    _assert_stopped_cleanly(result, "cannot write the run: --output-dir: the run folder", earlier=False)
    _assert_stopped_cleanly(result, "a-file is a file, not a folder", earlier=False)
    assert (result["outputs"].parent).read_text() == "not a folder"


def test_ns_train_read_only_output(ns_train_results: Dict[str, dict]) -> None:
    if "read-only output" not in ns_train_results:
        pytest.skip("cannot mount a read-only file system here (needs root and unshare)")
    _assert_stopped_cleanly(ns_train_results["read-only output"], "cannot write the run: --output-dir: nothing can be written to", earlier=False)
    _assert_stopped_cleanly(ns_train_results["read-only output"], "it is on a read-only file system", earlier=False)


def test_ns_train_process_stops_cleanly(good_scene: Path, tmp_path: Path) -> None:
    """One case as a real `python -m nerfstudio.scripts.train` process (the interpreter prints the message)."""
    scene = broken_copy(good_scene, tmp_path, truncated_jpeg)
    outputs = tmp_path / "outputs"
    result = subprocess.run(
        [sys.executable, "-m", "nerfstudio.scripts.train", "scalar-nerf", "--data", str(scene), "--output-dir", str(outputs), *_GUARD],
        capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"}, check=False
    )
    _assert_stopped_cleanly({"rc": result.returncode, "output": result.stdout + result.stderr, "outputs": outputs},
                            "bad scene: ", earlier=False)
    assert "frame 3 (images/frame_00003.jpg): the image" in result.stderr


@pytest.mark.slow  # trains
def test_grayscale_and_rgba_scene_trains(mixed_scene: Path, tmp_path: Path) -> None:
    """Grayscale, RGBA, palette and 16-bit images train (a few steps, through an eval image) with one note."""
    outputs = tmp_path / "outputs"
    before = sorted(str(p.relative_to(mixed_scene)) for p in mixed_scene.rglob("*"))
    tiny = [
        "--max-num-iterations", "3", "--steps-per-eval-image", "2", "--vis", "tensorboard",
        "--pipeline.model.field.log2-hashmap-size", "12", "--pipeline.model.field.max-resolution", "64",
        "--pipeline.model.num-samples-per-ray", "16", "--pipeline.datamanager.train-num-rays-per-batch", "256",
        "--pipeline.num-blocks", "2", "--pipeline.global-steps", "2", "--pipeline.block-steps", "1",
    ]
    result = subprocess.run(ns_train_command(mixed_scene, outputs, *tiny), capture_output=True, text=True, timeout=600,
                            env={**os.environ, "OMP_NUM_THREADS": "1"}, check=False)
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-3000:]
    assert "Traceback" not in output
    notes = [line for line in result.stdout.splitlines() if "will be used as RGB" in line]
    assert len(notes) == 1, output[-3000:]
    assert "2 grayscale images will be used as RGB" in notes[0] and "1 RGBA image will be composited" in notes[0]
    (run,) = run_dirs(outputs)
    assert (run / "nerfstudio_models").is_dir()
    assert sorted(str(p.relative_to(mixed_scene)) for p in mixed_scene.rglob("*")) == before  # the scene folder is untouched


def test_a_missing_relative_scene_names_where_it_was_looked_for(tmp_path: Path, monkeypatch) -> None:
    """A relative --data that does not exist names the directory it was looked for from (a run's
    config keeps the path as typed, so a command started elsewhere looks in the wrong place)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SceneError, match=f"scene folder scenes/town does not exist \\(a relative path, looked for from {tmp_path}"):
        scan_scene(Path("scenes/town"), eval_interval=8)
    with pytest.raises(SceneError, match=f"scene folder {tmp_path / 'town'} does not exist\\.$"):
        scan_scene(tmp_path / "town", eval_interval=8)
