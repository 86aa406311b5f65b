"""Which pixels a training step draws: uniformly (nerfstudio's sampler), or more where the model is wrong.

With ``ray_choice="error"`` the sampler keeps an error map: every training image cut into tiles of
``tile_px`` x ``tile_px`` pixels, each tile holding a running mean of the absolute colour error of the
rays drawn from it (``record_errors``, called by the pipeline after each step's forward pass). A step draws
``1 - uniform_share`` of its rays from tiles in proportion to tile area x error, then a uniform pixel
inside the tile, and the rest uniformly over all pixels, so every pixel keeps being seen and the map's
stale tiles are refreshed. Until errors are recorded every tile holds the same value and the draw is
uniform. The loss is not reweighted: hard pixels count more, as in instant-ngp's error map.

Batches with masks, and images of different sizes (nerfstudio collates those as lists), are drawn
uniformly. The map lives in memory only: a resumed run starts it again from uniform.

Either way, pixels drawn from 8-bit images (the training loader caches them so) come out as float32 in
[0, 1], the values nerfstudio's float32 images hold (``uint8 / 255``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, Literal, Optional, Type

import torch
from nerfstudio.data.pixel_samplers import PixelSampler, PixelSamplerConfig
from torch import Tensor

__all__ = ["ErrorMap", "ScalarPixelSampler", "ScalarPixelSamplerConfig"]


class ErrorMap:
    """Running mean absolute colour error per tile of each training image: ``values`` is ``[I, Ty, Tx]``.

    Images are added as their indices appear (``ensure``), at the mean of the tiles seen so far.
    """

    def __init__(self, *, height: int, width: int, tile_px: int, decay: float) -> None:
        if tile_px < 1 or not 0.0 < decay < 1.0:
            raise ValueError(f"error map: tile_px must be >= 1 and decay in (0, 1), got {tile_px} and {decay}")
        self.height, self.width, self.tile_px, self.decay = height, width, tile_px, decay
        self.tiles_y, self.tiles_x = math.ceil(height / tile_px), math.ceil(width / tile_px)
        ys = torch.clamp(height - torch.arange(self.tiles_y) * tile_px, max=tile_px)
        xs = torch.clamp(width - torch.arange(self.tiles_x) * tile_px, max=tile_px)
        self.tile_area = (ys[:, None] * xs[None, :]).float()  # [Ty, Tx] pixels inside the image
        self.values = torch.ones(0, self.tiles_y, self.tiles_x)  # [I, Ty, Tx]

    def ensure(self, num_images: int) -> None:
        """Room for image indices below ``num_images``; new images start at the map's mean."""
        have = self.values.shape[0]
        if num_images <= have:
            return
        fill = float(self.values.mean()) if have else 1.0
        grown = torch.full((num_images - have, self.tiles_y, self.tiles_x), fill)
        self.values = torch.cat([self.values, grown])

    def tile_of(self, y: Tensor, x: Tensor) -> Tensor:
        """Flat tile index within an image of pixels ``y``, ``x`` ([N] each)."""
        return (y // self.tile_px) * self.tiles_x + x // self.tile_px

    def record(self, image: Tensor, y: Tensor, x: Tensor, error: Tensor) -> None:
        """Blend each touched tile towards the mean ``error`` ([N], >= 0) of this batch's rays in it.

        Non-finite errors are ignored, so a diverged step cannot poison the map."""
        keep = torch.isfinite(error)
        image, y, x, error = image[keep].long(), y[keep].long(), x[keep].long(), error[keep].float()
        if image.numel() == 0:
            return
        self.ensure(int(image.max()) + 1)
        flat = image * (self.tiles_y * self.tiles_x) + self.tile_of(y, x)
        touched, slot = torch.unique(flat, return_inverse=True)  # sums over the batch's tiles, not the whole map
        sums = torch.zeros(len(touched)).index_add_(0, slot, error)
        counts = torch.zeros(len(touched)).index_add_(0, slot, torch.ones_like(error))
        values = self.values.view(-1)
        values[touched] = self.decay * values[touched] + (1.0 - self.decay) * sums / counts

    def draw(self, image_idx: Tensor, num: int, *, generator: Optional[torch.Generator] = None) -> Tensor:
        """``num`` pixels ``[num, 3]`` (position in ``image_idx``, y, x) drawn in proportion to tile area x error."""
        self.ensure(int(image_idx.max()) + 1)
        weights = (self.values[image_idx.long()] * self.tile_area).reshape(-1)  # [B * Ty * Tx]
        weights = torch.nan_to_num(weights, nan=0.0, posinf=0.0).clamp_(min=0.0)
        if not float(weights.sum()) > 0.0:
            weights = self.tile_area.expand(len(image_idx), -1, -1).reshape(-1)
        tiles = torch.multinomial(weights, num, replacement=True, generator=generator)
        per_image = self.tiles_y * self.tiles_x
        which, tile = tiles // per_image, tiles % per_image
        ty, tx = tile // self.tiles_x, tile % self.tiles_x
        y0, x0 = ty * self.tile_px, tx * self.tile_px
        span_y = torch.clamp(self.height - y0, max=self.tile_px)
        span_x = torch.clamp(self.width - x0, max=self.tile_px)
        u = torch.rand(num, 2, generator=generator)
        y = y0 + torch.clamp((u[:, 0] * span_y).long(), max=span_y - 1)
        x = x0 + torch.clamp((u[:, 1] * span_x).long(), max=span_x - 1)
        return torch.stack([which, y, x], dim=-1)


@dataclass
class ScalarPixelSamplerConfig(PixelSamplerConfig):
    """nerfstudio's pixel sampler, with the choice of training rays by error."""

    _target: Type = field(default_factory=lambda: ScalarPixelSampler)
    ray_choice: Literal["uniform", "error"] = "uniform"
    """How training pixels are drawn: ``uniform`` (nerfstudio's), or ``error``: more from the tiles of each
    image where the model's colour error is high (an error map refreshed from every step's rays)."""
    tile_px: int = 16
    """With ``error``: side of the error map's tiles, in pixels."""
    uniform_share: float = 0.5
    """With ``error``: share of each step's rays still drawn uniformly over every pixel (0 to 1)."""
    error_decay: float = 0.8
    """With ``error``: weight a tile's running error keeps each time rays land in it (0 to 1)."""


class ScalarPixelSampler(PixelSampler):
    """Draws uniformly as nerfstudio does, or by the error map (``ray_choice="error"``)."""

    config: ScalarPixelSamplerConfig

    def __init__(self, config: ScalarPixelSamplerConfig, **kwargs) -> None:
        super().__init__(config, **kwargs)
        if not 0.0 <= config.uniform_share <= 1.0:
            raise ValueError(f"pixel-sampler.uniform-share must lie in [0, 1], got {config.uniform_share}")
        self.error_map: Optional[ErrorMap] = None

    def sample(self, image_batch: Dict) -> Dict:
        """nerfstudio's draw; 8-bit colours (``image``, ``full_image``) come back as float32 in [0, 1]."""
        batch = super().sample(image_batch)
        for key in ("image", "full_image"):
            value = batch.get(key)
            if isinstance(value, Tensor) and value.dtype == torch.uint8:
                batch[key] = value.float() / 255.0
        return batch

    @property
    def by_error(self) -> bool:
        return self.config.ray_choice == "error"

    def collate_image_dataset_batch(self, batch: Dict, num_rays_per_batch: int, keep_full_image: bool = False):
        plain = self.config.is_equirectangular or self.config.fisheye_crop_radius is not None
        if not self.by_error or "mask" in batch or plain:
            return super().collate_image_dataset_batch(batch, num_rays_per_batch, keep_full_image)
        images: Tensor = batch["image"]  # [B, H, W, 3]
        num_images, height, width, _ = images.shape
        if self.error_map is None or (self.error_map.height, self.error_map.width) != (height, width):
            self.error_map = ErrorMap(height=height, width=width, tile_px=self.config.tile_px, decay=self.config.error_decay)
        num_uniform = int(round(num_rays_per_batch * self.config.uniform_share))
        uniform = (torch.rand(num_uniform, 3) * torch.tensor([num_images, height, width])).long()
        by_error = self.error_map.draw(batch["image_idx"].cpu(), num_rays_per_batch - num_uniform)
        indices = torch.cat([uniform, by_error]).to(images.device)  # [N, 3] (batch position, y, x)
        c, y, x = (i.flatten() for i in torch.split(indices, 1, dim=-1))
        c, y, x = c.cpu(), y.cpu(), x.cpu()
        collated = {key: value[c, y, x] for key, value in batch.items() if key != "image_idx" and value is not None}
        indices[:, 0] = batch["image_idx"][c]
        collated["indices"] = indices  # [N, 3] (training image index, y, x), as nerfstudio's
        if keep_full_image:
            collated["full_image"] = images
        return collated

    def record_errors(self, indices: Tensor, predicted: Tensor, target: Tensor) -> None:
        """Feed one step's rays back to the error map: ``indices`` ``[N, 3]`` (image, y, x) as the batch
        gave them, ``predicted`` and ``target`` ``[N, 3]`` colours. Nothing happens when drawing uniformly."""
        if not self.by_error or self.error_map is None:
            return
        error = (predicted.detach().float() - target[..., :3].detach().float()).abs().mean(dim=-1).cpu()  # [N]
        indices = indices.cpu()
        self.error_map.record(indices[:, 0], indices[:, 1], indices[:, 2], error)
