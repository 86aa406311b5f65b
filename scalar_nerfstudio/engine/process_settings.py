"""The process-wide settings of a process that runs a scalar-nerf model, made in one place.

nerfstudio's verbs (``ns-train``, ``ns-eval``, ``ns-render``, ``ns-viewer``, ``ns-export``) enter this
package through a config's ``setup()``: ``ScalarTrainerConfig.setup`` builds the trainer,
``ScalarPipelineConfig.setup`` the pipeline that every other verb loads. Each calls
:func:`apply_process_settings` before it builds anything, so no constructor changes the process.
The settings are idempotent: a training process passes through both.
"""

from __future__ import annotations

import os

import torch

from scalar_nerfstudio.engine.allocator import keep_freed_memory

__all__ = ["ONEDNN_CACHE_ENV", "apply_process_settings", "limit_onednn_kernel_cache"]


def apply_process_settings(device: str | torch.device) -> None:
    """Before a trainer or pipeline on ``device`` is built: oneDNN's kernel cache limited (the user's
    environment wins) and, on the CPU, glibc malloc keeping freed tensor memory for reuse
    (``engine/allocator.py``; the user's malloc settings win)."""
    limit_onednn_kernel_cache()
    if torch.device(device).type == "cpu":
        keep_freed_memory()


#: oneDNN's cache of compiled CPU kernels, one entry per distinct shape (default capacity 1024). A
#: training step's decoder runs on as many samples as survive empty-space skipping: a new shape almost
#: every step, so the cache fills with kernels that are never reused (measured: a 300-step town run
#: grew from 1.5 to 3.3 GB resident with the default, 1.95 GB with 0, at the same speed within 5 %).
ONEDNN_CACHE_ENV = "ONEDNN_PRIMITIVE_CACHE_CAPACITY"


def limit_onednn_kernel_cache(capacity: int = 0) -> bool:
    """Set oneDNN's kernel cache capacity for this process unless the user set it (the environment
    variable wins). It takes effect only if no oneDNN kernel has been created yet: call it where a
    process starts training. Returns True when this call set it."""
    if ONEDNN_CACHE_ENV in os.environ:
        return False
    os.environ[ONEDNN_CACHE_ENV] = str(int(capacity))
    return True
