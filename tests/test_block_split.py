"""Tests for scalar_nerfstudio.blocks.split (Alg. 1 block splitting)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from prerequisites import CASTLE, need_castle

from scalar_nerfstudio.blocks.split import (
    THIN_AXIS_FRACTION,
    BlockSplit,
    BlockSplitError,
    BlockSplitWarning,
    format_split_table,
    load_blocks_json,
    save_blocks_json,
    split_cameras,
)


def _castle() -> tuple[np.ndarray, list[str]]:
    need_castle()
    frames = json.loads((CASTLE / "transforms.json").read_text())["frames"]
    centres = np.array([np.asarray(f["transform_matrix"], dtype=np.float64)[:3, 3] for f in frames])
    return centres, [Path(f["file_path"]).name for f in frames]


def _membership(split: BlockSplit, num_images: int) -> np.ndarray:
    """[K, N] bool membership matrix."""
    member = np.zeros((len(split.blocks), num_images), dtype=bool)
    for b in split.blocks:
        member[b.index, list(b.image_indices)] = True
    return member


# --------------------------------------------------------------------------- real scene


# castle-P30's 30 cameras form a sparse ring (~5 m between neighbours); with K=4 the
# KMeans arcs' AABBs grown by 10 % per side (s=1.2) do not reach the next arc's cameras,
# so Alg. 1 first produces overlap at s~1.4 there.  That is the algorithm, not a bug.
@pytest.mark.parametrize(("k", "s"), [(2, 1.2), (3, 1.2), (4, 1.2), (4, 1.5)])
def test_castle_cover_overlap_superset_deterministic(k: int, s: float) -> None:
    centres, _ = _castle()
    n = len(centres)
    assert n == 30
    tight = split_cameras(centres, k, aabb_scale=(1.0, 1.0, 1.0), seed=0)
    loose = split_cameras(centres, k, aabb_scale=(s, s, s), seed=0)
    for split in (tight, loose):
        assert len(split.blocks) == k
        member = _membership(split, n)
        assert member.any(axis=0).all(), "every image must be in some block"
        for b in split.blocks:
            assert list(b.image_indices) == sorted(set(b.image_indices))
            assert np.allclose(b.centre, (np.array(b.aabb_min) + np.array(b.aabb_max)) / 2)
            inside = np.all((centres >= b.aabb_min) & (centres <= b.aabb_max), axis=1)
            assert set(np.flatnonzero(inside)) <= set(b.image_indices)
    loose_m, tight_m = _membership(loose, n), _membership(tight, n)
    if (k, s) != (4, 1.2):
        assert (loose_m.sum(axis=0) >= 2).any(), f"s={s} blocks must overlap"
    assert np.all(loose_m >= tight_m), f"s={s} blocks must be supersets of the s=1.0 blocks"
    assert loose_m.sum() > tight_m.sum() or (k, s) == (4, 1.2)
    assert split_cameras(centres, k, aabb_scale=(s, s, s), seed=0) == loose


def test_tight_blocks_contain_their_kmeans_group_and_partition_cover() -> None:
    centres, _ = _castle()
    split = split_cameras(centres, 3, aabb_scale=(1.0, 1.0, 1.0))
    # The union is everything and each block is non-empty.
    assert set().union(*(b.image_indices for b in split.blocks)) == set(range(len(centres)))
    assert all(b.image_indices for b in split.blocks)


def test_per_axis_scale_only_grows_x() -> None:
    centres, _ = _castle()
    base = split_cameras(centres, 3, aabb_scale=(1.0, 1.0, 1.0))
    wide = split_cameras(centres, 3, aabb_scale=(1.5, 1.0, 1.0))
    for b0, b1 in zip(base.blocks, wide.blocks):
        assert b1.aabb_min[0] < b0.aabb_min[0] and b1.aabb_max[0] > b0.aabb_max[0]
        assert b1.aabb_min[1:] == b0.aabb_min[1:] and b1.aabb_max[1:] == b0.aabb_max[1:]
        assert b1.centre == pytest.approx(b0.centre)
        assert set(b0.image_indices) <= set(b1.image_indices)


def test_scale_matches_alg1_diagonal_formula() -> None:
    rng = np.random.default_rng(1)
    centres = rng.uniform(-5, 5, size=(40, 3))
    s = np.array([1.3, 1.1, 1.2])
    split = split_cameras(centres, 1, aabb_scale=s)
    a, b = centres.max(axis=0), centres.min(axis=0)  # Alg. 1: A = max, B = min
    c = (a + b) / 2
    r, length = (a - b) / np.linalg.norm(a - b), np.linalg.norm(b - a) / 2
    assert np.allclose(split.blocks[0].aabb_max, c + s * r * length)
    assert np.allclose(split.blocks[0].aabb_min, c - s * r * length)


def test_seed_is_recorded_and_table_formats() -> None:
    centres, names = _castle()
    split = split_cameras(centres, 3, seed=7)
    assert split.seed == 7 and split.aabb_scale == (1.2, 1.2, 1.2)
    table = format_split_table(split, names)
    assert "3 block(s)" in table and names[split.blocks[0].image_indices[0]] in table
    assert len(table.splitlines()) == 3 + 3
    assert "block" in format_split_table(split)


# --------------------------------------------------------------------------- blocks.json


def test_json_round_trip(tmp_path: Path) -> None:
    centres, names = _castle()
    split = split_cameras(centres, 4, aabb_scale=(1.3, 1.2, 1.1), seed=3)
    path = tmp_path / "sub" / "blocks.json"
    save_blocks_json(split, path, names)
    loaded, loaded_names = load_blocks_json(path)
    assert loaded == split and loaded_names == names
    data = json.loads(path.read_text())
    assert data["num_blocks"] == 4 and data["seed"] == 3 and data["aabb_scale"] == [1.3, 1.2, 1.1]
    block0 = data["blocks"][0]
    assert block0["image_names"] == [names[i] for i in block0["image_indices"]]
    assert {"aabb_min", "aabb_max", "centre"} <= set(block0)
    assert [p.name for p in path.parent.iterdir()] == ["blocks.json"], "no temporary file left behind"


def test_json_errors(tmp_path: Path) -> None:
    centres, names = _castle()
    split = split_cameras(centres, 2)
    with pytest.raises(BlockSplitError, match="image_names has 3 entries"):
        save_blocks_json(split, tmp_path / "b.json", names[:3])
    with pytest.raises(BlockSplitError, match="cannot read"):
        load_blocks_json(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text('{"format": "something-else"}')
    with pytest.raises(BlockSplitError, match="not a scalar-nerf-blocks file"):
        load_blocks_json(tmp_path / "bad.json")
    (tmp_path / "bad2.json").write_text('{"format": "scalar-nerf-blocks", "blocks": []}')
    with pytest.raises(BlockSplitError, match="malformed"):
        load_blocks_json(tmp_path / "bad2.json")


# --------------------------------------------------------------------------- degenerate layouts


def test_all_identical_collapses_to_one_block_with_warning() -> None:
    centres = np.tile([[1.0, 2.0, 3.0]], (6, 1))
    with pytest.warns(BlockSplitWarning, match="1 distinct camera centre"):
        split = split_cameras(centres, 3)
    assert len(split.blocks) == 1
    assert split.blocks[0].image_indices == tuple(range(6))
    assert split.blocks[0].aabb_min == split.blocks[0].aabb_max == (1.0, 2.0, 3.0)


def test_fewer_distinct_than_k_collapses() -> None:
    centres = np.array([[0.0, 0, 0]] * 3 + [[10.0, 0, 0]] * 3)
    with pytest.warns(BlockSplitWarning, match="2 block"):
        split = split_cameras(centres, 4, aabb_scale=(1.0, 1.0, 1.0))
    assert [b.image_indices for b in split.blocks] == [(0, 1, 2), (3, 4, 5)]


def test_no_warning_in_normal_case() -> None:
    centres, _ = _castle()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        split_cameras(centres, 4)


def _courtyard(n: int = 200, seed: int = 0) -> np.ndarray:
    """Cameras scattered over a 40 m x 30 m courtyard at a height of exactly 1.6 m."""
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(0, 40, n), rng.uniform(0, 30, n), np.full(n, 1.6)], axis=1)


def test_exactly_planar_layout_keeps_flat_axis_and_overlaps() -> None:
    centres = _courtyard()
    split = split_cameras(centres, 4, aabb_scale=(1.2, 1.2, 1.2))
    member = _membership(split, len(centres))
    assert member.any(axis=0).all() and (member.sum(axis=0) >= 2).any()
    for b in split.blocks:
        assert b.aabb_min[2] < 1.6 < b.aabb_max[2]


def test_nearly_planar_layout_does_not_drop_neighbours_by_height() -> None:
    flat = _courtyard()
    noisy = flat.copy()
    # Ground rising 8 cm over 40 m plus millimetre jitter: each block's own height range
    # is a thin slab that would miss its neighbours' cameras without thin-axis handling.
    noisy[:, 2] += 0.002 * noisy[:, 0] + np.random.default_rng(1).uniform(-0.005, 0.005, size=len(flat))
    flat_split = split_cameras(flat, 4, seed=0)
    noisy_split = split_cameras(noisy, 4, seed=0)
    # Membership decided by x, y alone, exactly as for the planar layout: no neighbour
    # is dropped because its height differs by millimetres.
    assert [b.image_indices for b in noisy_split.blocks] == [b.image_indices for b in flat_split.blocks]
    member = _membership(noisy_split, len(noisy))
    assert (member.sum(axis=0) >= 2).any()
    for b in noisy_split.blocks:  # the flat axis spans every camera height
        assert b.aabb_min[2] <= noisy[:, 2].min() and b.aabb_max[2] >= noisy[:, 2].max()
    for b0, b1 in zip(flat_split.blocks, noisy_split.blocks):  # x, y bounds untouched by the noise
        assert b1.aabb_min[:2] == pytest.approx(b0.aabb_min[:2], abs=1e-9)


def test_collinear_layout() -> None:
    centres = np.stack([np.linspace(0, 10, 11), np.full(11, 2.0), np.full(11, -1.0)], axis=1)
    split = split_cameras(centres, 3, aabb_scale=(2.0, 2.0, 2.0))
    member = _membership(split, len(centres))
    assert member.any(axis=0).all() and (member.sum(axis=0) >= 2).any()


def test_thin_block_on_split_axis_is_widened_not_whole_layout() -> None:
    # Two rows of cameras far apart in y; each KMeans group is a row with zero y extent.
    row = np.linspace(0, 10, 11)
    centres = np.concatenate(
        [np.stack([row, np.zeros(11), np.zeros(11)], 1), np.stack([row, np.full(11, 10.0), np.zeros(11)], 1)]
    )
    centres[0, 1] += 1e-3  # a millimetre off its row
    split = split_cameras(centres, 2, aabb_scale=(1.2, 1.2, 1.2))
    assert [len(b.image_indices) for b in split.blocks] == [11, 11]
    for b in split.blocks:
        assert b.aabb_max[1] - b.aabb_min[1] == pytest.approx(1.2 * THIN_AXIS_FRACTION * 10.0, rel=1e-6)


def test_single_camera_groups_stay_small() -> None:
    centres = np.array([[0.0, 0, 0], [10.0, 0, 0], [0.0, 10, 0], [10.0, 10, 0]])
    split = split_cameras(centres, 4, aabb_scale=(1.2, 1.2, 1.2))
    assert sorted(b.image_indices for b in split.blocks) == [(0,), (1,), (2,), (3,)]


@pytest.mark.parametrize(
    ("centres", "k", "match"),
    [
        (np.zeros((0, 3)), 1, "N == 0"),
        (np.zeros((5, 2)), 1, r"shape \[N, 3\], got \[5, 2\]"),
        (np.zeros(3), 1, r"shape \[N, 3\], got \[3\]"),
        (np.array([[0.0, 0, 0], [np.nan, 0, 0], [1, np.inf, 0]]), 1, "NaN/inf in 2 of 3 rows"),
        (np.random.default_rng(0).normal(size=(5, 3)), 6, r"num_blocks \(6\) is larger than the number of images \(5\)"),
        (np.random.default_rng(0).normal(size=(5, 3)), 0, "num_blocks must be >= 1, got 0"),
        (np.random.default_rng(0).normal(size=(5, 3)), -2, "num_blocks must be >= 1, got -2"),
        (np.random.default_rng(0).normal(size=(5, 3)), 2.5, "num_blocks must be an integer"),
    ],
)
def test_invalid_inputs(centres: np.ndarray, k: int, match: str) -> None:
    with pytest.raises(BlockSplitError, match=match):
        split_cameras(centres, k)


@pytest.mark.parametrize(
    ("scale", "match"),
    [((1.2, 1.2), "3 entries"), ((0.5, 1.0, 1.0), ">= 1.0"), ((np.nan, 1.0, 1.0), "finite"), ("abc", "three numbers")],
)
def test_invalid_scale(scale: object, match: str) -> None:
    with pytest.raises(BlockSplitError, match=match):
        split_cameras(np.random.default_rng(0).normal(size=(5, 3)), 2, aabb_scale=scale)  # type: ignore[arg-type]


def test_min_images_per_block_error() -> None:
    centres = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0], [50.0, 0, 0]])
    with pytest.raises(BlockSplitError, match=r"min_images_per_block=2.*block 1: 1 image\(s\)"):
        split_cameras(centres, 2, aabb_scale=(1.0, 1.0, 1.0), min_images_per_block=2)
    assert len(split_cameras(centres, 2, min_images_per_block=1).blocks) == 2
    with pytest.raises(BlockSplitError, match="min_images_per_block must be >= 1"):
        split_cameras(centres, 2, min_images_per_block=0)


def test_invalid_seed() -> None:
    with pytest.raises(BlockSplitError, match="seed must be an integer"):
        split_cameras(np.random.default_rng(0).normal(size=(5, 3)), 2, seed=None)  # type: ignore[arg-type]
