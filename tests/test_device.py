"""The training device is chosen when the trainer is built, not when the method configs are imported."""

from __future__ import annotations

import os
import copy
import subprocess
import sys

import pytest
import torch

from scalar_nerfstudio.engine.device import AutoMachineConfig, resolve_device_type, resolve_machine
from scalar_nerfstudio.engine.trainer import ScalarTrainer


def test_importing_the_method_configs_does_not_look_for_a_gpu() -> None:
    code = (
        "import torch\n"
        "def looked(): raise SystemExit('torch.cuda.is_available() called at import')\n"
        "torch.cuda.is_available = looked\n"
        "import scalar_nerfstudio.method_configs as m\n"
        "print(m.scalar_nerf.config.machine.device_type, m.scalar_nerf.config.mixed_precision)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split()[-2:] == ["auto", "True"]


@pytest.mark.parametrize(
    ("cuda", "asked", "expected"),
    [
        (False, "auto", ("cpu", False)),
        (True, "auto", ("cuda", True)),
        (True, "cpu", ("cpu", False)),  # forced CPU on a GPU node (scalar-nerf-train-blocks): no grad scaler
        (False, "mps", ("mps", False)),
    ],
)
def test_device_and_mixed_precision_follow_the_machine(monkeypatch, cuda: bool, asked: str, expected) -> None:
    from scalar_nerfstudio.method_configs import scalar_nerf, scalar_nerf_block

    for spec in (scalar_nerf, scalar_nerf_block):
        assert isinstance(spec.config.machine, AutoMachineConfig)
        assert issubclass(spec.config._target, ScalarTrainer)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda)
    config = copy.deepcopy(scalar_nerf.config)
    config.machine.device_type = asked
    resolve_machine(config)
    assert (config.machine.device_type, config.mixed_precision) == expected
    assert resolve_device_type("auto") == ("cuda" if cuda else "cpu")


def test_onednn_kernel_cache_is_limited_unless_the_user_set_it(monkeypatch: pytest.MonkeyPatch) -> None:
    from scalar_nerfstudio.engine.device import ONEDNN_CACHE_ENV, limit_onednn_kernel_cache

    monkeypatch.delenv(ONEDNN_CACHE_ENV, raising=False)
    assert limit_onednn_kernel_cache() and os.environ[ONEDNN_CACHE_ENV] == "0"
    monkeypatch.setenv(ONEDNN_CACHE_ENV, "256")
    assert not limit_onednn_kernel_cache() and os.environ[ONEDNN_CACHE_ENV] == "256"
