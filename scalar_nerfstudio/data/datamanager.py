"""A datamanager over all training images or over one block's subset of them.

Every block shares the global model's world frame: the dataparser orients, centres and scales the
poses of *all* frames before the train/eval split, so parsing the scene again and keeping a subset
of the training images gives the block's images in the same frame. Only the subset's images are
loaded into memory, so memory stays bounded by the largest block, not by the number of blocks.

Images are read as 8-bit RGB whatever their kind (``ScalarInputDataset``): grayscale, palette,
16-bit and CMYK images are converted, and transparent ones composited over ``alpha_background``, in
memory (the scene check in ``data/validation.py`` accepts them and logs one line saying so).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional, Tuple, Type

import numpy as np
import numpy.typing as npt
import torch
from PIL import Image
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.datasets.base_dataset import InputDataset
from torch import Tensor

from scalar_nerfstudio.data.validation import to_rgb_array


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


class ScalarInputDataset(InputDataset):
    """nerfstudio's InputDataset, reading every image as 8-bit RGB [H, W, 3].

    nerfstudio's own reads the raw pixels: an RGBA image beside RGB ones fails to stack, a palette
    image gives its palette indices as grey levels, and a 16-bit one wraps around in uint8.
    """

    alpha_background: Tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Colour transparent pixels are composited over (set by the datamanager)."""

    def get_numpy_image(self, image_idx: int) -> npt.NDArray[np.uint8]:
        with Image.open(self._dataparser_outputs.image_filenames[image_idx]) as pil_image:
            image = to_rgb_array(pil_image, self.alpha_background)
        if self.scale_factor != 1.0:
            height, width = image.shape[:2]
            newsize = (int(width * self.scale_factor), int(height * self.scale_factor))
            image = np.asarray(Image.fromarray(image).resize(newsize, resample=Image.Resampling.BILINEAR), dtype=np.uint8)
        return image


@dataclass
class ScalarDataManagerConfig(VanillaDataManagerConfig):
    """nerfstudio's VanillaDataManager, optionally over a subset of the training images."""

    _target: Type = field(default_factory=lambda: ScalarDataManager)
    train_num_rays_per_batch: int = 4096
    """Rays per training step."""
    eval_num_rays_per_batch: int = 4096
    """Rays per evaluation batch."""
    image_subset: Optional[Tuple[int, ...]] = None
    """Indices of the training images to load (None: all). Set by the pipeline for a block."""
    alpha_background: Tuple[float, float, float] = (1.0, 1.0, 1.0)
    """RGB in [0, 1] that transparent pixels (RGBA, grayscale+alpha, transparent palette images) are
    composited over, in memory (the scene folder is not changed)."""


class ScalarDataManager(VanillaDataManager[ScalarInputDataset]):
    """VanillaDataManager whose training dataset is ``image_subset`` of the parsed training images."""

    config: ScalarDataManagerConfig

    def create_train_dataset(self) -> ScalarInputDataset:
        """Training dataset of the subset (only its images are ever read)."""
        if self.config.image_subset is not None:
            self.train_dataparser_outputs = subset_dataparser_outputs(self.train_dataparser_outputs, self.config.image_subset)
        return self._with_background(super().create_train_dataset())

    def create_eval_dataset(self) -> ScalarInputDataset:
        return self._with_background(super().create_eval_dataset())

    def _with_background(self, dataset: ScalarInputDataset) -> ScalarInputDataset:
        background = getattr(self.config, "alpha_background", ScalarInputDataset.alpha_background)
        dataset.alpha_background = tuple(float(c) for c in background)  # type: ignore[assignment]
        return dataset
