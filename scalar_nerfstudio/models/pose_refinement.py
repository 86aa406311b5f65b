"""Camera pose refinement: a correction per training image, learnt with the global model, used by the blocks.

nerfstudio's :class:`~nerfstudio.cameras.camera_optimizers.CameraOptimizer` holds the corrections (``SO3xR3``
or ``SE3``, 6 numbers per training image, its regulariser and metrics); this module applies them to a training
batch whose camera indices may be a block's own (its images' positions in the block) rather than the
capture's. The global phase learns the corrections; a block's phase applies them as they are (no gradient),
so a block trains on the poses its starting model was fitted to. Held-out views keep their given poses; so that
they stay in the frame the field is learnt in, the corrections' mean over the training images is removed (a
correction common to every camera would move that frame, not fix a pose).
"""

from __future__ import annotations

from typing import Dict, Optional, Sequence, Tuple

import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizer, CameraOptimizerConfig
from nerfstudio.cameras.lie_groups import exp_map_SE3, exp_map_SO3xR3
from nerfstudio.cameras.rays import RayBundle
from torch import Tensor, nn

__all__ = ["PoseRefinement", "corrected_rays"]


def corrected_rays(corrections: Tensor, origins: Tensor, directions: Tensor) -> Tuple[Tensor, Tensor]:
    """Rays moved by their cameras' corrections.

    Args:
        corrections: [R, 3, 4] each ray's camera correction (rotation | translation, in the world frame).
        origins: [R, 3] ray origins.
        directions: [R, 3] unit ray directions.

    Returns:
        ``(origins + t, R @ directions)``, [R, 3] each: nerfstudio's ``apply_to_raybundle``, also for one ray.
    """
    return origins + corrections[:, :3, 3], (corrections[:, :3, :3] @ directions[..., None])[..., 0]


class PoseRefinement(nn.Module):
    """The pose corrections of the capture's training images (``config.mode`` off: none, and nothing changes)."""

    def __init__(self, config: CameraOptimizerConfig, *, num_images: int) -> None:
        super().__init__()
        self.enabled = config.mode != "off"
        self.optimizer: CameraOptimizer = config.setup(num_cameras=num_images, device="cpu")
        """nerfstudio's module: ``pose_adjustment`` [num_images, 6] when enabled."""

    def centred_adjustment(self) -> Tensor:
        """[num_images, 6] the adjustments as applied: their mean over all training images removed."""
        adjustment = self.optimizer.pose_adjustment
        return adjustment - adjustment.mean(dim=0)

    def corrections(self, indices: Tensor) -> Tensor:
        """[N] training-image indices -> [N, 3, 4] their corrections (rotation | translation, world frame), from
        :meth:`centred_adjustment`."""
        centred = self.centred_adjustment()[indices]
        return exp_map_SO3xR3(centred) if self.optimizer.config.mode == "SO3xR3" else exp_map_SE3(centred)

    def parameters_to_learn(self) -> Sequence[nn.Parameter]:
        """The corrections' parameters (none when disabled)."""
        return list(self.optimizer.parameters()) if self.enabled else []

    def apply(self, ray_bundle: RayBundle, *, image_indices: Optional[Tensor] = None, learn: bool) -> None:
        """Move a training batch's rays by their images' corrections, in place.

        Args:
            ray_bundle: the batch; its ``camera_indices`` [R, 1] index the capture's training images, or with
                ``image_indices`` a block's images (and are left as they are: the block's appearance reads them).
            image_indices: [n] the capture's index of each of the block's images; None: the batch's own indices.
            learn: whether the corrections get gradients from this batch (the global phase) or are applied
                as they are (a block's phase).
        """
        if not self.enabled or ray_bundle.camera_indices is None:
            return
        indices = ray_bundle.camera_indices.reshape(-1).long()
        if image_indices is not None:
            indices = image_indices.to(indices.device)[indices]
        with torch.set_grad_enabled(learn and torch.is_grad_enabled()):
            corrections = self.corrections(indices).to(ray_bundle.origins.dtype)
        shape = ray_bundle.origins.shape
        origins, directions = corrected_rays(corrections, ray_bundle.origins.reshape(-1, 3), ray_bundle.directions.reshape(-1, 3))
        ray_bundle.origins, ray_bundle.directions = origins.reshape(shape), directions.reshape(shape)

    def add_losses(self, loss_dict: Dict[str, Tensor]) -> None:
        """Add the corrections' L2 regulariser (``camera_opt_regularizer``) to a training loss dict."""
        self.optimizer.get_loss_dict(loss_dict)

    def add_metrics(self, metrics_dict: Dict[str, Tensor]) -> None:
        """Add the applied (centred) corrections' mean and largest translation (world units of the normalised scene)
        and rotation (degrees), under nerfstudio's names (``camera_opt_translation_mean`` ...)."""
        centred = self.centred_adjustment().detach()
        translation, rotation = centred[:, :3].norm(dim=-1), torch.rad2deg(centred[:, 3:].norm(dim=-1))
        metrics_dict.update(camera_opt_translation_mean=translation.mean(), camera_opt_translation_max=translation.max(),
                            camera_opt_rotation_mean=rotation.mean(), camera_opt_rotation_max=rotation.max())
