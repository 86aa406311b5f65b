"""``scalar-nerf-process-data`` on photos of two cameras, among them two photos that cannot be used.

The capture is ``process_capture.render_capture``'s 24 views of the courtyard; a third of them
become a second camera (:data:`TELE_VIEWS`), and a truncated and a random-noise photo join them.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Dict, Tuple

import numpy as np
import pytest
from PIL import Image
from prerequisites import has_module, need, requires_pycolmap
from process_capture import (
    FOCAL_PX,
    GPS_ORIGIN,
    HEIGHT,
    NUM_VIEWS,
    WIDTH,
    capture_exif,
    pose_errors,
    render_capture,
    run_process_data,
    scene_poses,
)

from scalar_nerfstudio.process import geo

needs_pycolmap = requires_pycolmap


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Tuple[Path, Dict[str, np.ndarray]]:
    folder = tmp_path_factory.mktemp("capture") / "photos"
    return folder, render_capture(folder)


#: The second camera of the two-camera capture: every third view (from view 1) cropped to its centre
#: 240 x 180 and enlarged 1.25x, so a 300 x 225 photo with focal 1.25 x 256 = 320 px, principal point
#: at its centre (a narrower lens: 50 degrees across against 64).
TELE_VIEWS = range(1, NUM_VIEWS, 3)
TELE_SIZE, TELE_FOCAL_PX = (300, 225), 1.25 * FOCAL_PX
_TELE_CROP = (40, 30, 280, 210)


@pytest.fixture(scope="module")
def two_cameras(capture, tmp_path_factory) -> Tuple[Path, Dict[str, np.ndarray]]:
    """The capture's photos, a third of them as the second camera (:data:`TELE_VIEWS`; EXIF model
    "tele", its own size and focal length, GPS kept), plus two photos that cannot be used:
    ``broken.jpg`` (a truncated copy of a view) and ``noise.jpg`` (random pixels: nothing to match).
    Returns (folder, name -> [4, 4] true camera-to-world of the 24 views)."""
    folder = tmp_path_factory.mktemp("two-cameras") / "photos"
    folder.mkdir()
    for i, name in enumerate(sorted(capture[1])):
        gps = geo.enu_to_wgs84(capture[1][name][None, :3, 3], GPS_ORIGIN)[0]
        if i not in TELE_VIEWS:
            shutil.copy(capture[0] / name, folder / name)
            continue
        with Image.open(capture[0] / name) as image:
            tele = image.crop(_TELE_CROP).resize(TELE_SIZE, Image.Resampling.LANCZOS)
        exif = capture_exif(gps, model="tele", focal_px=TELE_FOCAL_PX, size=TELE_SIZE)
        tele.save(folder / name, quality=95, exif=exif)
    data = (capture[0] / "view_000.jpg").read_bytes()
    (folder / "broken.jpg").write_bytes(data[: len(data) // 2])
    noise = np.random.default_rng(0).integers(0, 255, (HEIGHT, WIDTH, 3), dtype=np.uint8)
    centre_gps = geo.enu_to_wgs84(np.array([[0.0, 0.0, 2.0]]), GPS_ORIGIN)[0]
    Image.fromarray(noise).save(folder / "noise.jpg", quality=95, exif=capture_exif(centre_gps))
    return folder, capture[1]


@pytest.fixture(scope="module")
def two_cameras_processed(two_cameras, tmp_path_factory) -> Tuple[Path, str, str]:
    """(scene folder, stdout, stderr) of process-data on :func:`two_cameras`."""
    need("pycolmap", has_module("pycolmap"))
    scene = tmp_path_factory.mktemp("two-cameras-processed") / "scene"
    code, out, err = run_process_data("--images", str(two_cameras[0]), "--output", str(scene))
    assert code == 0, out + err
    return scene, out, err


@needs_pycolmap
def test_two_cameras_get_their_own_intrinsics_and_every_pose(two_cameras_processed, two_cameras) -> None:
    """Photos of two cameras (sizes and focal lengths differ): each frame carries its camera's
    intrinsics, its downscales are of its own size, the project's scene check and nerfstudio's
    dataparser read the scene and a training batch is drawn from it; every pose is recovered."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from scalar_nerfstudio.data.datamanager import ScalarDataManagerConfig
    from scalar_nerfstudio.data.validation import scan_scene

    scene, out, _ = two_cameras_processed
    truth = two_cameras[1]
    transforms = json.loads((scene / "transforms.json").read_text())
    assert not {"fl_x", "fl_y", "cx", "cy", "w", "h"} & set(transforms), "per-camera intrinsics belong in the frames"
    tele = {f"view_{i:03d}.jpg" for i in TELE_VIEWS}
    for frame in transforms["frames"]:
        name = Path(frame["file_path"]).name
        (w, h), focal = (TELE_SIZE, TELE_FOCAL_PX) if name in tele else ((WIDTH, HEIGHT), FOCAL_PX)
        assert (frame["w"], frame["h"], frame["cx"], frame["cy"]) == (w, h, w / 2, h / 2), (name, frame)
        # Measured: both focal lengths within 0.3 % of the truth.
        assert abs(frame["fl_x"] - focal) < 0.02 * focal and abs(frame["fl_y"] - focal) < 0.02 * focal, (name, frame)
        for factor in (2, 4, 8):
            with Image.open(scene / f"images_{factor}" / name) as image:
                assert image.size == (w // factor, h // factor), (name, factor)
    assert "2 cameras: 320x240 px, scalar-nerf courtyard: fl_x" in out, out
    assert "300x225 px, scalar-nerf tele: fl_x" in out, out
    assert "(16 photos)" in out and "(8 photos)" in out, out
    _, rotation_error, position_error, size = pose_errors(scene_poses(scene), truth)
    summary = (f"rotation error max {rotation_error.max():.2f} deg, position error max "
               f"{position_error.max() / size:.4f} of the scene")
    # The bounds of test_process_data_recovers_the_known_poses (one camera).
    assert len(scene_poses(scene)) == len(truth), summary
    assert rotation_error.max() < 0.5 and position_error.max() < 0.005 * size, summary
    print(summary)
    assert scan_scene(scene, downscale_factor=2).num_frames == len(truth)
    config = ScalarDataManagerConfig(dataparser=NerfstudioDataParserConfig(data=scene, eval_mode="all"))
    manager = config.setup(device="cpu")
    cameras = manager.train_dataparser_outputs.cameras
    assert sorted({int(w) for w in cameras.width.reshape(-1)}) == [TELE_SIZE[0], WIDTH]
    ray_bundle, batch = manager.next_train(0)
    assert batch["image"].shape[0] == ray_bundle.shape[0] > 0


@needs_pycolmap
def test_photos_that_cannot_be_used_are_named_and_left_out(two_cameras_processed, two_cameras) -> None:
    """A photo that does not decode and one that SfM cannot place are named in the summary and left
    out of the scene; every other photo is in it."""
    scene, out, err = two_cameras_processed
    assert "registered 24 of 26 photos" in out, out
    assert "left out 2 of 26 photos: broken.jpg (cannot be read), noise.jpg (not registered)" in out, out
    assert "left out" in err and "broken.jpg: cannot be decoded" in err, err
    names = {Path(frame["file_path"]).name for frame in json.loads((scene / "transforms.json").read_text())["frames"]}
    assert names == set(two_cameras[1])
    assert sorted(p.name for p in (scene / "images").iterdir()) == sorted(two_cameras[1])
    print(out)
