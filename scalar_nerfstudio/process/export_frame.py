"""Map points and meshes between a run's model frame and the capture's frame.

nerfstudio's dataparser moves a scene's poses into a normalised "model" frame,
``p_model = scale * (transform @ [p_capture; 1])`` (``transform`` [3, 4]: rotation and translation),
and saves ``transform`` and ``scale`` in the run folder's ``dataparser_transforms.json``. Whatever
``ns-export`` writes (tsdf and poisson meshes; point clouds without ``--save-world-frame``) is in the
model frame; this module maps such a .ply or .obj back to the frame of the scene's
transforms.json (for a scene of scalar-nerf-process-data: the capture's frame, metres ENU with GPS).
Normals turn with the points and stay unit length. numpy and plyfile only.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import NamedTuple

import numpy as np
from plyfile import PlyData, PlyParseError  # plyfile comes with viser, a dependency of the project

from scalar_nerfstudio.atomic_io import atomic_write_bytes, atomic_write_text
from scalar_nerfstudio.process.errors import ProcessDataError

TRANSFORMS_NAME = "dataparser_transforms.json"


class DataparserTransform(NamedTuple):
    """``p_model = scale * (rotation @ p + translation)``."""

    transform: np.ndarray
    """[3, 4] rotation | translation."""
    scale: float

    @property
    def rotation(self) -> np.ndarray:
        return self.transform[:, :3]

    def to_model(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] capture-frame points -> [N, 3] model-frame points."""
        return self.scale * (np.asarray(points, dtype=np.float64) @ self.rotation.T + self.transform[:, 3])

    def to_capture(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] model-frame points -> [N, 3] capture-frame points (the inverse of :meth:`to_model`)."""
        return np.linalg.solve(self.rotation, (np.asarray(points, dtype=np.float64) / self.scale - self.transform[:, 3]).T).T

    def normals_to_capture(self, normals: np.ndarray) -> np.ndarray:
        """[N, 3] model-frame normals -> [N, 3] unit normals in the capture frame (zero stays zero)."""
        turned = np.asarray(normals, dtype=np.float64) @ self.rotation  # normals take the inverse transpose of rotation^-1
        length = np.linalg.norm(turned, axis=1, keepdims=True)
        return np.where(length > 0, turned / np.where(length > 0, length, 1.0), 0.0)


def find_transforms(load_config: Path) -> Path:
    """The run's ``dataparser_transforms.json`` beside ``load_config`` (a run's config.yml, or the run folder)."""
    load_config = Path(load_config)
    run = load_config if load_config.is_dir() else load_config.parent
    path = run / TRANSFORMS_NAME
    if not path.is_file():
        raise ProcessDataError(f"{path}: not found; ns-train writes it into the run folder (beside config.yml) when training starts")
    return path


def read_transform(path: Path) -> DataparserTransform:
    """Read ``dataparser_transforms.json`` (``{"transform": [3, 4], "scale": s}``)."""
    try:
        data = json.loads(Path(path).read_text())
        transform = np.asarray(data["transform"], dtype=np.float64)
        scale = float(data["scale"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise ProcessDataError(f"{path}: not a dataparser_transforms.json ({error})") from None
    if transform.shape != (3, 4) or not np.isfinite(transform).all() or not (np.isfinite(scale) and scale > 0):
        raise ProcessDataError(f"{path}: needs a finite 3x4 \"transform\" and a positive \"scale\"")
    if abs(np.linalg.det(transform[:, :3])) < 1e-9:
        raise ProcessDataError(f"{path}: the transform's 3x3 part is singular")
    return DataparserTransform(transform, scale)


def map_ply(source: Path, output: Path, transform: DataparserTransform) -> int:
    """Write ``source`` (.ply, ascii or binary, any other elements and properties kept) with its
    vertices' x, y, z (and nx, ny, nz when present) in the capture frame. Returns the vertex count."""
    try:
        ply = PlyData.read(str(source))
        vertex = ply["vertex"]
    except (OSError, ValueError, KeyError, IndexError, PlyParseError) as error:
        raise ProcessDataError(f"{source}: not a readable .ply with vertices ({error})") from None
    names = vertex.data.dtype.names
    if not all(axis in names for axis in "xyz"):
        raise ProcessDataError(f"{source}: its vertices have no x, y, z")
    data = vertex.data
    points = np.stack([data["x"], data["y"], data["z"]], axis=1).astype(np.float64)
    mapped = transform.to_capture(points)
    for k, axis in enumerate("xyz"):
        data[axis] = mapped[:, k].astype(data[axis].dtype)
    if all(n in names for n in ("nx", "ny", "nz")):
        normals = transform.normals_to_capture(np.stack([data["nx"], data["ny"], data["nz"]], axis=1))
        for k, axis in enumerate(("nx", "ny", "nz")):
            data[axis] = normals[:, k].astype(data[axis].dtype)
    buffer = io.BytesIO()
    ply.write(buffer)
    atomic_write_bytes(Path(output), buffer.getvalue())
    return len(points)


def map_obj(source: Path, output: Path, transform: DataparserTransform) -> int:
    """Write the Wavefront .obj ``source`` with its ``v`` lines (extra vertex colours kept) and
    ``vn`` lines in the capture frame; every other line unchanged. Returns the vertex count."""
    try:
        lines = Path(source).read_text().splitlines(keepends=True)
    except (OSError, UnicodeDecodeError) as error:
        raise ProcessDataError(f"{source}: not a readable .obj ({error})") from None
    kinds = {"v": [], "vn": []}
    for index, line in enumerate(lines):
        parts = line.split()
        if parts and parts[0] in kinds:
            try:
                kinds[parts[0]].append((index, [float(v) for v in parts[1:4]], parts[4:]))
            except ValueError:
                raise ProcessDataError(f"{source}:{index + 1}: bad {parts[0]} line {line.strip()!r}") from None
    for kind, entries in kinds.items():
        if not entries:
            continue
        values = np.array([e[1] for e in entries], dtype=np.float64)
        mapped = transform.to_capture(values) if kind == "v" else transform.normals_to_capture(values)
        for (index, _, rest), row in zip(entries, mapped):
            lines[index] = " ".join([kind, *(f"{v:.9g}" for v in row), *rest]) + "\n"
    atomic_write_text(Path(output), "".join(lines))
    return len(kinds["v"])


def map_file(source: Path, output: Path, transform: DataparserTransform) -> int:
    """:func:`map_ply` or :func:`map_obj` by the file's ending."""
    source, output = Path(source), Path(output)
    if not source.is_file():
        raise ProcessDataError(f"{source}: no such file")
    suffix = source.suffix.lower()
    if output.suffix.lower() != suffix:
        raise ProcessDataError(f"--output {output} must end in {suffix} like the input")
    if suffix == ".ply":
        return map_ply(source, output, transform)
    if suffix == ".obj":
        return map_obj(source, output, transform)
    raise ProcessDataError(f"{source}: only .ply and .obj files are mapped")
