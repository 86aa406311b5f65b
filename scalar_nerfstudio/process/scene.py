"""Write a reconstruction as a nerfstudio scene, all at once.

``SCENE/transforms.json``, ``SCENE/images/`` (the registered photos, hard-linked or copied at full
resolution), ``SCENE/images_2``, ``images_4``, ``images_8`` (downscaled to exactly the size
nerfstudio's dataparser expects: ``floor(w / f) x floor(h / f)``) and ``SCENE/sparse_pc.ply`` (the
sparse points in the poses' frame) are staged in a hidden folder inside SCENE and moved into place
when all are complete, ``transforms.json`` last: a scene folder has a ``transforms.json`` only when
everything it names is there.
"""

from __future__ import annotations

import json
import os
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Optional, Sequence, Tuple

import numpy as np
from PIL import Image

from scalar_nerfstudio.atomic_io import atomic_write_text
from scalar_nerfstudio.process.align import CaptureFrame
from scalar_nerfstudio.process.errors import ProcessDataError

DOWNSCALES = (2, 4, 8)
#: What process-data writes into SCENE (and what --overwrite removes; nothing else is touched).
OWNED = ("transforms.json", "sparse_pc.ply", "images", *(f"images_{f}" for f in DOWNSCALES), "colmap")
_STAGING_PREFIX = ".process-data-staging-"
_JPEG_QUALITY = 95


def check_output(output: Path, photos_folder: Path) -> None:
    """Refuse an output folder process-data would damage; writes nothing.

    Raises:
        ProcessDataError: ``output`` is a file, holds the photos in a folder process-data rewrites,
            or holds files that process-data did not write.
    """
    output, photos_folder = Path(output).absolute(), Path(photos_folder).absolute()
    if output.exists() and not output.is_dir():
        raise ProcessDataError(f"--output {output} is a file, not a folder")
    for name in OWNED:
        if photos_folder == output / name or (output / name) in photos_folder.parents:
            raise ProcessDataError(f"the photos folder {photos_folder} lies in {output / name}, which process-data rewrites; choose another --output")
    if photos_folder == output:
        raise ProcessDataError(f"--output {output} is the photos folder; choose a new folder for the scene")
    if output.is_dir():
        foreign = sorted(p.name for p in output.iterdir() if p.name not in OWNED and not p.name.startswith(_STAGING_PREFIX))
        if foreign:
            shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
            raise ProcessDataError(f"--output {output} holds files process-data did not write ({shown}); choose a new or empty folder")


def remove_outputs(output: Path) -> None:
    """Delete what process-data wrote into ``output`` (for --overwrite); other files stay."""
    for name in (*OWNED, *(p.name for p in Path(output).glob(_STAGING_PREFIX + "*"))):
        path = Path(output) / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()


def downscaled_size(size: Tuple[int, int], factor: int) -> Tuple[int, int]:
    """The size nerfstudio expects of ``images_{factor}``: its camera's float32 rescale, rounded down."""
    scale = np.float32(1.0 / factor)
    return int(np.float32(size[0]) * scale), int(np.float32(size[1]) * scale)


def _save(image: Image.Image, path: Path) -> None:
    suffix = path.suffix.lower()
    if suffix in (".jpg", ".jpeg"):
        image.save(path, quality=_JPEG_QUALITY)
    else:
        image.save(path)


def _link_or_copy(source: Path, target: Path) -> None:
    try:
        os.link(source, target)
    except OSError:
        shutil.copy2(source, target)


def _write_photo(source: Path, staging: Path, factors: Sequence[int]) -> None:
    """Full-size link/copy plus each downscale of one photo (raw pixel orientation, like COLMAP's)."""
    _link_or_copy(source, staging / "images" / source.name)
    if not factors:
        return
    with Image.open(source) as image:
        image.load()
        size = image.size
        current = image
        for factor in sorted(factors):
            current = current.resize(downscaled_size(size, factor), Image.Resampling.LANCZOS)
            _save(current, staging / f"images_{factor}" / source.name)


def write_ply(path: Path, points: np.ndarray, colours: np.ndarray) -> None:
    """Binary little-endian PLY of [P, 3] float32 points and [P, 3] uint8 colours (what nerfstudio's
    ``ply_file_path`` loader and open3d read)."""
    points = np.asarray(points, dtype="<f4").reshape(-1, 3)
    colours = np.asarray(colours, dtype=np.uint8).reshape(-1, 3)
    vertex = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = points.T
    vertex["red"], vertex["green"], vertex["blue"] = colours.T
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    with open(path, "wb") as handle:
        handle.write(header.encode("ascii"))
        handle.write(vertex.tobytes())


def _check_per_photo(names: Sequence[str], camera_to_world_cv: np.ndarray, intrinsics: Sequence[dict],
                     image_ids: Sequence[int]) -> None:
    if not len(names) == len(camera_to_world_cv) == len(intrinsics) == len(image_ids):
        raise ValueError(f"{len(names)} names, {len(camera_to_world_cv)} poses, {len(intrinsics)} intrinsics and "
                         f"{len(image_ids)} image ids: one of each per photo")


def transforms_json(names: Sequence[str], camera_to_world_cv: np.ndarray, *, intrinsics: Sequence[dict],
                    frame: CaptureFrame, image_ids: Sequence[int]) -> dict:
    """nerfstudio's transforms.json (OPENCV camera; OpenGL camera axes, as nerfstudio's COLMAP converter
    writes them) of cameras already in the capture's frame.

    Args:
        names: [N] photo file names.
        camera_to_world_cv: [N, 4, 4] poses, OpenCV camera axes.
        intrinsics: [N] w, h, fl_x, fl_y, cx, cy, k1, k2, p1, p2 of each photo. When all photos share
            one set it is written once, at the top level; else each frame carries its own (nerfstudio
            reads a key per frame when the top level lacks it).
        frame: the capture's frame (recorded as ``capture_frame``).
        image_ids: [N] COLMAP image ids.
    """
    _check_per_photo(names, camera_to_world_cv, intrinsics, image_ids)
    poses = np.array(camera_to_world_cv, dtype=np.float64)
    poses[:, :3, 1:3] *= -1.0  # OpenCV (x right, y down, z forward) -> OpenGL (y up, z backward)
    shared = all(values == intrinsics[0] for values in intrinsics)
    frames = [
        {"file_path": f"images/{name}", "transform_matrix": pose.tolist(), "colmap_im_id": int(image_id),
         **({} if shared else dict(values))}
        for name, pose, image_id, values in zip(names, poses, image_ids, intrinsics)
    ]
    return {
        "camera_model": "OPENCV",
        **(dict(intrinsics[0]) if shared and intrinsics else {}),
        "frames": frames,
        # The poses are in the capture's frame already: nerfstudio must not apply its own
        # COLMAP axis swap (it does when SCENE/colmap/sparse/0 exists and this key is absent), so
        # that "original space" (ns-export --save-world-frame) is the capture's frame.
        "applied_transform": np.eye(4)[:3].tolist(),
        "ply_file_path": "sparse_pc.ply",
        "capture_frame": frame.to_json(),
    }


def write_scene(
    output: Path,
    photos_folder: Path,
    *,
    names: Sequence[str],
    camera_to_world_cv: np.ndarray,
    image_ids: Sequence[int],
    intrinsics: Sequence[dict],
    points: np.ndarray,
    colours: np.ndarray,
    frame: CaptureFrame,
    factors: Sequence[int] = DOWNSCALES,
    workers: int = 2,
    advance: Optional[Callable[[int], None]] = None,
) -> Path:
    """Write the scene of the registered photos ``names`` ([N] poses ``camera_to_world_cv`` [N, 4, 4]
    and [P, 3] points in COLMAP's frame; they are moved to ``frame``'s; [N] ``intrinsics``, one dict
    per photo, see :func:`transforms_json`). Each photo's downscales are of its own size.
    Returns the path of ``transforms.json``."""
    _check_per_photo(names, camera_to_world_cv, intrinsics, image_ids)
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    staging = output / f"{_STAGING_PREFIX}{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    try:
        for folder in ("images", *(f"images_{f}" for f in factors)):
            (staging / folder).mkdir(parents=True)
        sim = frame.scene_from_colmap
        poses = sim.apply_to_poses(camera_to_world_cv)

        def one(name: str) -> None:
            try:
                _write_photo(Path(photos_folder) / name, staging, factors)
            except OSError as error:
                raise ProcessDataError(f"{Path(photos_folder) / name}: cannot be copied or downscaled ({error})") from None
            if advance is not None:
                advance(1)

        with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
            list(pool.map(one, names))
        write_ply(staging / "sparse_pc.ply", sim.apply(points), colours)
        transforms = transforms_json(names, poses, intrinsics=intrinsics, frame=frame, image_ids=image_ids)
        atomic_write_text(staging / "transforms.json", json.dumps(transforms, indent=2) + "\n")
        _publish(staging, output, ["images", *(f"images_{f}" for f in factors), "sparse_pc.ply", "transforms.json"])
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return output / "transforms.json"


def _publish(staging: Path, output: Path, entries: Sequence[str]) -> None:
    """Move staged entries into ``output``, replacing old ones; the old transforms.json goes first
    and the new one comes last, so no transforms.json ever names missing or stale files."""
    (output / "transforms.json").unlink(missing_ok=True)
    for name in entries:
        target = output / name
        if target.is_dir() and not target.is_symlink():
            trash = staging / f".old-{name}"
            target.rename(trash)
        elif target.exists() or target.is_symlink():
            target.unlink()
        (staging / name).rename(target)
