"""The samples along a batch of rays, and rays made safe to sample (NaN/inf rays neutralised)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Tuple

import torch
from torch import Tensor


def neutralise_bad_rays(origins: Tensor, directions: Tensor, *, nears: Tensor, fars: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Rays [R, 3] with a NaN/inf origin or direction (or near/far) are reported and made empty.

    They render as the background with zero accumulation instead of spreading NaN through the batch.
    """
    bad = ~(torch.isfinite(origins).all(-1) & torch.isfinite(directions).all(-1) & torch.isfinite(nears[:, 0]) & torch.isfinite(fars[:, 0]))
    if not bool(bad.any()):
        return origins, directions, nears, fars
    warnings.warn(f"{int(bad.sum())} of {bad.numel()} rays have a NaN/inf origin, direction or near/far; they render as background.")
    keep = ~bad[:, None]
    origins = torch.where(keep, origins, torch.zeros_like(origins))
    directions = torch.where(keep, directions, torch.tensor([0.0, 0.0, 1.0], dtype=directions.dtype, device=directions.device))
    nears = torch.where(keep, nears, torch.ones_like(nears))
    fars = torch.where(keep, fars, torch.ones_like(fars))
    return origins, directions, nears, fars


@dataclass(frozen=True)
class RaySamples:
    """Samples along R rays, S per ray (what a model's ``_ray_samples`` builds)."""

    origins: Tensor  # [R, 3]
    directions: Tensor  # [R, 3]
    fars: Tensor  # [R, 1]
    t_starts: Tensor  # [R, S]
    t_ends: Tensor  # [R, S]
    t_mid: Tensor  # [R, S]
    unit_positions: Tensor  # [R*S, 3] contracted unit cube

    def world_positions(self, sample_ids: Tensor) -> Tensor:
        """[M] flat sample indices into [R*S] -> [M, 3] their world positions."""
        ray_ids = torch.div(sample_ids, self.t_mid.shape[1], rounding_mode="floor")
        return self.origins[ray_ids] + self.directions[ray_ids] * self.t_mid.reshape(-1)[sample_ids, None]
