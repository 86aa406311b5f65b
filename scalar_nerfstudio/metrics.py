"""Image metrics that never download anything: PSNR, SSIM, and LPIPS only when its weights are on disk."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Dict, Optional

import torch
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor, nn
from torchmetrics.functional import structural_similarity_index_measure


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
        predicted_nchw = predicted.permute(2, 0, 1)[None].float()
        target_nchw = target.permute(2, 0, 1)[None].float()
        metrics = {
            "psnr": float(psnr(predicted, target)),
            "ssim": float(structural_similarity_index_measure(predicted_nchw, target_nchw, data_range=1.0)),
        }
        lpips = self._lpips_module(predicted.device)
        if lpips is not None:
            metrics["lpips"] = float(lpips(predicted_nchw, target_nchw))
        return metrics
