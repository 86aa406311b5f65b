"""The town as photos with GPS (scalar_nerfstudio/scenes/town/photos.py, ``scalar-nerf-make-scene --photos``).

What a user of process-data relies on: each photo is the frame's image, and its EXIF puts the camera where
the scene's transforms.json has it, to the centimetre, with the frame's field of view.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from tiny_town import write_tiny_town

from scalar_nerfstudio.scenes.town import iter_frames
from scalar_nerfstudio.scenes.town.photos import TOWN_ORIGIN, gps_of_town_point, write_photos


def _exif_position(photo: Path) -> tuple[float, float, float, int]:
    """(latitude, longitude, altitude, focal length in 35 mm) read back from ``photo``'s EXIF."""
    with Image.open(photo) as image:
        exif = image.getexif()
    gps, camera = exif.get_ifd(0x8825), exif.get_ifd(0x8769)

    def degrees(values, ref: str, negative: str) -> float:
        value = float(values[0]) + float(values[1]) / 60.0 + float(values[2]) / 3600.0
        return -value if ref == negative else value

    altitude = float(gps[6]) * (-1.0 if gps.get(5) in (1, b"\x01") else 1.0)
    return degrees(gps[2], gps[1], "S"), degrees(gps[4], gps[3], "W"), altitude, int(camera[0xA405])


def _metres_from_origin(latitude: float, longitude: float) -> tuple[float, float]:
    """East and north metres of a point from TOWN_ORIGIN on a sphere of the mean radius (an independent check)."""
    radius = 6371008.8
    lat0, lon0, _ = TOWN_ORIGIN
    return (math.radians(longitude - lon0) * radius * math.cos(math.radians(lat0)), math.radians(latitude - lat0) * radius)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_town(tmp_path_factory.mktemp("town") / "scene")


def test_each_photo_is_its_frame_with_the_camera_centre_and_field_of_view_in_its_exif(scene: Path, tmp_path: Path) -> None:
    photos = tmp_path / "photos"
    frames = list(iter_frames(scene))
    assert write_photos(scene, photos) == len(frames)
    content = json.loads((scene / "transforms.json").read_text())
    fov_deg = math.degrees(2 * math.atan(content["w"] / (2 * content["fl_x"])))
    for file_path, camera_to_world in frames:
        photo = photos / (Path(file_path).stem + ".jpg")
        with Image.open(photo) as image:
            assert image.format == "JPEG" and image.size == (content["w"], content["h"])
            pixels = np.asarray(image.convert("RGB"), dtype=np.float64)
        with Image.open(scene / file_path) as frame:
            assert np.abs(pixels - np.asarray(frame.convert("RGB"), dtype=np.float64)).mean() < 4.0  # JPEG at quality 95
        latitude, longitude, altitude, focal_35mm = _exif_position(photo)
        east, north, up = camera_to_world[:3, 3]
        got_east, got_north = _metres_from_origin(latitude, longitude)
        # a sphere against the ellipsoid differs by < 0.4 % over these few metres; EXIF seconds are to 1/10000 (3 mm)
        assert got_east == pytest.approx(east, abs=0.05 + 0.004 * abs(east)) and got_north == pytest.approx(north, abs=0.05 + 0.004 * abs(north))
        assert altitude == pytest.approx(TOWN_ORIGIN[2] + up, abs=1e-3)
        assert math.degrees(2 * math.atan(36.0 / (2 * focal_35mm))) == pytest.approx(fov_deg, abs=1.0)


def test_points_south_and_west_of_the_equator_and_meridian_keep_their_signs() -> None:
    point = gps_of_town_point(np.array([-1000.0, -1000.0, -5.0]), origin=(0.001, 0.001, 0.0))
    assert point.latitude < 0 and point.longitude < 0 and point.altitude == -5.0
    assert abs(point.latitude + 0.008) < 1e-3 and abs(point.longitude + 0.008) < 1e-3  # 1 km is about 0.009 degrees


def test_make_scene_writes_the_photos_beside_the_scene_and_refuses_a_non_empty_photos_folder(tmp_path: Path) -> None:
    def make(*extra: str) -> subprocess.CompletedProcess:
        command = [sys.executable, "-m", "scalar_nerfstudio.scripts.make_scene", "--output", str(tmp_path / "town"), "--num-images", "3",
                   "--width", "24", "--height", "16", "--blocks-x", "1", "--blocks-y", "1", *extra]
        return subprocess.run(command, capture_output=True, text=True, timeout=300, check=False)

    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.jpg").write_bytes(b"user data")
    refused = make("--photos", str(tmp_path / "full"))
    assert refused.returncode == 1 and "--photos" in refused.stderr and "not empty" in refused.stderr
    assert not (tmp_path / "town").exists()  # refused before anything was written
    result = make("--photos", str(tmp_path / "photos"))
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in (tmp_path / "photos").iterdir()) == ["frame_00000.jpg", "frame_00001.jpg", "frame_00002.jpg"]
    assert "JPEG photos with GPS" in result.stdout
