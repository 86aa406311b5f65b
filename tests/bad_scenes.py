"""The bad scenes of the bad-input tests: a good 6-image courtyard, the ways to break it (each with
a fragment of the message that must name the culprit), and the image conversions a scene may need."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Callable, Dict, Tuple

import numpy as np
from PIL import Image

from scalar_nerfstudio.scenes.courtyard import write_scene


def write_good_scene(folder: Path) -> Path:
    """The good scene every case breaks: 6 courtyard images of 32 x 24."""
    write_scene(folder, num_images=6, width=32, height=24)
    return folder


def write_mixed_scene(folder: Path) -> Path:
    """A 10-image scene with grayscale, RGBA, palette and 16-bit images among the RGB ones."""
    write_scene(folder, num_images=10, width=32, height=24)
    convert_images(folder)
    return folder


def broken_copy(good_scene: Path, tmp_path: Path, breaker: Callable[[Path], None]) -> Path:
    """A copy of ``good_scene`` under ``tmp_path``, broken by ``breaker``."""
    scene = tmp_path / "scene"
    shutil.copytree(good_scene, scene)
    breaker(scene)
    return scene


def read_transforms(scene: Path) -> dict:
    return json.loads((scene / "transforms.json").read_text())


def write_transforms(scene: Path, content: dict) -> None:
    (scene / "transforms.json").write_text(json.dumps(content))


def image_file(scene: Path, index: int) -> Path:
    return scene / read_transforms(scene)["frames"][index]["file_path"]


def _missing_image(scene: Path) -> None:
    image_file(scene, 2).unlink()


def _unreadable_image(scene: Path) -> None:
    image_file(scene, 1).write_bytes(b"not a png at all")


def _truncated_json(scene: Path) -> None:
    text = (scene / "transforms.json").read_text()
    (scene / "transforms.json").write_text(text[: len(text) // 2])


def _nan_pose(scene: Path) -> None:
    content = read_transforms(scene)
    content["frames"][3]["transform_matrix"][0][3] = math.nan
    write_transforms(scene, content)  # json writes the token NaN, which json (and nerfstudio) read back


def _inf_focal(scene: Path) -> None:
    content = read_transforms(scene)
    content["frames"][0]["fl_x"] = math.inf
    write_transforms(scene, content)


def _no_frames(scene: Path) -> None:
    content = read_transforms(scene)
    content["frames"] = []
    write_transforms(scene, content)


def _one_frame(scene: Path) -> None:  # interval eval mode holds it out: nothing left to train on
    content = read_transforms(scene)
    content["frames"] = content["frames"][:1]
    write_transforms(scene, content)


def _empty_folder(scene: Path) -> None:
    shutil.rmtree(scene)
    scene.mkdir()


def _wrong_size(scene: Path) -> None:  # the image is 2x the transforms' w/h
    path = image_file(scene, 4)
    Image.open(path).resize((64, 48)).save(path)


def _mixed_poses(scene: Path) -> None:  # frame 2 written as 3x4, the others 4x4
    content = read_transforms(scene)
    content["frames"][2]["transform_matrix"] = content["frames"][2]["transform_matrix"][:3]
    write_transforms(scene, content)


def _same_position(scene: Path) -> None:  # every camera at one point, looking different ways
    content = read_transforms(scene)
    for frame in content["frames"]:
        for row, value in zip(frame["transform_matrix"][:3], (1.5, -2.0, 0.5)):
            row[3] = value
    write_transforms(scene, content)


def truncated_jpeg(scene: Path) -> None:  # frame 3 as a JPEG, cut in the middle: its header still reads
    content = read_transforms(scene)
    png = scene / content["frames"][3]["file_path"]
    jpeg = png.with_suffix(".jpg")
    Image.open(png).save(jpeg, quality=95)
    png.unlink()
    data = jpeg.read_bytes()
    jpeg.write_bytes(data[: len(data) * 2 // 3])
    content["frames"][3]["file_path"] = str(jpeg.relative_to(scene))
    write_transforms(scene, content)


def _float_image(scene: Path) -> None:  # 32-bit float pixels: no colours to train on
    path = image_file(scene, 5).with_suffix(".tif")
    Image.fromarray(np.zeros((24, 32), dtype=np.float32)).save(path)
    content = read_transforms(scene)
    content["frames"][5]["file_path"] = str(path.relative_to(scene))
    write_transforms(scene, content)


def _no_height(scene: Path) -> None:  # nerfstudio asserts "height not specified in frame"
    content = read_transforms(scene)
    del content["h"]
    write_transforms(scene, content)


def _frame_without_mask(scene: Path) -> None:
    content = read_transforms(scene)
    for frame in content["frames"][1:]:
        frame["mask_path"] = frame["file_path"]
    write_transforms(scene, content)


def _unknown_camera_model(scene: Path) -> None:
    content = read_transforms(scene)
    content["camera_model"] = "PINHOLE_FANCY"
    write_transforms(scene, content)


def _bad_last_row(scene: Path) -> None:
    content = read_transforms(scene)
    content["frames"][1]["transform_matrix"][3] = [0, 0, 0, 0]
    write_transforms(scene, content)


def val_list_missing(scene: Path) -> None:  # nerfstudio: "The dataset's list of filenames for split val is missing."
    content = read_transforms(scene)
    content["train_filenames"] = [frame["file_path"] for frame in content["frames"][:4]]
    write_transforms(scene, content)


#: name -> (what breaks the good scene, a fragment of the message naming the culprit)
CASES: Dict[str, Tuple[Callable[[Path], None], str]] = {
    "missing image": (_missing_image, "does not exist"),
    "unreadable image": (_unreadable_image, "cannot be read as an image"),
    "truncated transforms": (_truncated_json, "is not valid JSON"),
    "nan pose": (_nan_pose, "frame 3"),
    "inf intrinsics": (_inf_focal, "fl_x=inf"),
    "no frames": (_no_frames, "lists no frames"),
    "no training image": (_one_frame, "leaves no training image"),
    "empty folder": (_empty_folder, "is empty"),
    "image size differs from w/h": (_wrong_size, "frame 4 (images/frame_00004.png): the image"),
    "3x4 and 4x4 poses": (_mixed_poses, "frame 2 (images/frame_00002.png) has a 3x4 \"transform_matrix\""),
    "identical camera centres": (_same_position, "all 6 frames put the camera at the same position (1.5, -2, 0.5)"),
    "truncated jpeg": (truncated_jpeg, "frame 3 (images/frame_00003.jpg): the image"),
    "float image": (_float_image, "frame 5 (images/frame_00005.tif): the image"),
    "no height": (_no_height, "has no \"h\""),
    "mask for some frames": (_frame_without_mask, "frame 0 (images/frame_00000.png) has none"),
    "unknown camera model": (_unknown_camera_model, "'PINHOLE_FANCY' is not a camera model nerfstudio knows"),
    "bad last pose row": (_bad_last_row, "frame 1 (images/frame_00001.png) has the last transform_matrix row [0.0, 0.0, 0.0, 0.0]"),
    "val list missing": (val_list_missing, "has train_filenames but no \"val_filenames\" list"),
}


def convert_images(scene: Path) -> None:
    """Frame 1 grayscale, 2 RGBA (left half transparent), 3 palette, 4 16-bit grayscale, 5 grayscale."""
    rgb = np.asarray(Image.open(image_file(scene, 1)))
    Image.open(image_file(scene, 1)).convert("L").save(image_file(scene, 1))
    Image.open(image_file(scene, 5)).convert("L").save(image_file(scene, 5))
    rgba = np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], axis=2)
    rgba[:, : rgb.shape[1] // 2, 3] = 0
    Image.fromarray(rgba, "RGBA").save(image_file(scene, 2))
    Image.open(image_file(scene, 3)).convert("P").save(image_file(scene, 3))
    grey16 = (np.asarray(Image.open(image_file(scene, 4)).convert("L")).astype(np.uint16) * 257)
    Image.fromarray(grey16).save(image_file(scene, 4))
