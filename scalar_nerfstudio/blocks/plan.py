"""The block plan of a run: everything a run decides about its own shape, decided once.

A run's shape is its number of blocks K (given, or automatic from the camera layout), the split of
its training images into blocks (Alg. 1), which blocks its model holds, and each block's table size
and finest resolution (``blocks/capacity.py``), plus the sphere its rays end at (:class:`SceneBound`,
fitted to the depth images by the pipeline). :func:`plan_blocks` decides the shape from the
parsed training cameras; :func:`save_plan` writes it into the run's ``blocks.json`` and
:func:`load_plan` reads it back, so that every later use of the run (resume, ``ns-eval``,
``ns-render`` in any mode, the viewer, ``ns-export``) builds exactly the model that was trained,
whatever the dataparser reports in that mode (``ns-render``'s inference mode parses the cameras at
full resolution, which would change an automatic K).

Pure numpy: no torch or nerfstudio import, so it is tested on its own.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Tuple

import numpy as np

from scalar_nerfstudio.atomic_io import atomic_write_text
from scalar_nerfstudio.blocks.capacity import BlockCapacity, LayoutScale, auto_num_blocks, block_capacity, layout_scale
from scalar_nerfstudio.blocks.length import LengthError, TrainingLength, length_from_json, length_to_json
from scalar_nerfstudio.blocks.split import BlockSplit, BlockSplitError, load_blocks_json, split_cameras, split_to_json

__all__ = ["BlockPlan", "PlanSettings", "SceneBound", "load_plan", "plan_blocks", "recorded_scene_bound", "save_plan"]


@dataclass(frozen=True)
class PlanSettings:
    """The options a plan is decided from (the pipeline config's block options)."""

    num_blocks: Optional[int] = None
    """K; None: automatic, ``ceil(R^2 / T)`` (blocks/capacity.py)."""
    log2_hashmap_size: int = 19
    """log2 rows of the global model's table (T of the automatic K)."""
    max_auto_blocks: int = 64
    auto_min_images_per_block: int = 6
    aabb_scale: Tuple[float, float, float] = (1.2, 1.2, 1.2)
    split_seed: int = 0
    min_images_per_block: int = 2
    min_overlap_images: int = 1
    only_block: Optional[int] = None
    """Hold this one block only (a ``scalar-nerf-block`` run)."""
    block_log2_hashmap_size: Optional[int] = None
    block_log2_hashmap_bounds: Tuple[int, int] = (14, 19)
    block_max_resolution: Optional[int] = None
    block_max_resolution_bounds: Tuple[int, int] = (64, 2048)
    global_max_resolution: Optional[int] = None
    """The global model's finest resolution; given: every block copies the global model's table size
    and finest resolution (``--pipeline.block-init global``) instead of sizing its own."""


@dataclass(frozen=True)
class SceneBound:
    """The sphere a run's rays end at, as the run decided it when it started (recorded in its blocks.json)."""

    radius: Optional[float]
    """Radius around the origin (world units of the normalised scene); None: unbounded rays."""


@dataclass(frozen=True)
class BlockPlan:
    """What a run decided about its shape.

    Attributes:
        split: the blocks of the training images (indices into ``image_names``).
        image_names: the training images, as stored in blocks.json.
        layout: how large the camera layout looks at the training resolution.
        auto_num_blocks: the automatic K, when K was not given (None: given, or the split was).
        held_blocks: blocks the model allocates (none when the automatic K is 1).
        capacities: table size and finest resolution of each held block.
        length: how long the run trains (blocks/length.py); None in a run from before lengths were planned
            (its config.yml gives the steps).
        scene_bound: the sphere its rays end at (fitted to the depth images, or none); None in a run
            from before bounds were recorded here (its config.yml gives the radius, if any).
    """

    split: BlockSplit
    image_names: Tuple[str, ...]
    layout: LayoutScale
    auto_num_blocks: Optional[int]
    held_blocks: Tuple[int, ...]
    capacities: Dict[int, BlockCapacity]
    length: Optional[TrainingLength] = None
    scene_bound: Optional[SceneBound] = None

    def bounded(self, radius: Optional[float]) -> "BlockPlan":
        """This plan, its rays ending at the sphere of ``radius`` (None: unbounded)."""
        return replace(self, scene_bound=SceneBound(radius))

    @property
    def single_model(self) -> bool:
        """The automatic K is 1: one block would repeat the global model, so none is trained."""
        return self.auto_num_blocks == 1


def _held_blocks(split: BlockSplit, only_block: Optional[int]) -> Tuple[int, ...]:
    if only_block is None:
        return tuple(range(split.num_blocks))
    if not 0 <= only_block < split.num_blocks:
        raise BlockSplitError(f"block {only_block} does not exist: the split has blocks 0..{split.num_blocks - 1}")
    return (only_block,)


def plan_blocks(
    centres: np.ndarray,
    directions: np.ndarray,
    focal_px: np.ndarray,
    *,
    image_pixels: Sequence[int],
    image_names: Sequence[str],
    settings: PlanSettings,
    given_split: Optional[BlockSplit] = None,
) -> BlockPlan:
    """Decide a run's shape from its training cameras.

    Args:
        centres: [N, 3] camera centres (the dataparser's frame).
        directions: [N, 3] optical axes.
        focal_px: [N] focal lengths in training pixels.
        image_pixels: [N] pixels of each training image.
        image_names: [N] training image names (as stored in blocks.json).
        settings: the block options.
        given_split: use this split (another run's blocks.json) instead of computing one.
    """
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    if not len(centres) == len(image_pixels) == len(image_names):
        raise ValueError(f"plan_blocks: {len(centres)} cameras, {len(image_pixels)} pixel counts, {len(image_names)} names")
    layout = layout_scale(centres, directions, focal_px)
    auto: Optional[int] = None
    if given_split is None:
        num_blocks = settings.num_blocks
        if num_blocks is None and settings.only_block is None:
            auto = auto_num_blocks(layout, log2_hashmap_size=settings.log2_hashmap_size, num_images=len(centres),
                                   min_images_per_block=settings.auto_min_images_per_block, max_blocks=settings.max_auto_blocks)
            num_blocks = auto
        split = split_cameras(
            centres, num_blocks if num_blocks is not None else 1, aabb_scale=settings.aabb_scale, seed=settings.split_seed,
            min_images_per_block=settings.min_images_per_block, min_overlap_images=settings.min_overlap_images,
        )
    else:
        split = given_split
    held = () if auto == 1 else _held_blocks(split, settings.only_block)
    capacities = {}
    for index in held:
        if settings.global_max_resolution is not None:  # blocks start as copies of the global model
            capacities[index] = BlockCapacity(log2_hashmap_size=settings.log2_hashmap_size, max_resolution=settings.global_max_resolution)
            continue
        block = split.blocks[index]
        extent = max(hi - lo for lo, hi in zip(block.aabb_min, block.aabb_max))
        chosen = block_capacity(
            layout, block_extent=extent, block_pixels=int(sum(image_pixels[i] for i in block.image_indices)),
            log2_hashmap_bounds=settings.block_log2_hashmap_bounds, max_resolution_bounds=settings.block_max_resolution_bounds,
        )
        capacities[index] = BlockCapacity(
            log2_hashmap_size=chosen.log2_hashmap_size if settings.block_log2_hashmap_size is None else settings.block_log2_hashmap_size,
            max_resolution=chosen.max_resolution if settings.block_max_resolution is None else settings.block_max_resolution,
        )
    return BlockPlan(split=split, image_names=tuple(str(n) for n in image_names), layout=layout, auto_num_blocks=auto,
                     held_blocks=held, capacities=capacities)


def save_plan(plan: BlockPlan, path: Path) -> None:
    """Write ``plan`` as a blocks.json (the split, readable by :func:`load_blocks_json`, plus the plan), atomically."""
    content = split_to_json(plan.split, plan.image_names)
    content["plan"] = {
        "auto_num_blocks": plan.auto_num_blocks,
        "held_blocks": list(plan.held_blocks),
        "capacities": {str(k): asdict(c) for k, c in sorted(plan.capacities.items())},
        "layout": asdict(plan.layout),
    }
    if plan.length is not None:
        content["plan"]["length"] = length_to_json(plan.length)
    if plan.scene_bound is not None:
        content["plan"]["scene_radius"] = plan.scene_bound.radius
    atomic_write_text(Path(path), json.dumps(content, indent=2) + "\n")


def load_plan(path: Path) -> BlockPlan:
    """Read the plan :func:`save_plan` wrote.

    Raises:
        BlockSplitError: the file is missing, malformed or newer than this code, or it holds a split
            but no plan (a split file, or a run's from before plans were saved: such a run's
            config.yml records no ``run_plan``, and its plan is decided again from its cameras).
    """
    path = Path(path)
    split, names = load_blocks_json(path)
    content: Dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    saved = content.get("plan")
    if not isinstance(saved, dict):
        raise BlockSplitError(f"{path} holds a block split but no plan (a split file, or a run's from before plans were saved)")
    try:
        held = tuple(int(k) for k in saved["held_blocks"])
        capacities = {int(k): BlockCapacity(**v) for k, v in saved["capacities"].items()}
        layout = LayoutScale(**saved["layout"])
        auto = saved["auto_num_blocks"]
        auto = None if auto is None else int(auto)
        length = None if saved.get("length") is None else length_from_json(saved["length"])
        bound = _scene_bound(saved)
    except (KeyError, TypeError, ValueError, LengthError) as error:
        raise BlockSplitError(f"malformed plan in {path}: {error!r}") from None
    if any(not 0 <= k < split.num_blocks for k in held) or set(capacities) != set(held):
        raise BlockSplitError(f"malformed plan in {path}: held blocks {list(held)} and capacities {sorted(capacities)} disagree with {split.num_blocks} blocks")
    return BlockPlan(split=split, image_names=tuple(names), layout=layout, auto_num_blocks=auto, held_blocks=held,
                     capacities=capacities, length=length, scene_bound=bound)


def _scene_bound(saved: Dict[str, Any]) -> Optional[SceneBound]:
    """The bound a saved plan records (None: it records none, a plan from before bounds were recorded)."""
    if "scene_radius" not in saved:
        return None
    radius = saved["scene_radius"]
    if radius is not None and (isinstance(radius, bool) or not isinstance(radius, (int, float))
                               or not (math.isfinite(radius) and radius > 0)):
        raise ValueError(f"scene_radius {radius!r}: must be a finite number > 0, or null (unbounded)")
    return SceneBound(None if radius is None else float(radius))


def recorded_scene_bound(path: Path) -> Optional[SceneBound]:
    """The bound recorded in the blocks.json at ``path`` (another run's, such as the global run of a
    ``scalar-nerf-block`` run); None: the file records no plan or no bound.

    Raises:
        BlockSplitError: the file is missing, malformed or newer than this code.
    """
    path = Path(path)
    load_blocks_json(path)  # checks the file and its version
    saved = json.loads(path.read_text(encoding="utf-8")).get("plan")
    if not isinstance(saved, dict):
        return None
    try:
        return _scene_bound(saved)
    except ValueError as error:
        raise BlockSplitError(f"malformed plan in {path}: {error}") from None
