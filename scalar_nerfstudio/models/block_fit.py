"""A block's hash table fitted to the global model before the block trains (``block_init`` ``fitted``).

A block with a frame of its own (``fresh``) resolves its region more finely than the global model
(its grid spans the block, not the scene), but starts from an empty table: its first few hundred
steps only relearn what the global model already knows. A block that copies the global model
(``global``) knows it from its first step, but keeps the global table's coarse cells.

Fitting gives a block both. The block copies the global decoder, so where the block's encoding
equals the global model's encoding of the same world point, the block renders what the global model
renders. The block's table is fitted to that by regression, level by level (no rendering, no images):

    min over the block's table of  mean || enc_block(x) - enc_global(x) ||^2

over world points ``x`` drawn in the global occupancy grid's occupied cells that the block's cameras
observe (the surfaces the block will be trained on). Only the hash grids run (forward, and backward
for the block), so a fit costs a fraction of one training step per step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch
from torch import Tensor

from scalar_nerfstudio.encodings import HashGridEncoding
from scalar_nerfstudio.model_components.sampling import cell_coordinates

__all__ = ["EncodingFit", "fit_encoding", "occupied_cell_sampler"]


@dataclass(frozen=True)
class EncodingFit:
    """What a fit did: its steps and the mean squared encoding error before and after."""

    steps: int
    initial_error: float
    final_error: float


def occupied_cell_sampler(cells: Tensor, resolution: int, *, to_world: Callable[[Tensor], Tensor],
                          generator: Optional[torch.Generator] = None) -> Callable[[int], Tensor]:
    """A sampler of world points, uniform over cells of a ``G^3`` grid of the contracted unit cube.

    Args:
        cells: [C] flat cell indices (``x * G^2 + y * G + z``) to draw from (C >= 1).
        resolution: G.
        to_world: [N, 3] unit-cube positions -> [N, 3] world positions (the grid owner's frame).
        generator: random source (the same generator gives the same points).

    Returns:
        ``sample(n)`` -> [n, 3] world points: a random cell of ``cells`` each, at a uniform point inside it.
    """
    if cells.numel() == 0:
        raise ValueError("occupied_cell_sampler needs at least one cell")
    g = resolution

    def sample(count: int) -> Tensor:
        picks = cells[torch.randint(0, cells.numel(), (count,), generator=generator, device=cells.device)]
        coords = cell_coordinates(picks, g)
        jitter = torch.rand(coords.shape, generator=generator, device=cells.device)
        return to_world((coords + jitter) / g)

    return sample


def fit_encoding(
    student: HashGridEncoding,
    *,
    student_unit: Callable[[Tensor], Tensor],
    teacher: HashGridEncoding,
    teacher_unit: Callable[[Tensor], Tensor],
    sample_points: Callable[[int], Tensor],
    steps: int,
    points_per_step: int = 1 << 15,
    learning_rate: float = 1e-2,
) -> EncodingFit:
    """Fit ``student``'s table so that its encoding of world points matches ``teacher``'s (Adam, MSE).

    Args:
        student: the hash grid whose table is fitted (same levels and features per level as the teacher).
        student_unit / teacher_unit: [N, 3] world points -> [N, 3] each grid's contracted unit-cube positions.
        teacher: the hash grid to match (read only).
        sample_points: ``n`` -> [n, 3] world points (e.g. :func:`occupied_cell_sampler`).
        steps: Adam steps (0: nothing is changed; the errors are still measured).
        points_per_step: points per step.
        learning_rate: Adam's learning rate on the table.

    Returns:
        The fit's :class:`EncodingFit` (errors on a fresh draw of points before and after).
    """
    if student.get_out_dim() != teacher.get_out_dim():
        raise ValueError(f"student encodes {student.get_out_dim()} features, teacher {teacher.get_out_dim()}: cannot fit")

    def error(points: Tensor) -> float:
        with torch.no_grad():
            return float(torch.mean((student(student_unit(points)) - teacher(teacher_unit(points))) ** 2))

    probe = sample_points(points_per_step)
    initial = error(probe)
    optimizer = torch.optim.Adam(student.parameters(), lr=learning_rate, eps=1e-15)
    with torch.enable_grad():
        for _ in range(steps):
            points = sample_points(points_per_step)
            with torch.no_grad():
                target = teacher(teacher_unit(points))
            loss = torch.mean((student(student_unit(points)) - target) ** 2)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
    return EncodingFit(steps=steps, initial_error=initial, final_error=error(probe))
