"""Volume rendering on a dense ``[num_rays, num_samples]`` layout, and of the kept samples alone.

Samples that were skipped (empty space, occluded) carry density 0, so they contribute nothing and
need no field evaluation. All functions stay finite for densities in ``[0, inf]``, zero-length and
very long intervals, and rays that hit nothing. :func:`render_kept_samples` renders without
gradients from the evaluated samples only (one C++ pass on the CPU, ``csrc/march.cpp``), with the
dense functions as its reference and its path elsewhere.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch
from torch import Tensor

from scalar_nerfstudio.encodings import _cpp

#: Background colour outside training (evaluation, rendering, the viewer, exports).
EVAL_BACKGROUND = 0.5

# exp(-MAX_OPTICAL_DEPTH) is ~1e-22: any larger optical depth is fully opaque in float32 anyway.
MAX_OPTICAL_DEPTH = 50.0


def alphas_from_densities(densities: Tensor, deltas: Tensor) -> Tensor:
    """Opacity of each interval.

    Args:
        densities: [R, S] volume density (1 / world unit), >= 0; NaN is treated as 0.
        deltas: [R, S] interval lengths in world units, >= 0.

    Returns:
        alphas: [R, S] in [0, 1].
    """
    optical_depth = (torch.nan_to_num(densities, nan=0.0) * deltas).clamp(0.0, MAX_OPTICAL_DEPTH)
    return 1.0 - torch.exp(-optical_depth)


def weights_from_alphas(alphas: Tensor) -> tuple[Tensor, Tensor]:
    """Volume-rendering weights ``w_i = T_i * alpha_i`` with ``T_i = prod_{j<i} (1 - alpha_j)``.

    Computed through the log-transmittance cumsum so that it is differentiable everywhere (also at
    alpha == 1, where a cumprod-based division would produce NaN gradients).

    Args:
        alphas: [R, S] in [0, 1].

    Returns:
        weights: [R, S] in [0, 1], summing to <= 1 per ray.
        transmittance: [R, S] light reaching each sample (before it), non-increasing along the ray.
    """
    optical_depth = -torch.log1p(-alphas.clamp(0.0, 1.0 - 1e-7))
    accumulated = torch.cumsum(optical_depth, dim=-1)
    exclusive = torch.cat([torch.zeros_like(accumulated[..., :1]), accumulated[..., :-1]], dim=-1)
    transmittance = torch.exp(-exclusive)
    weights = (transmittance * alphas).clamp(0.0, 1.0)
    return weights, transmittance


def render_weights(densities: Tensor, deltas: Tensor) -> tuple[Tensor, Tensor]:
    """[R, S] densities and interval lengths -> ([R, S] weights, [R, S] transmittance)."""
    return weights_from_alphas(alphas_from_densities(densities, deltas))


def composite(weights: Tensor, values: Tensor) -> Tensor:
    """Weighted sum along the ray: [R, S] weights, [R, S, C] values -> [R, C]."""
    return torch.sum(weights[..., None] * values, dim=-2)


def render_depth(weights: Tensor, t_mid: Tensor, t_far: Tensor) -> Tensor:
    """Expected termination depth, normalised by accumulation.

    Args:
        weights: [R, S].
        t_mid: [R, S] sample mid-points along the ray (world units).
        t_far: [R, 1] far bound used for rays that hit nothing.

    Returns:
        depth: [R, 1], in [t_mid.min, t_far].
    """
    accumulation = weights.sum(dim=-1, keepdim=True)
    depth = torch.sum(weights * t_mid, dim=-1, keepdim=True) / accumulation.clamp_min(1e-10)
    depth = torch.where(accumulation > 1e-10, depth, t_far)
    return torch.minimum(torch.nan_to_num(depth, nan=0.0, posinf=0.0), t_far)


class KeptRender(NamedTuple):
    """A render of rays from their kept samples (:func:`render_kept_samples`)."""

    rgb: Tensor
    """[R, 3] composited colour over ``background``."""
    depth: Tensor
    """[R, 1] expected termination depth (:func:`render_depth`)."""
    accumulation: Tensor
    """[R, 1] opacity."""
    sample_weights: Tensor
    """[M] the weight of each kept sample, in the order given."""
    weights: Optional[Tensor] = None
    """[R, S] the weights on the dense layout when the dense code rendered (None from the C++ pass)."""


def render_kept_samples(
    sample_ids: Tensor, density: Tensor, rgb: Tensor, *, deltas: Tensor, t_mid: Tensor, fars: Tensor, background: Tensor
) -> KeptRender:
    """Volume rendering from the evaluated samples alone: what the dense functions give when every other
    sample has density 0, without the ``[R, S]`` and ``[R, S, 3]`` scatter.

    Args:
        sample_ids: [M] flat indices into the ``[R * S]`` samples; each ray's in front-to-back order (rays may
            interleave, as the visibility sampler's rounds give them; the C++ pass checks it).
        density: [M] density of those samples.
        rgb: [M, 3] their colour.
        deltas: [R, S] interval lengths in world units.
        t_mid: [R, S] interval mid-points.
        fars: [R, 1] far bounds (the depth of rays that hit nothing).
        background: [R, 3] colour behind the rays.

    Float32 on the CPU without gradients goes through ``torch.ops.scalar_nerf_march.composite``; anything
    else (CUDA, autograd, other dtypes, no C++ build) through :func:`render_weights`, :func:`composite` and
    :func:`render_depth` on the dense layout. The two agree to float32 rounding (tests/test_march_kernels.py).
    """
    num_rays, num_samples = deltas.shape
    tensors = (density, rgb, deltas, t_mid, fars, background)
    plain = all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)
    needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    march = _cpp.march_ops() if plain and not needs_grad else None
    if march is not None:
        colour, depth, accumulation, weights = march.composite(
            sample_ids.contiguous(), density.contiguous(), rgb.contiguous(), deltas.contiguous(), t_mid.contiguous(),
            fars.reshape(-1).contiguous(), background.contiguous())
        return KeptRender(colour, depth, accumulation, weights)
    densities = density.new_zeros(num_rays * num_samples).index_put((sample_ids,), density).reshape(num_rays, num_samples)
    colours = rgb.new_zeros(num_rays * num_samples, 3).index_put((sample_ids,), rgb).reshape(num_rays, num_samples, 3)
    weights, _ = render_weights(densities, deltas)
    accumulation = weights.sum(dim=-1, keepdim=True)
    colour = composite(weights, colours) + (1.0 - accumulation) * background
    return KeptRender(colour, render_depth(weights, t_mid, fars), accumulation, weights.reshape(-1)[sample_ids], weights)


def dense_weights(kept: KeptRender, sample_ids: Tensor, num_rays: int, num_samples: int) -> Tensor:
    """[R, S] weights of a :class:`KeptRender` on the dense layout (0 at the samples not kept): the dense code's
    own (with their gradients) when it rendered, else the kept samples' scattered."""
    if kept.weights is not None:
        return kept.weights
    weights = kept.sample_weights
    return weights.new_zeros(num_rays * num_samples).index_put((sample_ids,), weights).reshape(num_rays, num_samples)


def distortion_loss(weights: Tensor, s_starts: Tensor, s_ends: Tensor) -> Tensor:
    """Mip-NeRF 360's distortion loss, per ray, in O(S) (prefix sums).

    Pulls each ray's weights into one compact interval, which removes the semi-transparent haze a
    NeRF otherwise uses to explain training views.

    Args:
        weights: [R, S] rendering weights.
        s_starts, s_ends: [R, S] interval bounds in normalised ray distance (e.g. lin-disp space, [0, 1]).

    Returns:
        [R] loss per ray (>= 0).
    """
    mids = (s_starts + s_ends) / 2.0
    widths = s_ends - s_starts
    weights_before = torch.cumsum(weights, dim=-1) - weights
    weighted_mids_before = torch.cumsum(weights * mids, dim=-1) - weights * mids
    bilateral = 2.0 * torch.sum(weights * (mids * weights_before - weighted_mids_before), dim=-1)
    unilateral = torch.sum(weights**2 * widths, dim=-1) / 3.0
    return bilateral + unilateral


def safe_normalise(vectors: Tensor, fallback: Tensor, eps: float = 1e-12) -> Tensor:
    """Unit vectors, finite for any input.

    Args:
        vectors: [..., 3] (any values; NaN/inf count as unusable).
        fallback: [..., 3] unit vectors (broadcastable) used where ``vectors`` is shorter than
            ``eps`` or not finite.

    Returns:
        [..., 3] unit vectors.
    """
    finite = torch.isfinite(vectors).all(dim=-1, keepdim=True)
    vectors = torch.where(finite, vectors, torch.zeros_like(vectors))
    # Scale by the largest component first: squaring tiny (1e-30) or huge (1e30) components stays finite.
    scale = vectors.abs().amax(dim=-1, keepdim=True)
    scaled = vectors / scale.clamp_min(1e-30)
    norm = torch.linalg.vector_norm(scaled, dim=-1, keepdim=True)
    usable = finite & (scale > eps)
    return torch.where(usable, scaled / norm.clamp_min(1e-30), fallback.to(vectors.dtype).expand_as(vectors))


def facing_normals(directions: Tensor) -> Tensor:
    """[R, 3] unit normals facing the camera (the reversed ray directions): the normal of a ray that
    no model gives one (nothing hit, or a flat density); +z where a direction is unusable."""
    return safe_normalise(-directions, torch.tensor([0.0, 0.0, 1.0], dtype=directions.dtype, device=directions.device))


def render_normals(weights: Tensor, normals: Tensor, fallback: Tensor) -> Tensor:
    """Expected surface normal of each ray: the normalised weighted sum of its samples' normals.

    Args:
        weights: [R, S] rendering weights.
        normals: [R, S, 3] unit (or zero: no normal) normals of the samples.
        fallback: [R, 3] unit vectors for rays whose weighted sum vanishes (nothing hit, zero
            density gradients), e.g. the reversed ray direction (facing the camera).

    Returns:
        [R, 3] unit normals, always finite.
    """
    return safe_normalise(composite(weights, normals), fallback)


def normals_to_unit_interval(normals: Tensor) -> Tensor:
    """[..., 3] unit normals in [-1, 1] -> [..., 3] in [0, 1] (``(n + 1) / 2``, nerfstudio's convention
    for a ``normals`` output: ``ns-export`` maps it back with ``2 x - 1``; the viewer shows it as colour)."""
    return ((normals + 1.0) / 2.0).clamp(0.0, 1.0)


def normals_from_unit_interval(encoded: Tensor) -> Tensor:
    """Inverse of :func:`normals_to_unit_interval`: [..., 3] in [0, 1] -> [..., 3] in [-1, 1]."""
    return encoded * 2.0 - 1.0
