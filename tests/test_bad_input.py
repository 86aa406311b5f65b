"""Bad scenes, options and output folders end with one clear paragraph naming the file/frame/option,
a non-zero exit, no traceback, and nothing written into the output folder. Images that can be used
safely (grayscale, RGBA, palette, 16-bit) are converted in memory, with one log line."""

from __future__ import annotations

import copy
import errno
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Optional, Tuple

import numpy as np
import pytest
from bad_scenes import (
    CASES,
    broken_copy,
    image_file,
    read_transforms,
    truncated_jpeg,
    val_list_missing,
    write_transforms,
)
from PIL import Image

from scalar_nerfstudio.config_checks import (
    OptionError,
    check_block_plan,
    check_options,
    check_output_dir,
    check_pipeline_options,
)
from scalar_nerfstudio.data.validation import SceneError, check_scene, scan_scene, to_rgb_array
from scalar_nerfstudio.scenes.courtyard import write_scene

#: More of each message, checked in the unit test.
DETAILS = {
    "image size differs from w/h": "is 64x48 pixels, but transforms.json gives w=32, h=24 (at its top level)",
    "truncated jpeg": "image file is truncated",
    "float image": "PIL mode 'F'",
    "3x4 and 4x4 poses": "needs a 4x4 camera-to-world matrix in every frame",
}


def test_good_scene_passes(good_scene: Path) -> None:
    assert check_scene(good_scene, eval_interval=8) == 6
    info = scan_scene(good_scene, eval_interval=4)
    assert (info.num_frames, info.num_train, info.downscale_factor, info.conversions) == (6, 4, 1, {})
    assert info.conversion_note() is None


@pytest.mark.parametrize("case", list(CASES))
def test_check_scene_names_the_problem(good_scene: Path, tmp_path: Path, case: str) -> None:
    breaker, message = CASES[case]
    scene = broken_copy(good_scene, tmp_path, breaker)
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
        val_list_missing(scene)
        content = read_transforms(scene)
        content["val_filenames"] = [frame["file_path"] for frame in content["frames"][4:]]
        write_transforms(scene, content)

    assert scan_scene(broken_copy(good_scene, tmp_path, lists), eval_interval=8).num_train == 4


def test_truncated_image_fails_in_nerfstudio_but_passes_pil_verify(good_scene: Path, tmp_path: Path) -> None:
    """Why the check decodes every pixel: PIL's verify() (a header check) accepts the truncated JPEG."""
    scene = broken_copy(good_scene, tmp_path, truncated_jpeg)
    path = image_file(scene, 3)
    with Image.open(path) as image:
        image.verify()
    with pytest.raises(OSError), Image.open(path) as image:
        image.load()


def test_large_scene_decodes_in_a_pool_with_progress(tmp_path: Path) -> None:
    """> 200 images: decoded by a thread pool behind a progress bar; a bad one is still named."""
    scene = tmp_path / "large"
    write_scene(scene, num_images=2, width=16, height=12)
    content = read_transforms(scene)
    frames = []
    for index in range(240):
        name = f"images/copy_{index:04d}.png"
        shutil.copy(scene / content["frames"][index % 2]["file_path"], scene / name)
        frames.append({**content["frames"][index % 2], "file_path": name})
    frames[1]["transform_matrix"] = content["frames"][1]["transform_matrix"]
    content["frames"] = frames
    write_transforms(scene, content)
    assert scan_scene(scene, eval_interval=8, workers=4).num_train == 210
    assert scan_scene(scene, eval_interval=8, workers=1).num_train == 210
    (scene / "images/copy_0233.png").write_bytes((scene / "images/copy_0233.png").read_bytes()[:100])
    with pytest.raises(SceneError, match=r"frame 233 \(images/copy_0233.png\): the image"):
        scan_scene(scene, eval_interval=8, workers=4)


# ------------------------------------------------------------------------------- downscale factor


def _with_images_2(scene: Path, size: Optional[Tuple[int, int]] = None) -> None:
    """images_2/ beside images/: every image at half size (``size`` for frame 1 instead)."""
    (scene / "images_2").mkdir()
    for index, frame in enumerate(read_transforms(scene)["frames"]):
        image = Image.open(scene / frame["file_path"])
        half = size if size is not None and index == 1 else (image.width // 2, image.height // 2)
        image.resize(half).save(scene / "images_2" / Path(frame["file_path"]).name)


def test_downscale_checks_the_images_nerfstudio_loads(good_scene: Path, tmp_path: Path) -> None:
    scene = broken_copy(good_scene, tmp_path, _with_images_2)
    info = scan_scene(scene, eval_interval=8, downscale_factor=2)
    assert info.downscale_factor == 2 and info.num_train == 5
    image_file(scene, 0).unlink()  # only images_2/ is read at downscale 2
    assert scan_scene(scene, eval_interval=8, downscale_factor=2).num_frames == 6
    with pytest.raises(SceneError, match="frame 0 lists the image .*frame_00000.png, which does not exist"):
        scan_scene(scene, eval_interval=8, downscale_factor=1)
    with pytest.raises(SceneError, match=r"--downscale-factor 4 reads .*images_4/frame_00000.png, which does not exist"):
        scan_scene(scene, eval_interval=8, downscale_factor=4)


def test_downscaled_image_of_the_wrong_size(good_scene: Path, tmp_path: Path) -> None:
    scene = broken_copy(good_scene, tmp_path, lambda s: _with_images_2(s, size=(17, 12)))
    with pytest.raises(SceneError) as raised:
        scan_scene(scene, eval_interval=8, downscale_factor=2)
    message = str(raised.value)
    assert "frame 1 (images/frame_00001.png)" in message and "images_2/frame_00001.png, which is 17x12 pixels" in message
    assert "divided by 2 and rounded down is 16x12" in message
    assert scan_scene(scene, eval_interval=8, downscale_factor=1).downscale_factor == 1  # full size is fine


def test_automatic_downscale_reads_images_2(good_scene: Path, tmp_path: Path) -> None:
    """Without --downscale-factor, nerfstudio halves images over 1600 pixels when images_2/ exists: so does the check."""
    def wide(scene: Path) -> None:
        content = read_transforms(scene)
        content.update(w=1700, h=20, cx=850, cy=10)
        write_transforms(scene, content)
        for frame in content["frames"]:
            Image.new("RGB", (1700, 20)).save(scene / frame["file_path"])
        _with_images_2(scene, size=(850, 11))

    scene = broken_copy(good_scene, tmp_path, wide)
    with pytest.raises(SceneError, match=r"downscale 2 loads .*images_2/frame_00001.png, which is 850x11 pixels"):
        scan_scene(scene, eval_interval=8)
    Image.new("RGB", (850, 10)).save(scene / "images_2" / "frame_00001.png")
    assert scan_scene(scene, eval_interval=8).downscale_factor == 2
    shutil.rmtree(scene / "images_2")
    assert scan_scene(scene, eval_interval=8).downscale_factor == 1


def test_per_frame_sizes(good_scene: Path, tmp_path: Path) -> None:
    """Frame-level w/h are compared when there are no top-level ones (a top-level value wins, as in nerfstudio)."""
    def per_frame(scene: Path) -> None:
        content = read_transforms(scene)
        for frame in content["frames"]:
            frame.update(w=content["w"], h=content["h"])
        del content["w"], content["h"]
        content["frames"][2]["w"] = 30
        write_transforms(scene, content)

    scene = broken_copy(good_scene, tmp_path, per_frame)
    with pytest.raises(SceneError, match=r"frame 2 \(images/frame_00002.png\): the image .* is 32x24 pixels, but transforms.json gives w=30, h=24 \(for frame 2\)"):
        scan_scene(scene, eval_interval=8)


# ---------------------------------------------------------------------------------- conversions


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
    ("pipeline.datamanager.pixel_sampler.ray_choice", "worst", None, "--pipeline.datamanager.pixel-sampler.ray-choice worst: must be uniform or error"),
    ("pipeline.datamanager.pixel_sampler.tile_px", 0, None, "--pipeline.datamanager.pixel-sampler.tile-px 0: must be a whole number >= 1"),
    ("pipeline.datamanager.pixel_sampler.uniform_share", 1.5, None, "--pipeline.datamanager.pixel-sampler.uniform-share 1.5: must be a number in [0, 1]"),
    ("pipeline.datamanager.pixel_sampler.error_decay", 1.0, None, "--pipeline.datamanager.pixel-sampler.error-decay 1: must be a number in (0, 1)"),
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
    ("pipeline.model.pose_gradient_share", 0.0, None, "--pipeline.model.pose-gradient-share 0: must be a number in (0, 1]"),
    ("pipeline.model.camera_optimizer.mode", "SO3", None, "--pipeline.model.camera-optimizer.mode SO3: must be off, SO3xR3 or SE3"),
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
