"""Which samples along a batch of rays the field evaluates: the visibility sampler.

Given the samples' contracted unit-cube positions ``[R*S, 3]`` and their interval lengths ``[R, S]``,
:class:`VisibilitySampler` keeps the samples that

1. lie in occupied cells of the occupancy grid and, once the grid prunes, that the grid's density
   estimates make opaque enough (``grid_alpha_skip``, :meth:`OccupancyGrid.worth_evaluating`);
2. are not occluded: the transmittance in front of them, from a no-grad density pass, is above
   ``transmittance_threshold``;
3. once the grid prunes, are themselves more opaque than ``alpha_threshold`` in that pass.

The field runs with gradients (training) or for colour (rendering) only on the kept samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Protocol, Tuple

import torch
from torch import Tensor

from scalar_nerfstudio.encodings import _cpp
from scalar_nerfstudio.model_components.rendering import alphas_from_densities, weights_from_alphas
from scalar_nerfstudio.model_components.sampling import OccupancyGrid

#: Samples per chunk of a no-grad density pass.
DENSITY_CHUNK = 1 << 16
#: Candidates per ray evaluated in one front-to-back round at render time (rays that turned opaque stop
#: being evaluated): smaller wastes fewer evaluations behind surfaces, larger makes fewer, larger rounds.
RENDER_GROUP = 4


class DensityField(Protocol):
    """What the sampler needs of a field: its hash-grid encoder and its density head."""

    def encoder(self, unit_positions: Tensor) -> Tensor:
        """[M, 3] unit-cube positions -> [M, L*F] encoding."""
        ...

    def density_at_unit(self, unit_positions: Tensor, encoding: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
        """[M, 3] unit-cube positions (and their encoding, if known) -> ([M] density, [M, F] geometry features)."""
        ...


@dataclass(frozen=True, eq=False)
class VisibilitySampler:
    """The samples of a ray batch a field evaluates (see the module docstring).

    Built per render by the model that owns ``grid`` and ``field``, from its config's thresholds.
    """

    grid: OccupancyGrid
    """The occupancy grid that decides which cells are empty (training or render grid)."""
    field: DensityField
    """The field whose density decides occlusion."""
    transmittance_threshold: float
    """Samples behind the point where a ray's transmittance drops below this are dropped (<= 0: none)."""
    alpha_threshold: float
    """Once the grid prunes, samples more transparent than this are dropped (0: none)."""
    grid_alpha_skip: bool
    """Once the grid prunes, drop samples its density estimates make more transparent than ``alpha_threshold``."""

    def skips_transparent(self) -> bool:
        """Whether samples more transparent than ``alpha_threshold`` are dropped now: once the
        occupancy grid marks cells empty (after its warm-up), unless the threshold is 0, and not
        while the field settles into a grid seeded from another model's (:attr:`OccupancyGrid.settling`)."""
        return self.alpha_threshold > 0 and self.grid.pruning and not self.grid.settling

    @torch.no_grad()
    def worth_evaluating(self, unit_positions: Tensor, deltas: Tensor) -> Tensor:
        """[R*S] bool: the samples (unit-cube positions [R*S, 3], world interval lengths [R*S]) the
        field evaluates: those in occupied cells and, once the grid prunes (as for the rendered
        samples' ``alpha_threshold``), only those the grid's estimates make opaque enough
        (``grid_alpha_skip``)."""
        if self.grid_alpha_skip and self.skips_transparent():
            return self.grid.worth_evaluating(unit_positions, deltas, self.alpha_threshold)
        return self.grid.is_occupied(unit_positions)

    @torch.no_grad()
    def visible(self, unit_positions: Tensor, deltas: Tensor) -> Tuple[Tensor, Optional[Tensor]]:
        """The samples that are in occupied cells and not occluded: ([M] flat indices into the [R*S]
        samples, [M, L*F] their hash-grid encoding from the no-grad pass, or None when there was no
        such pass), so that the pass with gradients does not encode them again.

        Args:
            unit_positions: [R*S, 3] contracted unit-cube positions of the samples.
            deltas: [R, S] world interval lengths.
        """
        if self.transmittance_threshold <= 0:
            return torch.nonzero(self.grid.is_occupied(unit_positions)).squeeze(-1), None
        candidate_ids = torch.nonzero(self.worth_evaluating(unit_positions, deltas.reshape(-1))).squeeze(-1)
        if candidate_ids.numel() == 0:
            return candidate_ids, None
        candidates = unit_positions[candidate_ids]
        densities: List[Tensor] = []
        encodings: List[Tensor] = []
        for chunk in torch.split(candidates, DENSITY_CHUNK):
            encodings.append(self.field.encoder(chunk))
            densities.append(self.field.density_at_unit(chunk, encoding=encodings[-1])[0].float())
        keep = self.kept_candidates(candidate_ids, torch.cat(densities), deltas)
        kept_encoding = torch.cat([encoding[chunk_keep] for encoding, chunk_keep in zip(encodings, torch.split(keep, DENSITY_CHUNK))])
        return candidate_ids[keep], kept_encoding

    @torch.no_grad()
    def visible_with_features(self, unit_positions: Tensor, deltas: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        """:meth:`visible` without gradients, keeping what the field computed on the way:
        ([M] flat sample indices, [M] density, [M, F] geometry features).

        The candidates (the samples :meth:`worth_evaluating` keeps) are taken front to back in rounds of
        :data:`RENDER_GROUP` per ray: a round evaluates the next candidates of the rays whose
        transmittance is still above the threshold, so a ray that turned opaque costs at most
        ``RENDER_GROUP - 1`` evaluations behind its surface (the kept samples and their values are those
        of one pass over every candidate). On the CPU a round's bookkeeping is two C++ passes
        (``torch.ops.scalar_nerf_march``); the torch code here is the path elsewhere and their reference.
        The kept samples come round by round, so each ray's are in front-to-back order."""
        num_rays, num_samples = deltas.shape
        threshold = self.transmittance_threshold
        if threshold <= 0 or num_rays == 0:
            candidate_ids = torch.nonzero(self.grid.is_occupied(unit_positions)).squeeze(-1)
            density, geo = self.field.density_at_unit(unit_positions[candidate_ids])
            return candidate_ids, density, geo
        occupied = self.worth_evaluating(unit_positions, deltas.reshape(-1)).reshape(num_rays, num_samples)
        candidate_ids = torch.nonzero(occupied.reshape(-1)).squeeze(-1)  # [C] ray-major, front to back in a ray
        counts = occupied.sum(dim=1)  # [R] candidates per ray
        firsts = torch.cumsum(counts, dim=0) - counts  # [R] each ray's first candidate in candidate_ids
        flat_deltas = deltas.reshape(-1).contiguous()
        log_threshold = math.log(threshold)
        depth_before = deltas.new_zeros(num_rays)  # [R] optical depth in front of the round
        group = max(int(RENDER_GROUP), 1)
        offsets = torch.arange(group, device=deltas.device)  # [k]
        kept_ids: List[Tensor] = []
        kept_density: List[Tensor] = []
        kept_geo: List[Tensor] = []
        most = int(counts.max()) if candidate_ids.numel() else 0
        march = _cpp.march_ops() if deltas.device.type == "cpu" and deltas.dtype == torch.float32 else None
        min_alpha = self.alpha_threshold if self.skips_transparent() else -1.0
        for rank in range(0, most, group):
            if march is not None:  # the same round in two C++ passes (csrc/march.cpp)
                ids, ray_of_ids = march.round_candidates(counts, firsts, candidate_ids, depth_before, rank, group, log_threshold)
                if ids.numel() == 0:
                    break
                density, geo = self.field.density_at_unit(unit_positions[ids])
                keep = march.round_keep(ids, ray_of_ids, density.float().contiguous(), flat_deltas, depth_before, threshold, min_alpha)
                kept = torch.nonzero(keep).squeeze(-1)  # once, not once per mask indexing below
                kept_ids.append(ids[kept])
                kept_density.append(density[kept])
                kept_geo.append(geo[kept])
                continue
            rays = torch.nonzero((counts > rank) & (-depth_before > log_threshold)).squeeze(-1)  # [A] light still reaches them
            if rays.numel() == 0:
                break
            valid = (rank + offsets)[None, :] < counts[rays, None]  # [A, k] the ray has that candidate
            ids = candidate_ids[(firsts[rays, None] + rank + offsets[None, :])[valid]]  # [N] flat sample ids, row-major over [A, k]
            density, geo = self.field.density_at_unit(unit_positions[ids])
            packed_density = deltas.new_zeros(rays.numel(), group)
            packed_density[valid] = density.float()
            packed_deltas = deltas.new_zeros(rays.numel(), group)
            packed_deltas[valid] = flat_deltas[ids]
            alphas = alphas_from_densities(packed_density, packed_deltas)  # [A, k]; 0 where there is no candidate
            optical = -torch.log1p(-alphas.clamp(0.0, 1.0 - 1e-7))
            accumulated = torch.cumsum(optical, dim=-1) + depth_before[rays, None]
            before = torch.cat([depth_before[rays, None], accumulated[:, :-1]], dim=-1)  # [A, k] in front of each candidate
            keep = (torch.exp(-before[valid]) > threshold) & (alphas[valid] > min_alpha)
            kept_ids.append(ids[keep])
            kept_density.append(density[keep])
            kept_geo.append(geo[keep])
            depth_before[rays] = accumulated[:, -1]
        if not kept_ids:
            empty = unit_positions[:0]
            density, geo = self.field.density_at_unit(empty)
            return torch.zeros(0, dtype=torch.long, device=unit_positions.device), density, geo
        return torch.cat(kept_ids), torch.cat(kept_density), torch.cat(kept_geo)

    @torch.no_grad()
    def kept_candidates(self, candidate_ids: Tensor, density: Tensor, deltas: Tensor) -> Tensor:
        """[C] bool over the occupied samples ``candidate_ids`` (flat indices into [R*S]) with ``density``
        [C]: True where the transmittance before the sample is above the threshold and (once the grid
        prunes) its opacity above ``alpha_threshold``."""
        num_rays, num_samples = deltas.shape
        densities = torch.zeros(num_rays * num_samples, device=deltas.device)
        densities[candidate_ids] = density.float()
        alphas = alphas_from_densities(densities.reshape(num_rays, num_samples), deltas)
        _, transmittance = weights_from_alphas(alphas)
        keep = transmittance.reshape(-1)[candidate_ids] > self.transmittance_threshold
        if self.skips_transparent():
            keep &= alphas.reshape(-1)[candidate_ids] > self.alpha_threshold
        return keep
