"""The decoder's MLPs in float32 on the CPU, forward and backward in one C++ kernel each (issue 67).

The sibling of :mod:`scalar_nerfstudio.fields.fused_mlp` (bfloat16, AVX512-BF16) for CPUs without
AVX512-BF16: ``csrc/mlp_f32.cpp`` takes rows 64 at a time through every layer with float32
fused multiply-adds, applying bias and ReLU as results are written, and computes each layer's
input, weight and bias gradients from one read of a tile. Its kernels are compiled twice, for
AVX2 + FMA (chosen at run time where the CPU has both) and for the compiler's baseline target (the
``"portable"`` fallback, the only one off x86).

:func:`float32_mlp_isa` says which kernels run here (or that the extension did not build);
:func:`fused_mlp_float32` is the differentiable call, :func:`mlp_float32_inference` the one without autograd. The result equals ``mlp(inputs)`` in float32
up to the order of the sums.
"""

from __future__ import annotations

import functools
from typing import Literal, Optional, cast

import torch
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from scalar_nerfstudio.encodings._cpp import load_extension
from scalar_nerfstudio.fields.fused_mlp import layer_gradients, mlp_arguments, padded_bias, padded_width

Float32Isa = Literal["avx2", "portable"]
_WIDTH_MULTIPLE = 8


@functools.lru_cache(maxsize=None)
def float32_mlp_isa() -> Optional[Float32Isa]:
    """The best float32 MLP kernels this process can run: ``"avx2"`` (AVX2 + FMA), ``"portable"`` (any
    CPU), or ``None`` when the C++ extension did not build. Answered once per process."""
    if load_extension() is None or not hasattr(torch.ops, "scalar_nerf_mlp_f32"):
        return None
    try:
        return "avx2" if str(torch.ops.scalar_nerf_mlp_f32.isa()) == "avx2" else "portable"
    except (AttributeError, RuntimeError):
        return None


def pack_weights_float32(weight: Tensor) -> tuple[Tensor, Tensor]:
    """[O, K] weight -> (forward [Kp, Op] = W^T, backward [Op, Kp] = W) float32, zero-padded to
    multiples of 8 (the kernel's layouts, csrc/mlp_f32.cpp)."""
    out_dim, in_dim = weight.shape
    shape = (padded_width(out_dim, _WIDTH_MULTIPLE), padded_width(in_dim, _WIDTH_MULTIPLE))
    padded = weight.new_zeros(shape, dtype=torch.float32)
    padded[:out_dim, :in_dim] = weight.detach()
    return padded.t().contiguous(), padded


class _FusedMlpFloat32(torch.autograd.Function):
    """inputs [N, K] float32, then (weight, bias) per layer -> [N, O_last] float32."""

    @staticmethod
    def forward(ctx, inputs: Tensor, relu: tuple[bool, ...], isa: str, *params: Tensor) -> Tensor:  # type: ignore[override]
        weights, biases = params[0::2], params[1::2]
        packed = [pack_weights_float32(w) for w in weights]
        padded_biases = [padded_bias(b, w.shape[0], w, multiple=_WIDTH_MULTIPLE) for w, b in zip(weights, biases)]
        flags = [int(r) for r in relu]
        results = torch.ops.scalar_nerf_mlp_f32.forward(
            inputs.contiguous(), [f for f, _ in packed], padded_biases, flags, weights[-1].shape[0], isa
        )
        ctx.save_for_backward(*results[1:], *[b for _, b in packed])
        ctx.flags = flags
        ctx.isa = isa
        ctx.shapes = [tuple(w.shape) for w in weights]
        ctx.has_bias = [b is not None for b in biases]
        ctx.in_dim = inputs.shape[1]
        return results[0]

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        saved = ctx.saved_tensors
        count = len(ctx.flags)
        activations, packed = list(saved[:count]), list(saved[count:])
        need_input = ctx.needs_input_grad[0]
        results = torch.ops.scalar_nerf_mlp_f32.backward(
            grad_out.float().contiguous(), activations, packed, ctx.flags, ctx.in_dim if need_input else 0, ctx.isa
        )
        grad_input = results[0] if need_input else None
        return (grad_input, None, None, *layer_gradients(results, ctx.shapes, has_bias=ctx.has_bias, needs_grad=ctx.needs_input_grad[3:]))


def fused_mlp_float32(mlp: nn.Sequential, inputs: Tensor, isa: Optional[Float32Isa] = None) -> Tensor:
    """``mlp(inputs)`` in float32 through the fused kernels, differentiable (once) in the inputs and
    parameters.

    Args:
        mlp: Linear layers (float32 parameters), each optionally followed by one ReLU (none after the last).
        inputs: [N, K] float32 CPU tensor.
        isa: which compiled kernels: ``"avx2"`` or ``"portable"``; None: :func:`float32_mlp_isa`.

    Returns:
        [N, O] float32.

    Raises:
        RuntimeError: if the extension did not build, or ``isa`` is ``"avx2"`` on a CPU without AVX2 and FMA.
        TypeError: if ``mlp`` holds other layers, or the inputs or parameters are not float32.
    """
    isa, relu, params = _checked_arguments("fused_mlp_float32", mlp, inputs, isa)
    return _FusedMlpFloat32.apply(inputs, relu, isa, *params)


def _checked_arguments(caller: str, mlp: nn.Sequential, inputs: Tensor, isa: Optional[Float32Isa]):
    """(the kernels to run, the ReLU flags, the parameters) of ``caller``'s call, raising as
    :func:`fused_mlp_float32` documents."""
    available = float32_mlp_isa()
    if available is None:
        raise RuntimeError(f"{caller} needs the C++ extension, which did not build (see the warning logged)")
    if isa is None:
        isa = available
    elif isa == "avx2" and available != "avx2":
        raise RuntimeError(f"{caller}: isa='avx2' asked for, but this CPU lacks AVX2 or FMA")
    relu, params = mlp_arguments(mlp)
    if inputs.dtype != torch.float32 or any(p is not None and p.dtype != torch.float32 for p in params):
        raise TypeError(f"{caller} takes float32 inputs and parameters, got inputs in {inputs.dtype}")
    return isa, relu, params


def mlp_float32_inference(mlp: nn.Sequential, inputs: Tensor, isa: Optional[Float32Isa] = None) -> Tensor:
    """``mlp(inputs)`` in float32 through the fused kernels, without autograd: each 64-row tile goes through
    every layer in per-thread buffers (no [N, width] activation is written between layers).

    Args:
        mlp: Linear layers (float32 parameters), each optionally followed by one ReLU (none after the last).
        inputs: [N, K] float32 CPU tensor.
        isa: which compiled kernels: ``"avx2"`` or ``"portable"``; None: :func:`float32_mlp_isa`.

    Returns:
        [N, O] float32, equal to ``mlp(inputs)`` up to the order of the sums.

    Raises:
        RuntimeError and TypeError as :func:`fused_mlp_float32`.
    """
    isa, relu, params = _checked_arguments("mlp_float32_inference", mlp, inputs, isa)
    # mlp_arguments: the weights (even entries) are never None, only biases may be
    weights, biases = [cast(Tensor, w) for w in params[0::2]], params[1::2]
    packed = [pack_weights_float32(w)[0] for w in weights]
    padded_biases = [padded_bias(b, w.shape[0], w, multiple=_WIDTH_MULTIPLE) for w, b in zip(weights, biases)]
    with torch.no_grad():
        return torch.ops.scalar_nerf_mlp_f32.infer(inputs.contiguous(), packed, padded_biases, [int(r) for r in relu], weights[-1].shape[0], isa)
