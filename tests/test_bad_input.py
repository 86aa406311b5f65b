"""Bad scenes, options and output folders end with one clear paragraph naming the file/frame/option,
a non-zero exit, no traceback, and nothing written into the output folder. Images that can be used
safely (grayscale, RGBA, palette, 16-bit) are converted in memory, with one log line."""

from __future__ import annotations

import copy
import errno
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
import pytest
from PIL import Image

from scalar_nerfstudio.config_checks import OptionError, check_block_plan, check_options, check_output_dir, check_pipeline_options
from scalar_nerfstudio.scenes.courtyard import write_scene
from scalar_nerfstudio.data.validation import SceneError, check_scene, scan_scene, to_rgb_array

from conftest import ns_train_command, run_dirs


@pytest.fixture(scope="module")
def good_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("good")
    write_scene(folder, num_images=6, width=32, height=24)
    return folder


def _transforms(scene: Path) -> dict:
    return json.loads((scene / "transforms.json").read_text())


def _write(scene: Path, content: dict) -> None:
    (scene / "transforms.json").write_text(json.dumps(content))


def _image(scene: Path, index: int) -> Path:
    return scene / _transforms(scene)["frames"][index]["file_path"]


def _missing_image(scene: Path) -> None:
    _image(scene, 2).unlink()


def _unreadable_image(scene: Path) -> None:
    _image(scene, 1).write_bytes(b"not a png at all")


def _truncated_json(scene: Path) -> None:
    text = (scene / "transforms.json").read_text()
    (scene / "transforms.json").write_text(text[: len(text) // 2])


def _nan_pose(scene: Path) -> None:
    content = _transforms(scene)
    content["frames"][3]["transform_matrix"][0][3] = math.nan
    _write(scene, content)  # json writes the token NaN, which json (and nerfstudio) read back


def _inf_focal(scene: Path) -> None:
    content = _transforms(scene)
    content["frames"][0]["fl_x"] = math.inf
    _write(scene, content)


def _no_frames(scene: Path) -> None:
    content = _transforms(scene)
    content["frames"] = []
    _write(scene, content)


def _one_frame(scene: Path) -> None:  # interval eval mode holds it out: nothing left to train on
    content = _transforms(scene)
    content["frames"] = content["frames"][:1]
    _write(scene, content)


def _empty_folder(scene: Path) -> None:
    shutil.rmtree(scene)
    scene.mkdir()


def _wrong_size(scene: Path) -> None:  # the image is 2x the transforms' w/h
    path = _image(scene, 4)
    Image.open(path).resize((64, 48)).save(path)


def _mixed_poses(scene: Path) -> None:  # frame 2 written as 3x4, the others 4x4
    content = _transforms(scene)
    content["frames"][2]["transform_matrix"] = content["frames"][2]["transform_matrix"][:3]
    _write(scene, content)


def _same_position(scene: Path) -> None:  # every camera at one point, looking different ways
    content = _transforms(scene)
    for frame in content["frames"]:
        for row, value in zip(frame["transform_matrix"][:3], (1.5, -2.0, 0.5)):
            row[3] = value
    _write(scene, content)


def _truncated_jpeg(scene: Path) -> None:  # frame 3 as a JPEG, cut in the middle: its header still reads
    content = _transforms(scene)
    png = scene / content["frames"][3]["file_path"]
    jpeg = png.with_suffix(".jpg")
    Image.open(png).save(jpeg, quality=95)
    png.unlink()
    data = jpeg.read_bytes()
    jpeg.write_bytes(data[: len(data) * 2 // 3])
    content["frames"][3]["file_path"] = str(jpeg.relative_to(scene))
    _write(scene, content)


def _float_image(scene: Path) -> None:  # 32-bit float pixels: no colours to train on
    path = _image(scene, 5).with_suffix(".tif")
    Image.fromarray(np.zeros((24, 32), dtype=np.float32)).save(path)
    content = _transforms(scene)
    content["frames"][5]["file_path"] = str(path.relative_to(scene))
    _write(scene, content)


def _no_height(scene: Path) -> None:  # nerfstudio asserts "height not specified in frame"
    content = _transforms(scene)
    del content["h"]
    _write(scene, content)


def _frame_without_mask(scene: Path) -> None:
    content = _transforms(scene)
    for frame in content["frames"][1:]:
        frame["mask_path"] = frame["file_path"]
    _write(scene, content)


def _unknown_camera_model(scene: Path) -> None:
    content = _transforms(scene)
    content["camera_model"] = "PINHOLE_FANCY"
    _write(scene, content)


def _bad_last_row(scene: Path) -> None:
    content = _transforms(scene)
    content["frames"][1]["transform_matrix"][3] = [0, 0, 0, 0]
    _write(scene, content)


def _val_list_missing(scene: Path) -> None:  # nerfstudio: "The dataset's list of filenames for split val is missing."
    content = _transforms(scene)
    content["train_filenames"] = [frame["file_path"] for frame in content["frames"][:4]]
    _write(scene, content)


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
    "truncated jpeg": (_truncated_jpeg, "frame 3 (images/frame_00003.jpg): the image"),
    "float image": (_float_image, "frame 5 (images/frame_00005.tif): the image"),
    "no height": (_no_height, "has no \"h\""),
    "mask for some frames": (_frame_without_mask, "frame 0 (images/frame_00000.png) has none"),
    "unknown camera model": (_unknown_camera_model, "'PINHOLE_FANCY' is not a camera model nerfstudio knows"),
    "bad last pose row": (_bad_last_row, "frame 1 (images/frame_00001.png) has the last transform_matrix row [0.0, 0.0, 0.0, 0.0]"),
    "val list missing": (_val_list_missing, "has train_filenames but no \"val_filenames\" list"),
}

#: More of each message, checked in the unit test.
DETAILS = {
    "image size differs from w/h": "is 64x48 pixels, but transforms.json gives w=32, h=24 (at its top level)",
    "truncated jpeg": "image file is truncated",
    "float image": "PIL mode 'F'",
    "3x4 and 4x4 poses": "needs a 4x4 camera-to-world matrix in every frame",
}


def _broken(good_scene: Path, tmp_path: Path, breaker: Callable[[Path], None]) -> Path:
    scene = tmp_path / "scene"
    shutil.copytree(good_scene, scene)
    breaker(scene)
    return scene


def test_good_scene_passes(good_scene: Path) -> None:
    assert check_scene(good_scene, eval_interval=8) == 6
    info = scan_scene(good_scene, eval_interval=4)
    assert (info.num_frames, info.num_train, info.downscale_factor, info.conversions) == (6, 4, 1, {})
    assert info.conversion_note() is None


@pytest.mark.parametrize("case", list(CASES))
def test_check_scene_names_the_problem(good_scene: Path, tmp_path: Path, case: str) -> None:
    breaker, message = CASES[case]
    scene = _broken(good_scene, tmp_path, breaker)
    with pytest.raises(SceneError) as raised:
        check_scene(scene, eval_interval=8)
    assert message in str(raised.value)
    assert DETAILS.get(case, "") in str(raised.value)
    assert "\n" not in str(raised.value)


@pytest.mark.parametrize(
    ("mode", "message"),
    [("fraction", "both need at least one"), ("filename", "needs \"train\" or \"eval\" in every image's file name")],
)
def test_empty_eval_split_in_other_modes(good_scene: Path, mode: str, message: str) -> None:
    fraction = 1.0 if mode == "fraction" else 0.9  # fraction 1.0 puts every image in training
    with pytest.raises(SceneError, match=message):
        check_scene(good_scene, eval_mode=mode, train_fraction=fraction)


def test_split_lists_give_the_training_count(good_scene: Path, tmp_path: Path) -> None:
    def lists(scene: Path) -> None:
        _val_list_missing(scene)
        content = _transforms(scene)
        content["val_filenames"] = [frame["file_path"] for frame in content["frames"][4:]]
        _write(scene, content)

    assert scan_scene(_broken(good_scene, tmp_path, lists), eval_interval=8).num_train == 4


def test_truncated_image_fails_in_nerfstudio_but_passes_pil_verify(good_scene: Path, tmp_path: Path) -> None:
    """Why the check decodes every pixel: PIL's verify() (a header check) accepts the truncated JPEG."""
    scene = _broken(good_scene, tmp_path, _truncated_jpeg)
    path = _image(scene, 3)
    with Image.open(path) as image:
        image.verify()
    with pytest.raises(OSError), Image.open(path) as image:
        image.load()


def test_large_scene_decodes_in_a_pool_with_progress(tmp_path: Path) -> None:
    """> 200 images: decoded by a thread pool behind a progress bar; a bad one is still named."""
    scene = tmp_path / "large"
    write_scene(scene, num_images=2, width=16, height=12)
    content = _transforms(scene)
    frames = []
    for index in range(240):
        name = f"images/copy_{index:04d}.png"
        shutil.copy(scene / content["frames"][index % 2]["file_path"], scene / name)
        frames.append({**content["frames"][index % 2], "file_path": name})
    frames[1]["transform_matrix"] = content["frames"][1]["transform_matrix"]
    content["frames"] = frames
    _write(scene, content)
    assert scan_scene(scene, eval_interval=8, workers=4).num_train == 210
    assert scan_scene(scene, eval_interval=8, workers=1).num_train == 210
    (scene / "images/copy_0233.png").write_bytes((scene / "images/copy_0233.png").read_bytes()[:100])
    with pytest.raises(SceneError, match=r"frame 233 \(images/copy_0233.png\): the image"):
        scan_scene(scene, eval_interval=8, workers=4)


# ------------------------------------------------------------------------------- downscale factor


def _with_images_2(scene: Path, size: Optional[Tuple[int, int]] = None) -> None:
    """images_2/ beside images/: every image at half size (``size`` for frame 1 instead)."""
    (scene / "images_2").mkdir()
    for index, frame in enumerate(_transforms(scene)["frames"]):
        image = Image.open(scene / frame["file_path"])
        half = size if size is not None and index == 1 else (image.width // 2, image.height // 2)
        image.resize(half).save(scene / "images_2" / Path(frame["file_path"]).name)


def test_downscale_checks_the_images_nerfstudio_loads(good_scene: Path, tmp_path: Path) -> None:
    scene = _broken(good_scene, tmp_path, _with_images_2)
    info = scan_scene(scene, eval_interval=8, downscale_factor=2)
    assert info.downscale_factor == 2 and info.num_train == 5
    _image(scene, 0).unlink()  # only images_2/ is read at downscale 2
    assert scan_scene(scene, eval_interval=8, downscale_factor=2).num_frames == 6
    with pytest.raises(SceneError, match="frame 0 lists the image .*frame_00000.png, which does not exist"):
        scan_scene(scene, eval_interval=8, downscale_factor=1)
    with pytest.raises(SceneError, match=r"--downscale-factor 4 reads .*images_4/frame_00000.png, which does not exist"):
        scan_scene(scene, eval_interval=8, downscale_factor=4)


def test_downscaled_image_of_the_wrong_size(good_scene: Path, tmp_path: Path) -> None:
    scene = _broken(good_scene, tmp_path, lambda s: _with_images_2(s, size=(17, 12)))
    with pytest.raises(SceneError) as raised:
        scan_scene(scene, eval_interval=8, downscale_factor=2)
    message = str(raised.value)
    assert "frame 1 (images/frame_00001.png)" in message and "images_2/frame_00001.png, which is 17x12 pixels" in message
    assert "divided by 2 and rounded down is 16x12" in message
    assert scan_scene(scene, eval_interval=8, downscale_factor=1).downscale_factor == 1  # full size is fine


def test_automatic_downscale_reads_images_2(good_scene: Path, tmp_path: Path) -> None:
    """Without --downscale-factor, nerfstudio halves images over 1600 pixels when images_2/ exists: so does the check."""
    def wide(scene: Path) -> None:
        content = _transforms(scene)
        content.update(w=1700, h=20, cx=850, cy=10)
        _write(scene, content)
        for frame in content["frames"]:
            Image.new("RGB", (1700, 20)).save(scene / frame["file_path"])
        _with_images_2(scene, size=(850, 11))

    scene = _broken(good_scene, tmp_path, wide)
    with pytest.raises(SceneError, match=r"downscale 2 loads .*images_2/frame_00001.png, which is 850x11 pixels"):
        scan_scene(scene, eval_interval=8)
    Image.new("RGB", (850, 10)).save(scene / "images_2" / "frame_00001.png")
    assert scan_scene(scene, eval_interval=8).downscale_factor == 2
    shutil.rmtree(scene / "images_2")
    assert scan_scene(scene, eval_interval=8).downscale_factor == 1


def test_per_frame_sizes(good_scene: Path, tmp_path: Path) -> None:
    """Frame-level w/h are compared when there are no top-level ones (a top-level value wins, as in nerfstudio)."""
    def per_frame(scene: Path) -> None:
        content = _transforms(scene)
        for frame in content["frames"]:
            frame.update(w=content["w"], h=content["h"])
        del content["w"], content["h"]
        content["frames"][2]["w"] = 30
        _write(scene, content)

    scene = _broken(good_scene, tmp_path, per_frame)
    with pytest.raises(SceneError, match=r"frame 2 \(images/frame_00002.png\): the image .* is 32x24 pixels, but transforms.json gives w=30, h=24 \(for frame 2\)"):
        scan_scene(scene, eval_interval=8)


# ---------------------------------------------------------------------------------- conversions


def _convert_images(scene: Path) -> None:
    """Frame 1 grayscale, 2 RGBA (left half transparent), 3 palette, 4 16-bit grayscale, 5 grayscale."""
    rgb = np.asarray(Image.open(_image(scene, 1)))
    Image.open(_image(scene, 1)).convert("L").save(_image(scene, 1))
    Image.open(_image(scene, 5)).convert("L").save(_image(scene, 5))
    rgba = np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], axis=2)
    rgba[:, : rgb.shape[1] // 2, 3] = 0
    Image.fromarray(rgba, "RGBA").save(_image(scene, 2))
    Image.open(_image(scene, 3)).convert("P").save(_image(scene, 3))
    grey16 = (np.asarray(Image.open(_image(scene, 4)).convert("L")).astype(np.uint16) * 257)
    Image.fromarray(grey16).save(_image(scene, 4))


@pytest.fixture(scope="module")
def mixed_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 10-image scene with grayscale, RGBA, palette and 16-bit images among the RGB ones."""
    folder = tmp_path_factory.mktemp("mixed")
    write_scene(folder, num_images=10, width=32, height=24)
    _convert_images(folder)
    return folder


def test_convertible_images_are_accepted_with_one_note(mixed_scene: Path) -> None:
    info = scan_scene(mixed_scene, eval_interval=8)
    assert info.conversions == {
        ("grayscale", "rgb"): 2, ("RGBA", "alpha"): 1, ("palette (indexed-colour)", "rgb"): 1, ("16-bit grayscale", "8bit"): 1,
    }
    note = info.conversion_note((0.0, 0.0, 0.0))
    assert note is not None and "\n" not in note
    assert "2 grayscale images will be used as RGB" in note
    assert "1 RGBA image will be composited over the background colour 0 0 0" in note
    assert "1 16-bit grayscale image will be used as 8-bit RGB" in note
    assert "1 palette (indexed-colour) image will be used as RGB" in note


def test_to_rgb_array() -> None:
    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[..., :3] = (200, 100, 50)
    rgba[0, :, 3] = 255
    rgba[1, 0, 3] = 0
    rgba[1, 1, 3] = 128
    out = to_rgb_array(Image.fromarray(rgba, "RGBA"), (1.0, 1.0, 1.0))
    assert out.dtype == np.uint8 and out.shape == (2, 2, 3)
    assert out[0, 0].tolist() == [200, 100, 50] and out[1, 0].tolist() == [255, 255, 255]
    assert np.abs(out[1, 1].astype(int) - [227, 177, 152]).max() <= 1
    assert to_rgb_array(Image.fromarray(np.full((2, 3), 7, np.uint8))).tolist() == [[[7] * 3] * 3] * 2
    assert to_rgb_array(Image.fromarray(np.full((2, 2), 65535, np.uint16))).max() == 255
    assert to_rgb_array(Image.fromarray(np.full((2, 2), 257 * 40, np.uint16)))[0, 0].tolist() == [40, 40, 40]
    la = Image.fromarray(np.dstack([np.full((1, 1), 90, np.uint8), np.zeros((1, 1), np.uint8)]), "LA")
    assert to_rgb_array(la, (0.0, 0.0, 0.0)).tolist() == [[[0, 0, 0]]]


def test_dataset_reads_every_kind_as_rgb(mixed_scene: Path) -> None:
    """What training reads (the datamanager's dataset): [H, W, 3] for every image, composited as configured."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from scalar_nerfstudio.data.datamanager import ScalarDataManager, ScalarInputDataset

    parser = NerfstudioDataParserConfig(data=mixed_scene, eval_mode="all").setup()
    dataset = ScalarInputDataset(parser.get_dataparser_outputs("train"))
    dataset.alpha_background = (0.0, 1.0, 0.0)
    names = [Path(p).name for p in dataset.image_filenames]
    for index in range(len(dataset)):
        image = dataset.get_image_float32(index)
        assert image.shape == (24, 32, 3), names[index]
    rgba = dataset.get_image_float32(names.index("frame_00002.png")).numpy()
    assert np.allclose(rgba[:, :16], (0.0, 1.0, 0.0))  # the transparent half shows the background
    grey16 = dataset.get_image_float32(names.index("frame_00004.png")).numpy()
    grey8 = np.asarray(Image.open(mixed_scene / "images/frame_00004.png")).astype(np.float64) / 257 / 255
    assert np.abs(grey16[..., 0] - grey8).max() < 1 / 255 + 1e-6
    assert ScalarDataManager.__orig_bases__[0].__args__ == (ScalarInputDataset,)  # what nerfstudio instantiates


# -------------------------------------------------------------------------------------- options


def _config():
    from scalar_nerfstudio.method_configs import scalar_nerf

    return copy.deepcopy(scalar_nerf.config)


def _set(config, path: str, value) -> None:
    *owners, name = path.split(".")
    target = config
    for owner in owners:
        target = getattr(target, owner)
    setattr(target, name, value)


#: (attribute of the trainer config, value, number of training images, message fragment)
OPTION_CASES = [
    ("pipeline.num_blocks", 0, None, "--pipeline.num-blocks 0: must be at least 1"),
    ("pipeline.num_blocks", 50, 9, "--pipeline.num-blocks 50: the scene has only 9 training images (10 frames, less those held out"),
    ("pipeline.aabb_scale", (-1.0, -1.0, -1.0), None, "--pipeline.aabb-scale -1 -1 -1: must be three finite numbers >= 1"),
    ("pipeline.aabb_scale", (1.2, math.nan, 1.2), None, "--pipeline.aabb-scale 1.2 nan 1.2"),
    ("pipeline.global_steps", -1, None, "--pipeline.global-steps -1: must be a whole number >= 0"),
    ("pipeline.block_steps", -5, None, "--pipeline.block-steps -5"),
    ("pipeline.min_images_per_block", 0, None, "--pipeline.min-images-per-block 0"),
    ("pipeline.min_images_per_block", 12, 9, "--pipeline.min-images-per-block 12: the scene has only 9 training images"),
    ("pipeline.max_auto_blocks", 0, None, "--pipeline.max-auto-blocks 0"),
    ("pipeline.min_overlap_images", -1, None, "--pipeline.min-overlap-images -1"),
    ("pipeline.split_seed", -3, None, "--pipeline.split-seed -3"),
    ("pipeline.one_model_restart", 1.0, None, "--pipeline.one-model-restart 1: must be a number in [0, 1)"),
    ("pipeline.one_model_restart", math.nan, None, "--pipeline.one-model-restart nan"),
    ("pipeline.block_log2_hashmap_bounds", (19, 14), None, "--pipeline.block-log2-hashmap-bounds 19 14: must be two whole numbers LOW HIGH"),
    ("pipeline.block_max_resolution_bounds", (2048, 64), None, "--pipeline.block-max-resolution-bounds 2048 64"),
    ("pipeline.block_log2_hashmap_size", 40, None, "--pipeline.block-log2-hashmap-size 40"),
    ("pipeline.datamanager.train_num_rays_per_batch", 0, None, "--pipeline.datamanager.train-num-rays-per-batch 0"),
    ("pipeline.datamanager.alpha_background", (2.0, 0.0, 0.0), None, "--pipeline.datamanager.alpha-background 2 0 0"),
    ("pipeline.datamanager.image_cache_mib", 0.0, None, "--pipeline.datamanager.image-cache-mib 0: must be a number of MiB > 0"),
    ("pipeline.datamanager.image_resample_every", 0, None, "--pipeline.datamanager.image-resample-every 0: must be a whole number >= 1"),
    ("pipeline.datamanager.dataparser.eval_interval", 0, None, "--eval-interval 0 (nerfstudio-data)"),
    ("pipeline.datamanager.dataparser.downscale_factor", 0, None, "--downscale-factor 0 (nerfstudio-data)"),
    ("pipeline.model.field.log2_hashmap_size", 0, None, "--pipeline.model.field.log2-hashmap-size 0"),
    ("pipeline.model.near_plane", 2000.0, None, "--pipeline.model.near-plane 2000"),
    ("pipeline.model.scene_radius", 0.0, None, "--pipeline.model.scene-radius 0"),
    ("pipeline.model.scene_radius", float("inf"), None, "--pipeline.model.scene-radius inf"),
    ("pipeline.model.block_fit_steps", -1, None, "--pipeline.model.block-fit-steps -1: must be a whole number >= 0"),
    ("pipeline.model.block_fit_points", 0, None, "--pipeline.model.block-fit-points 0"),
    ("pipeline.model.warmup_samples_per_ray", -1, None, "--pipeline.model.warmup-samples-per-ray -1: must be a whole number >= 0"),
    ("pipeline.model.nearest_idw_gamma", -1.0, None, "--pipeline.model.nearest-idw-gamma -1: must be a finite number >= 0"),
    ("pipeline.model.idw_gamma", math.inf, None, "--pipeline.model.idw-gamma inf: must be a finite number >= 0"),
    ("pipeline.model.guard_accumulation", 0.0, None, "--pipeline.model.guard-accumulation 0: must be a number in (0, 1]"),
    ("pipeline.model.guard_accumulation", 1.5, None, "--pipeline.model.guard-accumulation 1.5: must be a number in (0, 1]"),
    ("max_num_iterations", -1, None, "--max-num-iterations -1"),
    ("steps_per_save", 0, None, "--steps-per-save 0"),
]


def test_default_options_pass() -> None:
    check_options(_config(), num_train_images=5, num_frames=6)
    check_options(_config())


@pytest.mark.parametrize(("path", "value", "num_train", "message"), OPTION_CASES, ids=[f"{c[0]}={c[1]}" for c in OPTION_CASES])
def test_bad_option_is_named(path: str, value: object, num_train: Optional[int], message: str) -> None:
    config = _config()
    _set(config, path, value)
    with pytest.raises(OptionError) as raised:
        check_options(config, num_train_images=num_train, num_frames=10 if num_train is not None else None)
    assert message in str(raised.value)
    check_options(_config(), num_train_images=num_train)


def test_nothing_to_train() -> None:
    config = _config()
    config.pipeline.global_steps, config.pipeline.train_blocks = 0, False
    with pytest.raises(OptionError, match="leaves nothing to train"):
        check_pipeline_options(config.pipeline)


def test_fitted_blocks_with_independent_decoders_are_refused() -> None:
    config = _config()
    config.pipeline.block_init, config.pipeline.decoder_mode = "fitted", "independent"
    with pytest.raises(OptionError, match="--pipeline.block-init fitted with --pipeline.decoder-mode independent"):
        check_pipeline_options(config.pipeline)
    config.pipeline.decoder_mode = "frozen"
    check_pipeline_options(config.pipeline)


def test_counts_are_not_checked_for_a_given_split() -> None:
    """scalar-nerf-block reuses the global run's split: the number of blocks is not checked again."""
    config = _config()
    config.pipeline.num_blocks, config.pipeline.only_block = 8, 1
    check_pipeline_options(config.pipeline, num_train_images=3)


def test_block_split_dry_run(good_scene: Path) -> None:
    """A split that leaves a block too small is found before anything is written (5 disjoint blocks, 5 images)."""
    config = _config()
    config.pipeline.num_blocks, config.pipeline.aabb_scale, config.pipeline.min_overlap_images = 5, (1.0, 1.0, 1.0), 0
    check_options(config, num_train_images=5)  # the counts alone cannot tell
    with pytest.raises(OptionError, match=r"the block split with --pipeline.num-blocks 5, --pipeline.min-images-per-block 2 .* fails"):
        check_block_plan(config.pipeline, good_scene)
    config.pipeline.num_blocks = 2
    check_block_plan(config.pipeline, good_scene)


# -------------------------------------------------------------------------------- output folder


def test_output_dir_writable(tmp_path: Path) -> None:
    check_output_dir(tmp_path / "outputs" / "scene" / "scalar-nerf" / "2026")
    assert list(tmp_path.iterdir()) == []  # the probe file is gone, nothing was created


def test_output_dir_under_a_file(tmp_path: Path) -> None:
    (tmp_path / "outputs").write_text("a file")
    with pytest.raises(OptionError, match=r"because .*outputs is a file, not a folder"):
        check_output_dir(tmp_path / "outputs" / "scene" / "run")


def test_output_dir_not_writable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda path, mode: False if Path(path) == tmp_path else real_access(path, mode))
    with pytest.raises(OptionError, match=rf"nothing can be written to {tmp_path} \(where the run folder .* would be created\): it is not writable"):
        check_output_dir(tmp_path / "run")


def test_output_dir_read_only_filesystem(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    with pytest.raises(OptionError, match="it is on a read-only file system. Choose a writable --output-dir"):
        check_output_dir(tmp_path / "run")


# ------------------------------------------------------------------------- ns-train, end to end

# Runs `ns-train` once per job in forked children of one process that has imported nerfstudio once
# (an ns-train start costs ~10 s of imports): each child runs nerfstudio's real entry point with its
# own argv, stdout and stderr, and exits as the interpreter would (SystemExit message on stderr, a
# traceback for any other exception).
_DRIVER = textwrap.dedent(
    """
    import json, os, sys, traceback
    from nerfstudio.scripts.train import entrypoint

    for job in json.loads(sys.argv[1]):
        sys.stdout.flush(); sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            os.dup2(os.open(job["stdout"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC), 1)
            os.dup2(os.open(job["stderr"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC), 2)
            sys.argv = ["ns-train", *job["args"]]
            code = 0
            try:
                entrypoint()
            except SystemExit as exit:
                code = exit.code if isinstance(exit.code, int) else (0 if exit.code is None else 1)
                if not isinstance(exit.code, (int, type(None))):
                    print(exit.code, file=sys.stderr)
            except BaseException:
                traceback.print_exc()
                code = 1
            sys.stdout.flush(); sys.stderr.flush()
            os._exit(code)
        _, status = os.waitpid(pid, 0)
        with open(job["rc"], "w") as handle:
            handle.write(str(os.waitstatus_to_exitcode(status)))
    """
)

#: A guard, so that a case the checks miss trains one step and ends instead of hanging in the viewer.
_GUARD = ["--max-num-iterations", "1", "--vis", "tensorboard", "--viewer.quit-on-train-completion", "True"]

#: Option cases run through ns-train on the good scene: name -> (extra arguments, message fragment).
CLI_OPTION_CASES: Dict[str, Tuple[List[str], str]] = {
    "num-blocks 0": (["--pipeline.num-blocks", "0"], "bad option: --pipeline.num-blocks 0: must be at least 1"),
    "num-blocks 50": (["--pipeline.num-blocks", "50"], "bad option: --pipeline.num-blocks 50: the scene has only 5 training images"),
    "aabb-scale -1": (["--pipeline.aabb-scale", "-1", "-1", "-1"], "bad option: --pipeline.aabb-scale -1 -1 -1"),
    "global-steps -1": (["--pipeline.global-steps", "-1"], "bad option: --pipeline.global-steps -1"),
    "log2 bounds reversed": (["--pipeline.block-log2-hashmap-bounds", "19", "14"], "bad option: --pipeline.block-log2-hashmap-bounds 19 14"),
    "eval-interval 0": (["nerfstudio-data", "--eval-interval", "0"], "bad option: --eval-interval 0"),
    "block split too small": (["--pipeline.num-blocks", "5", "--pipeline.aabb-scale", "1", "1", "1", "--pipeline.min-overlap-images", "0"],
                              "bad option: the block split with --pipeline.num-blocks 5"),
}
#: Scene cases run through ns-train.
CLI_SCENE_CASES = ["missing image", "truncated transforms", "nan pose", "empty folder", "no training image", "image size differs from w/h",
                   "3x4 and 4x4 poses", "identical camera centres", "truncated jpeg"]


def _read_only_mount_works(folder: Path) -> bool:
    """Whether this machine lets us mount a read-only tmpfs in a private mount namespace (root, unshare)."""
    if shutil.which("unshare") is None:
        return False
    folder.mkdir(parents=True, exist_ok=True)
    probe = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o ro tmpfs '{folder}' && ! touch '{folder}/x' 2>/dev/null"],
                           capture_output=True, timeout=30)
    return probe.returncode == 0


@pytest.fixture(scope="module")
def ns_train_results(good_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Dict[str, dict]:
    """Every CLI case through ns-train in one process: name -> {rc, output, outputs folder, earlier file}."""
    root = tmp_path_factory.mktemp("cli")
    jobs, results = [], {}

    def add(name: str, scene: Path, extra: List[str], outputs: Optional[Path] = None) -> None:
        folder = root / f"case{len(jobs)}"
        folder.mkdir()
        if outputs is None:
            outputs = folder / "outputs"
            outputs.mkdir()
            (outputs / "earlier-run.txt").write_text("an earlier run's file")
        args = ["scalar-nerf", "--data", str(scene), "--output-dir", str(outputs), *_GUARD, *extra]  # a dataparser comes last
        jobs.append({"args": args, "stdout": str(folder / "out"), "stderr": str(folder / "err"), "rc": str(folder / "rc")})
        results[name] = {"folder": folder, "outputs": outputs}

    for case in CLI_SCENE_CASES:
        scene = root / f"scene-{len(jobs)}"
        shutil.copytree(good_scene, scene)
        CASES[case][0](scene)
        add(case, scene, [])
    for case, (extra, _) in CLI_OPTION_CASES.items():
        add(case, good_scene, extra)
    file_output = root / "a-file"
    file_output.write_text("not a folder")
    add("output under a file", good_scene, [], outputs=file_output / "outputs")
    read_only = root / "read-only"
    command = [sys.executable, "-c", _DRIVER]
    if _read_only_mount_works(read_only):
        add("read-only output", good_scene, [], outputs=read_only / "outputs")
        driver = f"mount -t tmpfs -o ro tmpfs '{read_only}' && exec \"$@\""
        command = ["unshare", "-m", "sh", "-c", driver, "sh", *command]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([*command, json.dumps(jobs)], capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    for name, result in results.items():
        folder = result["folder"]
        result["rc"] = int((folder / "rc").read_text())
        result["output"] = (folder / "out").read_text() + (folder / "err").read_text()
    return results


def _assert_stopped_cleanly(result: dict, message: str, earlier: bool = True) -> None:
    output = result["output"]
    assert result["rc"] != 0, output[-3000:]
    assert "Traceback" not in output, output[-3000:]
    assert message in " ".join(output.split()), output[-3000:]
    outputs: Path = result["outputs"]
    if earlier:
        assert sorted(p.name for p in outputs.rglob("*")) == ["earlier-run.txt"]
        assert (outputs / "earlier-run.txt").read_text() == "an earlier run's file"
    else:
        assert not outputs.exists()


@pytest.mark.parametrize("case", CLI_SCENE_CASES)
def test_ns_train_stops_cleanly_and_writes_nothing(ns_train_results: Dict[str, dict], case: str) -> None:
    _assert_stopped_cleanly(ns_train_results[case], "bad scene")
    _assert_stopped_cleanly(ns_train_results[case], CASES[case][1])


@pytest.mark.parametrize("case", list(CLI_OPTION_CASES))
def test_ns_train_bad_option_stops_before_writing(ns_train_results: Dict[str, dict], case: str) -> None:
    _assert_stopped_cleanly(ns_train_results[case], CLI_OPTION_CASES[case][1])


def test_ns_train_output_under_a_file(ns_train_results: Dict[str, dict]) -> None:
    result = ns_train_results["output under a file"]
    _assert_stopped_cleanly(result, "cannot write the run: --output-dir: the run folder", earlier=False)
    _assert_stopped_cleanly(result, "a-file is a file, not a folder", earlier=False)
    assert (result["outputs"].parent).read_text() == "not a folder"


def test_ns_train_read_only_output(ns_train_results: Dict[str, dict]) -> None:
    if "read-only output" not in ns_train_results:
        pytest.skip("cannot mount a read-only file system here (needs root and unshare)")
    _assert_stopped_cleanly(ns_train_results["read-only output"], "cannot write the run: --output-dir: nothing can be written to", earlier=False)
    _assert_stopped_cleanly(ns_train_results["read-only output"], "it is on a read-only file system", earlier=False)


def test_ns_train_process_stops_cleanly(good_scene: Path, tmp_path: Path) -> None:
    """One case as a real `python -m nerfstudio.scripts.train` process (the interpreter prints the message)."""
    scene = _broken(good_scene, tmp_path, _truncated_jpeg)
    outputs = tmp_path / "outputs"
    result = subprocess.run(
        [sys.executable, "-m", "nerfstudio.scripts.train", "scalar-nerf", "--data", str(scene), "--output-dir", str(outputs), *_GUARD],
        capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    _assert_stopped_cleanly({"rc": result.returncode, "output": result.stdout + result.stderr, "outputs": outputs},
                            "bad scene: ", earlier=False)
    assert "frame 3 (images/frame_00003.jpg): the image" in result.stderr


@pytest.mark.slow  # trains
def test_grayscale_and_rgba_scene_trains(mixed_scene: Path, tmp_path: Path) -> None:
    """Grayscale, RGBA, palette and 16-bit images train (a few steps, through an eval image) with one note."""
    outputs = tmp_path / "outputs"
    before = sorted(str(p.relative_to(mixed_scene)) for p in mixed_scene.rglob("*"))
    tiny = [
        "--max-num-iterations", "3", "--steps-per-eval-image", "2", "--vis", "tensorboard",
        "--pipeline.model.field.log2-hashmap-size", "12", "--pipeline.model.field.max-resolution", "64",
        "--pipeline.model.num-samples-per-ray", "16", "--pipeline.datamanager.train-num-rays-per-batch", "256",
        "--pipeline.num-blocks", "2", "--pipeline.global-steps", "2", "--pipeline.block-steps", "1",
    ]
    result = subprocess.run(ns_train_command(mixed_scene, outputs, *tiny), capture_output=True, text=True, timeout=600,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    output = result.stdout + result.stderr
    assert result.returncode == 0, output[-3000:]
    assert "Traceback" not in output
    notes = [line for line in result.stdout.splitlines() if "will be used as RGB" in line]
    assert len(notes) == 1, output[-3000:]
    assert "2 grayscale images will be used as RGB" in notes[0] and "1 RGBA image will be composited" in notes[0]
    (run,) = run_dirs(outputs)
    assert (run / "nerfstudio_models").is_dir()
    assert sorted(str(p.relative_to(mixed_scene)) for p in mixed_scene.rglob("*")) == before  # the scene folder is untouched


def test_a_missing_relative_scene_names_where_it_was_looked_for(tmp_path: Path, monkeypatch) -> None:
    """A relative --data that does not exist names the directory it was looked for from (a run's
    config keeps the path as typed, so a command started elsewhere looks in the wrong place)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SceneError, match=f"scene folder scenes/town does not exist \\(a relative path, looked for from {tmp_path}"):
        scan_scene(Path("scenes/town"), eval_interval=8)
    with pytest.raises(SceneError, match=f"scene folder {tmp_path / 'town'} does not exist\\.$"):
        scan_scene(tmp_path / "town", eval_interval=8)
