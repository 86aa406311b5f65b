"""Rays per chunk of a camera render (eval, ns-render, the viewer), by the device it renders on.

A CPU render is bound by arithmetic; chunks of 2^16 rays keep both cores busy with few per-chunk passes
(2^16 rendered a view in 0.86-0.90x the time of 2^14, 2^17 no faster; docs/results.md) at a few hundred MiB.
A CUDA render of small chunks is bound by the CPU's kernel launches (hundreds per chunk, the GPU idle
between them): larger chunks are what let a GPU work. The model config leaves the size at None ("by
device"); an explicit ``eval_num_rays_per_chunk`` wins. docs/results.md gives the measurements.
"""

from __future__ import annotations

from typing import Dict, Optional, Union

import torch

#: Rays per chunk of a camera render when ``eval_num_rays_per_chunk`` is left out.
RENDER_RAYS_PER_CHUNK: Dict[str, int] = {"cpu": 1 << 16, "cuda": 1 << 18}


def render_rays_per_chunk(configured: Optional[int], device: Union[torch.device, str]) -> int:
    """``configured`` if set, else :data:`RENDER_RAYS_PER_CHUNK` for ``device``'s type (the CPU's for
    any other type, e.g. "mps")."""
    if configured is not None:
        return int(configured)
    return RENDER_RAYS_PER_CHUNK.get(torch.device(device).type, RENDER_RAYS_PER_CHUNK["cpu"])
