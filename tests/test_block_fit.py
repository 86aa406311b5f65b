"""A block's table fitted to the global model (``--pipeline.block-init fitted``, models/block_fit.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import tiny_trainer

from scalar_nerfstudio.encodings import HashGridEncoding
from scalar_nerfstudio.models.block_fit import fit_encoding, occupied_cell_sampler
from scalar_nerfstudio.models.scalar_model import EVAL_BACKGROUND


def _grid(seed: int, scale: float, log2_hashmap_size: int = 10) -> HashGridEncoding:
    torch.manual_seed(seed)
    grid = HashGridEncoding(num_levels=4, features_per_level=4, log2_hashmap_size=log2_hashmap_size, base_resolution=4, max_resolution=32)
    with torch.no_grad():
        grid.table.uniform_(-scale, scale)
    return grid


def _uniform_points(generator: torch.Generator):
    return lambda count: torch.rand(count, 3, generator=generator)


@pytest.mark.parametrize("student_frame", ["same", "finer"])
def test_fit_reproduces_a_teacher_the_student_can_represent(student_frame: str) -> None:
    """A student over the same cube, or over the middle half of the teacher's cube (a block: cells half
    as large, so 8x as many cells: a table large enough not to collide), learns the teacher's encoding
    there: the error falls to a small part of its variance."""
    teacher, student = _grid(0, 0.5), _grid(1, 1e-4, log2_hashmap_size=10 if student_frame == "same" else 15)
    generator = torch.Generator().manual_seed(2)
    if student_frame == "same":
        to_student, sample = (lambda p: p), _uniform_points(generator)
    else:
        to_student, sample = (lambda p: (p - 0.5) * 2.0 + 0.5), (lambda count: 0.25 + 0.5 * torch.rand(count, 3, generator=generator))
    fit = fit_encoding(student, student_unit=to_student, teacher=teacher, teacher_unit=lambda p: p, sample_points=sample, steps=300,
                       points_per_step=16384, learning_rate=2e-2)
    assert fit.steps == 300
    assert fit.initial_error > 0.01  # the teacher's features: uniform in +-0.5, interpolated (variance ~0.025)
    assert fit.final_error < (0.01 if student_frame == "same" else 0.1) * fit.initial_error, fit  # finer cells: not aligned with the teacher's


def test_a_coarser_student_cannot_follow_the_teacher() -> None:
    """The other way round (a block's contracted outside, seen from the global frame) a fit leaves most
    of the error: what the fit reports is measured, not assumed."""
    teacher, student = _grid(0, 0.5), _grid(1, 1e-4)
    fit = fit_encoding(student, student_unit=lambda p: (p - 0.5) * 0.5 + 0.5, teacher=teacher, teacher_unit=lambda p: p,
                       sample_points=_uniform_points(torch.Generator().manual_seed(2)), steps=300, points_per_step=4096, learning_rate=2e-2)
    assert fit.final_error > 0.5 * fit.initial_error, fit


def test_fit_without_steps_changes_nothing() -> None:
    teacher, student = _grid(0, 0.5), _grid(1, 1e-4)
    before = student.table.detach().clone()
    fit = fit_encoding(student, student_unit=lambda p: p, teacher=teacher, teacher_unit=lambda p: p,
                       sample_points=_uniform_points(torch.Generator().manual_seed(0)), steps=0)
    assert torch.equal(student.table, before)
    assert fit.final_error == fit.initial_error


def test_fit_refuses_grids_of_different_widths() -> None:
    teacher = HashGridEncoding(num_levels=4, features_per_level=2, log2_hashmap_size=10, base_resolution=4, max_resolution=32)
    with pytest.raises(ValueError, match="encodes 16 features, teacher 8"):
        fit_encoding(_grid(1, 1e-4), student_unit=lambda p: p, teacher=teacher, teacher_unit=lambda p: p,
                     sample_points=_uniform_points(torch.Generator()), steps=1)


def test_cell_sampler_draws_inside_its_cells_and_repeats_with_its_seed() -> None:
    resolution = 8
    cells = torch.tensor([0, 9, 100, 511])
    draw = lambda seed: occupied_cell_sampler(  # noqa: E731
        cells, resolution, to_world=lambda u: u * 10.0, generator=torch.Generator().manual_seed(seed))(5000)
    points = draw(3)
    unit = points / 10.0
    index = (unit * resolution).long()
    flat = index[:, 0] * resolution * resolution + index[:, 1] * resolution + index[:, 2]
    assert set(flat.unique().tolist()) == set(cells.tolist())  # every cell drawn, no other
    assert torch.equal(points, draw(3)) and not torch.equal(points, draw(4))
    with pytest.raises(ValueError, match="at least one cell"):
        occupied_cell_sampler(cells[:0], resolution, to_world=lambda u: u)


def _block_render_errors(trainer, block: int) -> float:
    """Mean squared difference between the block's and the global model's renders of the block's first
    training images, with the block just started (before any step of its own)."""
    pipeline = trainer.pipeline
    model = pipeline.model
    model.begin_block(block)
    block_model, global_model = model.phase_model(block), model.global_model
    block_model.eval(), global_model.eval()
    cameras = pipeline.datamanager.train_dataset.cameras
    errors = []
    for index in pipeline.split.blocks[block].image_indices[:3]:
        with torch.no_grad():
            renders = [chosen.get_outputs_for_camera(cameras[index : index + 1])["rgb"] for chosen in (block_model, global_model)]
        errors.append(float(torch.mean((renders[0] - renders[1]) ** 2)))
    return sum(errors) / len(errors)


@pytest.mark.slow  # trains
def test_fitted_block_starts_close_to_the_global_model(scene: Path, tmp_path: Path) -> None:
    """A fresh block's first renders of its own images are far from the global model's (it starts empty);
    a fitted one, in the same frame with the same table, renders close to what the global model renders."""
    fitted_run = tiny_trainer(scene, tmp_path / "fitted", block_init="fitted", global_steps=150, train_blocks=False)
    fitted_run.train()  # the global phase only
    fresh_run = tiny_trainer(scene, tmp_path / "fresh", block_init="fresh", train_blocks=False)
    fresh_run.pipeline.model.global_model.load_state_dict(fitted_run.pipeline.model.global_model.state_dict())
    fitted, fresh = _block_render_errors(fitted_run, 0), _block_render_errors(fresh_run, 0)
    assert fresh > 3e-3, fresh  # the global model has learnt what a fresh block does not know
    assert fitted < 0.25 * fresh, (fitted, fresh)


def test_fitted_blocks_need_the_global_decoder(scene: Path, tmp_path: Path) -> None:
    """Refused when the trainer is set up, before any run folder holds weights."""
    with pytest.raises(SystemExit, match="bad option: --pipeline.block-init fitted with --pipeline.decoder-mode independent"):
        tiny_trainer(scene, tmp_path, block_init="fitted", decoder_mode="independent")
    assert not list(tmp_path.rglob("*.ckpt"))


@pytest.mark.slow  # trains
def test_fresh_block_learns_its_images_from_a_seeded_grid(scene: Path, tmp_path: Path) -> None:
    """A fresh block (the paper's: an empty table of its own and the global decoder) starts with its
    occupancy grid seeded from the global model's density and no warm-up. Its young field is nearly
    transparent everywhere, so dropping samples for their own transparency from the first step left it
    without a sample, and it ended as it started: the background colour on every pixel (the town at
    2^8, 2026-11-27). Trained, it must render its own training images, not the background."""
    run = tiny_trainer(scene, tmp_path, block_init="fresh", global_steps=150, block_steps=80)
    assert run.pipeline.model.config.seed_block_occupancy  # the default this guards
    run.train()
    pipeline = run.pipeline
    block = pipeline.model.resident_block(0)
    block.eval()
    dataset = pipeline.datamanager.train_dataset
    block_errors, background_errors, coverage = [], [], []
    for index in pipeline.split.blocks[0].image_indices[:3]:
        with torch.no_grad():
            outputs = block.get_outputs_for_camera(dataset.cameras[index : index + 1])
        image = dataset[index]["image"][..., :3].to(outputs["rgb"].dtype)
        block_errors.append(float(torch.mean((outputs["rgb"] - image) ** 2)))
        background_errors.append(float(torch.mean((EVAL_BACKGROUND - image) ** 2)))
        coverage.append(float(outputs["accumulation"].mean()))
    assert min(coverage) > 0.5, coverage
    assert sum(block_errors) < 0.3 * sum(background_errors), (block_errors, background_errors)
