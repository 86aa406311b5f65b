"""A preview image of a run in training: one held-out view rendered beside its ground truth.

Written as ``RUN/preview.png`` (replaced atomically, so an image viewer never sees half a file) and
kept per step as ``RUN/previews/step-NNNNNNNNN.png``, so a user sees what the model has learnt
without opening the viewer.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Tuple

import numpy as np
import torch
from PIL import Image

from scalar_nerfstudio.atomic_io import atomic_write_bytes
from scalar_nerfstudio.metrics import psnr

PREVIEW_NAME = "preview.png"
PREVIEW_DIR = "previews"


def _to_uint8(image: torch.Tensor) -> np.ndarray:
    """[H, W, 3] float in [0, 1] -> [H, W, 3] uint8 (NaN -> 0)."""
    return (torch.nan_to_num(image.detach().float().cpu(), nan=0.0).clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).numpy()


def _png_bytes(image: np.ndarray) -> bytes:
    """[H, W, 3] uint8 -> the bytes of a PNG file."""
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    return buffer.getvalue()


def preview_scale(width: int, height: int, max_size: int) -> float:
    """The factor that brings a ``width`` x ``height`` view's longer side to at most ``max_size``
    pixels (1.0 when it is within it, or when ``max_size`` <= 0: the full size)."""
    longest = max(int(width), int(height))
    if max_size <= 0 or longest <= max_size:
        return 1.0
    return max_size / longest


@torch.no_grad()
def write_preview(pipeline, run_dir: Path, *, step: int, max_size: int = 512) -> Tuple[Path, float]:
    """Render the first eval view with the pipeline's model (its current fusion) beside the ground
    truth, its longer side at most ``max_size`` pixels (0: the eval image's size); returns (the
    preview's path, the render's PSNR in dB against the ground truth at that size).

    The bound keeps a preview cheap at real resolutions: rendering costs per pixel, and a
    4000 x 3000 view takes minutes on a CPU."""
    datamanager = pipeline.datamanager
    dataset = datamanager.eval_dataset
    camera = dataset.cameras[0:1].to(pipeline.device)
    scale = preview_scale(int(camera.width[0, 0]), int(camera.height[0, 0]), max_size)
    if scale < 1.0:
        camera.rescale_output_resolution(scale)  # fields reassigned on this copy; the dataset's cameras are untouched
    model = pipeline.model
    was_training = model.training
    model.eval()
    try:
        outputs = model.get_outputs_for_camera(camera)
    finally:
        model.train(was_training)
    rendered = outputs["rgb"].float().cpu()  # [H, W, 3]
    truth = dataset[0]["image"].float()[..., :3]  # [H, W, 3]
    if truth.shape != rendered.shape:
        truth = torch.nn.functional.interpolate(truth.permute(2, 0, 1)[None], size=rendered.shape[:2], mode="area")[0].permute(1, 2, 0)
    score = float(psnr(rendered.clamp(0, 1), truth))
    png = _png_bytes(np.concatenate([_to_uint8(rendered), _to_uint8(truth)], axis=1))
    path = Path(run_dir) / PREVIEW_NAME
    atomic_write_bytes(Path(run_dir) / PREVIEW_DIR / f"step-{step:09d}.png", png)
    atomic_write_bytes(path, png)
    return path, score
