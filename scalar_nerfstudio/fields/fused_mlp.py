"""The decoder's MLPs in bfloat16 on the CPU, forward and backward in one C++ kernel each (issue 18).

``csrc/mlp.cpp`` takes rows 64 at a time through every layer with AVX512-BF16 dot products
(float32 accumulation), applying bias, ReLU and the conversions as results are written, and computes
each layer's input, weight and bias gradients from one read of a tile. Autograd's layer-by-layer
bfloat16 path does the same arithmetic in separate passes.

:func:`fused_mlp_available` says whether it can run here (the extension built and the CPU has
AVX512-BF16); :func:`fused_mlp` is the differentiable call. The result equals ``mlp(inputs)`` computed
with bfloat16-rounded inputs, weights, hidden activations and output gradients and float32 sums,
which is what CPU autocast's bfloat16 products compute too.
"""

from __future__ import annotations

import functools
from typing import Optional, Sequence

import torch
from torch import Tensor, nn

from scalar_nerfstudio.encodings._cpp import load_extension

_WIDTH_MULTIPLE = 16


def padded_width(width: int, multiple: int = _WIDTH_MULTIPLE) -> int:
    """``width`` rounded up to a multiple of ``multiple`` (the kernels' padded layer widths)."""
    return -(-width // multiple) * multiple


@functools.lru_cache(maxsize=None)
def fused_mlp_available() -> bool:
    """Whether :func:`fused_mlp` runs here: the C++ extension builds and the CPU has AVX512-BF16.
    Answered once per process (the extension is built at most once; the CPU does not change), so
    :func:`fused_mlp` can ask on every call."""
    if load_extension() is None or not hasattr(torch.ops, "scalar_nerf_mlp"):
        return False
    try:
        return bool(torch.ops.scalar_nerf_mlp.supported())
    except (AttributeError, RuntimeError):
        return False


def linear_layers(mlp: nn.Sequential) -> tuple[list[nn.Linear], list[bool]]:
    """The Linear layers of ``mlp`` and, for each, whether a ReLU follows it.

    Raises:
        TypeError: if ``mlp`` holds anything but Linear and ReLU layers, a ReLU not after a Linear,
            or a ReLU after the last Linear.
    """
    layers: list[nn.Linear] = []
    relu: list[bool] = []
    for module in mlp:
        if isinstance(module, nn.Linear):
            layers.append(module)
            relu.append(False)
        elif isinstance(module, nn.ReLU) and layers and not relu[-1]:
            relu[-1] = True
        else:
            raise TypeError(f"expected Linear layers each optionally followed by one ReLU, got {mlp}")
    if not layers or relu[-1]:
        raise TypeError(f"expected at least one Linear layer and no ReLU after the last: {mlp}")
    return layers, relu


def mlp_arguments(mlp: nn.Sequential) -> tuple[tuple[bool, ...], list[Optional[Tensor]]]:
    """What the fused MLP functions take for ``mlp``: the ReLU flag of each Linear layer and its
    parameters in order (weight 0, bias 0, weight 1, ...; a missing bias is None). Raises as
    :func:`linear_layers`."""
    layers, relu = linear_layers(mlp)
    params: list[Optional[Tensor]] = []
    for layer in layers:
        params.extend([layer.weight, layer.bias])
    return tuple(relu), params


def padded_bias(bias: Optional[Tensor], out_dim: int, like: Tensor, *, multiple: int = _WIDTH_MULTIPLE) -> Tensor:
    """Bias [O] (zeros where None) as float32 [Op], zero-padded to a multiple of ``multiple``, on ``like``'s device."""
    padded = like.new_zeros(padded_width(out_dim, multiple), dtype=torch.float32)
    if bias is not None:
        padded[:out_dim] = bias.detach().float()
    return padded


def layer_gradients(results: Sequence[Tensor], shapes: Sequence[tuple[int, int]], *, has_bias: Sequence[bool],
                    needs_grad: Sequence[bool]) -> list[Optional[Tensor]]:
    """The parameters' gradients from a fused backward's ``results`` (the input gradient, then per layer
    grad_wt [Kp, Op] and grad_b [Op]): per layer weight [O, K] then bias [O], None where ``needs_grad``
    (one flag per parameter, weight then bias) is false or the layer has no bias."""
    grads: list[Optional[Tensor]] = []
    for index, (out_dim, in_dim) in enumerate(shapes):
        grad_wt, grad_b = results[1 + 2 * index], results[2 + 2 * index]
        grads.append(grad_wt[:in_dim, :out_dim].t() if needs_grad[2 * index] else None)
        grads.append(grad_b[:out_dim] if has_bias[index] and needs_grad[2 * index + 1] else None)
    return grads


def pack_weights(weight: Tensor) -> tuple[Tensor, Tensor]:
    """[O, K] float32 weight -> (forward [Kp/2, Op, 2], backward [Op/2, Kp, 2]) bfloat16, zero-padded
    to multiples of 16 (the kernel's layouts, csrc/mlp.cpp)."""
    out_dim, in_dim = weight.shape
    padded = weight.new_zeros(padded_width(out_dim), padded_width(in_dim))
    padded[:out_dim, :in_dim] = weight.detach()
    padded = padded.to(torch.bfloat16)
    forward = padded.view(padded.shape[0], -1, 2).permute(1, 0, 2).contiguous()
    backward = padded.view(-1, 2, padded.shape[1]).permute(0, 2, 1).contiguous()
    return forward, backward


class _FusedMlp(torch.autograd.Function):
    """inputs [N, K], then (weight, bias) per layer -> [N, O_last] float32."""

    @staticmethod
    def forward(ctx, inputs: Tensor, relu: tuple[bool, ...], *params: Tensor) -> Tensor:  # type: ignore[override]
        weights, biases = params[0::2], params[1::2]
        packed = [pack_weights(w) for w in weights]
        padded_biases = [padded_bias(b, w.shape[0], w) for w, b in zip(weights, biases)]
        flags = [int(r) for r in relu]
        results = torch.ops.scalar_nerf_mlp.forward(
            inputs.contiguous(), [f for f, _ in packed], padded_biases, flags, weights[-1].shape[0]
        )
        ctx.save_for_backward(*results[1:], *[b for _, b in packed])
        ctx.flags = flags
        ctx.shapes = [tuple(w.shape) for w in weights]
        ctx.has_bias = [b is not None for b in biases]
        ctx.input_dtype = inputs.dtype
        ctx.in_dim = inputs.shape[1]
        return results[0]

    @staticmethod
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        saved = ctx.saved_tensors
        count = len(ctx.flags)
        activations, packed_t = list(saved[:count]), list(saved[count:])
        need_input = ctx.needs_input_grad[0]
        results = torch.ops.scalar_nerf_mlp.backward(
            grad_out.float().contiguous(), activations, packed_t, ctx.flags, ctx.in_dim if need_input else 0
        )
        grad_input = results[0].to(ctx.input_dtype) if need_input else None
        return (grad_input, None, *layer_gradients(results, ctx.shapes, has_bias=ctx.has_bias, needs_grad=ctx.needs_input_grad[2:]))


def fused_mlp(mlp: nn.Sequential, inputs: Tensor) -> Tensor:
    """``mlp(inputs)`` through the fused bfloat16 kernels, differentiable in the inputs and parameters.

    Args:
        mlp: Linear layers, each optionally followed by one ReLU (none after the last).
        inputs: [N, K] float32 or bfloat16 CPU tensor.

    Returns:
        [N, O] float32 (sums in float32 of bfloat16 products).
    """
    if not fused_mlp_available():
        raise RuntimeError("fused_mlp needs the C++ extension and a CPU with AVX512-BF16 (fused_mlp_available())")
    relu, params = mlp_arguments(mlp)
    return _FusedMlp.apply(inputs, relu, *params)

