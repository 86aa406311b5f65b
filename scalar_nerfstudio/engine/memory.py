"""Giving the C heap's freed memory back to the operating system after a camera render.

A camera render on the CPU allocates and frees hundreds of megabytes of per-sample tensors, chunk by
chunk (4096 rays x 64 samples at a time). glibc's malloc keeps freed blocks in its arenas, and its
mmap threshold rises after the first large frees, so later large tensors come from the arenas too.
The freed space is fragmented between images: the process's resident memory climbed by about
200-300 MiB per 256 x 192 eval image and passed 23 GiB in the second evaluation of 134 views of the
aerial 4 x 4 town, where the kernel killed it (2026-11-27). ``malloc_trim(0)`` returns the free
pages. Doing it after every image costs about a third of the render time (the next image faults its
pages in again), so :class:`HeapRelease` does it only once resident memory has grown by
:data:`RELEASE_AFTER_GROWTH_MIB` since the last release: memory stays bounded by that much plus one
render, for a few per cent of the time (``benchmarks/bench_eval_memory.py``).

Where glibc is not the C library (macOS, Windows, musl) :func:`release_freed_memory` does nothing; it
lives with glibc malloc's settings in :mod:`scalar_nerfstudio.engine.allocator`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from scalar_nerfstudio.engine.allocator import release_freed_memory

__all__ = ["RELEASE_AFTER_GROWTH_MIB", "HeapRelease", "release_freed_memory", "resident_mib"]

#: Growth of resident memory (MiB) since the last release after which :class:`HeapRelease` releases.
RELEASE_AFTER_GROWTH_MIB = 2048.0


def resident_mib() -> float:
    """This process's resident memory now (MiB)."""
    import psutil

    return psutil.Process().memory_info().rss / 2**20


@dataclass
class HeapRelease:
    """Calls :func:`release_freed_memory` once resident memory has grown by ``growth_mib`` since the
    last release (or since the first call). Call it after each large transient allocation, e.g. a
    camera render; between releases it only reads the process's resident size."""

    growth_mib: float = RELEASE_AFTER_GROWTH_MIB
    baseline_mib: Optional[float] = None
    """Resident memory after the last release (None: not called yet)."""

    def __call__(self) -> bool:
        """True when it released memory now."""
        now = resident_mib()
        if self.baseline_mib is None:
            self.baseline_mib = now
            return False
        if now - self.baseline_mib < self.growth_mib:
            return False
        released = release_freed_memory()
        self.baseline_mib = resident_mib()
        return released
