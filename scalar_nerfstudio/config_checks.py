"""Up-front checks of a run's options and output folder, run before ``ns-train`` writes anything.

``ScalarTrainerConfig.set_timestamp`` (called by ``ns-train`` before it writes config.yml) runs
:func:`check_options` (pure: option values, and the number of blocks against the number of training
images), :func:`check_block_plan` (the block split of the parsed cameras, done once as a dry run) and
:func:`check_output_dir`. Each raises :class:`OptionError` with one paragraph naming the option or
folder and what to do, so a bad option ends with that paragraph and no run folder instead of a
traceback once config.yml has been written.
"""

from __future__ import annotations

import errno
import math
import os
import tempfile
import warnings
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional, TypeGuard

from scalar_nerfstudio.blocks.length import LengthError, parse_duration
from scalar_nerfstudio.fields.decoder_kernels import kernel_conflict

if TYPE_CHECKING:  # the configs checked here (they import this module's callers, not this module)
    from scalar_nerfstudio.data.datamanager import ScalarDataManagerConfig
    from scalar_nerfstudio.data.ray_choice import ScalarPixelSamplerConfig
    from scalar_nerfstudio.engine.trainer import ScalarTrainerConfig
    from scalar_nerfstudio.models.scene_model import ScalarSceneModelConfig
    from scalar_nerfstudio.pipeline import ScalarPipelineConfig

__all__ = ["OptionError", "check_block_plan", "check_options", "check_output_dir", "check_pipeline_options", "check_trainer_options"]

#: log2 table rows beyond this (2^30 rows, 16 GiB per 4-feature level in float32) cannot be allocated anyway.
MAX_LOG2_HASHMAP_SIZE = 30


class OptionError(ValueError):
    """An option (or the output folder) cannot work; the message names it and says what to do."""


def _flag(name: str, prefix: str = "--pipeline.") -> str:
    return prefix + name.replace("_", "-")


def _show(value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return " ".join(_show(v) for v in value)
    return f"{value:g}" if isinstance(value, float) else str(value)


def _is_int(value: Any) -> TypeGuard[int]:
    return isinstance(value, int) and not isinstance(value, bool)


def _at_least(owner: Any, name: str, low: int, *, why: str = "", prefix: str = "--pipeline.", optional: bool = False) -> None:
    value = getattr(owner, name)
    if value is None and optional:
        return
    if not _is_int(value) or value < low:
        raise OptionError(f"{_flag(name, prefix)} {_show(value)}: must be a whole number >= {low}{why}.")


def _bounds(owner: Any, name: str, low: int, high: Optional[int] = None, prefix: str = "--pipeline.") -> None:
    value = getattr(owner, name)
    if value is None:
        return
    pair = tuple(value) if isinstance(value, (tuple, list)) else ()
    top = f" and <= {high}" if high is not None else ""
    if len(pair) != 2 or not all(_is_int(v) for v in pair) or not low <= pair[0] <= pair[1] or (high is not None and pair[1] > high):
        raise OptionError(f"{_flag(name, prefix)} {_show(value)}: must be two whole numbers LOW HIGH with {low} <= LOW <= HIGH{top}.")


def check_pipeline_options(pipeline: ScalarPipelineConfig, num_train_images: Optional[int] = None, num_frames: Optional[int] = None) -> None:
    """Check a :class:`ScalarPipelineConfig`'s options; pure (reads nothing from disk).

    Args:
        pipeline: the pipeline config (``config.pipeline``).
        num_train_images: training images left by the eval split (None: the checks that need it are skipped).
        num_frames: frames in the scene (only used to explain ``num_train_images``).

    Raises:
        OptionError: naming the first bad option, its value and what to do.
    """
    num_blocks = pipeline.num_blocks
    if num_blocks is not None and (not _is_int(num_blocks) or num_blocks < 1):
        raise OptionError(f"--pipeline.num-blocks {_show(num_blocks)}: must be at least 1 (1: the global model only), "
                          f"or leave the option out for the automatic number of blocks.")
    scale = pipeline.aabb_scale
    values = list(scale) if isinstance(scale, (tuple, list)) else []
    if len(values) != 3 or not all(isinstance(s, (int, float)) and math.isfinite(s) and s >= 1.0 for s in values):
        raise OptionError(f"--pipeline.aabb-scale {_show(scale)}: must be three finite numbers >= 1 (x y z scale of each block's "
                          f"camera box; 1 1 1 gives disjoint blocks, 1.2 1.2 1.2 is the paper's default).")
    _at_least(pipeline, "min_images_per_block", 1, why=" (a block needs at least one training image)")
    _at_least(pipeline, "max_auto_blocks", 1)
    _at_least(pipeline, "auto_min_images_per_block", 1)
    _at_least(pipeline, "min_overlap_images", 0, why=" (0: blocks are not grown to overlap)")
    seed = pipeline.split_seed
    if not _is_int(seed) or not 0 <= seed < 2**32:
        raise OptionError(f"--pipeline.split-seed {_show(seed)}: must be a whole number in [0, 2^32).")
    _at_least(pipeline, "global_steps", 0, why=" (or left out: planned from the capture or --pipeline.time-budget)", optional=True)
    _at_least(pipeline, "block_steps", 0, why=" (or left out: planned from the capture or --pipeline.time-budget)", optional=True)
    if pipeline.global_steps == 0 and (pipeline.block_steps == 0 or not pipeline.train_blocks):
        raise OptionError("--pipeline.global-steps 0 leaves nothing to train (the blocks get no steps either); give the global "
                          "phase (--pipeline.global-steps) or the blocks (--pipeline.block-steps, --pipeline.train-blocks True) some steps.")
    _check_length(pipeline)
    restart = pipeline.one_model_restart
    if isinstance(restart, bool) or not isinstance(restart, (int, float)) or not (math.isfinite(restart) and 0.0 <= restart < 1.0):
        raise OptionError(f"--pipeline.one-model-restart {_show(restart)}: must be a number in [0, 1) (the share of a one-model "
                          f"run after which its learning rates restart; 0: no restart).")
    _bounds(pipeline, "block_log2_hashmap_bounds", 1, MAX_LOG2_HASHMAP_SIZE)
    _bounds(pipeline, "block_max_resolution_bounds", 1)
    log2_size = pipeline.block_log2_hashmap_size
    if log2_size is not None and (not _is_int(log2_size) or not 1 <= log2_size <= MAX_LOG2_HASHMAP_SIZE):
        raise OptionError(f"--pipeline.block-log2-hashmap-size {_show(log2_size)}: must be a whole number from 1 to "
                          f"{MAX_LOG2_HASHMAP_SIZE}, or left out to size each block automatically.")
    _at_least(pipeline, "block_max_resolution", 1, optional=True)
    if pipeline.block_init == "fitted" and pipeline.decoder_mode == "independent":
        raise OptionError("--pipeline.block-init fitted with --pipeline.decoder-mode independent: a block's table is fitted to the "
                          "global model through the global decoder, which an independent decoder does not copy; use "
                          "--pipeline.decoder-mode finetune (or frozen), or --pipeline.block-init fresh.")
    _check_model(pipeline.model)
    _check_data(pipeline.datamanager)
    if num_train_images is not None:
        check_block_counts(pipeline, num_train_images, num_frames)


def _check_length(pipeline: ScalarPipelineConfig) -> None:
    """The options a run's length is planned from (blocks/length.py)."""
    budget = pipeline.time_budget
    if budget is not None:
        try:
            parse_duration(budget)
        except LengthError as error:
            raise OptionError(f"--pipeline.time-budget {budget}: {error}.") from None
        if pipeline.global_steps is not None and pipeline.block_steps is not None:
            raise OptionError(f"--pipeline.time-budget {budget} with --pipeline.global-steps and --pipeline.block-steps: the budget "
                              "plans the steps; leave one of the step counts out (or the budget).")
    for name in ("rays_per_pixel", "block_rays_per_pixel"):
        value = getattr(pipeline, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
            raise OptionError(f"{_flag(name)} {_show(value)}: must be a number > 0 (how often a phase draws each pixel on average).")
    _at_least(pipeline, "block_workers", 1, why=" (blocks that train at once, on other processes or machines)")


def check_block_counts(pipeline: ScalarPipelineConfig, num_train_images: int, num_frames: Optional[int] = None) -> None:
    """The options that depend on the scene: blocks and images per block against the training images.

    Raises:
        OptionError: naming the option, its value and the scene's image count.
    """
    splits = pipeline.blocks_json is None and pipeline.only_block is None
    if not splits:
        return
    num_blocks = pipeline.num_blocks
    images = f"{num_train_images} training image{'s' if num_train_images != 1 else ''}"
    if num_frames is not None and num_frames != num_train_images:
        images += f" ({num_frames} frames, less those held out for evaluation)"
    if num_blocks is not None and num_blocks > num_train_images:
        raise OptionError(f"--pipeline.num-blocks {num_blocks}: the scene has only {images}, and each block needs at least one; "
                          f"use at most {num_train_images} blocks, or leave the option out for the automatic number.")
    min_images = pipeline.min_images_per_block
    if min_images > num_train_images:
        raise OptionError(f"--pipeline.min-images-per-block {min_images}: the scene has only {images}; "
                          f"use at most {num_train_images}.")


def _check_model(model: ScalarSceneModelConfig) -> None:
    field = model.field
    prefix = "--pipeline.model.field."
    size = field.log2_hashmap_size
    if not _is_int(size) or not 1 <= size <= MAX_LOG2_HASHMAP_SIZE:
        raise OptionError(f"{prefix}log2-hashmap-size {_show(size)}: must be a whole number from 1 to {MAX_LOG2_HASHMAP_SIZE}.")
    for name in ("num_levels", "features_per_level", "base_resolution", "hidden_dim"):
        _at_least(field, name, 1, prefix=prefix)
    base, finest = field.base_resolution, field.max_resolution
    if not _is_int(finest) or finest < base:
        raise OptionError(f"{prefix}max-resolution {_show(finest)}: must be a whole number >= --pipeline.model.field.base-resolution ({base}).")
    conflict = kernel_conflict(field.cpu_decoder_kernel, field.decoder_precision,
                               field.fused_decoder)
    if conflict is not None:
        raise OptionError(f"{prefix}cpu-decoder-kernel: {conflict}; change one of the two.")
    prefix = "--pipeline.model."
    _at_least(model, "eval_num_rays_per_chunk", 1, prefix=prefix, optional=True)  # None: by device
    for name in ("num_samples_per_ray", "occupancy_resolution", "occupancy_update_every"):
        _at_least(model, name, 1, prefix=prefix)
    _at_least(model, "warmup_samples_per_ray", 0, why=" (0: num-samples-per-ray during the warm-up too)", prefix=prefix, optional=True)
    _at_least(model, "render_occupancy_resolution", 0, why=" (0: rendering uses the training grid)", prefix=prefix, optional=True)
    _at_least(model, "blocks_per_ray", 0, why=" (0: every block on every ray)", prefix=prefix, optional=True)
    for name in ("idw_gamma", "nearest_idw_gamma"):
        gamma = getattr(model, name)
        if gamma is not None and (isinstance(gamma, bool) or not isinstance(gamma, (int, float)) or not (math.isfinite(gamma) and gamma >= 0)):
            raise OptionError(f"{_flag(name, prefix)} {_show(gamma)}: must be a finite number >= 0 (0: equal weights).")
    guard = model.guard_accumulation
    if guard is not None and (isinstance(guard, bool) or not isinstance(guard, (int, float)) or not (math.isfinite(guard) and 0 < guard <= 1)):
        raise OptionError(f"{_flag('guard_accumulation', prefix)} {_show(guard)}: must be a number in (0, 1] (an accumulated opacity).")
    share = model.pose_gradient_share
    if isinstance(share, bool) or not isinstance(share, (int, float)) or not (math.isfinite(share) and 0 < share <= 1):
        raise OptionError(f"{_flag('pose_gradient_share', prefix)} {_show(share)}: must be a number in (0, 1] (a share of a batch's rays).")
    mode = model.camera_optimizer.mode
    if mode not in ("off", "SO3xR3", "SE3"):
        raise OptionError(f"--pipeline.model.camera-optimizer.mode {_show(mode)}: must be off, SO3xR3 or SE3.")
    _at_least(model, "block_fit_steps", 0, why=" (0: a fitted block keeps its fresh table)", prefix=prefix, optional=True)
    _at_least(model, "block_fit_points", 1, prefix=prefix, optional=True)
    near, far = model.near_plane, model.far_plane
    if not (isinstance(near, (int, float)) and isinstance(far, (int, float)) and 0 <= near < far):
        raise OptionError(f"--pipeline.model.near-plane {_show(near)} / --pipeline.model.far-plane {_show(far)}: need 0 <= near < far.")
    radius = model.scene_radius
    if radius is not None and (isinstance(radius, bool) or not isinstance(radius, (int, float)) or not (math.isfinite(radius) and radius > 0)):
        raise OptionError(f"--pipeline.model.scene-radius {_show(radius)}: must be a finite number > 0 (None: unbounded).")


def _check_data(datamanager: ScalarDataManagerConfig) -> None:
    prefix = "--pipeline.datamanager."
    for name in ("train_num_rays_per_batch", "eval_num_rays_per_batch"):
        _at_least(datamanager, name, 1, prefix=prefix)
    background = datamanager.alpha_background
    colour = list(background) if isinstance(background, (tuple, list)) else []
    if len(colour) != 3 or not all(isinstance(c, (int, float)) and 0.0 <= c <= 1.0 for c in colour):
        raise OptionError(f"{prefix}alpha-background {_show(background)}: must be three numbers R G B in [0, 1].")
    budget = datamanager.image_cache_mib
    if budget is not None and not (isinstance(budget, (int, float)) and math.isfinite(budget) and budget > 0):
        raise OptionError(f"{prefix}image-cache-mib {_show(budget)}: must be a number of MiB > 0, or left out for a quarter "
                          f"of the available memory.")
    _at_least(datamanager, "image_resample_every", 1, prefix=prefix, optional=True)
    scale = datamanager.camera_res_scale_factor
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise OptionError(f"{prefix}camera-res-scale-factor {_show(scale)}: must be a number > 0.")
    _check_ray_choice(datamanager.pixel_sampler, f"{prefix}pixel-sampler.")
    parser = datamanager.dataparser
    if parser is None:
        return
    factor = getattr(parser, "downscale_factor", None)
    if factor is not None and (not _is_int(factor) or factor < 1):
        raise OptionError(f"--downscale-factor {_show(factor)} (nerfstudio-data): must be a whole number >= 1, or left out for "
                          f"nerfstudio's automatic choice.")
    if getattr(parser, "eval_mode", None) == "interval":
        interval = getattr(parser, "eval_interval", 8)
        if not _is_int(interval) or interval < 1:
            raise OptionError(f"--eval-interval {_show(interval)} (nerfstudio-data): must be a whole number >= 1 "
                              f"(every N-th image is held out for evaluation).")
    if getattr(parser, "eval_mode", None) == "fraction":
        fraction = getattr(parser, "train_split_fraction", 0.9)
        if not (isinstance(fraction, (int, float)) and 0.0 < fraction <= 1.0):
            raise OptionError(f"--train-split-fraction {_show(fraction)} (nerfstudio-data): must be in (0, 1].")
    for name in ("scale_factor", "scene_scale"):
        value = getattr(parser, name, 1.0)
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise OptionError(f"--{name.replace('_', '-')} {_show(value)} (nerfstudio-data): must be a number > 0.")


def _check_ray_choice(sampler: ScalarPixelSamplerConfig, prefix: str) -> None:
    if sampler.ray_choice not in ("uniform", "error"):
        raise OptionError(f"{prefix}ray-choice {_show(sampler.ray_choice)}: must be uniform or error.")
    _at_least(sampler, "tile_px", 1, prefix=prefix)
    for name, open_interval in (("uniform_share", False), ("error_decay", True)):
        value = getattr(sampler, name)
        inside = isinstance(value, (int, float)) and not isinstance(value, bool) and (0 < value < 1 if open_interval else 0 <= value <= 1)
        if not inside:
            raise OptionError(f"{_flag(name, prefix)} {_show(value)}: must be a number in {'(0, 1)' if open_interval else '[0, 1]'}.")


def check_trainer_options(config: ScalarTrainerConfig) -> None:
    """Check the trainer-level options (step counts) of a ``ScalarTrainerConfig``; pure."""
    _at_least(config, "max_num_iterations", 0, why=" (0: train every phase)", prefix="--")
    _at_least(config, "steps_per_save", 1, prefix="--")
    for name in ("steps_per_eval_batch", "steps_per_eval_image", "steps_per_eval_all_images"):
        _at_least(config, name, 0, why=" (0: never)", prefix="--")


def check_options(config: ScalarTrainerConfig, num_train_images: Optional[int] = None, num_frames: Optional[int] = None) -> None:
    """:func:`check_trainer_options` and :func:`check_pipeline_options` of a ``ScalarTrainerConfig``; pure."""
    check_trainer_options(config)
    check_pipeline_options(config.scalar_pipeline, num_train_images, num_frames)


# ----------------------------------------------------------------------------------- block plan


def check_block_plan(pipeline: ScalarPipelineConfig, data: Path) -> None:
    """Decide the block plan of the parsed training cameras once, as the pipeline will, and turn a
    split that cannot work (a block left with fewer than ``min_images_per_block`` images) into an
    :class:`OptionError` before anything is written.

    Skipped (the pipeline reports it later) when the run reuses a split or plan, or when the
    dataparser is not one this check knows how to run without side effects.
    """
    if any(value is not None for value in (pipeline.blocks_json, pipeline.only_block, pipeline.run_plan)):
        return
    plan_settings = pipeline.plan_settings
    parser_config = pipeline.datamanager.dataparser
    if getattr(parser_config, "load_3D_points", False):  # any dataparser: only some have the option
        return
    try:
        from nerfstudio.utils.rich_utils import CONSOLE

        from scalar_nerfstudio.blocks.plan import plan_blocks
        from scalar_nerfstudio.blocks.split import BlockSplitError
        from scalar_nerfstudio.data.datamanager import camera_layout
    except ImportError:
        return
    quiet = CONSOLE.quiet
    try:
        CONSOLE.quiet = True  # the dataparser's own log lines come again when the run sets up
        parsed = replace(parser_config, data=Path(data)).setup().get_dataparser_outputs(split="train")
    except Exception:  # noqa: BLE001 - anything the scene check missed is reported by the run itself
        return
    finally:
        CONSOLE.quiet = quiet
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            layout = camera_layout(parsed)
            plan_blocks(layout.centres, layout.directions, layout.focal_px, image_pixels=layout.image_pixels,
                        image_names=[str(p) for p in parsed.image_filenames], settings=plan_settings())
    except BlockSplitError as error:
        asked = "--pipeline.num-blocks " + _show(pipeline.num_blocks) if pipeline.num_blocks is not None else "the automatic number of blocks"
        raise OptionError(
            f"the block split with {asked}, --pipeline.min-images-per-block {pipeline.min_images_per_block} and "
            f"--pipeline.aabb-scale {_show(pipeline.aabb_scale)} fails on these cameras: {error}"
        ) from None


# -------------------------------------------------------------------------------- output folder


def _nearest_existing(path: Path) -> Path:
    for candidate in (path, *path.parents):
        if os.path.lexists(candidate):
            return candidate
    return Path(path.anchor or ".")


def check_output_dir(path: Path, option: str = "--output-dir") -> None:
    """Make sure the run folder ``path`` can be created and written: its nearest existing ancestor
    must be a writable folder (``os.access`` and a real probe file, deleted at once).

    Raises:
        OptionError: naming the folder, why it cannot be written and what to do.
    """
    target = Path(os.path.abspath(path))
    existing = _nearest_existing(target)
    if not existing.is_dir():
        raise OptionError(f"{option}: the run folder {target} cannot be created, because {existing} is a file, not a "
                          f"folder. Choose another {option}.")
    reason = None
    if not os.access(existing, os.W_OK | os.X_OK):
        reason = "it is not writable by this user" if not _read_only(existing) else "it is on a read-only file system"
    else:
        try:
            handle, probe = tempfile.mkstemp(prefix=".scalar-nerf-write-probe-", dir=existing)
            os.close(handle)
            os.unlink(probe)
        except OSError as error:
            reason = {
                errno.EROFS: "it is on a read-only file system",
                errno.EACCES: "it is not writable by this user",
                errno.EPERM: "it is not writable by this user",
                errno.ENOSPC: "its disk is full",
                errno.EDQUOT: "the disk quota is exceeded",
            }.get(error.errno or 0, f"writing there fails ({error.strerror or error})")
    if reason is not None:
        place = f"the folder {existing}" if existing == target else f"{existing} (where the run folder {target} would be created)"
        raise OptionError(f"{option}: nothing can be written to {place}: {reason}. Choose a writable {option}.")


def _read_only(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):
        return False
