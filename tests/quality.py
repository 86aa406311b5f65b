"""What the end-to-end tests compare a trained run with: its own model before training, the mean
training image, its global model alone, and its own render of the same camera.

A broken product still renders *something* in the right range of PSNR (a run whose blocks render
only background scored 13 dB), so the tests compare against these references instead of checking
that a number lies in a wide range.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Dict, Iterator, Tuple

import numpy as np
import torch
import yaml
from nerfstudio.utils.eval_utils import eval_setup

from scalar_nerfstudio.fusion_eval import render_eval_images

#: How far below its global model a fused render may score on a tiny test run (dB). The blocks start
#: as copies of the global model and only train a few steps, so the fusion may cost a little.
FUSION_TOLERANCE_DB = 0.3
#: How much a tiny test run must beat its own untrained model on the held-out views (dB). The suite's
#: runs (100 global steps) gain about 3-4 dB; a run that did not learn, or whose checkpoint did not
#: load, gains nothing.
TRAINED_MARGIN_DB = 2.0


@contextlib.contextmanager
def working_directory(path: Path) -> Iterator[None]:
    """Run the block in ``path`` (a run trained with a relative ``--data`` loads from where it was trained)."""
    previous = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(previous)


def load_pipeline(run: Path):
    """The run's pipeline from its newest checkpoint, in eval mode, as ``ns-eval`` loads it."""
    _, pipeline, _, _ = eval_setup(run / "config.yml", test_mode="test")
    pipeline.eval()
    return pipeline


def untrained_psnr(run: Path) -> float:
    """Held-out PSNR of the run's model at step 0: the same config, fresh weights (seeded as ns-train)."""
    config = yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader)
    torch.manual_seed(config.machine.seed)
    pipeline = config.pipeline.setup(device="cpu", test_mode="test")
    pipeline.eval()
    return float(pipeline.get_average_eval_image_metrics()["psnr"])


def mean_image_psnr(pipeline) -> float:
    """PSNR on the eval views of the mean training image (the trivial baseline)."""
    train_images = [pipeline.datamanager.train_dataset[i]["image"][..., :3] for i in range(len(pipeline.datamanager.train_dataset))]
    mean_image = torch.stack(train_images).mean(dim=0)
    scores = []
    for _, batch in pipeline.datamanager.fixed_indices_eval_dataloader:
        mse = torch.mean((batch["image"][..., :3].to(mean_image) - mean_image) ** 2)
        scores.append(float(-10.0 * torch.log10(mse)))
    return sum(scores) / len(scores)


def eval_renders(pipeline, fusion: str | None = None) -> Tuple[Dict[str, float], list]:
    """Mean held-out metrics of ``pipeline`` (under ``fusion``, else its configured one) and its eval
    images ``[H, W, 3]`` in [0, 1], in the eval dataloader's order (as ``ns-eval`` renders them)."""
    mode = fusion if fusion is not None else str(pipeline.model.fusion_mode)
    with torch.no_grad():
        metrics, images = render_eval_images(pipeline, mode)
    return metrics, [image.numpy() for image in images]


def image_difference(saved: Path, rendered: np.ndarray) -> float:
    """Mean absolute difference in 8-bit levels between an image file and a render ``[H, W, 3]`` in [0, 1]."""
    from PIL import Image

    on_disk = np.asarray(Image.open(saved).convert("RGB"), dtype=np.float32)
    assert on_disk.shape == rendered.shape, f"{saved}: {on_disk.shape} against the render's {rendered.shape}"
    return float(np.abs(on_disk - rendered * 255.0).mean())
