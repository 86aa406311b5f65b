"""The photos of a capture: which files, whether they decode, their size, camera and EXIF GPS.

Everything here only reads the photos; :func:`inspect_photos` checks a folder before
process-data writes anything. A photo that does not decode is left out (named in
:attr:`PhotoSet.unreadable`); :class:`ProcessDataError` is raised, naming the files at fault, when
too few photos remain. Photos of several cameras or sizes are grouped (:meth:`PhotoSet.camera_groups`):
each group gets its own intrinsics.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, NamedTuple, Optional, Tuple

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

    @property
    def camera_key(self) -> "CameraKey":
        """What one set of intrinsics is fitted to: photos with the same key share a camera."""
        return CameraKey(camera=self.camera, width=self.size[0], height=self.size[1],
                         focal_mm=None if self.focal_mm is None else round(self.focal_mm, 1))


class CameraKey(NamedTuple):
    """One camera of a capture: EXIF make and model, image size and EXIF focal length (a zoom lens at
    another focal length, or the same body at another image size, is another camera)."""

    camera: str
    width: int
    height: int
    focal_mm: Optional[float]

    def describe(self) -> str:
        """E.g. ``3600x2700 px, DJI FC6310, 8.8 mm``."""
        what = f"{self.width}x{self.height} px"
        if self.camera:
            what += f", {self.camera}"
        if self.focal_mm is not None:
            what += f", {self.focal_mm:g} mm"
        return what


@dataclass(frozen=True)
class PhotoSet:
    """The checked photos of a capture folder, sorted by name."""

    folder: Path
    photos: Tuple[Photo, ...]
    """The photos that decode (the ones structure-from-motion is given)."""
    unreadable: Tuple[Tuple[str, str], ...] = ()
    """(file name, why) of the photos left out because they do not decode."""

    @property
    def names(self) -> List[str]:
        return [photo.name for photo in self.photos]

    @property
    def num_in_folder(self) -> int:
        """Photos in the folder, the unreadable ones included."""
        return len(self.photos) + len(self.unreadable)

    def camera_groups(self) -> Dict[CameraKey, List[str]]:
        """Camera -> names of its photos (cameras in the order of their first photo by name)."""
        groups: Dict[CameraKey, List[str]] = {}
        for photo in self.photos:
            groups.setdefault(photo.camera_key, []).append(photo.name)
        return groups

    def camera_of(self) -> Dict[str, CameraKey]:
        """Photo name -> its camera."""
        return {photo.name: photo.camera_key for photo in self.photos}

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


def inspect_photos(folder: Path, progress: Optional[Callable[[int], None]] = None, workers: int = 2) -> PhotoSet:
    """Check a capture folder before anything is written.

    Args:
        folder: the photos (read only).
        progress: called with 1 after each photo is decoded.
        workers: photos decoded at once.

    Returns:
        The photos that decode; those that do not are left out and named in ``unreadable``.

    Raises:
        ProcessDataError: the folder is missing, or fewer than :data:`MIN_PHOTOS` of its photos
            decode (the ones that do not are named).
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
    unreadable = tuple((name, str(r)) for name, r in zip(names, results) if isinstance(r, ProcessDataError))
    photos = tuple(r for r in results if isinstance(r, Photo))
    if len(photos) < MIN_PHOTOS:
        raise ProcessDataError(
            f"{len(unreadable)} of {len(names)} photo(s) cannot be decoded, leaving {len(photos)}; "
            f"structure-from-motion needs at least {MIN_PHOTOS} overlapping photos:\n"
            + "\n".join(f"  {why}" for _, why in unreadable)
        )
    return PhotoSet(folder=folder, photos=photos, unreadable=unreadable)
