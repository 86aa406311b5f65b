"""Lazy, once-per-process JIT build of the C++/OpenMP CPU kernels.

The kernels (``scalar_nerfstudio/csrc/hash_grid.cpp``, ``csrc/sampling.cpp`` and ``csrc/mlp.cpp``) are compiled
into one extension with :func:`torch.utils.cpp_extension.load` on first use (~20 s; cached
afterwards in torch's extension directory, ``$TORCH_EXTENSIONS_DIR`` or
``~/.cache/torch_extensions``). It registers the ops ``torch.ops.scalar_nerf_hash_grid.forward``
and ``.backward`` (the hash grid), and ``torch.ops.scalar_nerf_sampling.unit_positions`` and
``.worth_evaluating`` (ray samples and the occupancy test), and ``torch.ops.scalar_nerf_mlp.forward``,
``.backward`` and ``.supported`` (the fused bfloat16 decoder, ``fields/fused_mlp.py``).
If the build fails (no C++ compiler, no ninja, ...) one warning is logged and callers fall back
to their pure-torch implementations.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from torch._ops import _OpNamespace

EXTENSION_NAME = "scalar_nerf_hash_grid"
SOURCES = [Path(__file__).resolve().parent.parent / "csrc" / name for name in ("hash_grid.cpp", "sampling.cpp", "mlp.cpp")]
SAMPLING_NAMESPACE = "scalar_nerf_sampling"

_logger = logging.getLogger(__name__)
_lock = threading.Lock()
_attempted = False
_ops: _OpNamespace | None = None
_error: str | None = None


def load_extension() -> _OpNamespace | None:
    """Build (first call only) and return the op namespace of the C++ kernel.

    Returns:
        ``torch.ops.scalar_nerf_hash_grid`` (with ``forward`` and ``backward``), or ``None`` when
        the extension cannot be built; the reason is then available from :func:`extension_error`.
    """
    global _attempted, _ops, _error
    with _lock:
        if not _attempted:
            _attempted = True
            try:
                from torch.utils.cpp_extension import load

                load(
                    name=EXTENSION_NAME,
                    sources=[str(source) for source in SOURCES],
                    extra_cflags=["-O3", "-fopenmp"],
                    extra_ldflags=["-fopenmp"],
                    is_python_module=False,
                    verbose=False,
                )
                _ops = getattr(torch.ops, EXTENSION_NAME)
            except Exception as exc:  # noqa: BLE001 - any build/load failure means "use the torch path"
                _error = f"{type(exc).__name__}: {exc}"
                _logger.warning(
                    "Could not build the C++ kernels (%s); falling back to the pure-torch "
                    "implementations, which are several times slower on CPU.",
                    _error.splitlines()[0],
                )
        return _ops


def sampling_ops() -> _OpNamespace | None:
    """``torch.ops.scalar_nerf_sampling`` (``unit_positions``, ``worth_evaluating``), or ``None``
    when the extension cannot be built (builds it on first call)."""
    if load_extension() is None:
        return None
    return getattr(torch.ops, SAMPLING_NAMESPACE)


def require_extension() -> _OpNamespace:
    """The op namespace of the C++ kernel (built on first call).

    Raises:
        RuntimeError: if the extension cannot be built.
    """
    ops = load_extension()
    if ops is None:
        raise RuntimeError(f"The C++ hash-grid kernel is unavailable: {_error}")
    return ops


def extension_available() -> bool:
    """Whether the C++ kernel is usable in this process (builds it on first call)."""
    return load_extension() is not None


def extension_error() -> str | None:
    """Why the C++ kernel could not be built, or ``None`` if it built (or was not tried yet)."""
    return _error
