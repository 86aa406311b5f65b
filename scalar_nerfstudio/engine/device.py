"""The training device, chosen when the trainer is built (not when a config is imported or written).

The method configs say ``--machine.device-type auto`` and ``--mixed-precision True``: train on CUDA
when the process that trains has a CUDA device, else on the CPU, and use mixed precision only where
the device has it (CUDA). ``ScalarTrainer`` settles both (:func:`resolve_machine`) just before
nerfstudio's ``Trainer.__init__`` reads them, so a config made, copied or saved on one machine
trains on whatever the machine that runs it has. ``--machine.device-type cpu`` (or ``cuda``, ``mps``)
still forces a device.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import torch
from nerfstudio.configs.base_config import MachineConfig

# glibc malloc's settings live in engine/allocator.py; pipeline.py and the tests import these two from here.
from scalar_nerfstudio.engine.allocator import GLIBC_MALLOC_ENV, keep_freed_memory  # noqa: F401

DeviceType = Literal["auto", "cpu", "cuda", "mps"]


@dataclass
class AutoMachineConfig(MachineConfig):
    """nerfstudio's MachineConfig, with the device chosen when training starts by default."""

    device_type: DeviceType = "auto"
    """auto: CUDA when this process has a CUDA device, else the CPU; cpu / cuda / mps: that device."""


def resolve_device_type(device_type: str) -> str:
    """The device ``device_type`` means in this process ("auto": "cuda" when available, else "cpu")."""
    if device_type != "auto":
        return device_type
    return "cuda" if torch.cuda.is_available() else "cpu"


def resolve_machine(config: Any) -> None:
    """Settle a trainer config's device ("auto") and mixed precision (only on CUDA), in place."""
    device = resolve_device_type(config.machine.device_type)
    config.machine.device_type = device
    config.mixed_precision = bool(config.mixed_precision) and device == "cuda"



#: oneDNN's cache of compiled CPU kernels, one entry per distinct shape (default capacity 1024). A
#: training step's decoder runs on as many samples as survive empty-space skipping: a new shape almost
#: every step, so the cache fills with kernels that are never reused (measured: a 300-step town run
#: grew from 1.5 to 3.3 GB resident with the default, 1.95 GB with 0, at the same speed within 5 %).
ONEDNN_CACHE_ENV = "ONEDNN_PRIMITIVE_CACHE_CAPACITY"


def limit_onednn_kernel_cache(capacity: int = 0) -> bool:
    """Set oneDNN's kernel cache capacity for this process unless the user set it (the environment
    variable wins). It takes effect only if no oneDNN kernel has been created yet: call it where a
    process starts training. Returns True when this call set it."""
    import os

    if ONEDNN_CACHE_ENV in os.environ:
        return False
    os.environ[ONEDNN_CACHE_ENV] = str(int(capacity))
    return True
