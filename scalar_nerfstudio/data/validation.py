"""Check a nerfstudio-format scene before a run writes anything, and say plainly what is wrong.

nerfstudio's dataparser fails deep inside training set-up on a bad scene (a KeyError, a
FileNotFoundError or a NaN much later), after the run folder has been created. ``check_scene``
reads ``transforms.json`` and every image header up front and raises :class:`SceneError` with one
paragraph naming the file, the frame and the problem.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Dict, List, Optional

from PIL import Image, UnidentifiedImageError

INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")


class SceneError(ValueError):
    """The scene folder cannot be trained on; the message says which file/frame and why."""


def _transforms_path(data: Path) -> Path:
    if data.suffix == ".json":
        return data
    if not data.exists():
        raise SceneError(f"The scene folder {data} does not exist.")
    if data.is_dir() and not any(data.iterdir()):
        raise SceneError(f"The scene folder {data} is empty: it needs a transforms.json and the images it lists.")
    return data / "transforms.json"


def _load_json(path: Path) -> Dict[str, Any]:
    if not path.is_file():
        raise SceneError(f"{path} is missing: a nerfstudio scene needs a transforms.json listing its images and camera poses.")
    try:
        content = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as error:
        raise SceneError(f"{path} is not valid JSON (line {error.lineno}, column {error.colno}: {error.msg}); is it truncated?") from None
    except (OSError, UnicodeDecodeError) as error:
        raise SceneError(f"{path} cannot be read: {error}.") from None
    if not isinstance(content, dict) or not isinstance(content.get("frames"), list):
        raise SceneError(f"{path} has no \"frames\" list; it is not a nerfstudio transforms.json.")
    if not content["frames"]:
        raise SceneError(f"{path} lists no frames: there are no images to train on.")
    return content


def _number(value: Any) -> Optional[float]:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number


def _check_pose(path: Path, index: int, frame: Dict[str, Any]) -> None:
    matrix = frame.get("transform_matrix")
    name = frame.get("file_path", f"#{index}")
    if not isinstance(matrix, list) or len(matrix) not in (3, 4) or any(not isinstance(r, list) or len(r) != 4 for r in matrix):
        raise SceneError(f"{path}: frame {index} ({name}) has no 3x4 or 4x4 \"transform_matrix\".")
    values = [_number(v) for row in matrix for v in row]
    if any(v is None or not math.isfinite(v) for v in values):
        raise SceneError(f"{path}: frame {index} ({name}) has a NaN, infinite or non-numeric value in its camera pose (transform_matrix).")


def _check_intrinsics(path: Path, index: int, frame: Dict[str, Any], defaults: Dict[str, Any]) -> None:
    name = frame.get("file_path", f"#{index}")
    for key in INTRINSICS:
        raw = frame.get(key, defaults.get(key))
        if raw is None:
            if key in ("fl_x", "fl_y"):
                raise SceneError(f"{path}: frame {index} ({name}) has no focal length \"{key}\" (neither in the frame nor at the top level).")
            continue
        value = _number(raw)
        if value is None or not math.isfinite(value) or (key in ("fl_x", "fl_y", "w", "h") and value <= 0):
            raise SceneError(f"{path}: frame {index} ({name}) has an invalid intrinsic {key}={raw!r} (must be a finite number{', > 0' if key != 'cx' and key != 'cy' else ''}).")


def _check_image(path: Path, index: int, image: Path) -> None:
    if not image.is_file():
        raise SceneError(f"{path}: frame {index} lists the image {image}, which does not exist.")
    try:
        with Image.open(image) as handle:
            handle.verify()
    except (UnidentifiedImageError, OSError, SyntaxError) as error:
        raise SceneError(f"{path}: frame {index}: the image {image} cannot be read as an image ({error}).") from None


def check_scene(
    data: Path, eval_interval: Optional[int] = None, eval_mode: str = "interval", train_fraction: float = 0.9
) -> int:
    """Validate a nerfstudio-format scene; returns its number of frames.

    Args:
        data: the scene folder (or its transforms.json).
        eval_interval: with nerfstudio-data's ``interval`` eval mode, every ``eval_interval``-th
            image is held out; the check makes sure that leaves both a train and an eval image.
        eval_mode: nerfstudio-data's ``--eval-mode`` (interval, fraction, filename, all).
        train_fraction: ``--train-split-fraction`` of the ``fraction`` mode.

    Raises:
        SceneError: naming the file, frame and problem.
    """
    data = Path(data)
    transforms = _transforms_path(data)
    content = _load_json(transforms)
    root = transforms.parent
    frames: List[Dict[str, Any]] = content["frames"]
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict) or "file_path" not in frame:
            raise SceneError(f"{transforms}: frame {index} has no \"file_path\".")
        _check_pose(transforms, index, frame)
        _check_intrinsics(transforms, index, frame, content)
        _check_image(transforms, index, root / frame["file_path"])
    names = [str(frame["file_path"]) for frame in frames]
    if eval_mode == "fraction":
        num_train = math.ceil(len(frames) * train_fraction)
        if num_train < 1 or len(frames) - num_train < 1:
            raise SceneError(
                f"{transforms}: {len(frames)} frame(s) split {train_fraction:g} for training leaves "
                f"{num_train} training and {len(frames) - num_train} eval image(s); both need at least one."
            )
    if eval_mode == "filename":
        for kind in ("train", "eval"):
            if not any(kind in name for name in names):
                raise SceneError(f"{transforms}: --eval-mode filename needs image names containing \"{kind}\"; none do, so that split would be empty.")
    if eval_mode == "interval" and eval_interval is not None:
        if eval_interval < 1:
            raise SceneError(f"--eval-interval {eval_interval}: must be at least 1.")
        num_eval = len(range(0, len(frames), eval_interval))
        if len(frames) - num_eval < 1:
            raise SceneError(f"{transforms}: {len(frames)} frame(s) with every {eval_interval}th held out for evaluation leaves no training image.")
    return len(frames)
