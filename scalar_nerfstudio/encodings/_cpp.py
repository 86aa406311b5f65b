"""Lazy, once-per-process JIT builds of the C++/OpenMP CPU kernels and the CUDA hash grid.

The CPU kernels (``scalar_nerfstudio/csrc/hash_grid.cpp``, ``csrc/sampling.cpp``, ``csrc/march.cpp``,
``csrc/mlp.cpp`` and ``csrc/mlp_f32.cpp``) are compiled
into one extension with :func:`torch.utils.cpp_extension.load` on first use (~20 s; cached
afterwards in torch's extension directory, ``$TORCH_EXTENSIONS_DIR`` or
``~/.cache/torch_extensions``). It registers the ops ``torch.ops.scalar_nerf_hash_grid.forward``
and ``.backward`` (the hash grid), and ``torch.ops.scalar_nerf_sampling.unit_positions`` and
``.worth_evaluating`` (ray samples and the occupancy test), ``torch.ops.scalar_nerf_march.round_candidates``,
``.round_keep`` and ``.composite`` (the render march without gradients), and ``torch.ops.scalar_nerf_mlp.forward``,
``.backward`` and ``.supported`` (the fused bfloat16 decoder, ``fields/fused_mlp.py``), and
``torch.ops.scalar_nerf_mlp_f32.forward``, ``.backward`` and ``.isa`` (the fused float32 decoder,
``fields/fused_mlp_float32.py``). No ``-march`` flag: the binary runs on any CPU of its architecture
(the cache is keyed by the sources, not the CPU); kernels for newer instruction sets (AVX512-BF16,
AVX2 + FMA) are compiled per function and chosen at run time.

The CUDA hash grid (``csrc/hash_grid_cuda.cu``, ops ``torch.ops.scalar_nerf_hash_grid_cuda.forward``
and ``.backward``) is a second extension, built with nvcc the first time a CUDA tensor is encoded
(about a minute; cached likewise). Importing this package builds neither.

If a build fails (no C++ compiler, no ninja, no nvcc, ...) one warning is logged and callers fall
back to their pure-torch implementations.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

if TYPE_CHECKING:
    from torch._ops import _OpNamespace

CSRC = Path(__file__).resolve().parent.parent / "csrc"
EXTENSION_NAME = "scalar_nerf_hash_grid"
SOURCES = [CSRC / name for name in ("hash_grid.cpp", "sampling.cpp", "march.cpp", "mlp.cpp", "mlp_f32.cpp")]
SAMPLING_NAMESPACE = "scalar_nerf_sampling"
MARCH_NAMESPACE = "scalar_nerf_march"
CUDA_EXTENSION_NAME = "scalar_nerf_hash_grid_cuda"
CUDA_SOURCES = [CSRC / "hash_grid_cuda.cu"]

_logger = logging.getLogger(__name__)


class JitExtension:
    """One extension built by :func:`torch.utils.cpp_extension.load` on the first :meth:`load`
    (per process, thread-safe); a failed build is remembered and not retried.

    Args:
        name: the extension's (and its op namespace's) name.
        sources: its source files.
        what: how the warning of a failed build names it.
        build_options: further keyword arguments of ``load`` (compiler flags).
    """

    def __init__(self, name: str, sources: list[Path], what: str, **build_options: Any) -> None:
        self.name = name
        self.sources = sources
        self.what = what
        self.build_options = build_options
        self._lock = threading.Lock()
        self._attempted = False
        self._ops: _OpNamespace | None = None
        self._error: str | None = None

    def load(self) -> _OpNamespace | None:
        """Build (first call only) and return ``torch.ops.<name>``, or ``None`` when the extension
        cannot be built; the reason is then available from :meth:`error`."""
        with self._lock:
            if not self._attempted:
                self._attempted = True
                try:
                    from torch.utils.cpp_extension import load

                    load(
                        name=self.name,
                        sources=[str(source) for source in self.sources],
                        is_python_module=False,
                        verbose=False,
                        **self.build_options,
                    )
                    self._ops = getattr(torch.ops, self.name)
                except Exception as exc:  # noqa: BLE001 - any build/load failure means "use the torch path"
                    self._error = f"{type(exc).__name__}: {exc}"
                    _logger.warning(
                        "Could not build the %s (%s); falling back to the pure-torch implementations, "
                        "which are several times slower.",
                        self.what,
                        self._error.splitlines()[0],
                    )
            return self._ops

    def require(self) -> _OpNamespace:
        """``torch.ops.<name>`` (built on first call).

        Raises:
            RuntimeError: if the extension cannot be built.
        """
        ops = self.load()
        if ops is None:
            raise RuntimeError(f"the {self.what} are unavailable: {self._error}")
        return ops

    def available(self) -> bool:
        """Whether the extension is usable in this process (builds it on first call)."""
        return self.load() is not None

    def error(self) -> str | None:
        """Why the extension could not be built, or ``None`` if it built (or was not tried yet)."""
        return self._error


CPU_KERNELS = JitExtension(
    EXTENSION_NAME, SOURCES, "C++ kernels", extra_cflags=["-O3", "-fopenmp"], extra_ldflags=["-fopenmp"]
)
CUDA_HASH_GRID = JitExtension(
    CUDA_EXTENSION_NAME,
    CUDA_SOURCES,
    "CUDA hash-grid kernels",
    extra_cflags=["-O3"],
    # No fused multiply-adds: the kernel's float32 results are then those of the C++ kernel.
    extra_cuda_cflags=["-O3", "--fmad=false"],
)


def load_extension() -> _OpNamespace | None:
    """Build (first call only) and return the op namespace of the C++ kernels.

    Returns:
        ``torch.ops.scalar_nerf_hash_grid`` (with ``forward`` and ``backward``), or ``None`` when
        the extension cannot be built; the reason is then available from :func:`extension_error`.
    """
    return CPU_KERNELS.load()


def sampling_ops() -> _OpNamespace | None:
    """``torch.ops.scalar_nerf_sampling`` (``unit_positions``, ``worth_evaluating``), or ``None``
    when the extension cannot be built (builds it on first call)."""
    if load_extension() is None:
        return None
    return getattr(torch.ops, SAMPLING_NAMESPACE)


def march_ops() -> _OpNamespace | None:
    """``torch.ops.scalar_nerf_march`` (``round_candidates``, ``round_keep``, ``composite``), or ``None``
    when the extension cannot be built (builds it on first call)."""
    if load_extension() is None:
        return None
    return getattr(torch.ops, MARCH_NAMESPACE)


def require_extension() -> _OpNamespace:
    """The op namespace of the C++ kernels (built on first call).

    Raises:
        RuntimeError: if the extension cannot be built.
    """
    return CPU_KERNELS.require()


def extension_available() -> bool:
    """Whether the C++ kernels are usable in this process (builds them on first call)."""
    return CPU_KERNELS.available()


def extension_error() -> str | None:
    """Why the C++ kernels could not be built, or ``None`` if they built (or were not tried yet)."""
    return CPU_KERNELS.error()
