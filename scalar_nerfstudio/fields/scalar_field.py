"""SCALAR-NeRF field: hash-grid encoder + shared decoder + per-image appearance embedding.

The decoder is its own module so that a block's local model can start from a copy of the global
model's decoder (fine-tuned, frozen or replaced), while the encoder is always the block's own.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field
from typing import Literal, Optional, Type

import torch
from nerfstudio.configs.base_config import InstantiateConfig
from nerfstudio.field_components.activations import trunc_exp
from nerfstudio.field_components.encodings import SHEncoding
from torch import Tensor, nn

from scalar_nerfstudio.encodings import HashGridEncoding, _cpp
from scalar_nerfstudio.encodings.hash_grid import level_corners, sanitise_positions
from scalar_nerfstudio.fields.decoder_kernels import CpuDecoderKernel, choose_cpu_decoder_kernel
from scalar_nerfstudio.fields.fused_mlp import fused_mlp, fused_mlp_available, linear_layers
from scalar_nerfstudio.fields.fused_mlp_float32 import float32_mlp_isa, fused_mlp_float32, mlp_float32_inference

_logger = logging.getLogger(__name__)

# Values beyond this magnitude are clamped before contraction: far enough to contract to the
# boundary (2 - 1e-30 == 2 in float32) and small enough that squaring cannot overflow float32.
_MAX_COORDINATE = 1e18


def contract(positions: Tensor) -> Tensor:
    """Mip-NeRF 360 scene contraction (L2): x for |x| <= 1, (2 - 1/|x|) x/|x| beyond.

    Args:
        positions: [N, 3] world positions (any finite or infinite values; NaN maps to the origin).

    Returns:
        [N, 3] contracted positions, inside the closed ball of radius 2.
    """
    x = torch.nan_to_num(positions, nan=0.0, posinf=_MAX_COORDINATE, neginf=-_MAX_COORDINATE)
    x = x.clamp(-_MAX_COORDINATE, _MAX_COORDINATE)
    norm = torch.linalg.vector_norm(x, dim=-1, keepdim=True)  # [N, 1]; squares of |x| <= 1e18 stay finite
    inverse = 1.0 / norm.clamp_min(1.0)
    # one [N, 1] factor, then one pass over [N, 3]: x inside the unit ball, (2 - 1/|x|) x/|x| beyond
    return x * torch.where(norm <= 1.0, torch.ones_like(norm), (2.0 - inverse) * inverse)


def contract_to_unit_cube(positions: Tensor) -> Tensor:
    """[N, 3] world positions -> [N, 3] in [0, 1]^3 (contracted ball of radius 2 mapped to the cube)."""
    return (contract(positions) / 4.0 + 0.5).clamp(0.0, 1.0)


def to_region_frame(positions: Tensor, centre: Tensor, radius: float) -> Tensor:
    """[N, 3] world positions -> [N, 3] in a region's frame (``centre`` [3] at the origin, ``radius``
    world units to 1); the positions themselves for the whole scene's frame (centre 0, radius 1)."""
    if radius == 1.0 and not bool(centre.any()):
        return positions
    return (positions - centre.to(positions.dtype)) / radius


def contract_rays_to_unit_cube(origins: Tensor, directions: Tensor, t: Tensor, *, centre: Tensor, radius: float) -> Tensor:
    """The samples at distances ``t`` along rays, in the contracted unit cube of a region.

    ``contract_to_unit_cube((origins + directions * t - centre) / radius)`` for every sample, in one
    pass of the C++ kernel on the CPU (no [R, S, 3] temporaries), in torch elsewhere or when the
    kernel does not build.

    Args:
        origins: [R, 3] world ray origins.
        directions: [R, 3] world ray directions.
        t: [R, S] distances along the rays (world units).
        centre: [3] the region's centre (world).
        radius: the region's radius (world units per unit of the region frame).

    Returns:
        [R * S, 3] positions in [0, 1]^3, ray-major.
    """
    on_cpu_float32 = all(x.device.type == "cpu" and x.dtype == torch.float32 for x in (origins, directions, t, centre))
    ops = _cpp.sampling_ops() if on_cpu_float32 else None
    if ops is not None:
        return ops.unit_positions(origins.contiguous(), directions.contiguous(), t.contiguous(), centre.contiguous(), float(radius))
    positions = (origins[:, None, :] + directions[:, None, :] * t[..., None]).reshape(-1, 3)
    return contract_to_unit_cube(to_region_frame(positions, centre, radius))


def unit_cube_to_world(unit_positions: Tensor) -> Tensor:
    """Inverse of :func:`contract_to_unit_cube`: [N, 3] in [0, 1]^3 -> [N, 3] world positions.

    Points of the cube outside the contracted ball (its corners) and its boundary sphere (infinity)
    map to radius ``1 / (2 - 1.999)`` = 1000 in their direction, so every result is finite.
    """
    contracted = (unit_positions.clamp(0.0, 1.0) - 0.5) * 4.0
    norm = torch.linalg.vector_norm(contracted, dim=-1, keepdim=True)
    radius = 1.0 / (2.0 - norm.clamp(1.0, 1.999))
    return torch.where(norm <= 1.0, contracted, contracted / norm.clamp_min(1.0) * radius)


def encode_with_position_gradients(encoder: HashGridEncoding, positions: Tensor) -> Tensor:
    """The hash-grid encoding of ``encoder``, differentiable with respect to the positions.

    The training kernels give the table gradients and the positions none (training never needs
    d(features)/d(position)). Surface normals do: this pure-torch version (any device) computes the
    same trilinear interpolation with autograd on the interpolation weights, reading a detached
    table (no table gradients). It is slower than the C++ kernel and used only for normals.

    Args:
        encoder: the hash grid (its table and layout are read).
        positions: [N, 3] contracted unit-cube positions (NaN -> 0 and clamped to [0, 1] like the
            kernels; clamped coordinates get zero gradient).

    Returns:
        [N, L * F] float32 features, equal to ``encoder(positions)`` up to float32 summation order.
    """
    if positions.ndim != 2 or positions.shape[-1] != 3:
        raise ValueError(f"positions must have shape [N, 3], got {tuple(positions.shape)}")
    table = encoder.table.detach()
    layout = encoder.layout
    num_features = table.shape[1]
    coords = sanitise_positions(positions.to(torch.float32)).t()  # [3, N]
    levels = []
    for level, resolution in enumerate(layout.resolutions):
        start, stop = layout.level_offsets[level], layout.level_offsets[level + 1]
        rows, weights = level_corners(coords, resolution, layout.hashmap_size)  # [8, N] each
        corner_features = table[start:stop].index_select(0, rows.reshape(-1)).view(8, -1, num_features)
        levels.append((corner_features * weights.unsqueeze(-1)).sum(0))  # [N, F]
    return torch.cat(levels, dim=-1)


def fused_linear_available() -> bool:
    """Whether oneDNN's fused linear + bias + activation CPU kernel (``torch.ops.mkldnn._linear_pointwise``) exists here."""
    try:
        return bool(torch.backends.mkldnn.is_available()) and hasattr(torch.ops.mkldnn, "_linear_pointwise")
    except (AttributeError, RuntimeError):
        return False


def cpu_autocast_dtype() -> Optional[torch.dtype]:
    """The dtype CPU autocast runs matrix products in here, or None when it is off (torch >= 2.1)."""
    if hasattr(torch, "get_autocast_dtype"):  # torch >= 2.4; the older functions below are deprecated there
        return torch.get_autocast_dtype("cpu") if torch.is_autocast_enabled("cpu") else None
    return torch.get_autocast_cpu_dtype() if torch.is_autocast_cpu_enabled() else None


def run_mlp_fused(mlp: nn.Sequential, inputs: Tensor, dtype: torch.dtype) -> Tensor:
    """A stack of ``nn.Linear`` (each optionally followed by ``nn.ReLU``) on the CPU without autograd,
    through oneDNN's fused kernel: bias and ReLU are applied as the product is written, instead of
    a bias broadcast before it and a ReLU pass after it (each a full pass over an [N, 128] tensor).
    The colour head on 355k samples: 51 -> 36 ms in bfloat16, 111 -> 64 ms in float32 (2 cores).

    Args:
        mlp: Linear layers, each optionally followed by one ReLU (:func:`linear_layers`); their
            weights are cast to ``dtype`` per call (a few kB).
        inputs: [N, in] CPU tensor.
        dtype: precision of the products and of the result (bfloat16 or float32).

    Returns:
        [N, out] in ``dtype``, equal to ``mlp(inputs)`` in that precision.
    """
    layers, relus = linear_layers(mlp)
    hidden = inputs.to(dtype)
    for layer, relu in zip(layers, relus):
        bias = layer.bias.to(dtype) if layer.bias is not None else None
        hidden = torch.ops.mkldnn._linear_pointwise(hidden, layer.weight.to(dtype), bias, "relu" if relu else "none", [], "")
    return hidden


class Decoder(nn.Module):
    """MLP decoder of depth 5 (2 density layers + 3 colour layers), all hidden layers of one width.

    Args:
        in_dim: encoder output size (levels * features per level).
        hidden_dim: width of every hidden layer.
        geo_feat_dim: features passed from the density head to the colour head.
        direction_dim: size of the encoded view direction.
        appearance_dim: size of the per-image appearance embedding.
        training_kernel: how the layers run with gradients on the CPU: ``"avx512bf16"``: under
            bfloat16 autocast through :func:`fused_mlp` (csrc/mlp.cpp) where this CPU has
            AVX512-BF16; ``"avx2"``: in float32 (no autocast) through :func:`fused_mlp_float32`
            (csrc/mlp_f32.cpp) where it has AVX2 and FMA; ``"torch"``: autograd layer by layer
            (also wherever the named kernel cannot run).
    """

    def __init__(
        self,
        *,
        in_dim: int,
        hidden_dim: int,
        geo_feat_dim: int,
        direction_dim: int,
        appearance_dim: int,
        density_bias: float,
        training_kernel: Literal["avx512bf16", "avx2", "torch"] = "avx512bf16",
    ) -> None:
        super().__init__()
        self.geo_feat_dim = geo_feat_dim
        self.density_bias = density_bias
        self.fused_cpu_inference = fused_linear_available()
        self.fused_cpu_training = training_kernel == "avx512bf16" and fused_mlp_available()
        self.float32_cpu_training = training_kernel == "avx2" and float32_mlp_isa() == "avx2"
        self.float32_cpu_inference = self.float32_cpu_training
        """Float32 layers without autograd on the CPU run through the same AVX2 kernels, tile by tile
        (:func:`mlp_float32_inference`), instead of oneDNN layer by layer."""
        self.density_mlp = nn.Sequential(
            nn.Linear(in_dim, hidden_dim), nn.ReLU(inplace=True), nn.Linear(hidden_dim, 1 + geo_feat_dim)
        )
        self.colour_mlp = nn.Sequential(
            nn.Linear(geo_feat_dim + direction_dim + appearance_dim, hidden_dim),
            nn.ReLU(inplace=True),
            nn.Linear(hidden_dim, hidden_dim),
            nn.ReLU(inplace=True),
            nn.Linear(hidden_dim, 3),
        )

    def density(self, features: Tensor) -> tuple[Tensor, Tensor]:
        """[N, in_dim] encoder features -> ([N] float32 density in 1/world unit, [N, geo_feat_dim] features).

        Under autocast the matrix products run in low precision; the density's exponential does not.
        Without autograd on the CPU the layers run fused (:func:`run_mlp_fused`).
        """
        out = self._mlp(self.density_mlp, features)
        density = trunc_exp(out[:, 0].float() + self.density_bias)
        return density, out[:, 1:]

    def colour(self, geo_features: Tensor, encoded_directions: Tensor, appearance: Tensor) -> Tensor:
        """[N, geo], [N, dir], [N, app] -> [N, 3] float32 RGB in [0, 1]."""
        dtype = torch.bfloat16 if self._fused_training_applies(geo_features) else geo_features.dtype
        inputs = torch.cat([geo_features.to(dtype), encoded_directions.to(dtype), appearance.to(dtype)], dim=-1)
        return torch.sigmoid(self._mlp(self.colour_mlp, inputs).float())

    def _fused_training_applies(self, inputs: Tensor) -> bool:
        """Whether :meth:`_mlp` takes the fused bfloat16 training kernels for ``inputs``."""
        return (
            self.fused_cpu_training
            and torch.is_grad_enabled()
            and inputs.device.type == "cpu"
            and cpu_autocast_dtype() == torch.bfloat16
        )

    def _float32_training_applies(self, inputs: Tensor) -> bool:
        """Whether :meth:`_mlp` takes the fused float32 training kernels for ``inputs``."""
        return (
            self.float32_cpu_training
            and torch.is_grad_enabled()
            and inputs.device.type == "cpu"
            and inputs.dtype == torch.float32
            and cpu_autocast_dtype() is None
        )

    def _mlp(self, mlp: nn.Sequential, inputs: Tensor) -> Tensor:
        """``mlp(inputs)``. On the CPU under bfloat16 autocast with autograd, through :func:`fused_mlp`
        (float32 result) where enabled; on the CPU in float32 (no autocast) with autograd, through
        :func:`fused_mlp_float32` where enabled; without autograd on the CPU in float32, through
        :func:`mlp_float32_inference` where those kernels are enabled, else through :func:`run_mlp_fused` in
        the precision autocast asks for (float32 outside autocast), except bfloat16 on a CPU without
        native bfloat16 products (:func:`cpu_bfloat16_is_fast`), where oneDNN has no such kernel."""
        if self._fused_training_applies(inputs):
            return fused_mlp(mlp, inputs)
        if self._float32_training_applies(inputs):
            return fused_mlp_float32(mlp, inputs, "avx2")
        if torch.is_grad_enabled() or inputs.device.type != "cpu":
            return mlp(inputs)
        dtype = cpu_autocast_dtype() or inputs.dtype
        if self.float32_cpu_inference and dtype == torch.float32:
            return mlp_float32_inference(mlp, inputs.float(), "avx2")
        if not self.fused_cpu_inference:
            return mlp(inputs)
        if dtype == torch.bfloat16 and not cpu_bfloat16_is_fast():  # oneDNN has no bfloat16 inner product on this CPU
            return mlp(inputs)
        return run_mlp_fused(mlp, inputs, dtype)


@functools.lru_cache(maxsize=1)
def cpu_bfloat16_is_fast() -> bool:
    """Whether this CPU has native bfloat16 matrix products (AVX512-BF16 / AMX through oneDNN). Asked
    once per process: the decoder's inference asks it on every MLP call under bfloat16."""
    try:
        return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


@functools.lru_cache(maxsize=None)
def _warn_once(message: str) -> None:
    """Logs ``message`` as a warning the first time it comes in this process (a run builds many fields)."""
    _logger.warning(message)


@dataclass
class ScalarFieldConfig(InstantiateConfig):
    """Hyper-parameters of the field (paper Sec. 4 defaults, except the decoder's width: see ``hidden_dim``)."""

    _target: Type = field(default_factory=lambda: ScalarField)
    num_levels: int = 16
    """Hash-grid levels."""
    features_per_level: int = 4
    """Features per level."""
    log2_hashmap_size: int = 19
    """log2 of the hash table rows per level (T = 2^19 in the paper)."""
    base_resolution: int = 16
    """Coarsest grid resolution (cells per axis of the contracted cube)."""
    max_resolution: int = 2048
    """Finest grid resolution (cells per axis of the contracted cube)."""
    encoder_implementation: Literal["auto", "cpp", "cuda", "torch"] = "auto"
    """Hash-grid kernel: "auto" uses the C++ kernel on CPU and the CUDA kernel on CUDA, each when it
    builds (a warning says when not), torch otherwise."""
    # The paper's decoder is 128 wide (Sec. 4); 64 (Instant-NGP's width) trains faster on the CPU with
    # held-out quality at least as high at equal wall-clock (benchmark notes: "A narrower decoder").
    hidden_dim: int = 64
    """Width of the decoder's hidden layers (neurons); 128 gives the paper's decoder."""
    decoder_precision: Literal["auto", "float32", "bfloat16"] = "auto"
    """Precision of the decoder's matrix products on CPU; "auto": bfloat16 where the CPU multiplies it
    natively, else float32 (float32 also when ``cpu_decoder_kernel`` is "avx2"). On CUDA the trainer's
    mixed precision decides."""
    fused_decoder: bool = True
    """Train the decoder on the CPU through the fused C++ kernels (see ``cpu_decoder_kernel``); off:
    autograd's layer-by-layer products (``cpu_decoder_kernel`` "torch")."""
    cpu_decoder_kernel: CpuDecoderKernel = "auto"
    """Kernels that train the decoder on the CPU: "avx512bf16" (bfloat16 products, fused; needs
    AVX512-BF16), "avx2" (float32 products, fused; needs AVX2 and FMA), "torch" (autograd layer by
    layer). "auto": avx512bf16 for bfloat16 products, avx2 for float32 ones. A kernel the CPU lacks
    falls back to "auto" with a warning. Sets the precision when ``decoder_precision`` is "auto"."""
    geo_feat_dim: int = 15
    """Features from the density head to the colour head."""
    appearance_dim: int = 8
    """Per-image appearance embedding size (NeRF-W style)."""
    sh_degree: int = 4
    """Spherical-harmonics levels of the view-direction encoding (levels^2 outputs)."""
    density_bias: float = -4.0
    """Added before the density activation: a fresh field is nearly transparent (exp(-4) ~ 0.02 per
    unit) instead of a haze that explains training views and generalises badly."""


class ScalarField(nn.Module):
    """Encoder + decoder + appearance embedding, on flat point batches.

    Args:
        config: field hyper-parameters.
        num_images: number of training images (appearance embeddings).
    """

    def __init__(self, config: ScalarFieldConfig, num_images: int) -> None:
        super().__init__()
        self.config = config
        self.encoder = HashGridEncoding(
            num_levels=config.num_levels,
            features_per_level=config.features_per_level,
            log2_hashmap_size=config.log2_hashmap_size,
            base_resolution=config.base_resolution,
            max_resolution=config.max_resolution,
            implementation=config.encoder_implementation,
        )
        self.direction_encoding = SHEncoding(levels=config.sh_degree, implementation="torch")
        choice = choose_cpu_decoder_kernel(
            config.cpu_decoder_kernel,
            config.decoder_precision,
            fused=config.fused_decoder,
            bfloat16_is_fast=cpu_bfloat16_is_fast(),
            has_avx512bf16=fused_mlp_available(),
            has_avx2=float32_mlp_isa() == "avx2",
        )
        if choice.note is not None:
            _warn_once(choice.note)
        self.cpu_decoder_kernel = choice.kernel
        self.decoder = Decoder(
            in_dim=self.encoder.get_out_dim(),
            hidden_dim=config.hidden_dim,
            geo_feat_dim=config.geo_feat_dim,
            direction_dim=self.direction_encoding.get_out_dim(),
            appearance_dim=config.appearance_dim,
            density_bias=config.density_bias,
            training_kernel=choice.kernel,
        )
        self.appearance = nn.Embedding(max(num_images, 1), config.appearance_dim)
        nn.init.normal_(self.appearance.weight, std=0.01)
        self.cpu_bfloat16 = choice.bfloat16

    def _decoder_autocast(self, like: Tensor) -> torch.autocast:
        """bfloat16 autocast for the decoder on CPU when configured; a no-op context otherwise."""
        return torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.cpu_bfloat16 and like.device.type == "cpu")

    def density_at_unit(
        self, unit_positions: Tensor, encoding: Optional[Tensor] = None, *, gradient_rows: Optional[Tensor] = None
    ) -> tuple[Tensor, Tensor]:
        """[N, 3] contracted unit-cube positions -> ([N] float32 density, [N, geo_feat_dim] features).

        When ``unit_positions`` requires grad (and grad mode is on), the density is differentiable
        with respect to the positions: without ``encoding`` (surface normals) the encoding runs through
        :func:`encode_with_position_gradients` (no table gradient) and the decoder in float32 (no
        autocast); with it (a training step that refines poses) the table gets the kernels' gradient and
        the positions that function's. Otherwise the fast kernels (positions get no gradient) and the
        configured decoder precision are used.

        Args:
            unit_positions: [N, 3] contracted unit-cube positions.
            encoding: [N, L * F] ``self.encoder(unit_positions)`` computed earlier without autograd
                (a training step's no-grad pass): it is not computed again, and the table still
                gets its gradient (:meth:`HashGridEncoding.with_table_gradient`).
            gradient_rows: [G] with ``encoding``: the rows whose positions get a gradient (the others none);
                None: every row.
        """
        position_gradients = unit_positions.requires_grad and torch.is_grad_enabled()
        if position_gradients and encoding is None:
            features = encode_with_position_gradients(self.encoder, unit_positions)
            with torch.autocast(device_type=features.device.type, enabled=False):
                return self.decoder.density(features)
        if encoding is not None:
            features = self.encoder.with_table_gradient(unit_positions.detach(), encoding)
            if position_gradients:  # the kernels' values and table gradient, the positions' gradient from torch
                rows = unit_positions if gradient_rows is None else unit_positions[gradient_rows]
                through = encode_with_position_gradients(self.encoder, rows)
                through = through - through.detach()  # zero, with the positions' gradient
                features = features + through if gradient_rows is None else features.index_add(0, gradient_rows, through)
        else:
            features = self.encoder(unit_positions)
        with self._decoder_autocast(features):
            return self.decoder.density(features)

    def appearance_for(self, camera_indices: Optional[Tensor], num_points: int) -> Tensor:
        """[N] training-image indices -> [N, app]; the mean embedding when not training or no index."""
        if self.training and camera_indices is not None:
            return self.appearance(camera_indices.clamp(0, self.appearance.num_embeddings - 1))
        mean = self.appearance.weight.mean(dim=0, keepdim=True)
        return mean.expand(num_points, -1)

    def colour(self, geo_features: Tensor, ray_directions: Tensor, ray_ids: Tensor, *, camera_indices: Optional[Tensor]) -> Tensor:
        """RGB of samples on rays: the view-direction encoding and the appearance are computed once per ray.

        Args:
            geo_features: [M, geo] features of the samples (from :meth:`density_at_unit`).
            ray_directions: [R, 3] unit view directions of the rays.
            ray_ids: [M] the ray of each sample (indices into the R rays).
            camera_indices: [R] training-image index of each ray, or None.

        Returns:
            [M, 3] float32 RGB in [0, 1].
        """
        encoded = self.direction_encoding(ray_directions)[ray_ids]  # torch SH takes unit vectors in [-1, 1]
        appearance = self.appearance_for(camera_indices, ray_directions.shape[0])[ray_ids]
        with self._decoder_autocast(geo_features):
            return self.decoder.colour(geo_features, encoded, appearance)
