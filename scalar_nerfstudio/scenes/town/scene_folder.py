"""The town's scene folder in nerfstudio format: writing it (:func:`write_town`) and reading it back.

Output of :func:`write_town`::

    OUT/transforms.json        nerfstudio format (OPENCV, no distortion; OpenGL camera axes)
    OUT/images/frame_XXXXX.png RGB, frames numbered in capture order
    OUT/depths/frame_XXXXX.png 16-bit depth in millimetres along the optical axis (z-depth, the
                               convention of nerfstudio's depth loaders, is_euclidean_depth=False);
                               0 = sky or farther than 65.535 m
    OUT/depths/frame_XXXXX.npy instead of the PNGs when an aerial flight's ground lies beyond 65.535 m:
                               float32 millimetres, the same z-depth (0 = sky); nerfstudio reads both
    OUT/scene.json             generator options, streets and the list of boxes

The frames are numbered in capture order, so nerfstudio's ``--eval-mode interval --eval-interval 8``
holds out every 8th frame along the same paths (nerfstudio sorts frames by file name). The town of a
written scene is rebuilt by :func:`load_town` (from the options in its scene.json), so the exact
float depth of any frame is available again with :func:`~.render.render_town_image`.
"""

from __future__ import annotations

import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np
from PIL import Image

from scalar_nerfstudio.engine.allocator import keep_render_temporaries
from scalar_nerfstudio.scenes.town.cameras import deepest_aerial_depth_m, town_camera_poses, town_intrinsics
from scalar_nerfstudio.scenes.town.config import (
    DEPTH_PNG_MAX_M,
    DEPTH_PNG_UNIT_M,
    GENERATOR_ID,
    GENERATOR_VERSION,
    READABLE_VERSIONS,
    TownConfig,
)
from scalar_nerfstudio.scenes.town.layout import STYLES, Town, build_town
from scalar_nerfstudio.scenes.town.render import render_town_image

__all__ = ["depth_suffix", "iter_frames", "load_town", "read_depth", "write_town"]


def depth_suffix(config: TownConfig) -> str:
    """The file type of a scene's depth images: ``.png`` (16-bit millimetres), or ``.npy`` (float32
    millimetres) when its aerial frames' ground can lie beyond the PNGs' 65.535 m."""
    aerial = config.capture in ("aerial", "aerial+rig")
    return ".npy" if aerial and deepest_aerial_depth_m(config) > DEPTH_PNG_MAX_M else ".png"


def read_depth(path: Path) -> np.ndarray:
    """[H, W] metres from a depth image written by :func:`write_town`, PNG or ``.npy`` (0 where unknown:
    sky, or beyond a PNG's range)."""
    path = Path(path)
    if path.suffix == ".npy":
        return np.load(path).astype(np.float64) * DEPTH_PNG_UNIT_M
    with Image.open(path) as image:
        return np.asarray(image, dtype=np.float64) * DEPTH_PNG_UNIT_M


def _depth_png(z_depth: np.ndarray) -> np.ndarray:
    """[H, W] metres -> [H, W] uint16 millimetres; inf and > 65.535 m -> 0 (unknown to nerfstudio)."""
    mm = np.where(np.isfinite(z_depth), np.round(z_depth / DEPTH_PNG_UNIT_M), 0.0)
    return np.where(mm > 65535, 0, mm).astype(np.uint16)


def _depth_npy(z_depth: np.ndarray) -> np.ndarray:
    """[H, W] metres -> [H, W] float32 millimetres; inf (sky) -> 0 (unknown to nerfstudio)."""
    return np.where(np.isfinite(z_depth), z_depth / DEPTH_PNG_UNIT_M, 0.0).astype(np.float32)


#: The town of a worker process of :func:`write_town` (built once per worker by ``_worker_init``).
_WORKER_TOWN: Optional[Town] = None


def _frame_names(num_images: int) -> List[str]:
    digits = max(5, len(str(num_images - 1)))
    return [f"frame_{k:0{digits}d}.png" for k in range(num_images)]


def _write_frames(town: Town, out_dir: Path, poses: np.ndarray, names: Sequence[str], indices: Sequence[int]) -> int:
    """Render and write frames ``indices`` (image and depth, as :func:`depth_suffix` says); returns how many."""
    suffix = depth_suffix(town.config)
    for k in indices:
        rgb, _, z_depth = render_town_image(town, poses[k])
        Image.fromarray((rgb * 255.0 + 0.5).astype(np.uint8)).save(out_dir / "images" / names[k], format="PNG")
        depth_path = out_dir / "depths" / Path(names[k]).with_suffix(suffix)
        if suffix == ".npy":
            np.save(depth_path, _depth_npy(z_depth))
        else:
            Image.fromarray(_depth_png(z_depth)).save(depth_path, format="PNG")
    return len(indices)


def _worker_init(config_json: Dict[str, Any]) -> None:
    global _WORKER_TOWN
    keep_render_temporaries()
    _WORKER_TOWN = build_town(TownConfig.from_json(config_json))


def _worker_frames(out_dir: str, indices: List[int]) -> int:
    assert _WORKER_TOWN is not None
    town = _WORKER_TOWN
    return _write_frames(town, Path(out_dir), town_camera_poses(town), _frame_names(town.config.num_images), indices)


class _Progress:
    """A progress bar over ``total`` frames: rich, else tqdm, else nothing."""

    def __init__(self, total: int, description: str, enabled: bool) -> None:
        self._advance: Callable[[int], object] = lambda n: None  # what it returns (tqdm's update: a bool) is unused
        self._close: Callable[[], None] = lambda: None
        if not enabled:
            return
        try:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn())
            progress.start()
            task = progress.add_task(description, total=total)
            self._advance = lambda n: progress.advance(task, n)
            self._close = progress.stop
            return
        except ImportError:
            pass
        try:
            from tqdm import tqdm

            bar = tqdm(total=total, desc=description, unit="frame")
            self._advance = bar.update
            self._close = bar.close
        except ImportError:
            pass

    def advance(self, n: int = 1) -> None:
        self._advance(n)

    def close(self) -> None:
        self._close()


def _depth_description(suffix: str) -> Dict[str, Any]:
    """scene.json's entry on the depth images (``depth_png``, or ``depth_npy`` for float32 ``.npy`` files)."""
    far = f"sky, or farther than {DEPTH_PNG_MAX_M} m" if suffix == ".png" else "sky"
    return {f"depth_{suffix[1:]}": {"folder": "depths", "unit_m": DEPTH_PNG_UNIT_M,
                                    "kind": "z-depth along the optical axis (nerfstudio's is_euclidean_depth=False convention)",
                                    "zero_means": far}}


def _scene_description(town: Town, names: Sequence[str]) -> Dict[str, Any]:
    config = town.config
    return {
        "generator": GENERATOR_ID,
        "version": GENERATOR_VERSION,
        "config": config.to_json(),
        "units": "metres; z up; ground at z = 0",
        "extent": list(config.extent),
        "street_extent": list(config.street_extent),
        "street_x": town.street_x.tolist(),
        "street_y": town.street_y.tolist(),
        "street_width": config.street_width,
        "road_width": config.road_width,
        **_depth_description(depth_suffix(config)),
        "frames": len(names),
        "boxes": [
            {"lo": town.lo[b].tolist(), "hi": town.hi[b].tolist(), "cell": int(town.cell[b]), "style": STYLES[int(town.style[b])], "shops": bool(town.shops[b])}
            for b in range(town.num_buildings)
        ],
    }


def _prepare_output(out_dir: Path, overwrite: bool) -> None:
    """Create ``out_dir`` (must be empty unless ``overwrite``) and check that it is writable."""
    if out_dir.exists() and not out_dir.is_dir():
        raise FileExistsError(f"The output {out_dir} exists and is not a folder.")
    if out_dir.is_dir() and any(out_dir.iterdir()) and not overwrite:
        raise FileExistsError(f"The output folder {out_dir} is not empty; choose another folder or pass overwrite=True (--overwrite).")
    try:
        (out_dir / "images").mkdir(parents=True, exist_ok=True)
        (out_dir / "depths").mkdir(parents=True, exist_ok=True)
        probe = out_dir / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        raise PermissionError(f"The output folder {out_dir} cannot be written: {error.strerror or error}.") from None
    if overwrite:  # stale frames of an earlier, larger scene would be left behind
        for folder, pattern in (("images", "frame_*.png"), ("depths", "frame_*.png"), ("depths", "frame_*.npy")):
            for stale in (out_dir / folder).glob(pattern):
                stale.unlink()
        for name in ("transforms.json", "scene.json"):
            if (out_dir / name).exists():
                (out_dir / name).unlink()


def write_town(out_dir: Path, config: Optional[TownConfig] = None, *, progress: bool = True, overwrite: bool = False,
               workers: int = 1) -> Path:
    """Generate the town, render every frame and write the nerfstudio scene (see the module docstring).

    Args:
        out_dir: the scene folder (created; must be empty unless ``overwrite``).
        config: the options (default :class:`TownConfig`()).
        progress: show a progress bar (rich or tqdm, when installed).
        overwrite: write into a non-empty folder, replacing an earlier scene's frames.
        workers: processes rendering frames at once (the output does not depend on it).

    On glibc this keeps freed memory in the process for reuse
    (:func:`~scalar_nerfstudio.engine.allocator.keep_render_temporaries`), unless the user set malloc's
    own settings.

    Returns:
        The path of the written ``transforms.json`` (written last: its presence means a complete scene).
    """
    config = config or TownConfig()
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"write_town: workers must be a positive integer, got {workers!r}")
    out_dir = Path(out_dir)
    town = build_town(config)
    poses = town_camera_poses(town)  # raises on a capture that cannot be flown, before anything is written
    _prepare_output(out_dir, overwrite)
    keep_render_temporaries()
    names = _frame_names(config.num_images)
    bar = _Progress(config.num_images, f"Rendering the town ({config.num_images} frames)", progress)
    try:
        batches = [list(range(k, min(k + 4, config.num_images))) for k in range(0, config.num_images, 4)]
        if workers == 1:
            for batch in batches:
                bar.advance(_write_frames(town, out_dir, poses, names, batch))
        else:
            # spawn, not fork: the caller may hold threads (torch, a viewer) that a fork would copy mid-lock.
            context = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_worker_init, initargs=(config.to_json(),)) as pool:
                for done in pool.map(_worker_frames, [str(out_dir)] * len(batches), batches):
                    bar.advance(done)
    finally:
        bar.close()
    suffix = depth_suffix(config)
    frames = [
        {"file_path": f"images/{name}", "depth_file_path": f"depths/{Path(name).with_suffix(suffix)}", "transform_matrix": pose.tolist()}
        for name, pose in zip(names, poses)
    ]
    transforms = {
        "camera_model": "OPENCV",
        **town_intrinsics(config),
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "frames": frames,
    }
    (out_dir / "scene.json").write_text(json.dumps(_scene_description(town, names), indent=1))
    path = out_dir / "transforms.json"
    path.write_text(json.dumps(transforms, indent=2))
    return path


def load_town(scene: Path) -> Town:
    """The :class:`Town` of a scene written by :func:`write_town` (rebuilt from its scene.json
    options; the geometry is checked against the boxes recorded there)."""
    scene = Path(scene)
    path = scene if scene.suffix == ".json" else scene / "scene.json"
    if path.name == "transforms.json":
        path = path.parent / "scene.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: not a town scene written by write_town.")
    content = json.loads(path.read_text())
    if content.get("generator") != GENERATOR_ID:
        raise ValueError(f"{path} was not written by the town generator (its generator is not {GENERATOR_ID!r}).")
    if content.get("version") not in READABLE_VERSIONS:
        raise ValueError(f"{path} was written by town generator version {content.get('version')}; this one (version {GENERATOR_VERSION}) reads versions {list(READABLE_VERSIONS)}.")
    town = build_town(TownConfig.from_json(content["config"]))
    recorded = np.array([[*box["lo"], *box["hi"]] for box in content["boxes"]])
    if recorded.shape != (town.num_buildings, 6) or not np.array_equal(recorded, np.concatenate([town.lo, town.hi], axis=1)):
        raise ValueError(f"{path}: the recorded boxes differ from the ones its options generate (edited file or other numpy version?).")
    return town


def iter_frames(scene: Path) -> Iterator[Tuple[str, np.ndarray]]:
    """(file_path, [4, 4] camera-to-world) of every frame of a written scene's transforms.json."""
    content = json.loads((Path(scene) / "transforms.json").read_text())
    for frame in content["frames"]:
        yield frame["file_path"], np.array(frame["transform_matrix"], dtype=np.float64)
