"""Multi-resolution hash-grid encoding (Instant-NGP), fast on CPU and exact.

Semantics (shared by every implementation in this module and by the C++ kernel):

* **Levels.** ``L = num_levels`` levels with resolutions ``R_l = floor(base * b**l)`` where
  ``b = exp((ln max_resolution - ln base) / (L - 1))`` (``R_0 = base`` when ``L == 1``); a 1e-6
  tolerance is added before the floor so float round-off cannot turn e.g. 4096 into 4095.
  Level ``l`` has grid vertices at integer coordinates ``0..R_l`` along each axis.
* **Interpolation.** A point ``p`` in ``[0, 1]^3`` (unitless, normalised scene coordinates) is
  scaled to ``pos = p * R_l`` (float32); its cell corner is ``cell = min(floor(pos), R_l - 1)``
  (so ``p == 1`` lies in the last cell with weight 1 on the upper vertex) and
  ``frac = pos - cell`` gives the trilinear weights of the 8 vertices ``cell + {0, 1}^3``.
* **Table rows.** With ``T = 2**log2_hashmap_size``, a level is *dense* when
  ``(R_l + 1)^3 <= T``: it owns exactly ``(R_l + 1)^3`` rows and vertex ``(x, y, z)`` maps to row
  ``x + y (R_l + 1) + z (R_l + 1)^2``. Otherwise the level owns ``T`` rows and the row is
  ``(x * 1 XOR y * 2654435761 XOR z * 805459861) mod T`` in uint32 arithmetic (as tiny-cuda-nn).
  All levels live in one flat ``table`` of shape ``[sum_l rows_l, F]``; level ``l`` starts at row
  ``level_offsets[l]``.
* **Out-of-range inputs.** Coordinates are sanitised before use: NaN -> 0, then clamped to
  ``[0, 1]`` (so +-inf and huge values land on the boundary). Outputs are therefore always finite
  and every row index is in range.
* **Gradients.** Only the table receives gradients; positions get none (the field never needs
  d(features)/d(positions)).

Implementations: ``"cpp"`` (C++/OpenMP kernel JIT-built on first use, CPU tensors only; uses
``torch.get_num_threads()`` threads and gives bitwise the same results for any thread count),
``"cuda"`` (CUDA kernel JIT-built with nvcc on first use, CUDA tensors only; one launch per pass,
its backward adds with atomics) and ``"torch"`` (vectorised pure torch, any device). ``"auto"``
uses the kernel of the tensors' device when it builds and ``"torch"`` otherwise. All agree with
the tests' oracle, ``reference_hash_encoding`` in ``encodings/_reference.py``, up to float32
summation order.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import torch
from torch import Tensor, nn

from scalar_nerfstudio.encodings import _cpp

if TYPE_CHECKING:
    from torch._ops import _OpNamespace

Implementation = Literal["auto", "cpp", "cuda", "torch"]

PRIME_Y = 2654435761
PRIME_Z = 805459861
CPP_FEATURES_PER_LEVEL = (1, 2, 4, 8)  # F values the C++ and CUDA kernels are specialised for


def grid_resolutions(num_levels: int, base_resolution: int, max_resolution: int) -> list[int]:
    """Per-level grid resolutions ``R_l`` (cells per axis), geometric from base to max.

    Args:
        num_levels: number of levels ``L`` (>= 1).
        base_resolution: resolution of level 0.
        max_resolution: resolution of level ``L - 1`` (ignored when ``L == 1``).

    Returns:
        ``L`` integers ``floor(base * b**l + 1e-6)``, ``b = exp((ln max - ln base) / (L - 1))``.
    """
    if num_levels == 1:
        return [base_resolution]
    growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / (num_levels - 1))
    return [math.floor(base_resolution * growth**level + 1e-6) for level in range(num_levels)]


def is_dense_level(resolution: int, hashmap_size: int) -> bool:
    """Whether a level of ``resolution`` cells per axis is stored densely (no hashing)."""
    return (resolution + 1) ** 3 <= hashmap_size


def level_row_counts(resolutions: Sequence[int], hashmap_size: int) -> list[int]:
    """Table rows of each level: ``(R + 1)^3`` for dense levels, ``hashmap_size`` otherwise."""
    return [(r + 1) ** 3 if is_dense_level(r, hashmap_size) else hashmap_size for r in resolutions]


def sanitise_positions(positions: Tensor) -> Tensor:
    """Map NaN to 0 and clamp to ``[0, 1]``: ``[N, 3] -> [N, 3]`` (new tensor, same dtype)."""
    return torch.nan_to_num(positions, nan=0.0, posinf=1.0, neginf=0.0).clamp_(0.0, 1.0)


def level_corners(coords: Tensor, resolution: int, hashmap_size: int) -> tuple[Tensor, Tensor]:
    """Rows and trilinear weights of the 8 vertices around each point on one level.

    Coordinate- and corner-major layouts (``[3, N]`` in, ``[8, N]`` out): every elementwise op
    then runs over long contiguous rows, several times faster in torch than broadcasting over
    tiny trailing dimensions.

    Args:
        coords: ``[3, N]`` float32 (x, y and z rows), already sanitised (see
            :func:`sanitise_positions`).
        resolution: ``R`` of the level (cells per axis).
        hashmap_size: ``T``, a power of two.

    Returns:
        ``rows`` ``[8, N]`` int64, relative to the level's first table row, in ``[0, rows_l)``;
        ``weights`` ``[8, N]`` float32. Corner ``c = i + 2 j + 4 k`` is ``cell + (i, j, k)``.
    """
    scaled = coords * resolution
    cell_f = scaled.floor().clamp_(max=resolution - 1)
    frac = scaled - cell_f
    dense = is_dense_level(resolution, hashmap_size)
    side = resolution + 1
    mult_y, mult_z = (side, side * side) if dense else (PRIME_Y, PRIME_Z)
    cell = cell_f.long()
    # Coordinates are < 2^24, so the int64 products cannot overflow and their low 32 bits (all
    # that survives the mask of a hashed level) equal the uint32 wrap-around products.
    hx = torch.stack((cell[0], cell[0] + 1))  # [2, N]: lower / upper corner terms per axis
    hy = torch.stack((cell[1], cell[1] + 1)) * mult_y
    hz = torch.stack((cell[2], cell[2] + 1)) * mult_z
    if dense:
        rows = (hz[:, None, None] + hy[None, :, None]) + hx[None, None, :]  # [k, j, i, N]
    else:
        rows = ((hz[:, None, None] ^ hy[None, :, None]) ^ hx[None, None, :]) & (hashmap_size - 1)
    lower_w = 1.0 - frac
    wx, wy, wz = (torch.stack((lower_w[d], frac[d])) for d in range(3))  # [2, N] each
    weights = (wx[None, None, :] * wy[None, :, None]) * wz[:, None, None]  # [k, j, i, N]
    return rows.view(8, -1), weights.view(8, -1)


@dataclass(frozen=True)
class GridLayout:
    """Static description of the table layout (plain Python ints: no device syncs).

    Attributes:
        resolutions: ``R_l`` per level, length ``L``.
        level_offsets: first row of each level plus the total row count, length ``L + 1``.
        hashmap_size: ``T = 2**log2_hashmap_size``.
    """

    resolutions: tuple[int, ...]
    level_offsets: tuple[int, ...]
    hashmap_size: int


def _torch_table_gradient(coords: Tensor, grad_out: Tensor, layout: GridLayout, table_shape: torch.Size) -> Tensor:
    """Table gradient ``[rows, F]`` of the encoding at ``coords`` ``[3, N]`` (sanitised) for ``grad_out`` ``[N, L * F]``."""
    num_features = table_shape[1]
    grad_table = torch.zeros(table_shape, dtype=grad_out.dtype, device=grad_out.device)
    # [L, N, F]: contiguous per-level slices make the products below several times faster.
    grad_levels = grad_out.reshape(grad_out.shape[0], -1, num_features).transpose(0, 1).contiguous()
    for level, res in enumerate(layout.resolutions):
        start, stop = layout.level_offsets[level], layout.level_offsets[level + 1]
        rows, weights = level_corners(coords, res, layout.hashmap_size)
        contributions = weights.unsqueeze(-1) * grad_levels[level].unsqueeze(0)  # [8, N, F]
        grad_table[start:stop].index_add_(0, rows.view(-1), contributions.view(-1, num_features))
    return grad_table


def _kernel_table_gradient(
    kernel: _OpNamespace, positions: Tensor, grad_out: Tensor, layout: GridLayout, num_features: int
) -> Tensor:
    """Table gradient ``[rows, F]`` of a kernel's encoding (C++ or CUDA ops) at ``positions`` ``[N, 3]`` for ``grad_out`` ``[N, L * F]``."""
    return kernel.backward(
        grad_out.contiguous(), positions, list(layout.level_offsets), list(layout.resolutions), layout.hashmap_size, num_features
    )


class _TorchHashGrid(torch.autograd.Function):
    """Vectorised torch hash-grid encoding with a single-gradient-table backward (any device)."""

    @staticmethod
    def forward(ctx: Any, positions: Tensor, table: Tensor, layout: GridLayout) -> Tensor:
        """``positions`` ``[N, 3]`` (sanitised), ``table`` ``[rows, F]`` -> ``[N, L * F]``."""
        num_features = table.shape[1]
        coords = positions.t().contiguous()
        out = torch.empty(
            positions.shape[0], len(layout.resolutions) * num_features, dtype=table.dtype, device=table.device
        )
        for level, res in enumerate(layout.resolutions):
            start, stop = layout.level_offsets[level], layout.level_offsets[level + 1]
            rows, weights = level_corners(coords, res, layout.hashmap_size)
            corner_features = table[start:stop].index_select(0, rows.view(-1)).view(8, -1, num_features)
            out[:, level * num_features : (level + 1) * num_features] = (corner_features * weights.unsqueeze(-1)).sum(0)
        ctx.save_for_backward(coords)
        ctx.layout = layout
        ctx.table_shape = table.shape
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad_out: Tensor) -> tuple[None, Tensor | None, None]:
        """``grad_out`` ``[N, L * F]`` -> gradient of the table ``[rows, F]`` (none for positions)."""
        if not ctx.needs_input_grad[1]:
            return None, None, None
        (coords,) = ctx.saved_tensors
        return None, _torch_table_gradient(coords, grad_out, ctx.layout, ctx.table_shape), None


class _KernelHashGrid(torch.autograd.Function):
    """Hash-grid encoding by a kernel: the C++/OpenMP ops (CPU) or the CUDA ops (float32, contiguous inputs)."""

    @staticmethod
    def forward(ctx: Any, positions: Tensor, table: Tensor, layout: GridLayout, kernel: _OpNamespace) -> Tensor:
        """``positions`` ``[N, 3]``, ``table`` ``[rows, F]`` -> ``[N, L * F]``; sanitises internally."""
        out = kernel.forward(positions, table, list(layout.level_offsets), list(layout.resolutions), layout.hashmap_size)
        ctx.save_for_backward(positions)
        ctx.layout, ctx.kernel = layout, kernel
        ctx.num_features = table.shape[1]
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad_out: Tensor) -> tuple[None, Tensor | None, None, None]:
        """``grad_out`` ``[N, L * F]`` -> gradient of the table ``[rows, F]`` (none for positions)."""
        if not ctx.needs_input_grad[1]:
            return None, None, None, None
        (positions,) = ctx.saved_tensors
        return None, _kernel_table_gradient(ctx.kernel, positions, grad_out, ctx.layout, ctx.num_features), None, None


class _PrecomputedEncoding(torch.autograd.Function):
    """An encoding computed earlier without autograd, joined to the table's graph: the forward returns
    it unchanged (no table lookups), the backward is the chosen implementation's table gradient.

    The features are linear in the table, so their gradient needs only the positions: a training
    step that has already encoded its samples in a no-grad pass does not encode them again."""

    @staticmethod
    def forward(  # noqa: PLR0917 - torch's Function.apply passes the inputs positionally
        ctx: Any, positions: Tensor, table: Tensor, layout: GridLayout, encoding: Tensor, kernel: _OpNamespace | None
    ) -> Tensor:
        """``positions`` ``[N, 3]`` float32, ``encoding`` ``[N, L * F]`` (their encoding by ``table``) -> ``encoding``.
        ``kernel``: the C++ or CUDA ops whose backward gives the table gradient, ``None`` for torch's."""
        ctx.save_for_backward(positions if kernel is not None else sanitise_positions(positions).t().contiguous())
        ctx.layout, ctx.kernel, ctx.table_shape = layout, kernel, table.shape
        return encoding.view_as(encoding)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad_out: Tensor) -> tuple[None, Tensor | None, None, None, None]:
        """``grad_out`` ``[N, L * F]`` -> gradient of the table ``[rows, F]`` (none for positions or the encoding)."""
        if not ctx.needs_input_grad[1]:
            return None, None, None, None, None
        (saved,) = ctx.saved_tensors
        if ctx.kernel is not None:
            grad_table = _kernel_table_gradient(ctx.kernel, saved, grad_out, ctx.layout, ctx.table_shape[1])
        else:
            grad_table = _torch_table_gradient(saved, grad_out, ctx.layout, ctx.table_shape)
        return None, grad_table, None, None, None


def hash_encoding_torch(positions: Tensor, table: Tensor, layout: GridLayout) -> Tensor:
    """Vectorised pure-torch encoding: ``[N, 3]`` float32 -> ``[N, L * F]``; any device."""
    return _TorchHashGrid.apply(sanitise_positions(positions), table, layout)


def hash_encoding_cpp(positions: Tensor, table: Tensor, layout: GridLayout) -> Tensor:
    """C++ encoding: ``[N, 3]`` -> ``[N, L * F]``.

    Raises:
        RuntimeError: if the kernel cannot be built, or ``positions`` / ``table`` are not
            contiguous float32 CPU tensors of shapes ``[N, 3]`` / ``[rows, F]`` (F in 1, 2, 4, 8).
    """
    return _KernelHashGrid.apply(positions, table, layout, _cpp.require_extension())


def hash_encoding_cuda(positions: Tensor, table: Tensor, layout: GridLayout) -> Tensor:
    """CUDA encoding: ``[N, 3]`` -> ``[N, L * F]`` (built with nvcc on first call).

    Raises:
        RuntimeError: if the kernel cannot be built, or ``positions`` / ``table`` are not
            contiguous float32 CUDA tensors of shapes ``[N, 3]`` / ``[rows, F]`` (F in 1, 2, 4, 8).
    """
    return _KernelHashGrid.apply(positions, table, layout, _cpp.CUDA_HASH_GRID.require())


class HashGridEncoding(nn.Module):
    """Multi-resolution hash-grid encoding of points in ``[0, 1]^3`` (see the module docstring).

    Args:
        num_levels: number of levels ``L``.
        features_per_level: features ``F`` stored per table row (the C++ kernel supports 1, 2, 4 and
            8; ``"auto"`` uses torch for other values).
        log2_hashmap_size: ``log2 T``; hashed levels have ``T`` rows.
        base_resolution: resolution (cells per axis) of the coarsest level.
        max_resolution: resolution of the finest level.
        implementation: ``"auto"`` (the C++ kernel on CPU and the CUDA kernel on CUDA, each when it
            builds, torch otherwise), ``"cpp"`` (C++ on CPU, error if it cannot be built; CUDA tensors
            use torch), ``"cuda"`` (the CUDA kernel on CUDA, error if it cannot be built; CPU tensors as
            ``"auto"``) or ``"torch"``.
        init_scale: table entries are initialised uniformly in ``[-init_scale, init_scale]``.

    Attributes:
        table: ``[sum_l rows_l, F]`` float32 parameter, all levels stacked.
        level_offsets: ``[L + 1]`` int64 buffer, first row of each level and the total.
        resolutions: ``L`` ints ``R_l``.
    """

    level_offsets: Tensor

    def __init__(
        self,
        *,
        num_levels: int = 16,
        features_per_level: int = 4,
        log2_hashmap_size: int = 19,
        base_resolution: int = 16,
        max_resolution: int = 2048,
        implementation: Implementation = "auto",
        init_scale: float = 1e-4,
    ) -> None:
        super().__init__()
        if num_levels < 1 or features_per_level < 1:
            raise ValueError("num_levels and features_per_level must be >= 1")
        if not 1 <= log2_hashmap_size <= 31:
            raise ValueError(f"log2_hashmap_size must be in [1, 31], got {log2_hashmap_size}")
        if not 1 <= base_resolution <= max_resolution < 2**24:
            raise ValueError(
                f"need 1 <= base_resolution <= max_resolution < 2**24, got {base_resolution}, {max_resolution}"
            )
        if implementation not in ("auto", "cpp", "cuda", "torch"):
            raise ValueError(f"implementation must be 'auto', 'cpp', 'cuda' or 'torch', got {implementation!r}")
        if implementation in ("cpp", "cuda") and features_per_level not in CPP_FEATURES_PER_LEVEL:
            raise ValueError(f"the {implementation} kernel supports features_per_level in {CPP_FEATURES_PER_LEVEL}")
        self.num_levels = num_levels
        self.features_per_level = features_per_level
        self.log2_hashmap_size = log2_hashmap_size
        self.hashmap_size = 2**log2_hashmap_size
        self.implementation: Implementation = implementation
        self.resolutions: list[int] = grid_resolutions(num_levels, base_resolution, max_resolution)
        offsets = [0]
        for rows in level_row_counts(self.resolutions, self.hashmap_size):
            offsets.append(offsets[-1] + rows)
        self.layout = GridLayout(tuple(self.resolutions), tuple(offsets), self.hashmap_size)
        self.register_buffer("level_offsets", torch.tensor(offsets, dtype=torch.int64), persistent=False)
        self.table = nn.Parameter(torch.empty(offsets[-1], features_per_level).uniform_(-init_scale, init_scale))

    def get_out_dim(self) -> int:
        """Output feature dimension ``L * F``."""
        return self.num_levels * self.features_per_level

    @property
    def active_implementation(self) -> Literal["cpp", "cuda", "torch"]:
        """Implementation :meth:`forward` uses for the table's current device (may build the kernel)."""
        return self.implementation_for(self.table.device)

    def implementation_for(self, device: torch.device | str) -> Literal["cpp", "cuda", "torch"]:
        """Implementation :meth:`forward` uses for tensors on ``device`` (may build the kernel; allocates
        nothing there).

        Raises:
            RuntimeError: if ``implementation`` names a kernel for that device that cannot be built.
        """
        device = torch.device(device)
        if self._kernel(device) is None:
            return "torch"
        return "cuda" if device.type == "cuda" else "cpp"

    def _kernel(self, device: torch.device) -> _OpNamespace | None:
        """The ops of the kernel that encodes tensors on ``device`` (C++ on CPU, CUDA on CUDA), or
        ``None`` for the torch implementation (builds the kernel on first call)."""
        if self.implementation == "torch" or self.features_per_level not in CPP_FEATURES_PER_LEVEL:
            return None
        if device.type == "cpu":
            extension, required = _cpp.CPU_KERNELS, self.implementation == "cpp"
        elif device.type == "cuda" and self.implementation != "cpp":
            extension, required = _cpp.CUDA_HASH_GRID, self.implementation == "cuda"
        else:
            return None
        if required:
            try:
                return extension.require()
            except RuntimeError as exc:
                raise RuntimeError(f"implementation={self.implementation!r} but {exc}") from exc
        return extension.load()

    def forward(self, positions: Tensor) -> Tensor:
        """Encode points.

        Args:
            positions: ``[..., 3]`` coordinates in ``[0, 1]`` (float32; other float dtypes are cast).
                NaN -> 0, values outside ``[0, 1]`` are clamped. No gradient flows to them.

        Returns:
            ``[..., L * F]`` float32 features, level-major.
        """
        if positions.shape[-1] != 3 or not positions.is_floating_point():
            raise ValueError(
                f"positions must be a float tensor of shape [..., 3], got {positions.dtype} {tuple(positions.shape)}"
            )
        flat = positions.reshape(-1, 3).to(torch.float32).contiguous()
        kernel = self._kernel(flat.device)
        if kernel is not None:
            out = _KernelHashGrid.apply(flat, self.table, self.layout, kernel)
        else:
            out = hash_encoding_torch(flat, self.table, self.layout)
        return out.view(*positions.shape[:-1], self.get_out_dim())

    def with_table_gradient(self, positions: Tensor, encoding: Tensor) -> Tensor:
        """``encoding``, the output of :meth:`forward` for ``positions`` computed earlier without
        autograd, as if :meth:`forward` had just computed it: the table gets the same gradient.

        Args:
            positions: ``[N, 3]`` float32 coordinates the encoding was computed at.
            encoding: ``[N, L * F]`` float32, ``self(positions)`` with the table unchanged since.

        Returns:
            ``[N, L * F]``: the values of ``encoding``, differentiable with respect to the table.
        """
        if positions.ndim != 2 or positions.shape[-1] != 3 or encoding.shape != (positions.shape[0], self.get_out_dim()):
            raise ValueError(
                f"positions [N, 3] and encoding [N, {self.get_out_dim()}] expected, got {tuple(positions.shape)} and {tuple(encoding.shape)}"
            )
        if not (torch.is_grad_enabled() and self.table.requires_grad):  # nothing to join: no positions to keep
            return encoding
        flat = positions.to(torch.float32).contiguous()
        return _PrecomputedEncoding.apply(flat, self.table, self.layout, encoding, self._kernel(flat.device))

    def extra_repr(self) -> str:
        return (
            f"num_levels={self.num_levels}, features_per_level={self.features_per_level}, "
            f"log2_hashmap_size={self.log2_hashmap_size}, resolutions={self.resolutions}, "
            f"implementation={self.implementation!r}"
        )
