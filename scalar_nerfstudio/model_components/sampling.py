"""Ray sampling for unbounded scenes and a CPU-friendly occupancy grid for empty-space skipping.

nerfacc's occupancy grid is CUDA-only; this one is plain torch (its per-sample test runs in one
pass of a C++ kernel on the CPU, ``csrc/sampling.cpp``, when that builds). It stores a density estimate per
cell of a ``[G, G, G]`` grid over the *contracted* scene cube ``[0, 1]^3`` (see
``fields.scalar_field.contract_to_unit_cube``), so one grid covers the whole unbounded scene.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable

import torch
from torch import Tensor, nn

from scalar_nerfstudio.encodings import _cpp

if TYPE_CHECKING:
    from torch._ops import _OpNamespace


def lin_disp_spacing(t: Tensor) -> Tensor:
    """Mip-NeRF 360 style spacing: linear in ``t`` up to 1 world unit, linear in disparity beyond.

    Maps t in [0, inf) to s in [0, 1).
    """
    return torch.where(t < 1.0, t / 2.0, 1.0 - 1.0 / (2.0 * t.clamp_min(1.0)))


def lin_disp_spacing_inverse(s: Tensor) -> Tensor:
    """Inverse of :func:`lin_disp_spacing`: s in [0, 1) -> t in [0, inf)."""
    return torch.where(s < 0.5, 2.0 * s, 1.0 / (2.0 * (1.0 - s).clamp_min(1e-6)))


def sphere_interval(origins: Tensor, directions: Tensor, radius: float) -> tuple[Tensor, Tensor]:
    """Where rays are inside the sphere of ``radius`` around the origin.

    Args:
        origins: [R, 3] ray origins.
        directions: [R, 3] unit ray directions.
        radius: the sphere's radius (> 0).

    Returns:
        t_entry, t_exit: [R, 1] distances along each ray at which it enters and leaves the sphere
        (t_entry < 0 for an origin inside it). A ray that misses the sphere, or whose origin or
        direction is not finite, gets t_entry = t_exit = 0, so that a caller clamping it to its
        near plane leaves it empty. Stays finite for origins at any distance (the squared distance
        of the ray to the centre is taken from the point of closest approach, not from |o|^2).
    """
    along = (origins * directions).sum(dim=-1, keepdim=True)  # [R, 1] o . d
    closest = origins - along * directions  # [R, 3] the ray's (line's) point nearest the centre
    half_chord_sq = radius * radius - (closest * closest).sum(dim=-1, keepdim=True)
    hit = (half_chord_sq > 0) & torch.isfinite(half_chord_sq) & torch.isfinite(along)
    half_chord = torch.sqrt(torch.where(hit, half_chord_sq, torch.zeros_like(half_chord_sq)))
    zeros = torch.zeros_like(along)
    t_entry = torch.where(hit, -along - half_chord, zeros)
    t_exit = torch.where(hit, -along + half_chord, zeros)
    return t_entry, t_exit


def sample_intervals(nears: Tensor, fars: Tensor, *, num_samples: int, jitter: bool) -> tuple[Tensor, Tensor]:
    """Intervals along each ray, evenly spaced in :func:`lin_disp_spacing` space.

    Args:
        nears: [R, 1] near bound (world units, >= 0).
        fars: [R, 1] far bound (world units, > nears).
        num_samples: S, intervals per ray.
        jitter: shift all bins of a ray by one random fraction (stratified sampling, training).

    Returns:
        t_starts, t_ends: [R, S] interval bounds in world units, contiguous, non-decreasing.
    """
    s_near, s_far = lin_disp_spacing(nears), lin_disp_spacing(fars)
    bins = torch.linspace(0.0, 1.0, num_samples + 1, device=nears.device, dtype=nears.dtype)[None, :]
    if jitter:
        offset = (torch.rand_like(nears) - 0.5) / num_samples
        bins = (bins + offset).clamp(0.0, 1.0)
    t_edges = lin_disp_spacing_inverse(s_near + (s_far - s_near) * bins)
    t_edges = torch.maximum(torch.minimum(t_edges, fars), nears)
    return t_edges[:, :-1], t_edges[:, 1:]


def cell_coordinates(cells: Tensor, resolution: int) -> Tensor:
    """[M] flat cell indices of a ``G^3`` grid (``x * G^2 + y * G + z``) -> [M, 3] float32 integer
    coordinates (x, y, z) of the cells' low corners, in cells."""
    g = resolution
    return torch.stack([cells // (g * g), (cells // g) % g, cells % g], dim=-1).float()


def flat_cell_indices(unit_positions: Tensor, resolution: int) -> Tensor:
    """[M, 3] positions in the unit cube -> [M] flat indices of their cells in a ``G^3`` grid
    (always in range: NaN counts as 0, positions outside are clamped to the edge cells)."""
    g = resolution
    cells = (torch.nan_to_num(unit_positions, nan=0.0) * g).long().clamp(0, g - 1)
    return cells[:, 0] * (g * g) + cells[:, 1] * g + cells[:, 2]


def face_neighbourhood_max(values: Tensor, resolution: int) -> Tensor:
    """[G^3] per-cell values (flat cell order) -> [G^3] the largest value of each cell and its 6 face
    neighbours (no wrap-around: edge cells have fewer)."""
    g = resolution
    grid = values.reshape(g, g, g)
    largest = grid.clone()
    for axis in range(3):
        ahead = grid.narrow(axis, 1, g - 1)
        behind = grid.narrow(axis, 0, g - 1)
        largest.narrow(axis, 0, g - 1).copy_(torch.maximum(largest.narrow(axis, 0, g - 1), ahead))
        largest.narrow(axis, 1, g - 1).copy_(torch.maximum(largest.narrow(axis, 1, g - 1), behind))
    return largest.reshape(-1)


def _tensor_key(tensor: Tensor) -> tuple[int, int, torch.device]:
    """What identifies a tensor's values for a cache: its storage, its in-place version, its device."""
    return (tensor.data_ptr(), tensor._version, tensor.device)


#: Jittered points per cell of the update that follows the warm-up (which starts the estimates afresh).
RESTART_POINTS_PER_CELL = 4


class OccupancyGrid(nn.Module):
    """Occupancy over the contracted unit cube, updated from the field's density as it trains.

    Args:
        resolution: G, cells per axis.
        update_every: steps between updates.
        warmup_steps: until this step every update re-evaluates all cells and no cell is marked
            empty (surfaces must form before empty space is decided). The first update after it
            re-evaluates every cell at :data:`RESTART_POINTS_PER_CELL` points and replaces the
            estimates (the haze of a young field is forgotten); later, a random quarter of the
            cells per update. A seeded grid has no warm-up.
        ema_decay: exponential moving average decay of a cell's density estimate.
        opacity_threshold: a cell is occupied when the opacity of its density estimate over the
            cell's world-space size, 1 - exp(-density * size), exceeds min(threshold, mean opacity)
            (as nerfacc's grid does; the mean keeps a grid of a barely trained field from emptying).
        world_scale: world length of one unit of the region frame the grid's cube contracts
            (a block's radius), so cell sizes and the opacity threshold are in world units.
        neighbourhood_alpha_test: :meth:`worth_evaluating` judges a sample by the largest estimate
            of its cell and the 6 cells beside it (estimates from a few random points can miss a
            surface that grazes a cell); False: by its cell's own estimate, for a grid built by
            :meth:`refresh`, whose estimates are already the largest density at the cell's corners.
    """

    density_ema: Tensor
    """[G^3] float32 density estimate per cell (1 / world unit; inf: never evaluated)."""
    occupied: Tensor
    """[G^3] bool: cells marked occupied."""
    cell_sizes: Tensor
    """[G^3] world-space edge length of each cell (not saved)."""
    seeded: Tensor
    """[] bool: the grid was seeded from known densities (not saved)."""

    def __init__(
        self,
        *,
        resolution: int = 64,
        update_every: int = 16,
        warmup_steps: int = 256,
        ema_decay: float = 0.95,
        opacity_threshold: float = 0.01,
        world_scale: float = 1.0,
        neighbourhood_alpha_test: bool = True,
    ) -> None:
        super().__init__()
        self.neighbourhood_alpha_test = neighbourhood_alpha_test
        self.resolution = resolution
        self.update_every = update_every
        self.warmup_steps = warmup_steps
        self.ema_decay = ema_decay
        self.opacity_threshold = opacity_threshold
        num_cells = resolution**3
        # A fresh grid is all occupied: nothing is skipped until the field has been looked at.
        self.register_buffer("density_ema", torch.full((num_cells,), float("inf")))
        self.register_buffer("occupied", torch.ones(num_cells, dtype=torch.bool))
        self.register_buffer("cell_sizes", world_scale * self._world_cell_sizes(resolution), persistent=False)
        # Seeded from another model's density (a block from the global model): no warm-up. Not saved
        # (checkpoints of older runs load): a resumed grid keeps its saved cells through a warm-up.
        self.register_buffer("seeded", torch.zeros((), dtype=torch.bool), persistent=False)
        self._warming_up = True
        self._settles = False  # see seed(settle=True)
        # caches keyed by the tensors' identity and version (in-place writes and swapped storage renew them)
        self._neighbourhood: tuple[tuple[int, int, torch.device], Tensor] | None = None  # see neighbourhood_estimates
        self._pruning: tuple[tuple[int, int, torch.device], bool] | None = None  # see pruning

    @property
    def warming_up(self) -> bool:
        """Whether the step of the latest :meth:`update` call is inside the warm-up (True before the
        first call; always False for a seeded grid, see :meth:`seed`)."""
        return self._warming_up and not bool(self.seeded)

    @property
    def settling(self) -> bool:
        """Whether the grid was seeded from another model's density (``seed(..., settle=True)``) and
        the step of the latest :meth:`update` is still inside ``warmup_steps``: its own field is young,
        so its model evaluates every sample in an occupied cell however transparent the field finds
        it (else a nearly transparent fresh field would get no sample, hence no gradient, for good)."""
        return self._settles and self._warming_up

    @staticmethod
    def _world_cell_sizes(resolution: int) -> Tensor:
        """[G^3] world-space edge length of each cell (cells of the contracted cube grow as r^2 outside r=1)."""
        centres = (torch.stack(torch.meshgrid(*[torch.arange(resolution)] * 3, indexing="ij"), dim=-1).reshape(-1, 3) + 0.5) / resolution
        contracted_radius = torch.linalg.vector_norm((centres - 0.5) * 4.0, dim=-1).clamp(max=2.0 - 1e-3)
        world_radius = torch.where(contracted_radius <= 1.0, torch.ones_like(contracted_radius), 1.0 / (2.0 - contracted_radius))
        return (4.0 / resolution) * world_radius**2

    def cell_centres(self) -> Tensor:
        """[G^3, 3] centres of the cells in the contracted unit cube, in flat cell order."""
        g = self.resolution
        return (cell_coordinates(torch.arange(g**3, device=self.density_ema.device), g) + 0.5) / g

    @torch.no_grad()
    def seed(self, densities: Tensor, settle: bool = False) -> None:
        """Start from known densities ``[G^3]`` (1 / world unit) at :meth:`cell_centres` instead of a
        warm-up: cells are marked at once and later updates are partial, as after the warm-up. The
        estimates decay as the model's own densities come in.

        ``settle``: the densities are another model's (a fresh block's grid seeded from the global
        model), so this grid's own field has not learnt the scene yet: :attr:`settling` holds until
        an :meth:`update` at or past ``warmup_steps``."""
        if densities.shape != self.density_ema.shape:
            raise ValueError(f"seed densities must have shape {list(self.density_ema.shape)}, got {list(densities.shape)}")
        self.density_ema.copy_(torch.nan_to_num(densities.float(), nan=0.0, posinf=1e6).clamp_min(0.0))
        self._neighbourhood = None
        opacities = 1.0 - torch.exp(-(self.density_ema * self.cell_sizes).clamp(max=50.0))
        self.occupied.copy_(opacities > min(self.opacity_threshold, float(opacities.mean())))
        self.seeded.fill_(True)
        self._settles = settle

    @torch.no_grad()
    def refresh(self, density_fn: Callable[[Tensor], Tensor], chunk_cells: int = 1 << 18) -> None:
        """Estimate every cell from the field as it is now, replacing the estimates (not their
        maximum with the old ones), and mark the cells: how a model's render grid is built when its
        training ends (:meth:`ScalarModel.finish_training`), without the haze a training grid
        remembers from earlier steps. A cell's estimate is the largest density at its 8 corners
        (the field is evaluated once at each of the ``(G + 1)^3`` corners of the grid): a surface
        that crosses a cell crosses it between corners, where the field's density falls off over
        about a cell of the finest levels. Deterministic; the grid counts as seeded afterwards (no
        warm-up).

        Args:
            density_fn: [M, 3] contracted unit-cube positions -> [M] density (1 / world unit).
            chunk_cells: corners evaluated per call of ``density_fn``.
        """
        g = self.resolution
        corners = torch.empty((g + 1) ** 3, device=self.density_ema.device)
        for ids in torch.split(torch.arange((g + 1) ** 3, device=self.density_ema.device), chunk_cells):
            corners[ids] = density_fn(cell_coordinates(ids, g + 1) / g).float()
        corners = torch.nan_to_num(corners, nan=0.0, posinf=1e6).reshape(1, 1, g + 1, g + 1, g + 1)
        self.seed(torch.nn.functional.max_pool3d(corners, kernel_size=2, stride=1).reshape(-1))

    def cell_indices(self, unit_positions: Tensor) -> Tensor:
        """[M, 3] positions in the contracted unit cube -> [M] flat cell indices (always in range)."""
        return flat_cell_indices(unit_positions, self.resolution)

    def density_estimates(self, unit_positions: Tensor) -> Tensor:
        """[M, 3] contracted unit-cube positions -> [M] float32 density estimates of their cells
        (0 in cells marked empty or never evaluated)."""
        cells = self.cell_indices(unit_positions)
        estimates = torch.where(self.occupied, self.density_ema, torch.zeros_like(self.density_ema))
        return torch.nan_to_num(estimates, nan=0.0, posinf=0.0)[cells]

    def is_occupied(self, unit_positions: Tensor) -> Tensor:
        """[M, 3] contracted unit-cube positions -> [M] bool."""
        ops = self._cpu_kernels(unit_positions)
        if ops is not None:
            return ops.worth_evaluating(unit_positions.contiguous(), unit_positions.new_empty(0), self.occupied, unit_positions.new_empty(0), self.resolution, 0.0)
        return self.occupied[self.cell_indices(unit_positions)]

    def _cpu_kernels(self, unit_positions: Tensor) -> _OpNamespace | None:
        """``torch.ops.scalar_nerf_sampling`` for float32 positions on the CPU when the C++ kernels
        build (one pass, no [M, 3] temporaries); None: the torch code."""
        if unit_positions.device.type != "cpu" or unit_positions.dtype != torch.float32 or self.density_ema.device.type != "cpu":
            return None
        return _cpp.sampling_ops()

    def worth_evaluating(self, unit_positions: Tensor, deltas: Tensor, alpha_threshold: float) -> Tensor:
        """[M] bool: samples in occupied cells whose opacity over their own interval, from the density
        estimates around their cell, reaches ``alpha_threshold``.

        A cell is occupied by its opacity over the cell's size; a sample is rendered only when its
        opacity over its interval (often half a cell or less) exceeds ``alpha_threshold``. Occupied
        cells of faint haze hold many samples that would be evaluated only to be dropped: this test
        drops them first. The estimate is the largest density seen in the cell and its 6 face
        neighbours (:meth:`neighbourhood_estimates`): a cell's own estimate comes from a few random
        points and can miss a surface that only grazes it, its neighbour inside the surface does not
        (without ``neighbourhood_alpha_test``, the cell's own estimate). Cells never evaluated (infinite estimate) and NaN or infinite intervals are always worth
        evaluating.

        Args:
            unit_positions: [M, 3] contracted unit-cube positions.
            deltas: [M] interval lengths in world units (the unit of the density estimates).
            alpha_threshold: opacity below which a sample is not worth evaluating.
        """
        cell_estimates = self.neighbourhood_estimates() if self.neighbourhood_alpha_test else self.density_ema
        # 1 - exp(-d) >= a  <=>  d >= -log(1 - a)
        min_optical_depth = -math.log1p(-min(max(alpha_threshold, 0.0), 1.0 - 1e-7))
        ops = self._cpu_kernels(unit_positions) if deltas.dtype == torch.float32 else None
        if ops is not None:
            return ops.worth_evaluating(unit_positions.contiguous(), deltas.contiguous(), self.occupied, cell_estimates.contiguous(), self.resolution, min_optical_depth)
        cells = self.cell_indices(unit_positions)
        # NaN (inf * 0: a cell never evaluated, or a NaN interval) counts as opaque: evaluated
        optical_depth = torch.nan_to_num(cell_estimates[cells] * deltas, nan=float("inf"))
        return self.occupied[cells] & (optical_depth >= min_optical_depth)

    def neighbourhood_estimates(self) -> Tensor:
        """[G^3] the largest density estimate of each cell and its 6 face neighbours (cached until
        the estimates change: :meth:`update`, :meth:`seed`, loading a state)."""
        key = _tensor_key(self.density_ema)
        if self._neighbourhood is None or self._neighbourhood[0] != key:
            self._neighbourhood = (key, face_neighbourhood_max(self.density_ema, self.resolution))
        return self._neighbourhood[1]

    def _load_from_state_dict(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        self._neighbourhood = None
        super()._load_from_state_dict(*args, **kwargs)

    @property
    def pruning(self) -> bool:
        """Whether the grid marks any cell empty yet (never during the warm-up). Cached until the
        cells change: a render asks once per segment, and a 128^3 grid has 2 M cells."""
        key = _tensor_key(self.occupied)
        if self._pruning is None or self._pruning[0] != key:
            self._pruning = (key, not bool(self.occupied.all()))
        return self._pruning[1]

    def occupied_fraction(self) -> float:
        """Share of cells currently marked occupied."""
        return float(self.occupied.float().mean())

    @torch.no_grad()
    def update(self, step: int, density_fn: Callable[[Tensor], Tensor]) -> None:
        """Re-estimate density at a jittered point of (some) cells and re-threshold.

        Args:
            step: training step; nothing happens unless ``step % update_every == 0``.
            density_fn: [M, 3] contracted unit-cube positions -> [M] density (1 / world unit).
        """
        self._warming_up = step < self.warmup_steps
        if step % self.update_every != 0:
            return
        g = self.resolution
        device = self.density_ema.device
        num_cells = g**3
        warming_up = self.warming_up
        # The first update after the warm-up starts the estimates afresh from the field as it is now
        # (the largest of a few jittered points per cell): the warm-up's early haze is forgotten.
        restart = step - self.update_every < self.warmup_steps <= step and not bool(self.seeded)
        if warming_up or restart:
            cells = torch.arange(num_cells, device=device)
        else:
            cells = torch.randint(0, num_cells, (num_cells // 4,), device=device)
        coords = cell_coordinates(cells, g)
        points = RESTART_POINTS_PER_CELL if restart else 1
        positions = (coords[None] + torch.rand((points, *coords.shape), device=device)) / g
        densities = torch.nan_to_num(density_fn(positions.reshape(-1, 3)).reshape(points, -1).float(), nan=0.0, posinf=1e6).amax(0)
        self._neighbourhood = None
        if restart:
            self.density_ema[cells] = densities
        else:
            previous = self.density_ema[cells]
            decayed = torch.where(torch.isinf(previous), densities, previous * self.ema_decay)
            self.density_ema[cells] = torch.maximum(decayed, densities)
        opacities = 1.0 - torch.exp(-(self.density_ema * self.cell_sizes).clamp(max=50.0))
        threshold = min(self.opacity_threshold, float(opacities.mean()))
        if not warming_up:
            self.occupied.copy_(opacities > threshold)
