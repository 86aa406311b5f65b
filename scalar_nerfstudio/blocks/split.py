"""Block splitting of the training cameras (SCALAR-NeRF Sec. 3.3, Alg. 1).

Algorithm
---------
1. KMeans (scikit-learn, fixed ``seed`` and ``n_init``) on the camera centres gives
   K disjoint groups ("KMeans groups").
2. Each group's camera AABB ``[min, max]`` is scaled about its centre, per axis, by
   ``aabb_scale`` (half-extent * s).  Alg. 1 writes this with the AABB diagonal,
   ``C +/- s * r * len`` with ``r * len = (A - B) / 2``, which is exactly the per-axis
   half-extent times ``s``.
3. Every image whose camera centre lies inside a scaled AABB (bounds inclusive) joins
   that block, so blocks overlap when ``s > 1``.

With ``s == 1`` every block is *at least* its KMeans group; the AABBs of different
groups may still contain each other's cameras (KMeans cells are Voronoi cells, not
boxes), so blocks can overlap even at ``s == 1``.  That is the algorithm as published
and is kept deliberately.  Every image is in at least one block (its own group's); the
group members are added explicitly, so no floating-point rounding of the scaled bounds
can drop them.

Degenerate layouts (all decisions are deliberate and tested)
-----------------------------------------------------------
* Wrong shape, ``N == 0``, NaN/inf centres, ``num_blocks < 1`` or ``> N``, a scale
  that is not three finite numbers ``>= 1``, ``min_images_per_block < 1``, a seed that
  is not an integer in ``[0, 2**32)``:
  :class:`BlockSplitError` naming the problem and the numbers.
* Fewer *distinct* camera centres than ``num_blocks`` (e.g. all cameras identical):
  KMeans cannot produce that many non-empty clusters, so K is reduced to the number of
  distinct centres and a :class:`BlockSplitWarning` is emitted; ``len(split.blocks)``
  is then smaller than ``num_blocks``.  (All cameras identical -> one block holding
  every image.)
* Thin axes (collinear / planar / nearly planar layouts, e.g. a courtyard whose camera
  heights vary by centimetres).  Let ``L`` be the largest extent of the whole layout
  and ``t = THIN_AXIS_FRACTION * L`` (5 %).

  - An axis on which the *whole layout* is thinner than ``t`` is not a split axis:
    every block spans the whole layout's range on it (at least ``t`` wide), scaled by
    ``s``.  Cameras differing by millimetres on that axis are never dropped.
  - On the other axes a *block* thinner than ``t`` (e.g. a single-camera group or a
    row of cameras) is widened to ``t`` about its centre before scaling, so its
    neighbours within ``s * t / 2`` are still picked up instead of a zero-width box.
    (It is *not* widened to the whole layout: that would turn every small block into
    the whole scene.)
* A block ending with fewer than ``min_images_per_block`` images:
  :class:`BlockSplitError` (no silent merge), naming the block and the counts and
  suggesting fewer blocks or a larger scale.

Blocks are ordered canonically by the smallest image index of their KMeans group, so
the result does not depend on KMeans' arbitrary label numbering.
"""

from __future__ import annotations

import json
import warnings
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from scalar_nerfstudio.atomic_io import atomic_write_text
from scalar_nerfstudio.runs import RUN_SCHEMA_VERSION, RunSchemaError, upgrade_blocks_json

__all__ = [
    "KMEANS_N_INIT",
    "THIN_AXIS_FRACTION",
    "Block",
    "BlockSplit",
    "BlockSplitError",
    "BlockSplitWarning",
    "format_split_table",
    "load_blocks_json",
    "save_blocks_json",
    "split_to_json",
    "split_cameras",
]

#: An axis thinner than this fraction of the layout's largest extent is "thin".
THIN_AXIS_FRACTION: float = 0.05
#: Number of KMeans restarts (fixed, so the split is reproducible for a given seed).
KMEANS_N_INIT: int = 10
#: Identifier and version written to blocks.json (the run's schema version, ``runs.py``).
BLOCKS_JSON_FORMAT: str = "scalar-nerf-blocks"
BLOCKS_JSON_VERSION: int = RUN_SCHEMA_VERSION

Vec3 = tuple[float, float, float]


class BlockSplitError(ValueError):
    """Invalid input to, or impossible result of, the block split."""


class BlockSplitWarning(UserWarning):
    """The split had to deviate from the request (e.g. fewer blocks than asked)."""


@dataclass(frozen=True)
class Block:
    """One (possibly overlapping) block of training images.

    Attributes:
        index: Block index, ``0..K-1``.
        image_indices: Sorted indices into the training images given to ``split_cameras``.
        aabb_min: Scaled AABB minimum corner, world units of the camera centres.
        aabb_max: Scaled AABB maximum corner, world units of the camera centres.
        centre: Centre of the scaled AABB, world units.
    """

    index: int
    image_indices: tuple[int, ...]
    aabb_min: Vec3
    aabb_max: Vec3
    centre: Vec3


@dataclass(frozen=True)
class BlockSplit:
    """Result of :func:`split_cameras`.

    Attributes:
        blocks: The blocks, ordered by the smallest image index of their KMeans group.
        aabb_scale: Per-axis AABB scale factor ``(s_x, s_y, s_z)``.
        seed: KMeans random seed.
    """

    blocks: tuple[Block, ...]
    aabb_scale: Vec3
    seed: int

    @property
    def num_blocks(self) -> int:
        """Number of blocks actually produced."""
        return len(self.blocks)


# --------------------------------------------------------------------------- validation


def _validate_centres(camera_centres: np.ndarray) -> np.ndarray:
    """Return the centres as a float64 ``[N, 3]`` array or raise BlockSplitError."""
    try:
        centres = np.asarray(camera_centres, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise BlockSplitError(f"camera_centres must be numeric, got {type(camera_centres).__name__}: {exc}") from exc
    if centres.ndim != 2 or centres.shape[1] != 3:
        raise BlockSplitError(f"camera_centres must have shape [N, 3], got {list(centres.shape)}")
    if centres.shape[0] == 0:
        raise BlockSplitError("camera_centres is empty (N == 0): cannot split zero images into blocks")
    bad_rows = np.flatnonzero(~np.isfinite(centres).all(axis=1))
    if bad_rows.size:
        shown = ", ".join(str(i) for i in bad_rows[:10]) + (", ..." if bad_rows.size > 10 else "")
        raise BlockSplitError(f"camera_centres has NaN/inf in {bad_rows.size} of {centres.shape[0]} rows (images {shown})")
    return centres


def _validate_scale(aabb_scale: Sequence[float]) -> Vec3:
    """Return the scale as three floats ``>= 1`` or raise BlockSplitError."""
    try:
        scale = tuple(float(s) for s in aabb_scale)
    except (TypeError, ValueError) as exc:
        raise BlockSplitError(f"aabb_scale must be three numbers, got {aabb_scale!r}") from exc
    if len(scale) != 3:
        raise BlockSplitError(f"aabb_scale must have 3 entries (s_x, s_y, s_z), got {len(scale)}: {aabb_scale!r}")
    if not all(np.isfinite(s) and s >= 1.0 for s in scale):
        raise BlockSplitError(
            f"aabb_scale entries must be finite and >= 1.0 (s < 1 would shrink a block below its own cameras), got {scale}"
        )
    return (scale[0], scale[1], scale[2])


def _validate_counts(num_blocks: int, num_images: int, min_images_per_block: int) -> None:
    """Raise BlockSplitError for an impossible number of blocks or minimum block size."""
    if isinstance(num_blocks, bool) or not isinstance(num_blocks, (int, np.integer)):
        raise BlockSplitError(f"num_blocks must be an integer, got {num_blocks!r}")
    if num_blocks < 1:
        raise BlockSplitError(f"num_blocks must be >= 1, got {num_blocks}")
    if num_blocks > num_images:
        raise BlockSplitError(f"num_blocks ({num_blocks}) is larger than the number of images ({num_images})")
    if isinstance(min_images_per_block, bool) or not isinstance(min_images_per_block, (int, np.integer)):
        raise BlockSplitError(f"min_images_per_block must be an integer, got {min_images_per_block!r}")
    if min_images_per_block < 1:
        raise BlockSplitError(f"min_images_per_block must be >= 1, got {min_images_per_block}")


def _validate_seed(seed: int) -> int:
    """Return ``seed`` as a non-negative int (KMeans' random_state) or raise BlockSplitError."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**32:
        raise BlockSplitError(f"seed must be an integer in [0, 2**32), got {seed!r}")
    return int(seed)


# --------------------------------------------------------------------------- algorithm


def _kmeans_groups(centres: np.ndarray, num_blocks: int, seed: int) -> list[np.ndarray]:
    """Cluster ``centres`` [N, 3] into disjoint groups of image indices.

    K is reduced (with a warning) when there are fewer distinct centres than blocks.
    Groups are returned sorted by their smallest image index; none is empty.
    """
    num_distinct = np.unique(centres, axis=0).shape[0]
    k = num_blocks
    if num_distinct < num_blocks:
        warnings.warn(
            f"only {num_distinct} distinct camera centre(s) among {centres.shape[0]} images; "
            f"splitting into {num_distinct} block(s) instead of the requested {num_blocks}",
            BlockSplitWarning,
            stacklevel=3,
        )
        k = num_distinct
    if k == 1:
        labels = np.zeros(centres.shape[0], dtype=np.int64)
    else:
        from sklearn.cluster import KMeans  # here: importing scikit-learn takes seconds, and only a split needs it

        kmeans = KMeans(
            n_clusters=k,
            n_init=KMEANS_N_INIT,  # pyright: ignore[reportArgumentType]  # sklearn: int | "auto", inferred str
            random_state=seed,
            algorithm="lloyd",
        )
        labels = kmeans.fit_predict(centres)
    groups = [np.flatnonzero(labels == label) for label in np.unique(labels)]
    return sorted((g for g in groups if g.size > 0), key=lambda g: int(g[0]))


def _layout_stats(centres: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Layout statistics: (thin threshold t, layout min [3], layout max [3], thin-axis mask [3])."""
    lo, hi = centres.min(axis=0), centres.max(axis=0)
    thin = THIN_AXIS_FRACTION * float((hi - lo).max())
    return thin, lo, hi, (hi - lo) < thin


def _scaled_aabb(
    members: np.ndarray, scale: np.ndarray, *, thin: float, layout_lo: np.ndarray, layout_hi: np.ndarray, flat: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Scaled AABB (min [3], max [3]) of one group's camera centres ``members`` [M, 3].

    Layout-flat axes use the whole layout range; thin block axes are widened to ``thin``.
    The raw group bounds are always kept inside the result.
    """
    raw_lo, raw_hi = members.min(axis=0), members.max(axis=0)
    lo = np.where(flat, layout_lo, raw_lo)
    hi = np.where(flat, layout_hi, raw_hi)
    centre = (lo + hi) / 2.0
    half = np.maximum((hi - lo) / 2.0, thin / 2.0)
    out_lo = np.minimum(centre - scale * half, raw_lo)
    out_hi = np.maximum(centre + scale * half, raw_hi)
    return out_lo, out_hi


def _to_vec3(values: np.ndarray) -> Vec3:
    """Convert a length-3 array to a tuple of Python floats."""
    return (float(values[0]), float(values[1]), float(values[2]))


def split_cameras(
    camera_centres: np.ndarray,
    num_blocks: int,
    *,
    aabb_scale: Sequence[float] = (1.2, 1.2, 1.2),
    seed: int = 0,
    min_images_per_block: int = 1,
    min_overlap_images: int = 0,
) -> BlockSplit:
    """Split training images into overlapping blocks (Alg. 1).

    Args:
        camera_centres: ``[N, 3]`` camera centres in world units (e.g. ``transform_matrix[:3, 3]``).
        num_blocks: Requested number of blocks K (``1 <= K <= N``); may be reduced, with a
            :class:`BlockSplitWarning`, when there are fewer distinct centres than K.
        aabb_scale: Per-axis scale ``(s_x, s_y, s_z)``, each ``>= 1``, of each group's AABB.
        seed: KMeans random seed.
        min_images_per_block: Minimum number of images a final block must hold.
        min_overlap_images: With any scale > 1, a block whose scaled AABB takes in fewer images of
            other groups than this is grown further, uniformly about its centre, until it does
            (sparse layouts, e.g. a ring of cameras, leave gaps wider than 10 % of a block). 0 is
            Alg. 1 verbatim; scale 1 never grows a block.

    Returns:
        The :class:`BlockSplit`; every image is in at least one block.

    Raises:
        BlockSplitError: On invalid input or a block smaller than ``min_images_per_block``.
    """
    centres = _validate_centres(camera_centres)
    scale = _validate_scale(aabb_scale)
    _validate_counts(num_blocks, centres.shape[0], min_images_per_block)
    seed = _validate_seed(seed)
    groups = _kmeans_groups(centres, int(num_blocks), seed)
    thin, layout_lo, layout_hi, flat = _layout_stats(centres)
    scale_arr = np.asarray(scale, dtype=np.float64)
    blocks = []
    for index, group in enumerate(groups):
        lo, hi = _scaled_aabb(centres[group], scale_arr, thin=thin, layout_lo=layout_lo, layout_hi=layout_hi, flat=flat)
        if min_overlap_images > 0 and (scale_arr > 1.0).any() and len(groups) > 1:
            lo, hi = _grow_to_overlap(centres, group, lo, hi, min_overlap_images)
        inside = np.all((centres >= lo) & (centres <= hi), axis=1)
        inside[group] = True
        members = tuple(int(i) for i in np.flatnonzero(inside))
        blocks.append(Block(index, members, _to_vec3(lo), _to_vec3(hi), _to_vec3((lo + hi) / 2.0)))
    _check_min_size(blocks, min_images_per_block, int(num_blocks), centres.shape[0])
    return BlockSplit(blocks=tuple(blocks), aabb_scale=scale, seed=seed)


def _grow_to_overlap(
    centres: np.ndarray, group: np.ndarray, lo: np.ndarray, hi: np.ndarray, min_overlap: int
) -> tuple[np.ndarray, np.ndarray]:
    """Grow the box [lo, hi] about its centre until it holds ``min_overlap`` cameras not in ``group``."""
    others = np.setdiff1d(np.arange(centres.shape[0]), group)
    if others.size == 0:
        return lo, hi
    centre, half = (lo + hi) / 2.0, np.maximum((hi - lo) / 2.0, 1e-12)
    factors = np.max(np.abs(centres[others] - centre) / half, axis=1)  # growth that takes each camera in
    needed = np.sort(factors)[min(min_overlap, factors.size) - 1]
    if needed <= 1.0:
        return lo, hi
    grown = half * needed * (1.0 + 1e-9)
    return np.minimum(centre - grown, lo), np.maximum(centre + grown, hi)


def _check_min_size(blocks: Sequence[Block], min_images: int, num_blocks: int, num_images: int) -> None:
    """Raise BlockSplitError if any block has fewer than ``min_images`` images."""
    small = [(b.index, len(b.image_indices)) for b in blocks if len(b.image_indices) < min_images]
    if small:
        detail = ", ".join(f"block {i}: {n} image(s)" for i, n in small)
        raise BlockSplitError(
            f"{len(small)} block(s) have fewer than min_images_per_block={min_images} images ({detail}); "
            f"{num_images} images split into {num_blocks} blocks. Use fewer blocks or a larger aabb_scale."
        )


# --------------------------------------------------------------------------- blocks.json


def split_to_json(split: BlockSplit, image_names: Sequence[str]) -> dict[str, Any]:
    """Serialisable dict of ``split`` with the image names of all training images."""
    names = [str(n) for n in image_names]
    max_index = max((max(b.image_indices) for b in split.blocks if b.image_indices), default=-1)
    if max_index >= len(names):
        raise BlockSplitError(f"image_names has {len(names)} entries but the split refers to image index {max_index}")
    blocks = [
        {
            "index": b.index,
            "num_images": len(b.image_indices),
            "image_indices": list(b.image_indices),
            "image_names": [names[i] for i in b.image_indices],
            "aabb_min": list(b.aabb_min),
            "aabb_max": list(b.aabb_max),
            "centre": list(b.centre),
        }
        for b in split.blocks
    ]
    return {
        "format": BLOCKS_JSON_FORMAT,
        "version": BLOCKS_JSON_VERSION,
        "num_blocks": split.num_blocks,
        "aabb_scale": list(split.aabb_scale),
        "seed": split.seed,
        "image_names": names,
        "blocks": blocks,
    }


def save_blocks_json(split: BlockSplit, path: Path, image_names: Sequence[str]) -> None:
    """Write ``split`` to ``path`` (blocks.json) atomically (:func:`atomic_write_text`).

    Args:
        split: The split to save.
        path: Destination file; its parent directory is created if needed.
        image_names: File names of all training images, indexed like ``Block.image_indices``.
    """
    atomic_write_text(Path(path), json.dumps(split_to_json(split, image_names), indent=2) + "\n")


def _vec3(value: Any, what: str) -> Vec3:
    """Parse a JSON list of three numbers."""
    if not isinstance(value, list) or len(value) != 3:
        raise BlockSplitError(f"{what} must be a list of 3 numbers, got {value!r}")
    return (float(value[0]), float(value[1]), float(value[2]))


def _block_from_json(entry: dict[str, Any], num_images: int) -> Block:
    """Parse one block entry of blocks.json."""
    indices = tuple(int(i) for i in entry["image_indices"])
    if any(i < 0 or i >= num_images for i in indices):
        raise BlockSplitError(f"block {entry['index']} refers to an image index outside [0, {num_images})")
    return Block(
        index=int(entry["index"]),
        image_indices=indices,
        aabb_min=_vec3(entry["aabb_min"], "aabb_min"),
        aabb_max=_vec3(entry["aabb_max"], "aabb_max"),
        centre=_vec3(entry["centre"], "centre"),
    )


def load_blocks_json(path: Path) -> tuple[BlockSplit, list[str]]:
    """Read a blocks.json written by :func:`save_blocks_json`.

    Returns:
        ``(split, image_names)`` where ``image_names`` lists all training images.

    Raises:
        BlockSplitError: If the file is missing, not JSON, not a valid blocks file, or written by a
            newer version (a file of an older version is upgraded, ``runs.upgrade_blocks_json``).
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise BlockSplitError(f"cannot read blocks file {path}: {exc}") from exc
    try:
        if data.get("format") != BLOCKS_JSON_FORMAT:
            raise BlockSplitError(f"{path} is not a {BLOCKS_JSON_FORMAT} file (format={data.get('format')!r})")
        data = upgrade_blocks_json(data, path)
        names = [str(n) for n in data["image_names"]]
        blocks = tuple(_block_from_json(entry, len(names)) for entry in data["blocks"])
        if int(data["num_blocks"]) != len(blocks):
            raise BlockSplitError(f"{path}: num_blocks={data['num_blocks']} but {len(blocks)} blocks are listed")
        split = BlockSplit(blocks=blocks, aabb_scale=_vec3(data["aabb_scale"], "aabb_scale"), seed=int(data["seed"]))
    except RunSchemaError as exc:
        raise BlockSplitError(str(exc)) from None
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        if isinstance(exc, BlockSplitError):
            raise
        raise BlockSplitError(f"malformed blocks file {path}: {exc!r}") from exc
    return split, names


# --------------------------------------------------------------------------- reporting


def _names_preview(block: Block, image_names: Sequence[str], limit: int = 3) -> str:
    """A few image names of ``block``, e.g. ``a.png, b.png, c.png, +4``."""
    names = [str(image_names[i]) for i in block.image_indices[:limit]]
    rest = len(block.image_indices) - len(names)
    return ", ".join(names) + (f", +{rest}" if rest > 0 else "")


def format_split_table(split: BlockSplit, image_names: Sequence[str] | None = None) -> str:
    """Short human-readable table: block, #images, AABB centre, AABB extent (and a few names)."""
    header = f"{'block':>5}  {'#img':>5}  {'centre (x, y, z)':>28}  {'extent (dx, dy, dz)':>28}"
    if image_names is not None:
        header += "  images"
    lines = [
        f"{split.num_blocks} block(s), aabb_scale={tuple(round(s, 4) for s in split.aabb_scale)}, seed={split.seed}",
        header,
    ]
    for b in split.blocks:
        extent = tuple(hi - lo for lo, hi in zip(b.aabb_min, b.aabb_max))
        centre = ", ".join(f"{v:8.3f}" for v in b.centre)
        ext = ", ".join(f"{v:8.3f}" for v in extent)
        line = f"{b.index:>5}  {len(b.image_indices):>5}  {centre:>28}  {ext:>28}"
        if image_names is not None:
            line += "  " + _names_preview(b, image_names)
        lines.append(line)
    counts = Counter(i for b in split.blocks for i in b.image_indices)
    shared = sum(1 for c in counts.values() if c > 1)
    lines.append(f"{len(counts)} image(s) covered, {shared} in more than one block")
    return "\n".join(lines)
