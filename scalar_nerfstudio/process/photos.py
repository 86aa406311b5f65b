"""The photos of a capture: which files, whether they decode, their size, camera and EXIF GPS.

Everything here only reads the photos; :func:`inspect_photos` checks a folder before
process-data writes anything and raises :class:`ProcessDataError` naming the files at fault.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
from PIL import ExifTags, Image, ImageFile

from scalar_nerfstudio.process.errors import ProcessDataError

#: File name endings read as photos (case-insensitive), the formats COLMAP and nerfstudio both read.
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
#: Fewest photos structure-from-motion is tried on.
MIN_PHOTOS = 3


@dataclass(frozen=True)
class Photo:
    """What process-data needs of one photo."""

    name: str
    """File name inside the photos folder."""
    size: Tuple[int, int]
    """(width, height) in pixels, as stored (EXIF orientation is not applied, as COLMAP and nerfstudio read it)."""
    camera: str
    """EXIF make and model ("" when absent)."""
    focal_mm: Optional[float]
    """EXIF focal length in mm (None when absent)."""
    gps: Optional[Tuple[float, float, float]]
    """EXIF GPS latitude, longitude (degrees, north and east positive) and altitude (m; NaN when the
    photo has a position but no altitude), or None."""


@dataclass(frozen=True)
class PhotoSet:
    """The checked photos of a capture folder, sorted by name."""

    folder: Path
    photos: Tuple[Photo, ...]

    @property
    def names(self) -> List[str]:
        return [photo.name for photo in self.photos]

    @property
    def size(self) -> Tuple[int, int]:
        """(width, height) shared by all photos."""
        return self.photos[0].size

    @property
    def all_have_gps(self) -> bool:
        return all(photo.gps is not None for photo in self.photos)

    def without_gps(self) -> List[str]:
        return [photo.name for photo in self.photos if photo.gps is None]

    def gps_by_name(self) -> Dict[str, np.ndarray]:
        """Name -> [3] lat, lon, alt of the photos with GPS; a missing altitude reads 0 when no
        photo has one (positions on one level), else the photos' median altitude."""
        altitudes = [photo.gps[2] for photo in self.photos if photo.gps is not None and math.isfinite(photo.gps[2])]
        fill = float(np.median(altitudes)) if altitudes else 0.0
        out = {}
        for photo in self.photos:
            if photo.gps is not None:
                lat, lon, alt = photo.gps
                out[photo.name] = np.array([lat, lon, alt if math.isfinite(alt) else fill])
        return out


def list_photos(folder: Path) -> List[str]:
    """Names of the photo files directly inside ``folder`` (sorted; sub-folders are not read)."""
    return sorted(p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))


def _rational(value) -> float:
    return float(value[0]) / float(value[1]) if isinstance(value, tuple) else float(value)


def _degrees(dms, ref: str, negative: str) -> float:
    degrees, minutes, seconds = (_rational(v) for v in dms)
    value = degrees + minutes / 60.0 + seconds / 3600.0
    return -value if str(ref).strip().upper().startswith(negative) else value


def _gps(exif: Image.Exif) -> Optional[Tuple[float, float, float]]:
    """EXIF GPS IFD -> (lat, lon, alt) or None when it has no complete position."""
    try:
        gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
    except (KeyError, ValueError, TypeError, OSError):
        return None
    tags = ExifTags.GPS
    if not gps or tags.GPSLatitude not in gps or tags.GPSLongitude not in gps:
        return None
    try:
        lat = _degrees(gps[tags.GPSLatitude], gps.get(tags.GPSLatitudeRef, "N"), "S")
        lon = _degrees(gps[tags.GPSLongitude], gps.get(tags.GPSLongitudeRef, "E"), "W")
        alt = math.nan
        if tags.GPSAltitude in gps:
            alt = _rational(gps[tags.GPSAltitude])
            ref = gps.get(tags.GPSAltitudeRef, b"\x00")
            if (ref[0] if isinstance(ref, (bytes, bytearray)) and ref else ref) == 1:
                alt = -alt  # below sea level
    except (TypeError, ValueError, ZeroDivisionError, IndexError):
        return None
    if not (math.isfinite(lat) and math.isfinite(lon) and -90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
        return None
    if lat == 0.0 and lon == 0.0:  # a camera's placeholder for "no fix"
        return None
    return lat, lon, alt


def read_photo(path: Path) -> Photo:
    """Decode ``path`` completely (a truncated or corrupt file fails here) and read its EXIF.

    Raises:
        ProcessDataError: naming the file and what is wrong with it.
    """
    ImageFile.LOAD_TRUNCATED_IMAGES = False  # nerfstudio or a caller may have switched it on
    try:
        with Image.open(path) as image:
            size = image.size
            exif = image.getexif()
            if image.format == "JPEG":
                image.draft("RGB", (max(1, size[0] // 8), max(1, size[1] // 8)))  # still reads every byte
            image.load()
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as error:
        raise ProcessDataError(f"{path}: cannot be decoded ({error}); remove or replace the file") from None
    make = str(exif.get(ExifTags.Base.Make, "") or "").strip("\x00 ")
    model = str(exif.get(ExifTags.Base.Model, "") or "").strip("\x00 ")
    camera = model if model.startswith(make) else f"{make} {model}".strip()
    focal = None
    try:
        value = exif.get_ifd(ExifTags.IFD.Exif).get(ExifTags.Base.FocalLength)
        focal = _rational(value) if value is not None else None
    except (KeyError, ValueError, TypeError, ZeroDivisionError, OSError):
        focal = None
    if focal is not None and not (math.isfinite(focal) and focal > 0):
        focal = None
    return Photo(name=path.name, size=(int(size[0]), int(size[1])), camera=camera, focal_mm=focal, gps=_gps(exif))


def _examples(names: Sequence[str], limit: int = 3) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f" and {len(names) - limit} more" if len(names) > limit else "")


def _check_one_camera(folder: Path, photos: Sequence[Photo]) -> None:
    """Refuse photos of different sizes or cameras: process-data fits one camera to all of them."""
    groups: Dict[Tuple, List[str]] = {}
    for photo in photos:
        focal = None if photo.focal_mm is None else round(photo.focal_mm, 2)
        groups.setdefault((photo.size, photo.camera, focal), []).append(photo.name)
    if len(groups) == 1:
        return
    lines = []
    for (size, camera, focal), names in sorted(groups.items(), key=lambda item: -len(item[1])):
        what = f"{size[0]}x{size[1]} px"
        if camera:
            what += f", {camera}"
        if focal is not None:
            what += f", {focal:g} mm"
        lines.append(f"  {what}: {len(names)} photo(s): {_examples(names)}")
    raise ProcessDataError(
        f"{folder}: the photos come from {len(groups)} different cameras or image sizes, and process-data fits one "
        "camera (one set of intrinsics) to all photos:\n" + "\n".join(lines) + "\n"
        "Process each camera's photos on their own (one folder each), or leave out the odd ones."
    )


def inspect_photos(folder: Path, progress: Optional[Callable[[int], None]] = None, workers: int = 2) -> PhotoSet:
    """Check a capture folder before anything is written.

    Args:
        folder: the photos (read only).
        progress: called with 1 after each photo is decoded.
        workers: photos decoded at once.

    Raises:
        ProcessDataError: the folder is missing or has fewer than :data:`MIN_PHOTOS` photos, a photo
            does not decode (all such files are named), or the photos differ in size or camera.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ProcessDataError(f"{folder}: no such folder of photos")
    names = list_photos(folder)
    if not names:
        raise ProcessDataError(f"{folder}: no photos in this folder (looked for {', '.join(IMAGE_SUFFIXES)} files; sub-folders are not read)")
    if len(names) < MIN_PHOTOS:
        raise ProcessDataError(f"{folder}: {len(names)} photo(s) ({', '.join(names)}); structure-from-motion needs at least {MIN_PHOTOS} overlapping photos")

    def read(name: str):
        try:
            return read_photo(folder / name)
        except ProcessDataError as error:
            return error
        finally:
            if progress is not None:
                progress(1)

    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        results = list(pool.map(read, names))
    errors = [str(r) for r in results if isinstance(r, ProcessDataError)]
    if errors:
        raise ProcessDataError(f"{len(errors)} of {len(names)} photo(s) cannot be decoded:\n" + "\n".join(f"  {e}" for e in errors))
    photos = tuple(r for r in results if isinstance(r, Photo))
    _check_one_camera(folder, photos)
    return PhotoSet(folder=folder, photos=photos)
