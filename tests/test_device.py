"""The training device is chosen when the trainer is built, not when the method configs are imported; the
process settings for CPU work (oneDNN's kernel cache, glibc's reuse of freed memory)."""

from __future__ import annotations

import copy
import os
import resource
import subprocess
import sys

import pytest
import torch

from scalar_nerfstudio.engine.allocator import GLIBC_MALLOC_ENV, keep_freed_memory
from scalar_nerfstudio.engine.device import AutoMachineConfig, resolve_device_type, resolve_machine
from scalar_nerfstudio.engine.trainer import ScalarTrainer


def test_importing_the_method_configs_does_not_look_for_a_gpu() -> None:
    """No code of this project asks for a GPU at import (the device is chosen when the trainer is built).

    A package it imports may: on a machine with a GPU (the lent H200), torch's own inductor, which
    nerfstudio's imports load, asks ``torch.cuda.is_available()`` (``torch/_inductor/runtime/
    benchmarking.py``). Such a call is let through and named on stderr; a call whose nearest caller
    outside torch is this project's code fails the test.
    """
    code = (
        "import os, sys, traceback, torch\n"
        "asked = torch.cuda.is_available\n"
        "torch_dir = os.path.dirname(torch.__file__)\n"
        "def looked():\n"
        "    stack = traceback.extract_stack()[:-1]\n"
        "    callers = [f for f in stack if not f.filename.startswith(torch_dir) and not f.filename.startswith('<frozen')]\n"
        "    where = ''.join(traceback.format_list(stack[-12:]))\n"
        "    if callers and os.sep + 'scalar_nerfstudio' + os.sep in callers[-1].filename:\n"
        "        raise SystemExit('torch.cuda.is_available() called at import by this project:\\n' + where)\n"
        "    print('torch.cuda.is_available() called at import by a dependency:\\n' + where, file=sys.stderr)\n"
        "    return asked()\n"
        "torch.cuda.is_available = looked\n"
        "import scalar_nerfstudio.method_configs as m\n"
        "print(m.scalar_nerf.config.machine.device_type, m.scalar_nerf.config.mixed_precision)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.split()[-2:] == ["auto", "True"]
    print(result.stderr[-3000:])  # shown with -rP: which dependency asked, where one did


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
    from scalar_nerfstudio.engine.process_settings import ONEDNN_CACHE_ENV, limit_onednn_kernel_cache

    monkeypatch.delenv(ONEDNN_CACHE_ENV, raising=False)
    assert limit_onednn_kernel_cache() and os.environ[ONEDNN_CACHE_ENV] == "0"
    monkeypatch.setenv(ONEDNN_CACHE_ENV, "256")
    assert not limit_onednn_kernel_cache() and os.environ[ONEDNN_CACHE_ENV] == "256"


_REALLOCATE = """
import resource, torch
from scalar_nerfstudio.engine.allocator import keep_freed_memory
assert keep_freed_memory()
def faults(): return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(2):  # 64 MB, allocated and freed: the heap grows to hold it
    torch.ones(1 << 24)
for _ in range(15):
    before = faults()
    torch.ones(1 << 24)
    print(faults() - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_freed_tensor_memory_is_reused_without_new_page_faults() -> None:
    # By default glibc maps every large tensor afresh: each 64 MB tensor faults in its 16384 pages again.
    # With the setting, one of the first few tensors may still take fresh pages (seen on a loaded machine:
    # a small allocation of another thread splits the freed block), so the median of 15 is asserted:
    # at most 7 of them may fault, where the default faults in all 15.
    env = {k: v for k, v in os.environ.items() if k not in GLIBC_MALLOC_ENV}
    result = subprocess.run([sys.executable, "-c", _REALLOCATE], env=env, capture_output=True, text=True, check=True)
    faults_per_tensor = sorted(int(line) for line in result.stdout.split())
    pages_per_tensor = (1 << 26) // resource.getpagesize()
    assert faults_per_tensor[len(faults_per_tensor) // 2] < 0.05 * pages_per_tensor, faults_per_tensor


@pytest.mark.parametrize("name", GLIBC_MALLOC_ENV)
def test_malloc_settings_of_the_user_are_left_alone(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(name, "1")
    assert not keep_freed_memory()


def test_the_process_settings_are_made_where_nerfstudio_enters_the_package(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every ns- verb builds the trainer or the pipeline through its config's setup(): the settings are
    made there, before the object is built, for the device it is built on."""
    import scalar_nerfstudio.engine.trainer as trainer_module
    import scalar_nerfstudio.pipeline as pipeline_module
    from scalar_nerfstudio.method_configs import scalar_nerf

    calls = []
    for module in (trainer_module, pipeline_module):
        monkeypatch.setattr(module, "apply_process_settings", lambda device: calls.append(("settings", str(device))))
    pipeline_config = copy.deepcopy(scalar_nerf.config.pipeline)
    pipeline_config._target = lambda config, **kwargs: calls.append(("built", kwargs["device"]))
    pipeline_config.setup(device="cpu", test_mode="test")
    trainer_config = copy.deepcopy(scalar_nerf.config)
    trainer_config.machine.device_type = "cpu"
    trainer_config._target = lambda config, **kwargs: calls.append(("built", "trainer"))
    trainer_config.setup(local_rank=0, world_size=1)
    assert calls == [("settings", "cpu"), ("built", "cpu"), ("settings", "cpu"), ("built", "trainer")]
