"""A written town scene as a camera's photos: JPEGs (quality 95, no chroma subsampling) that carry their camera's GPS position and focal length.

``scalar-nerf-make-scene --photos DIR`` writes ``DIR/frame_XXXXX.jpg``, one per frame of the scene, so that
``scalar-nerf-process-data --images DIR`` can be tried on a capture whose poses are known (the scene's
transforms.json). The EXIF of each photo holds what a drone's or a phone's would:

- GPS latitude, longitude and altitude of the camera centre: the town's metres (x east, y north, z up from
  the ground) placed at :data:`TOWN_ORIGIN` on the WGS84 ellipsoid by a local tangent-plane approximation
  (under 1 mm of error per km from the origin, far below a consumer GPS's metres);
- the focal length in 35 mm film terms (the horizontal field of view on a 36 mm wide frame), the camera's
  make and model, the pixel size.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Tuple

import numpy as np
from PIL import Image

from scalar_nerfstudio.scenes.town.scene_folder import iter_frames

__all__ = ["TOWN_ORIGIN", "GeoPoint", "gps_of_town_point", "write_photos"]

#: Where the town's origin (x = y = 0 on the ground) is placed: latitude and longitude in degrees, height
#: above the ellipsoid in metres. Any place works; this one is an open field.
TOWN_ORIGIN: Tuple[float, float, float] = (47.3769, 8.5417, 400.0)

_WGS84_A = 6378137.0  # semi-major axis (m)
_WGS84_E2 = 6.69437999014e-3  # first eccentricity squared
_EXIF_IFD, _GPS_IFD = 0x8769, 0x8825


@dataclass(frozen=True)
class GeoPoint:
    """A position on the globe: degrees north and east, metres above the ellipsoid."""

    latitude: float
    longitude: float
    altitude: float


def gps_of_town_point(east_north_up: np.ndarray, origin: Tuple[float, float, float] = TOWN_ORIGIN) -> GeoPoint:
    """The town point ``[3]`` (metres east, north and up of the town's origin) on the globe, by the local
    tangent plane at ``origin``: the meridian and prime-vertical radii of curvature there scale metres to
    degrees."""
    lat0, lon0, alt0 = origin
    east, north, up = (float(v) for v in np.asarray(east_north_up, dtype=np.float64).reshape(3))
    sin_lat = math.sin(math.radians(lat0))
    w = math.sqrt(1.0 - _WGS84_E2 * sin_lat**2)
    meridian = _WGS84_A * (1.0 - _WGS84_E2) / w**3  # m per radian of latitude
    prime_vertical = _WGS84_A / w  # times cos(lat): m per radian of longitude
    latitude = lat0 + math.degrees(north / meridian)
    longitude = lon0 + math.degrees(east / (prime_vertical * math.cos(math.radians(lat0))))
    return GeoPoint(latitude, longitude, alt0 + up)


def _degrees_minutes_seconds(value: float) -> Tuple[Fraction, Fraction, Fraction]:
    """|value| degrees as EXIF's three rationals (seconds to 1/10000)."""
    value = abs(value)
    degrees = int(value)
    minutes = int((value - degrees) * 60.0)
    seconds = round(((value - degrees) * 60.0 - minutes) * 60.0 * 10000)
    return Fraction(degrees), Fraction(minutes), Fraction(seconds, 10000)


def _exif(point: GeoPoint, focal_35mm: float, width: int, height: int) -> Image.Exif:
    exif = Image.Exif()
    exif[0x010F] = "scalar-nerfstudio"  # Make
    exif[0x0110] = "town generator"  # Model
    camera = exif.get_ifd(_EXIF_IFD)
    camera[0xA405] = max(1, round(focal_35mm))  # FocalLengthIn35mmFilm
    camera[0xA002], camera[0xA003] = width, height  # PixelXDimension, PixelYDimension
    gps = exif.get_ifd(_GPS_IFD)
    gps[0x0000] = b"\x02\x03\x00\x00"  # GPSVersionID
    gps[0x0001] = "N" if point.latitude >= 0 else "S"
    gps[0x0002] = _degrees_minutes_seconds(point.latitude)
    gps[0x0003] = "E" if point.longitude >= 0 else "W"
    gps[0x0004] = _degrees_minutes_seconds(point.longitude)
    gps[0x0005] = b"\x00" if point.altitude >= 0 else b"\x01"  # above / below the ellipsoid
    gps[0x0006] = Fraction(round(abs(point.altitude) * 1000), 1000)
    return exif


def write_photos(scene: Path, photos: Path, *, quality: int = 95, origin: Tuple[float, float, float] = TOWN_ORIGIN) -> int:
    """Write every frame of the town ``scene`` (a folder :func:`~.scene_folder.write_town` wrote) to ``photos``
    as ``<frame>.jpg`` with its GPS position and focal length in its EXIF (see the module docstring).
    Returns the number of photos written."""
    scene, photos = Path(scene), Path(photos)
    content = json.loads((scene / "transforms.json").read_text())
    width, height = int(content["w"]), int(content["h"])
    focal_35mm = 36.0 * float(content["fl_x"]) / width  # the horizontal field of view on a 36 mm frame
    photos.mkdir(parents=True, exist_ok=True)
    count = 0
    for file_path, camera_to_world in iter_frames(scene):
        point = gps_of_town_point(camera_to_world[:3, 3], origin)
        with Image.open(scene / file_path) as image:
            rgb = image.convert("RGB")
        rgb.save(photos / (Path(file_path).stem + ".jpg"), quality=quality, subsampling=0, exif=_exif(point, focal_35mm, width, height))
        count += 1
    return count
