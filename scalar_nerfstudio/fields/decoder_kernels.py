"""Which kernels train the decoder on the CPU, and in which precision (issue 67).

Three ways to run the decoder's layers with autograd on the CPU:

* ``"avx512bf16"``: bfloat16 products in one fused C++ kernel per pass (``fields/fused_mlp.py``),
  where the CPU has AVX512-BF16;
* ``"avx2"``: float32 products in one fused C++ kernel per pass (``fields/fused_mlp_float32.py``),
  where the CPU has AVX2 and FMA;
* ``"torch"``: autograd layer by layer, in float32 or under bfloat16 autocast.

:func:`choose_cpu_decoder_kernel` turns the configured request and precision into one of them; it
is a pure function of what it is told about the CPU, so every combination can be tested on any
machine.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Optional

CpuDecoderKernel = Literal["auto", "avx512bf16", "avx2", "torch"]
DecoderPrecision = Literal["auto", "float32", "bfloat16"]


@dataclass(frozen=True)
class DecoderKernelChoice:
    """What :func:`choose_cpu_decoder_kernel` decided."""

    kernel: Literal["avx512bf16", "avx2", "torch"]
    """The kernels that train the decoder on the CPU."""
    bfloat16: bool
    """Whether the decoder's products run in bfloat16 (CPU autocast) rather than float32."""
    note: Optional[str] = None
    """Why the requested kernel was not taken (it cannot run here), or None."""


def kernel_conflict(requested: str, precision: str, fused: bool) -> Optional[str]:
    """Why ``cpu_decoder_kernel`` = ``requested`` contradicts ``decoder_precision`` = ``precision`` or
    ``fused_decoder`` = ``fused``, or None when it does not (whatever the CPU)."""
    if requested == "avx512bf16" and precision == "float32":
        return "cpu_decoder_kernel='avx512bf16' multiplies in bfloat16, but decoder_precision='float32'"
    if requested == "avx2" and precision == "bfloat16":
        return "cpu_decoder_kernel='avx2' multiplies in float32, but decoder_precision='bfloat16'"
    if not fused and requested in ("avx512bf16", "avx2"):
        return f"cpu_decoder_kernel={requested!r} names a fused kernel, but fused_decoder=False"
    return None


def choose_cpu_decoder_kernel(
    requested: CpuDecoderKernel,
    precision: DecoderPrecision,
    *,
    fused: bool,
    bfloat16_is_fast: bool,
    has_avx512bf16: bool,
    has_avx2: bool,
) -> DecoderKernelChoice:
    """The decoder's CPU training kernel and precision.

    Args:
        requested: ``"auto"``: avx512bf16 for bfloat16 products, avx2 for float32 ones, each where it
            runs, else torch; a named kernel that cannot run here falls back to ``"auto"``'s choice
            (with a note).
        precision: ``"auto"``: bfloat16 where the requested kernel is avx512bf16 or the CPU
            multiplies bfloat16 natively (``bfloat16_is_fast``), float32 where it is avx2 or
            otherwise.
        fused: False forces ``"torch"`` (the field's ``fused_decoder`` switch).
        bfloat16_is_fast: whether the CPU has native bfloat16 products (oneDNN's check).
        has_avx512bf16: whether the bfloat16 fused kernels run here (extension built, AVX512-BF16).
        has_avx2: whether the float32 fused kernels run here with AVX2 + FMA.

    Raises:
        ValueError: for contradictory settings (:func:`kernel_conflict`).
    """
    conflict = kernel_conflict(requested, precision, fused)
    if conflict is not None:
        raise ValueError(conflict)
    if not fused:
        requested = "torch"
    note = None
    if requested == "avx512bf16" and not has_avx512bf16:
        note = "cpu_decoder_kernel='avx512bf16' cannot run here (no AVX512-BF16, or the C++ extension did not build)"
        requested = "auto"
    elif requested == "avx2" and not has_avx2:
        note = "cpu_decoder_kernel='avx2' cannot run here (no AVX2 and FMA, or the C++ extension did not build)"
        requested = "auto"
    if requested == "avx512bf16":
        return DecoderKernelChoice("avx512bf16", True)
    if requested == "avx2":
        return DecoderKernelChoice("avx2", False)
    bfloat16 = precision == "bfloat16" or (precision == "auto" and bfloat16_is_fast)
    if requested == "torch":
        return DecoderKernelChoice("torch", bfloat16, note)
    if bfloat16 and has_avx512bf16:
        kernel: Literal["avx512bf16", "avx2", "torch"] = "avx512bf16"
    elif not bfloat16 and has_avx2:
        kernel = "avx2"
    else:
        kernel = "torch"
    if note is not None:
        note += f"; training the decoder with {kernel!r} in {'bfloat16' if bfloat16 else 'float32'} instead"
    return DecoderKernelChoice(kernel, bfloat16, note)
