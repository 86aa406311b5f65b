"""Check a nerfstudio-format scene before a run writes anything, and say plainly what is wrong.

nerfstudio's dataparser fails deep inside training set-up on a bad scene (a KeyError, an
AssertionError, a ZeroDivisionError, PIL's ``OSError: Truncated File Read`` or a NaN much later),
after the run folder has been created. :func:`scan_scene` reads ``transforms.json``, checks every
frame the way nerfstudio-data will read it (poses, intrinsics, train/eval split, the camera layout)
and fully decodes every image nerfstudio will load (``images_N/`` for ``--downscale-factor N``),
comparing its size with the frame's ``w``/``h``. It raises :class:`SceneError` with one paragraph
naming the file, the frame and what to do.

Images that can be used safely are accepted and converted in memory by :func:`to_rgb_array` (the
training dataset uses it; the scene folder is never changed): grayscale, 1-bit, palette, 16-bit
grayscale and CMYK images become 8-bit RGB, and images with an alpha channel are composited over a
background colour. :meth:`SceneInfo.conversion_note` says so in one line.
"""

from __future__ import annotations

import json
import math
import os
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence, Tuple, Union, cast

import numpy as np
from PIL import Image, UnidentifiedImageError

INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
#: nerfstudio-data's automatic downscale keeps images at most this many pixels across (MAX_AUTO_RESOLUTION).
MAX_AUTO_RESOLUTION = 1600
#: Scenes with more images than this show a progress bar while their images are decoded.
PROGRESS_MIN_IMAGES = 200
#: Camera centres closer together than this fraction of their distance from the origin (or 1e-6 scene
#: units) count as one position.
SAME_POSITION_TOLERANCE = 1e-6

# Image modes (PIL) and what becomes of them. RGB is used as is.
_GRAYSCALE = {"L": "grayscale", "1": "1-bit black-and-white"}
_SIXTEEN_BIT = {"I;16", "I;16L", "I;16B", "I;16N"}
_WITH_ALPHA = {"RGBA", "RGBa", "LA", "La", "PA"}
_OTHER_COLOUR = {"CMYK", "YCbCr"}


class SceneError(ValueError):
    """The scene folder cannot be trained on; the message says which file/frame and why."""


@dataclass(frozen=True)
class ImageInfo:
    """What decoding one image found: PIL mode, size (width, height), and whether it has transparency."""

    mode: str
    size: Tuple[int, int]
    has_alpha: bool


#: What an image needs: a label for the log line ("grayscale", "RGBA", ...) and the action:
#: "rgb" (used as RGB), "8bit" (16 bits scaled to 8) or "alpha" (composited over a background).
ImageKind = Tuple[str, str]


@dataclass
class SceneInfo:
    """A checked scene: its frame and training image counts and what its images need converting."""

    transforms: Path
    num_frames: int
    num_train: int
    downscale_factor: int
    """The factor nerfstudio-data loads the images at (1: the images themselves, N: ``images_N/``)."""
    conversions: Dict[ImageKind, int] = field(default_factory=dict)
    """What some images need (:func:`image_kind`) -> how many images need it."""

    def conversion_note(self, background: Sequence[float] = (1.0, 1.0, 1.0)) -> Optional[str]:
        """One line saying which images will be converted and how (None when all are 8-bit RGB)."""
        if not self.conversions:
            return None
        actions = {
            "rgb": "will be used as RGB",
            "8bit": "will be used as 8-bit RGB",
            "alpha": f"will be composited over the background colour {_colour(background)} (--pipeline.datamanager.alpha-background)",
        }
        parts = [f"{count} {label} image{'s' if count != 1 else ''} {actions[action]}"
                 for (label, action), count in sorted(self.conversions.items())]
        return "; ".join(parts) + " (converted in memory; the scene folder is not changed)."


def _colour(rgb: Sequence[float]) -> str:
    return " ".join(f"{float(c):g}" for c in rgb)


# ----------------------------------------------------------------------------------- conversion


def image_kind(mode: str, has_alpha: bool = False) -> Optional[ImageKind]:
    """What an image of PIL ``mode`` needs (None: 8-bit RGB, used as is), see :data:`ImageKind`.

    Raises:
        ValueError: the mode cannot be used as colours (e.g. 32-bit float).
    """
    if mode == "RGB":
        return None
    if mode in _WITH_ALPHA or (mode == "P" and has_alpha):
        return ("transparent palette" if mode.startswith("P") else mode, "alpha")
    if mode in _GRAYSCALE:
        return (_GRAYSCALE[mode], "rgb")
    if mode in _SIXTEEN_BIT or mode == "I":
        return ("16-bit grayscale", "8bit")
    if mode == "P":
        return ("palette (indexed-colour)", "rgb")
    if mode in _OTHER_COLOUR:
        return (mode, "rgb")
    raise ValueError(f"its pixels are of PIL mode {mode!r}, which is not a colour image nerfstudio can train on")


def to_rgb_array(image: Image.Image, background: Sequence[float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """``image`` as an 8-bit RGB array [H, W, 3]: grayscale/palette/CMYK converted, 16-bit scaled to 8
    bits, an alpha channel composited over ``background`` (RGB in [0, 1])."""
    mode = image.mode
    if mode == "RGB":
        return np.asarray(image, dtype=np.uint8)
    if mode in _SIXTEEN_BIT or mode == "I":
        values = np.asarray(image).astype(np.float32)
        grey = np.clip(values / 257.0 + 0.5, 0, 255).astype(np.uint8)
        return np.repeat(grey[:, :, None], 3, axis=2)
    if mode in _WITH_ALPHA or (mode == "P" and "transparency" in image.info):
        rgba = np.asarray(image.convert("RGBA"), dtype=np.uint16)
        alpha = rgba[:, :, 3:4]
        back = np.array([round(255 * float(c)) for c in background], dtype=np.uint16)
        return ((rgba[:, :, :3] * alpha + back * (255 - alpha) + 127) // 255).astype(np.uint8)
    return np.asarray(image.convert("RGB"), dtype=np.uint8)


# ------------------------------------------------------------------------------ transforms.json


def _transforms_path(data: Path) -> Path:
    if data.suffix == ".json":
        return data
    if not data.exists():
        where = "" if data.is_absolute() else f" (a relative path, looked for from {Path.cwd()}: run from the directory it was given in)"
        raise SceneError(f"The scene folder {data} does not exist{where}.")
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
    if isinstance(value, bool):
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number


def _frame_name(index: int, frame: Dict[str, Any]) -> str:
    return f"frame {index} ({frame.get('file_path', '?')})"


def _pose(path: Path, index: int, frame: Dict[str, Any]) -> np.ndarray:
    """The frame's 4x4 camera-to-world matrix (nerfstudio-data multiplies 4x4 poses; 3x4 ones fail there)."""
    matrix = frame.get("transform_matrix")
    name = _frame_name(index, frame)
    if not isinstance(matrix, list) or len(matrix) != 4 or any(not isinstance(r, list) or len(r) != 4 for r in matrix):
        widths = {len(r) for r in matrix if isinstance(r, list)} if isinstance(matrix, list) else set()
        if matrix is None:
            shape = "has no"
        elif isinstance(matrix, list) and matrix and len(widths) == 1 and all(isinstance(r, list) for r in matrix):
            shape = f"has a {len(matrix)}x{widths.pop()}"
        else:
            shape = "has a malformed"
        raise SceneError(
            f"{path}: {name} {shape} \"transform_matrix\"; nerfstudio-data needs a 4x4 camera-to-world "
            f"matrix in every frame (give a 3x4 pose the fourth row [0, 0, 0, 1])."
        )
    values = [_number(v) for row in matrix for v in row]
    if any(v is None or not math.isfinite(v) for v in values):
        raise SceneError(f"{path}: {name} has a NaN, infinite or non-numeric value in its camera pose (transform_matrix); fix that pose or remove the frame.")
    pose = np.array(values, dtype=np.float64).reshape(4, 4)
    if not np.allclose(pose[3], (0.0, 0.0, 0.0, 1.0), atol=1e-4):
        raise SceneError(f"{path}: {name} has the last transform_matrix row {pose[3].tolist()}; a camera-to-world pose ends in [0, 0, 0, 1].")
    return pose


def _intrinsics(path: Path, index: int, frame: Dict[str, Any], meta: Dict[str, Any]) -> Dict[str, float]:
    """fl_x, fl_y, cx, cy, w, h as nerfstudio-data reads them: a top-level value wins over the frame's
    (an invalid value is refused wherever it is)."""
    values = {}
    for key in INTRINSICS:
        if key not in meta and frame.get(key) is None:
            raise SceneError(f"{path}: {_frame_name(index, frame)} has no \"{key}\" (neither in the frame nor at the top level); "
                             f"nerfstudio-data needs fl_x, fl_y, cx, cy, w and h for every image.")
        given = ([(_frame_name(index, frame), frame[key])] if key in frame else []) + ([("the top level", meta[key])] if key in meta else [])
        for where, raw in given:
            value = _number(raw)
            positive = key in ("fl_x", "fl_y", "w", "h")
            if value is None or not math.isfinite(value) or (positive and value <= 0) or (key in ("w", "h") and value != int(value)):
                need = "a positive whole number" if key in ("w", "h") else "a finite number" + (" > 0" if positive else "")
                raise SceneError(f"{path}: {where} has an invalid intrinsic {key}={raw!r} (must be {need}).")
            values[key] = value  # the top-level value, when there is one, comes last
    return values


def _check_layout(path: Path, poses: np.ndarray) -> None:
    """Refuse a layout whose cameras all stand at one point (nerfstudio divides by their spread)."""
    centres = poses[:, :3, 3]
    spread = float(np.abs(centres - centres.mean(axis=0)).max())
    if spread <= SAME_POSITION_TOLERANCE * max(1.0, float(np.abs(centres).max())):
        if len(centres) == 1:
            raise SceneError(f"{path} has a single frame: a NeRF needs views from several camera positions.")
        where = ", ".join(f"{c:g}" for c in centres[0])
        raise SceneError(
            f"{path}: all {len(centres)} frames put the camera at the same position ({where}). A NeRF needs views from "
            f"different positions (nerfstudio-data scales the scene by the cameras' spread, which is zero here). Check "
            f"that each transform_matrix is that image's camera-to-world pose, with the camera position in its last column."
        )


def _num_train(path: Path, meta: Dict[str, Any], names: List[str], *, image_key: Callable[[str], str],
               eval_mode: str, eval_interval: Optional[int], train_fraction: float) -> int:
    """The number of training images nerfstudio-data's split leaves (refusing an empty train or eval split)."""
    num = len(names)
    lists = [f"{split}_filenames" for split in ("train", "val", "test") if f"{split}_filenames" in meta]
    if lists:
        keys = [image_key(name) for name in names]
        for split in ("train", "val"):
            listed = meta.get(f"{split}_filenames")
            if not isinstance(listed, list):
                raise SceneError(f"{path} has {', '.join(lists)} but no \"{split}_filenames\" list; nerfstudio-data then refuses "
                                 f"the {split} split. List that split's images too, or remove the *_filenames lists.")
            unknown = [name for name in listed if image_key(str(name)) not in keys]
            if unknown:
                raise SceneError(f"{path}: \"{split}_filenames\" names {len(unknown)} image(s) no frame has, e.g. {unknown[0]!r}.")
            if not listed:
                raise SceneError(f"{path}: \"{split}_filenames\" is empty; the {split} split needs at least one image.")
        train = {image_key(str(name)) for name in meta["train_filenames"]}
        return sum(key in train for key in keys)
    if eval_mode == "fraction":
        if not 0.0 < train_fraction <= 1.0:
            raise SceneError(f"--train-split-fraction {train_fraction:g}: must be in (0, 1].")
        num_train = math.ceil(num * train_fraction)
        if num_train < 1 or num - num_train < 1:
            raise SceneError(
                f"{path}: {num} frame(s) split {train_fraction:g} for training leaves "
                f"{num_train} training and {num - num_train} eval image(s); both need at least one."
            )
        return num_train
    if eval_mode == "filename":
        basenames = [Path(name).name for name in names]
        unsplit = [name for name in basenames if "train" not in name and "eval" not in name]
        if unsplit:
            raise SceneError(f"{path}: --eval-mode filename needs \"train\" or \"eval\" in every image's file name; "
                             f"{len(unsplit)} have neither, e.g. {unsplit[0]!r}.")
        for kind in ("train", "eval"):
            if not any(kind in name for name in basenames):
                raise SceneError(f"{path}: --eval-mode filename needs image names containing \"{kind}\"; none do, so that split would be empty.")
        return sum("train" in name for name in basenames)
    if eval_mode == "interval" and eval_interval is not None:
        if eval_interval < 1:
            raise SceneError(f"--eval-interval {eval_interval}: must be at least 1.")
        num_eval = len(range(0, num, eval_interval))
        if num - num_eval < 1:
            raise SceneError(f"{path}: {num} frame(s) with every {eval_interval}th held out for evaluation leaves no training image.")
        return num - num_eval
    return num  # "all", or interval mode with no interval given


# ------------------------------------------------------------------------------------- images


def _downscale_factor(root: Path, first: str, configured: Optional[int]) -> int:
    """The factor nerfstudio-data reads the images at (its ``_get_fname``): the configured one, or
    automatically halved while the first frame's image is over 1600 pixels and ``images_2N/`` exists."""
    if configured is not None:
        return int(configured)
    try:
        with Image.open(root / first) as image:
            max_res = max(image.size)
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError):
        return 1  # the image check below reports it
    factor = 0
    while max_res / 2**factor > MAX_AUTO_RESOLUTION and (root / f"images_{2 ** (factor + 1)}" / Path(first).name).exists():
        factor += 1
    return 2**factor


def _loaded_path(root: Path, file_path: str, factor: int) -> Path:
    """The image nerfstudio-data loads for ``file_path`` at downscale ``factor``."""
    return root / f"images_{factor}" / Path(file_path).name if factor > 1 else root / file_path


def _expected_size(width: float, height: float, factor: int) -> Tuple[int, int]:
    """Camera size after nerfstudio's ``rescale_output_resolution(1 / factor)`` (float32, rounded down)."""
    scale = np.float32(1.0 / factor)
    return int(np.float32(width) * scale), int(np.float32(height) * scale)


def decode_image(path: Path) -> Union[ImageInfo, str]:
    """Fully decode ``path``: its :class:`ImageInfo`, or why it cannot be used (a short phrase)."""
    try:
        with Image.open(path) as image:
            image.load()  # decodes every pixel: a truncated or corrupt file fails here, not in training
            has_alpha = image.mode in _WITH_ALPHA or (image.mode == "P" and "transparency" in image.info)
            if image.mode == "I":
                low, high = cast(Tuple[float, float], image.getextrema())
                if low < 0 or high > 65535:
                    return f"its 32-bit pixel values ({low}..{high}) are not a 16-bit image"
            return ImageInfo(mode=image.mode, size=image.size, has_alpha=has_alpha)
    except Image.DecompressionBombError as error:
        return f"it is too large to decode safely ({error})"
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as error:
        return f"cannot be read as an image ({error})"


def _decode_all(paths: Sequence[Path], workers: Optional[int]) -> List[Union[ImageInfo, str]]:
    """:func:`decode_image` of every path, in a thread pool (PIL releases the GIL while decoding),
    with a progress bar for scenes of more than :data:`PROGRESS_MIN_IMAGES` images."""
    if workers is None:
        workers = min(8, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    with ExitStack() as stack:
        results: Iterable[Union[ImageInfo, str]] = map(decode_image, paths)
        if workers > 1 and len(paths) > 1:
            results = stack.enter_context(ThreadPoolExecutor(max_workers=workers)).map(decode_image, paths)
        if len(paths) <= PROGRESS_MIN_IMAGES:
            return list(results)
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        console = Console(stderr=True)  # on a terminal only: a log file gets no bar
        columns = (TextColumn("checking images"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
        progress = stack.enter_context(Progress(*columns, console=console, transient=True, disable=not console.is_terminal))
        task = progress.add_task("decode", total=len(paths))
        collected: List[Union[ImageInfo, str]] = []
        for result in results:
            collected.append(result)
            progress.advance(task)
        return collected


def _check_images(path: Path, root: Path, frames: List[Dict[str, Any]], *, intrinsics: List[Dict[str, float]],
                  meta: Dict[str, Any], factor: int, auto_factor: bool, workers: Optional[int]) -> Dict[ImageKind, int]:
    """Decode every image nerfstudio-data will load and compare its size with the frame's w/h;
    returns the conversions needed (kind -> count)."""
    paths = [_loaded_path(root, str(frame["file_path"]), factor) for frame in frames]
    for index, (frame, image) in enumerate(zip(frames, paths)):
        if not image.is_file():
            if factor > 1:
                how = "nerfstudio-data's automatic downscale" if auto_factor else f"--downscale-factor {factor}"
                raise SceneError(
                    f"{path}: {_frame_name(index, frame)}: {how} reads {image}, which does not exist. Put the images "
                    f"downscaled {factor}x in {root / f'images_{factor}'}/ (same file names), or pick another --downscale-factor."
                )
            raise SceneError(f"{path}: frame {index} lists the image {image}, which does not exist; restore it or remove that frame from transforms.json.")
    results = _decode_all(paths, workers)
    conversions: Counter[ImageKind] = Counter()
    for index, (frame, image, result) in enumerate(zip(frames, paths, results)):
        name = _frame_name(index, frame)
        if isinstance(result, str):
            others = sum(isinstance(r, str) for r in results[index + 1:])
            more = f" ({others} more image(s) after it fail too)" if others else ""
            raise SceneError(f"{path}: {name}: the image {image} {result}. Replace it with a complete image file{more}.")
        try:
            kind = image_kind(result.mode, result.has_alpha)
        except ValueError as error:
            raise SceneError(f"{path}: {name}: the image {image}: {error}. Save it as an 8-bit RGB PNG or JPEG.") from None
        if kind is not None:
            conversions[kind] += 1
        width, height = intrinsics[index]["w"], intrinsics[index]["h"]
        expected = _expected_size(width, height, factor)
        if tuple(result.size) != expected:
            where = "at its top level" if "w" in meta and "h" in meta else f"for frame {index}"
            got = f"{result.size[0]}x{result.size[1]}"
            if factor == 1:
                raise SceneError(
                    f"{path}: {name}: the image {image} is {got} pixels, but transforms.json gives w={width:g}, h={height:g} ({where}). "
                    f"Correct w/h (and fl_x, fl_y, cx, cy with them) or use the image at that size."
                )
            raise SceneError(
                f"{path}: {name}: downscale {factor} loads {image}, which is {got} pixels, but w={width:g}, h={height:g} "
                f"(transforms.json, {where}) divided by {factor} and rounded down is {expected[0]}x{expected[1]}. Recreate "
                f"{root / f'images_{factor}'}/ at exactly 1/{factor} of the full size, or correct w/h in transforms.json."
            )
    return dict(conversions)


def _check_side_files(path: Path, frames: List[Dict[str, Any]]) -> None:
    """Masks and depth maps are given for every frame or for none (nerfstudio-data asserts it)."""
    for key in ("mask_path", "depth_file_path"):
        having = [i for i, frame in enumerate(frames) if key in frame]
        if having and len(having) != len(frames):
            missing = next(i for i in range(len(frames)) if key not in frames[i])
            raise SceneError(f"{path}: {len(having)} of {len(frames)} frames have a \"{key}\" but {_frame_name(missing, frames[missing])} "
                             f"has none; give it for every frame or for none.")


def _check_camera_model(path: Path, meta: Dict[str, Any]) -> None:
    model = meta.get("camera_model")
    if model is None:
        return
    try:
        from nerfstudio.cameras.cameras import CAMERA_MODEL_TO_TYPE
    except ImportError:  # nerfstudio absent: nothing to compare with
        return
    if model not in CAMERA_MODEL_TO_TYPE:
        raise SceneError(f"{path}: \"camera_model\": {model!r} is not a camera model nerfstudio knows ({', '.join(CAMERA_MODEL_TO_TYPE)}).")


# ---------------------------------------------------------------------------------------- scene


def scan_scene(
    data: Path,
    *,
    eval_interval: Optional[int] = None,
    eval_mode: str = "interval",
    train_fraction: float = 0.9,
    downscale_factor: Optional[int] = None,
    workers: Optional[int] = None,
) -> SceneInfo:
    """Validate a nerfstudio-format scene the way nerfstudio-data will read it.

    Args:
        data: the scene folder (or its transforms.json).
        eval_interval: with nerfstudio-data's ``interval`` eval mode, every ``eval_interval``-th
            image is held out; the check makes sure that leaves both a train and an eval image.
        eval_mode: nerfstudio-data's ``--eval-mode`` (interval, fraction, filename, all).
        train_fraction: ``--train-split-fraction`` of the ``fraction`` mode.
        downscale_factor: nerfstudio-data's ``--downscale-factor`` (None: its automatic choice);
            the images of ``images_N/`` are then checked against ``w/N`` x ``h/N``.
        workers: threads decoding the images (None: one per CPU this process may use, at most 8; 1: no pool).

    Raises:
        SceneError: naming the file, frame and problem.
    """
    data = Path(data)
    transforms = _transforms_path(data)
    meta = _load_json(transforms)
    root = transforms.parent
    frames: List[Dict[str, Any]] = meta["frames"]
    _check_camera_model(transforms, meta)
    poses, intrinsics = [], []
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str) or not frame["file_path"]:
            raise SceneError(f"{transforms}: frame {index} has no \"file_path\".")
        poses.append(_pose(transforms, index, frame))
        intrinsics.append(_intrinsics(transforms, index, frame, meta))
    _check_side_files(transforms, frames)
    if downscale_factor is not None and downscale_factor < 1:
        raise SceneError(f"--downscale-factor {downscale_factor}: must be at least 1 (1: the images themselves).")
    factor = _downscale_factor(root, str(frames[0]["file_path"]), downscale_factor)
    names = [str(frame["file_path"]) for frame in frames]
    num_train = _num_train(transforms, meta, names, image_key=lambda name: str(_loaded_path(root, name, factor)),
                           eval_mode=eval_mode, eval_interval=eval_interval, train_fraction=train_fraction)
    _check_layout(transforms, np.stack(poses))
    conversions = _check_images(transforms, root, frames, intrinsics=intrinsics, meta=meta, factor=factor,
                                auto_factor=downscale_factor is None, workers=workers)
    return SceneInfo(transforms=transforms, num_frames=len(frames), num_train=num_train, downscale_factor=factor, conversions=conversions)


def check_scene(
    data: Path, *, eval_interval: Optional[int] = None, eval_mode: str = "interval", train_fraction: float = 0.9,
    downscale_factor: Optional[int] = None,
) -> int:
    """Validate a nerfstudio-format scene (:func:`scan_scene`); returns its number of frames."""
    return scan_scene(data, eval_interval=eval_interval, eval_mode=eval_mode, train_fraction=train_fraction,
                      downscale_factor=downscale_factor).num_frames
