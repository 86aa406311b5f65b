"""Bad scenes end with one clear paragraph naming the file/frame, a non-zero exit, no traceback,
and nothing written into the output folder."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Callable

import pytest

from scalar_nerfstudio.data.synthetic_scene import write_scene
from scalar_nerfstudio.data.validation import SceneError, check_scene


@pytest.fixture(scope="module")
def good_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("good")
    write_scene(folder, num_images=6, width=32, height=24)
    return folder


def _transforms(scene: Path) -> dict:
    return json.loads((scene / "transforms.json").read_text())


def _write(scene: Path, content: dict) -> None:
    (scene / "transforms.json").write_text(json.dumps(content))


def _missing_image(scene: Path) -> None:
    (scene / _transforms(scene)["frames"][2]["file_path"]).unlink()


def _unreadable_image(scene: Path) -> None:
    (scene / _transforms(scene)["frames"][1]["file_path"]).write_bytes(b"not a png at all")


def _truncated_json(scene: Path) -> None:
    text = (scene / "transforms.json").read_text()
    (scene / "transforms.json").write_text(text[: len(text) // 2])


def _nan_pose(scene: Path) -> None:
    content = _transforms(scene)
    content["frames"][3]["transform_matrix"][0][3] = math.nan
    _write(scene, content)  # json writes the token NaN, which json (and nerfstudio) read back


def _inf_focal(scene: Path) -> None:
    content = _transforms(scene)
    content["frames"][0]["fl_x"] = math.inf
    _write(scene, content)


def _no_frames(scene: Path) -> None:
    content = _transforms(scene)
    content["frames"] = []
    _write(scene, content)


def _one_frame(scene: Path) -> None:  # interval eval mode holds it out: nothing left to train on
    content = _transforms(scene)
    content["frames"] = content["frames"][:1]
    _write(scene, content)


def _empty_folder(scene: Path) -> None:
    shutil.rmtree(scene)
    scene.mkdir()


CASES = {
    "missing image": (_missing_image, "does not exist"),
    "unreadable image": (_unreadable_image, "cannot be read as an image"),
    "truncated transforms": (_truncated_json, "is not valid JSON"),
    "nan pose": (_nan_pose, "frame 3"),
    "inf intrinsics": (_inf_focal, "fl_x=inf"),
    "no frames": (_no_frames, "lists no frames"),
    "no training image": (_one_frame, "leaves no training image"),
    "empty folder": (_empty_folder, "is empty"),
}


def _broken(good_scene: Path, tmp_path: Path, breaker: Callable[[Path], None]) -> Path:
    scene = tmp_path / "scene"
    shutil.copytree(good_scene, scene)
    breaker(scene)
    return scene


def test_good_scene_passes(good_scene: Path) -> None:
    assert check_scene(good_scene, eval_interval=8) == 6


@pytest.mark.parametrize("case", list(CASES))
def test_check_scene_names_the_problem(good_scene: Path, tmp_path: Path, case: str) -> None:
    breaker, message = CASES[case]
    scene = _broken(good_scene, tmp_path, breaker)
    with pytest.raises(SceneError, match=message.replace("(", r"\(")):
        check_scene(scene, eval_interval=8)


@pytest.mark.parametrize(
    ("mode", "message"),
    [("fraction", "both need at least one"), ("filename", "needs image names containing")],
)
def test_empty_eval_split_in_other_modes(good_scene: Path, mode: str, message: str) -> None:
    fraction = 1.0 if mode == "fraction" else 0.9  # fraction 1.0 puts every image in training
    with pytest.raises(SceneError, match=message):
        check_scene(good_scene, eval_mode=mode, train_fraction=fraction)


@pytest.mark.parametrize("case", ["missing image", "truncated transforms", "nan pose", "empty folder", "no training image"])
def test_ns_train_stops_cleanly_and_writes_nothing(good_scene: Path, tmp_path: Path, case: str) -> None:
    breaker, message = CASES[case]
    scene = _broken(good_scene, tmp_path, breaker)
    outputs = tmp_path / "outputs"
    earlier = outputs / "earlier-run.txt"
    earlier.parent.mkdir()
    earlier.write_text("an earlier run's file")
    result = subprocess.run(
        [sys.executable, "-m", "nerfstudio.scripts.train", "scalar-nerf", "--data", str(scene), "--output-dir", str(outputs)],
        capture_output=True, text=True, timeout=300,
    )
    output = result.stdout + result.stderr
    assert result.returncode != 0
    assert "bad scene" in output and message in output
    assert "Traceback" not in output
    assert sorted(p.name for p in outputs.rglob("*")) == ["earlier-run.txt"]
    assert earlier.read_text() == "an earlier run's file"
