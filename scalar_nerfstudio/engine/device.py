"""The training device, chosen when the trainer is built (not when a config is imported or written).

The method configs say ``--machine.device-type auto`` and ``--mixed-precision True``: train on CUDA
when the process that trains has a CUDA device, else on the CPU, and use mixed precision only where
the device has it (CUDA). ``ScalarTrainer`` settles both (:func:`resolve_device_type`) and hands them
to nerfstudio's ``Trainer.__init__`` (``seam.trainer.TrainerBase``) while its config keeps ``auto``, so a
config made, copied or saved on one machine trains on whatever the machine that runs it has.
``--machine.device-type cpu`` (or ``cuda``, ``mps``) still forces a device. :func:`resolve_machine`
settles a config in place, for nerfstudio's own trainer (the benchmark's nerfacto runs).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import torch
from nerfstudio.configs.base_config import MachineConfig

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
