"""A datamanager over all training images or over one block's subset of them.

Every block shares the global model's world frame: the dataparser orients, centres and scales the
poses of *all* frames before the train/eval split, so parsing the scene again and keeping a subset
of the training images gives the block's images in the same frame. Only the subset's images are
loaded into memory, so memory stays bounded by the largest block, not by the number of blocks.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional, Tuple, Type

import torch
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.datasets.base_dataset import InputDataset
from torch import Tensor


def subset_dataparser_outputs(outputs: DataparserOutputs, image_indices: Tuple[int, ...]) -> DataparserOutputs:
    """The parsed outputs restricted to ``image_indices`` (indices into ``outputs.image_filenames``).

    Scene box, dataparser transform and scale are kept, so the subset stays in the same frame.
    """
    num_images = len(outputs.image_filenames)
    bad = [i for i in image_indices if not 0 <= i < num_images]
    if not image_indices or bad:
        raise ValueError(f"image subset {list(image_indices)[:8]} is empty or out of range for {num_images} training images")
    index_tensor = torch.tensor(image_indices, dtype=torch.long)
    masks = [outputs.mask_filenames[i] for i in image_indices] if outputs.mask_filenames is not None else None
    depths = outputs.metadata.get("depth_filenames")
    metadata = dict(outputs.metadata)
    if depths is not None:
        metadata["depth_filenames"] = [depths[i] for i in image_indices]
    return replace(
        outputs,
        image_filenames=[outputs.image_filenames[i] for i in image_indices],
        cameras=outputs.cameras[index_tensor],
        mask_filenames=masks,
        metadata=metadata,
    )


def camera_centres(outputs: DataparserOutputs) -> Tensor:
    """[N, 3] camera centres of the parsed training images, in the dataparser's (normalised) frame."""
    return outputs.cameras.camera_to_worlds[:, :3, 3].clone()


@dataclass
class ScalarDataManagerConfig(VanillaDataManagerConfig):
    """nerfstudio's VanillaDataManager, optionally over a subset of the training images."""

    _target: Type = field(default_factory=lambda: ScalarDataManager)
    image_subset: Optional[Tuple[int, ...]] = None
    """Indices of the training images to load (None: all). Set by the pipeline for a block."""


class ScalarDataManager(VanillaDataManager[InputDataset]):
    """VanillaDataManager whose training dataset is ``image_subset`` of the parsed training images."""

    config: ScalarDataManagerConfig

    def create_train_dataset(self) -> InputDataset:
        """Training dataset of the subset (only its images are ever read)."""
        if self.config.image_subset is not None:
            self.full_train_dataparser_outputs = self.train_dataparser_outputs
            self.train_dataparser_outputs = subset_dataparser_outputs(self.train_dataparser_outputs, self.config.image_subset)
        return super().create_train_dataset()
