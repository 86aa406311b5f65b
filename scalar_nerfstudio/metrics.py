"""Image metrics that never download anything: PSNR, SSIM, and LPIPS only when its weights are on disk;
depth metrics against a scene's ground-truth depth, where it has one."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Dict, Optional, cast

import torch
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor, nn


def alexnet_weights_path() -> Optional[Path]:
    """Where torchvision keeps the AlexNet weights LPIPS needs, or None if torchvision is missing."""
    try:
        from torchvision.models import AlexNet_Weights
    except ImportError:
        return None
    file_name = os.path.basename(AlexNet_Weights.IMAGENET1K_V1.url)
    return Path(torch.hub.get_dir()) / "checkpoints" / file_name


def psnr(predicted: Tensor, target: Tensor) -> Tensor:
    """Peak signal-to-noise ratio in dB of [..., 3] images in [0, 1] (capped at 100 dB)."""
    mse = torch.mean((predicted - target) ** 2)
    return -10.0 * torch.log10(mse.clamp_min(1e-10))


#: A pixel's depth counts as right (``depth_delta1``) within this factor of the truth, the usual
#: threshold of depth estimation (Eigen et al. 2014).
DEPTH_DELTA1_FACTOR = 1.25


def depth_metrics(predicted: Tensor, truth: Tensor) -> Dict[str, float]:
    """How well a rendered depth map matches the ground truth, over the pixels whose truth is known.

    Tells a reconstruction from "fog" (colour right on average, surfaces in the wrong place), which
    PSNR alone cannot: a model that renders blurred colour from far-away haze can still score a
    fair PSNR.

    Args:
        predicted: [H, W, 1] (or [H, W]) rendered distance along each ray.
        truth: the same shape, the true distance in the same units; 0, negative or non-finite where
            unknown (sky).

    Returns:
        ``{"depth_delta1", "depth_median_rel_error", "depth_known_pixels"}``: the share of known
        pixels whose depth is within :data:`DEPTH_DELTA1_FACTOR` of the truth (higher is better), the
        median of ``|predicted - truth| / truth`` over them (lower is better), and their count. A
        non-finite predicted depth counts as wrong. With no known pixel (an image of sky) the first
        two are NaN: the keys are always there, as nerfstudio's averaging over images needs.
    """
    if predicted.shape != truth.shape:
        raise ValueError(f"depth_metrics: predicted {tuple(predicted.shape)} and truth {tuple(truth.shape)} differ in shape")
    truth = truth.detach().float().reshape(-1)
    predicted = predicted.detach().float().reshape(-1).to(truth.device)
    known = torch.isfinite(truth) & (truth > 0)
    if not bool(known.any()):
        return {"depth_delta1": float("nan"), "depth_median_rel_error": float("nan"), "depth_known_pixels": 0.0}
    truth, predicted = truth[known], predicted[known]
    finite = torch.isfinite(predicted)
    relative_error = torch.where(finite, (predicted - truth).abs() / truth, torch.full_like(truth, float("inf")))
    ratio = torch.maximum(predicted / truth, truth / predicted.clamp_min(1e-30))
    within = finite & (predicted > 0) & (ratio < DEPTH_DELTA1_FACTOR)
    return {
        "depth_delta1": float(within.float().mean()),
        "depth_median_rel_error": float(relative_error.median()),
        "depth_known_pixels": float(known.sum()),
    }


class ImageMetrics:
    """PSNR, SSIM and, only where AlexNet's weights are already on disk, LPIPS.

    LPIPS is built lazily on first use; if the weights are missing it is skipped with one message
    (no download is attempted, so an offline machine never fails here). Deliberately not an
    ``nn.Module``: LPIPS's weights must never enter a model's checkpoint.
    """

    def __init__(self) -> None:
        self._lpips: Optional[nn.Module] = None
        self._lpips_checked = False

    def _lpips_module(self, device: torch.device) -> Optional[nn.Module]:
        if not self._lpips_checked:
            self._lpips_checked = True
            weights = alexnet_weights_path()
            if weights is None or not weights.is_file():
                CONSOLE.print(f"[yellow]LPIPS skipped: its AlexNet weights are not on disk ({weights}); nothing is downloaded.")
            else:
                from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

                self._lpips = LearnedPerceptualImagePatchSimilarity(normalize=True)
        return self._lpips.to(device) if self._lpips is not None else None

    @torch.no_grad()
    def __call__(self, predicted: Tensor, target: Tensor) -> Dict[str, float]:
        """[H, W, 3] predicted and target images in [0, 1] -> {"psnr", "ssim"[, "lpips"]}."""
        from torchmetrics.functional import structural_similarity_index_measure  # here: its import takes seconds

        predicted_nchw = predicted.permute(2, 0, 1)[None].float()
        target_nchw = target.permute(2, 0, 1)[None].float()
        metrics = {
            "psnr": float(psnr(predicted, target)),
            # a Tensor: only return_full_image=True makes it a (score, image) tuple
            "ssim": float(cast(Tensor, structural_similarity_index_measure(predicted_nchw, target_nchw, data_range=1.0))),
        }
        lpips = self._lpips_module(predicted.device)
        if lpips is not None:
            metrics["lpips"] = float(lpips(predicted_nchw, target_nchw))
        return metrics
