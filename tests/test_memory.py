"""Resident memory after camera renders: freed heap memory is given back to the operating system
(``scalar_nerfstudio/engine/memory.py``), so an evaluation of many views stays bounded."""

from __future__ import annotations

import sys
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
import torch
from conftest import tiny_trainer

from scalar_nerfstudio.engine import allocator, memory
from scalar_nerfstudio.engine.memory import HeapRelease, release_freed_memory, resident_mib

GLIBC = sys.platform.startswith("linux") and allocator._malloc_trim() is not None


@pytest.mark.skipif(not GLIBC, reason="malloc_trim is glibc's")
def test_freed_heap_memory_goes_back_to_the_operating_system() -> None:
    """400 MiB of 64 KiB blocks (below malloc's mmap threshold: they live in its heap), all freed but
    the last, which pins the heap's top: freeing leaves them resident, the release returns them."""
    blocks = [np.ones(64 * 1024, dtype=np.uint8) for _ in range(6400)]
    last = blocks[-1]
    grown = resident_mib()
    del blocks
    freed = resident_mib()
    assert release_freed_memory()
    released = resident_mib()
    assert grown - released > 300, (grown, freed, released)
    assert last.sum() == 64 * 1024  # live memory is untouched


def test_the_release_waits_until_memory_has_grown_by_its_slack() -> None:
    """The first call only records resident memory; later calls release once it has grown by
    ``growth_mib`` since then, and measure again after releasing."""
    readings = iter([1000.0, 1500.0, 3100.0, 1200.0, 2000.0, 3300.0, 1100.0])
    with mock.patch.object(memory, "resident_mib", lambda: next(readings)), \
            mock.patch.object(memory, "release_freed_memory", return_value=True) as release:
        heap_release = HeapRelease(growth_mib=2048.0)
        assert heap_release() is False and heap_release.baseline_mib == 1000.0  # first call: the baseline
        assert heap_release() is False  # +500
        assert heap_release() is True and heap_release.baseline_mib == 1200.0  # +2100: released, measured again
        assert heap_release() is False  # +800 over the new baseline
        assert heap_release() is True and heap_release.baseline_mib == 1100.0
        assert release.call_count == 2


def test_a_cpu_camera_render_offers_its_freed_memory_back(scene: Path, tmp_path: Path) -> None:
    """Every camera render of the fused model (evaluation, ns-render, the viewer) ends with the model's
    heap release on the CPU; a ray batch (training) does not."""
    trainer = tiny_trainer(scene, tmp_path)
    model = trainer.pipeline.model
    if model.device.type != "cpu":
        pytest.skip("the release is for the CPU's heap")
    model.eval()
    model.heap_release = mock.Mock(return_value=False)
    cameras = trainer.pipeline.datamanager.train_dataset.cameras
    with torch.no_grad():
        for index in range(2):
            model.get_outputs_for_camera(cameras[index : index + 1].to(model.device))
    assert model.heap_release.call_count == 2
