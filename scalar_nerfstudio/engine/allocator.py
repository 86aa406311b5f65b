"""glibc malloc's settings for this process, all in one place, with one opt-out.

By default glibc gives large freed blocks back to the operating system, and the next tensor or numpy
temporary faults its pages in again. Two presets keep freed memory in the process instead:

* :func:`keep_freed_memory`: training, evaluation and rendering with torch (``M_MMAP_MAX`` 0: large
  blocks come from the heap; ``M_TRIM_THRESHOLD`` :data:`KEPT_FREE_BYTES`: freed blocks stay there).
* :func:`keep_render_temporaries`: the scene generators' numpy ray casting, which allocates and frees a
  few MiB per chunk of rays (``M_TRIM_THRESHOLD`` 256 MiB, ``M_MMAP_THRESHOLD`` 32 MiB).

The opt-out: when any of :data:`GLIBC_MALLOC_ENV` is set in the environment, the user tuned malloc and
neither preset changes anything (:func:`user_tuned_malloc`). Both do nothing where the C library is not
glibc. :func:`release_freed_memory` (``malloc_trim(0)``) changes no setting: it returns the free pages
the heap holds now, so it runs whatever the settings are.
"""

from __future__ import annotations

import ctypes
import functools
import os
import sys
from typing import Callable, Mapping, Optional, Sequence, Tuple

__all__ = [
    "GLIBC_MALLOC_ENV", "KEPT_FREE_BYTES", "RENDER_MMAP_THRESHOLD_BYTES", "RENDER_TRIM_THRESHOLD_BYTES", "keep_freed_memory",
    "keep_render_temporaries", "release_freed_memory", "user_tuned_malloc",
]

#: glibc's malloc settings in the environment (``MALLOC_MMAP_MAX_`` and friends, or ``GLIBC_TUNABLES``):
#: when any is set, the user tuned malloc and this module's presets leave it alone.
GLIBC_MALLOC_ENV = ("MALLOC_MMAP_MAX_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "GLIBC_TUNABLES")

# mallopt's parameter numbers (glibc's malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_MMAP_MAX = -4

#: :func:`keep_freed_memory`: free memory at the top of the heap beyond which glibc still returns it to
#: the system (bytes; 2 GiB - 1).
KEPT_FREE_BYTES = 2**31 - 1
#: :func:`keep_render_temporaries`: the trim threshold (bytes).
RENDER_TRIM_THRESHOLD_BYTES = 256 << 20
#: :func:`keep_render_temporaries`: blocks at least this large are mapped afresh (bytes).
RENDER_MMAP_THRESHOLD_BYTES = 32 << 20


def user_tuned_malloc(environ: Optional[Mapping[str, str]] = None) -> bool:
    """True when ``environ`` (default: this process's environment) sets any of :data:`GLIBC_MALLOC_ENV`."""
    environ = os.environ if environ is None else environ
    return any(name in environ for name in GLIBC_MALLOC_ENV)


@functools.lru_cache(maxsize=1)
def _glibc() -> Optional[ctypes.CDLL]:
    """The process's C library when it is glibc (Linux), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # glibc only: other C libraries' mallopt differs or is a stub
    except (OSError, AttributeError):
        return None
    return libc


def _set(settings: Sequence[Tuple[int, int]]) -> bool:
    """``mallopt(parameter, value)`` for each of ``settings`` unless the user tuned malloc or the C library
    is not glibc; True when every call was accepted."""
    libc = None if user_tuned_malloc() else _glibc()
    if libc is None:
        return False
    mallopt = libc.mallopt
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return all([bool(mallopt(parameter, value)) for parameter, value in settings])


def keep_freed_memory() -> bool:
    """Make glibc's malloc keep freed memory for the next tensors instead of unmapping it (Linux).

    By default every tensor above a few MB gets fresh pages from ``mmap`` and gives them back to the
    system when freed, so each step of CPU training (and each render) faults in a few hundred MB of new
    pages. With ``M_MMAP_MAX`` 0 large blocks come from the heap, and with ``M_TRIM_THRESHOLD``
    :data:`KEPT_FREE_BYTES` the freed blocks stay there for reuse. Resident memory then stays near its
    peak instead of dropping between steps.

    Does nothing where the C library is not glibc, or where the user set any of :data:`GLIBC_MALLOC_ENV`.
    Returns True when this call changed the settings.
    """
    return _set([(_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, KEPT_FREE_BYTES)])


def keep_render_temporaries() -> bool:
    """Let the freed numpy temporaries of ray casting stay with the process (Linux, glibc): trim threshold
    :data:`RENDER_TRIM_THRESHOLD_BYTES`, mmap threshold :data:`RENDER_MMAP_THRESHOLD_BYTES`.

    The scene generators allocate and free a few MiB per chunk of rays; with glibc's defaults each round
    trip costs page faults. The setting is process-wide and holds at most the peak memory of the
    rendering (tens of MiB). Same opt-out as :func:`keep_freed_memory`; True when this call changed the
    settings.
    """
    return _set([(_M_TRIM_THRESHOLD, RENDER_TRIM_THRESHOLD_BYTES), (_M_MMAP_THRESHOLD, RENDER_MMAP_THRESHOLD_BYTES)])


@functools.lru_cache(maxsize=1)
def _malloc_trim() -> Optional[Callable[[int], int]]:
    """glibc's ``malloc_trim`` (None where the C library has none)."""
    libc = _glibc()
    trim = getattr(libc, "malloc_trim", None) if libc is not None else None
    if trim is None:
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


def release_freed_memory() -> bool:
    """Return the pages of memory that has been freed to the operating system (glibc's ``malloc_trim(0)``,
    a walk over malloc's arenas); True when some were returned, False when none were or where glibc is
    absent. Live memory is not touched, and no setting is changed."""
    trim = _malloc_trim()
    return bool(trim(0)) if trim is not None else False
