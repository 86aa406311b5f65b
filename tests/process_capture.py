"""The rendered capture with known poses that the ``scalar-nerf-process-data`` tests run on, and helpers.

The capture: the project's courtyard (its geometry, ray-cast by ``scenes.courtyard.render_rays``)
seen by 24 cameras on a ring looking inwards, 320 x 240 JPEGs with EXIF focal length and GPS
positions (exact: the world's metres as east-north-up about a reference point). The courtyard's own
texture is replaced here by a 3-D value noise: the generator's checker flips on the round-off sign of
hit points that lie on its cell edges (the ground z = 0 and box faces at multiples of 0.5 m), a
speckle that differs between views, and SIFT then finds too few consistent features to place the
cameras.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
from pathlib import Path
from typing import Dict, Tuple

import numpy as np
from PIL import ExifTags, Image, TiffImagePlugin

from scalar_nerfstudio.process import geo
from scalar_nerfstudio.scenes.courtyard import look_at, render_rays
from scalar_nerfstudio.scripts import process_data

#: Where the courtyard's world origin lies on Earth (lat, lon in degrees, altitude in m).
GPS_ORIGIN = np.array([46.5197, 6.6323, 372.0])
NUM_VIEWS, WIDTH, HEIGHT = 24, 320, 240
FOCAL_PX = 0.8 * WIDTH


def _hash(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, salt: int) -> np.ndarray:
    h = (ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791) ^ (salt * 2654435761)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF) / 65535.0


def _value_noise(points: np.ndarray, cell: float, salt: int) -> np.ndarray:
    """[P, 3] world points -> [P] smooth 3-D value noise in [0, 1] with cells of ``cell`` metres."""
    scaled = points / cell
    corner = np.floor(scaled).astype(np.int64)
    f = scaled - corner
    f = f * f * (3.0 - 2.0 * f)
    out = np.zeros(len(points))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                weight = (f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1]) * (f[:, 2] if dz else 1 - f[:, 2])
                out += weight * _hash(corner[:, 0] + dx, corner[:, 1] + dy, corner[:, 2] + dz, salt)
    return out


def _dms(value: float) -> tuple:
    value = abs(value)
    degrees = int(value)
    minutes = int((value - degrees) * 60.0)
    seconds = (value - degrees - minutes / 60.0) * 3600.0
    rational = TiffImagePlugin.IFDRational
    return rational(degrees, 1), rational(minutes, 1), rational(int(round(seconds * 1e5)), 100000)


def capture_exif(gps: np.ndarray = None, *, model: str = "courtyard", focal_px: float = FOCAL_PX,
          size: Tuple[int, int] = (WIDTH, HEIGHT)) -> Image.Exif:
    """EXIF of a test photo: make/model, 35-mm equivalent focal length of ``focal_px`` at ``size``
    (diagonal, as COLMAP reads it) and, when given, GPS [3] lat, lon, alt."""
    exif = Image.Exif()
    exif[ExifTags.Base.Make], exif[ExifTags.Base.Model] = "scalar-nerf", model
    focal_35mm = int(round(focal_px * 43.27 / math.hypot(*size)))
    exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = focal_35mm
    if gps is not None:
        tags = ExifTags.GPS
        exif.get_ifd(ExifTags.IFD.GPSInfo).update({
            tags.GPSVersionID: b"\x02\x03\x00\x00",
            tags.GPSLatitudeRef: "N" if gps[0] >= 0 else "S", tags.GPSLatitude: _dms(gps[0]),
            tags.GPSLongitudeRef: "E" if gps[1] >= 0 else "W", tags.GPSLongitude: _dms(gps[1]),
            tags.GPSAltitudeRef: b"\x00" if gps[2] >= 0 else b"\x01", tags.GPSAltitude: TiffImagePlugin.IFDRational(int(round(abs(gps[2]) * 1000)), 1000),
        })
    return exif


def render_capture(folder: Path, num_views: int = NUM_VIEWS, gps: bool = True) -> Dict[str, np.ndarray]:
    """Write the ring capture's JPEGs into ``folder``; returns name -> [4, 4] true camera-to-world
    (OpenGL axes, world metres: x east, y north, z up)."""
    folder.mkdir(parents=True, exist_ok=True)
    u, v = np.meshgrid(np.arange(WIDTH) + 0.5, np.arange(HEIGHT) + 0.5)
    camera_dirs = np.stack([(u - WIDTH / 2) / FOCAL_PX, -(v - HEIGHT / 2) / FOCAL_PX, -np.ones_like(u)], axis=-1).reshape(-1, 3)
    camera_dirs /= np.linalg.norm(camera_dirs, axis=1, keepdims=True)
    truth = {}
    for i, angle in enumerate(np.linspace(0.0, 2.0 * np.pi, num_views, endpoint=False)):
        position = np.array([4.5 * np.cos(angle), 4.5 * np.sin(angle), 1.8 + 0.4 * np.sin(3 * angle)])
        c2w = look_at(position, np.array([0.3 * np.cos(5 * angle), 0.3 * np.sin(5 * angle), 0.6]))
        directions = camera_dirs @ c2w[:3, :3].T
        origins = np.broadcast_to(c2w[:3, 3], directions.shape)
        rgb, depth = render_rays(origins, directions)
        hit = np.isfinite(depth)
        points = origins[hit] + directions[hit] * depth[hit, None]
        grey = 0.25 + 0.35 * _value_noise(points, 0.6, 1) + 0.25 * _value_noise(points, 0.15, 2) + 0.15 * _value_noise(points, 0.05, 3)
        rgb[hit] = grey[:, None] * np.array([1.0, 0.95, 0.85])
        name = f"view_{i:03d}.jpg"
        image = Image.fromarray((rgb.reshape(HEIGHT, WIDTH, 3) * 255.0 + 0.5).astype(np.uint8))
        position_gps = geo.enu_to_wgs84(position[None], GPS_ORIGIN)[0] if gps else None
        image.save(folder / name, quality=95, exif=capture_exif(position_gps))
        truth[name] = c2w
    return truth


def run_process_data(*args: str) -> Tuple[int, str, str]:
    """scalar-nerf-process-data in this process: (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = process_data.main([*args, "--threads", "2"])
    return code, out.getvalue(), err.getvalue()


def scene_poses(scene: Path) -> Dict[str, np.ndarray]:
    transforms = json.loads((scene / "transforms.json").read_text())
    return {Path(f["file_path"]).name: np.array(f["transform_matrix"]) for f in transforms["frames"]}


def pose_errors(recovered: Dict[str, np.ndarray], truth: Dict[str, np.ndarray]) -> Tuple[geo.Similarity, np.ndarray, np.ndarray, float]:
    """Fit recovered -> true camera centres; (similarity, [N] rotation errors in degrees, [N] position
    errors in metres, the scene's size: the largest distance between two true camera centres)."""
    names = sorted(recovered)
    rec = np.stack([recovered[n] for n in names])
    true = np.stack([truth[n] for n in names])
    sim = geo.umeyama(rec[:, :3, 3], true[:, :3, 3])
    aligned = sim.apply_to_poses(rec)
    rotation_error = geo.rotation_angle_deg(aligned[:, :3, :3], true[:, :3, :3])
    position_error = np.linalg.norm(aligned[:, :3, 3] - true[:, :3, 3], axis=1)
    size = float(max(np.linalg.norm(a - b) for a in true[:, :3, 3] for b in true[:, :3, 3]))
    return sim, rotation_error, position_error, size
