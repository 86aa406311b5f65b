"""The method's story on a scene trained in half a minute: blocks that start from the global model learn what it
did not, so the default fusion beats its own global model by a margin, and the fused image differs from the global
model's where the blocks render.

The margin was measured over seeds (docs/notebook/story-test.md, "The courtyard at 2^8"): 48 views of 96 x 72,
tables of 2^8, 100 global steps and 2 blocks of 100 steps of 1024 rays gave +0.66, +0.77 and +0.84 dB at seeds 42, 1
and 2, on the CPU without AVX-512 (float32 decoder kernels, which the run asks for on either CPU). The test asserts
FUSION_MARGIN_DB at seed 42. A run whose blocks learn nothing, or whose fusion never renders them, scores the global
model's PSNR and fails.

Not asserted, because it was not seen on a scene this small: that the blocks beat one table at equal wall-clock
(they lose at two of the three seeds here, and by 0.4-0.5 dB at 1000 steps per worker; the small aerial town learns
nothing at all: docs/notebook/story-test.md).
"""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Dict

import numpy as np
import pytest
from conftest import ns_train_command, run_dirs
from quality import eval_renders, load_pipeline

from scalar_nerfstudio.scenes.courtyard import write_scene

#: How much the default fusion must beat its own global model on the held-out views (dB): the smallest margin
#: measured over three seeds (+0.66) less about the spread between seeds (0.18), rounded down.
FUSION_MARGIN_DB = 0.4
#: How far the fused held-out images must differ from the global model's on average (8-bit levels).
MIN_DIFFERENCE_LEVELS = 1.0


def _train(folder: Path) -> Path:
    scene = folder / "scene"
    write_scene(scene, num_images=48, width=96, height=72)
    output = folder / "outputs"
    command = ns_train_command(
        scene, output,
        "--vis", "tensorboard",
        "--machine.seed", "42",
        "--pipeline.num-blocks", "2",
        "--pipeline.global-steps", "100",
        "--pipeline.block-steps", "100",
        "--pipeline.model.field.log2-hashmap-size", "8",
        "--pipeline.datamanager.train-num-rays-per-batch", "1024",
        # The decoder path the margin was measured on, on either CPU (AVX512-BF16 CPUs have AVX2 as well).
        "--pipeline.model.field.cpu-decoder-kernel", "avx2",
    )
    result = subprocess.run(command, capture_output=True, text=True, timeout=900, check=False)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    (run,) = run_dirs(output)
    return run


@pytest.fixture(scope="module")
def story_renders(tmp_path_factory: pytest.TempPathFactory) -> Dict[str, tuple]:
    """The small courtyard's run, rendered on its held-out views with the default fusion and with its global model alone."""
    run = _train(tmp_path_factory.mktemp("story"))
    pipeline = load_pipeline(run)
    default = str(pipeline.model.fusion_mode)
    assert default == "nearest-guarded", default
    return {mode: eval_renders(pipeline, mode) for mode in (default, "global-only")}


@pytest.mark.slow
def test_the_default_fusion_beats_its_own_global_model(story_renders: Dict[str, tuple]) -> None:
    fused = story_renders["nearest-guarded"][0]["psnr"]
    global_only = story_renders["global-only"][0]["psnr"]
    assert fused >= global_only + FUSION_MARGIN_DB, f"fused {fused:.2f} dB against its global model's {global_only:.2f} dB"


@pytest.mark.slow
def test_the_fused_images_are_the_blocks_not_the_global_models(story_renders: Dict[str, tuple]) -> None:
    fused_images, global_images = story_renders["nearest-guarded"][1], story_renders["global-only"][1]
    levels = float(np.mean([np.abs(a - b).mean() * 255.0 for a, b in zip(fused_images, global_images)]))
    assert levels >= MIN_DIFFERENCE_LEVELS, f"the fused images differ from the global model's by {levels:.2f} levels only"
