"""A datamanager over all training images or over one block's subset of them.

Every block shares the global model's world frame: the dataparser orients, centres and scales the
poses of *all* frames before the train/eval split, so parsing the scene again and keeping a subset
of the training images gives the block's images in the same frame. Only the subset's images are
loaded into memory, so memory stays bounded by the largest block, not by the number of blocks.

Images are read as 8-bit RGB whatever their kind (``ScalarInputDataset``): grayscale, palette,
16-bit and CMYK images are converted, and transparent ones composited over ``alpha_background``, in
memory (the scene check in ``data/validation.py`` accepts them and logs one line saying so). The
training loader caches them as 8-bit (:class:`Uint8Images`: a quarter of float32's memory); the pixel
sampler turns the pixels a step draws into float32, the values nerfstudio's float32 images hold.

Where the scene has depth images (``depth_file_path`` in transforms.json, as the generated town
writes), the eval images carry them as ``ray_depth`` (distance along each pixel's ray, in the
model's units), so evaluation also scores the geometry (:func:`scalar_nerfstudio.metrics.depth_metrics`).
Training batches never load them: no method here trains on depth.
"""

from __future__ import annotations

import gc
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Dict, Iterator, List, NamedTuple, Optional, Tuple, Type

import numpy as np
import numpy.typing as npt
import torch
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.data.utils.dataloaders import CacheDataloader
from nerfstudio.model_components.ray_generators import RayGenerator
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image
from torch import Tensor

from scalar_nerfstudio.blocks.capacity import LayoutScale, layout_scale
from scalar_nerfstudio.data.depth import depth_scale, missing_depth_files, ray_depth_image
from scalar_nerfstudio.data.ray_choice import ScalarPixelSampler, ScalarPixelSamplerConfig
from scalar_nerfstudio.data.validation import to_rgb_array
from scalar_nerfstudio.engine.allocator import release_freed_memory
from scalar_nerfstudio.seam.data import dataparser_outputs, loader_options


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


def training_image_names(filenames: List[Path], data: Optional[Path]) -> List[str]:
    """Training image names as stored in blocks.json: paths relative to the scene folder ``data`` (a
    folder or its transforms.json) when possible, else file names."""
    root = None
    if data is not None:
        root = Path(data).resolve()
        root = root.parent if root.suffix == ".json" else root
    names = []
    for path in filenames:
        resolved = Path(path).resolve()
        names.append(str(resolved.relative_to(root)) if root is not None and resolved.is_relative_to(root) else resolved.name)
    return names


def camera_centres(outputs: DataparserOutputs) -> Tensor:
    """[N, 3] camera centres of the parsed training images, in the dataparser's (normalised) frame."""
    return outputs.cameras.camera_to_worlds[:, :3, 3].clone()


class CameraLayout(NamedTuple):
    """The parsed training cameras as the block plan reads them (``blocks/plan.py``), float64 numpy."""

    centres: np.ndarray
    """[N, 3] camera centres (the dataparser's frame)."""
    directions: np.ndarray
    """[N, 3] optical axes: -z of the OpenGL camera-to-world pose."""
    focal_px: np.ndarray
    """[N] focal lengths in training pixels."""
    image_pixels: List[int]
    """[N] pixels of each training image."""


def camera_layout(outputs: DataparserOutputs) -> CameraLayout:
    """:class:`CameraLayout` of the parsed training cameras."""
    cameras = outputs.cameras
    poses = cameras.camera_to_worlds.double()
    return CameraLayout(
        centres=poses[:, :3, 3].numpy(),
        directions=(-poses[:, :3, 2]).numpy(),
        focal_px=cameras.fx.reshape(-1).double().numpy(),
        image_pixels=(cameras.width * cameras.height).reshape(-1).tolist(),
    )


def parsed_layout_scale(outputs: DataparserOutputs) -> LayoutScale:
    """:class:`LayoutScale` of the parsed training cameras."""
    cameras = camera_layout(outputs)
    return layout_scale(cameras.centres, cameras.directions, cameras.focal_px)


class ScalarInputDataset(InputDataset):
    """nerfstudio's InputDataset, reading every image as 8-bit RGB [H, W, 3].

    nerfstudio's own reads the raw pixels: an RGBA image beside RGB ones fails to stack, a palette
    image gives its palette indices as grey levels, and a 16-bit one wraps around in uint8.
    """

    alpha_background: Tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Colour transparent pixels are composited over (set by the datamanager)."""
    load_ray_depth: bool = False
    """Add ``ray_depth`` [H, W, 1] to each image's data from the scene's depth images (set by the
    datamanager for the eval images, when the scene has them)."""

    def get_metadata(self, data: Dict) -> Dict:
        """``ray_depth`` [H, W, 1] float32 when :attr:`load_ray_depth` (else nothing)."""
        if not self.load_ray_depth:
            return {}
        return {"ray_depth": self.ray_depth(int(data["image_idx"]))}

    def ray_depth(self, image_idx: int) -> Tensor:
        """[H, W, 1] float32 distance from the camera centre to the surface along each pixel's ray, in
        the dataparser's units (what the models' ``depth`` output holds); 0 where the depth image
        says unknown (0: sky, or farther than its format holds). See :func:`ray_depth_image`."""
        outputs = dataparser_outputs(self)
        filenames = outputs.metadata.get("depth_filenames")
        if filenames is None:
            raise ValueError("this scene has no depth images (no depth_file_path in transforms.json)")
        image = ray_depth_image(self.cameras, image_idx, path=Path(filenames[image_idx]), scale=depth_scale(outputs))
        return image.ray_depth[..., None]

    def get_numpy_image(self, image_idx: int) -> npt.NDArray[np.uint8]:
        with Image.open(dataparser_outputs(self).image_filenames[image_idx]) as pil_image:
            image = to_rgb_array(pil_image, self.alpha_background)
        if self.scale_factor != 1.0:
            height, width = image.shape[:2]
            newsize = (int(width * self.scale_factor), int(height * self.scale_factor))
            image = np.asarray(Image.fromarray(image).resize(newsize, resample=Image.Resampling.BILINEAR), dtype=np.uint8)
        return image


class Uint8Images:
    """A dataset's images as the training loader caches them: each item is its data with ``image``
    ``[H, W, 3]`` uint8. Everything else (the viewer's thumbnails, evaluation) reads the dataset itself,
    in float32. A dataset with a ``mask_color`` keeps float32 here too (nerfstudio paints it in floats)."""

    def __init__(self, dataset: InputDataset) -> None:
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, image_idx: int) -> Dict:
        return self.dataset.get_data(image_idx, image_type="float32" if self.dataset.mask_color else "uint8")


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
    """RGB colour (each in [0, 1]) that transparent pixels are composited over, in memory (the scene
    folder is not changed)."""
    image_cache_mib: Optional[float] = None
    """Memory for the decoded training (8-bit) and eval (float32) images (MiB); None: a quarter of the memory
    available at start. Images that do not fit are cached as a random subset, replaced every
    image-resample-every steps."""
    image_resample_every: int = 250
    """Steps between fresh random image subsets, when not every image fits ``image_cache_mib``."""
    pixel_sampler: ScalarPixelSamplerConfig = field(default_factory=ScalarPixelSamplerConfig)
    """How training pixels are drawn (``ray-choice``: uniformly, or more where the model's error is high)."""


def images_that_fit(num_images: int, bytes_per_image: int, budget_bytes: float) -> int:
    """How many images a cache of ``budget_bytes`` holds: all (-1) or a number >= 1.

    nerfstudio loads a new subset while the old one is still referenced, so at that moment two
    subsets are in memory: a subset may take half the budget.
    """
    if num_images <= 0 or bytes_per_image <= 0 or num_images * bytes_per_image <= budget_bytes:
        return -1
    return max(1, int(budget_bytes // (2 * bytes_per_image)))


def available_memory_bytes() -> float:
    """Memory available to new allocations now (psutil's ``available``)."""
    import psutil

    return float(psutil.virtual_memory().available)


class ScalarDataManager(VanillaDataManager[ScalarInputDataset]):
    """VanillaDataManager whose training dataset is ``image_subset`` of the parsed training images."""

    config: ScalarDataManagerConfig

    def create_train_dataset(self) -> ScalarInputDataset:
        """Training dataset of the subset (only its images are ever read)."""
        if self.config.image_subset is not None:
            self.train_dataparser_outputs = subset_dataparser_outputs(self.train_dataparser_outputs, self.config.image_subset)
        return self._with_background(super().create_train_dataset())

    def create_eval_dataset(self) -> ScalarInputDataset:
        dataset = self._with_background(super().create_eval_dataset())
        missing = missing_depth_files(dataset.metadata)
        if missing:  # e.g. images_N/ for a downscaled load without depths_N/ beside it
            CONSOLE.print(f"[yellow]depth metrics skipped: {len(missing)} of the eval images' depth files are missing "
                          f"(first: {missing[0]})")
        dataset.load_ray_depth = missing is not None and not missing
        return dataset

    def image_cache_budget_bytes(self) -> float:
        """The decoded-image budget: ``image_cache_mib``, or a quarter of the available memory."""
        if self.config.image_cache_mib is not None:
            return float(self.config.image_cache_mib) * 2**20
        return available_memory_bytes() / 4.0

    @property
    def caches_uint8(self) -> bool:
        """Whether the training loader caches 8-bit images: when the pixel sampler is scalar-nerf's, which turns
        the pixels it draws into float32."""
        return isinstance(self.config.pixel_sampler, ScalarPixelSamplerConfig)

    @cached_property
    def image_cache_plan(self) -> Tuple[float, int, int]:
        """(budget in bytes, training images cached at a time, eval images cached at a time); -1: all.

        The budget is split between the training and eval caches in proportion to their images.
        Decided once, so the training and eval loaders (set up one after the other) agree with the log."""
        budget = self.image_cache_budget_bytes()
        fits = []
        datasets = [self.train_dataset, self.eval_dataset]
        total = sum(len(d) for d in datasets if d is not None)
        for dataset in datasets:
            if dataset is None or len(dataset) == 0:
                fits.append(-1)
                continue
            cameras = dataset.cameras
            bytes_per_value = 1 if dataset is self.train_dataset and self.caches_uint8 else 4  # uint8 / float32 RGB, as cached
            bytes_per_image = int((cameras.width * cameras.height).max().item()) * 3 * bytes_per_value
            fits.append(images_that_fit(len(dataset), bytes_per_image, budget * len(dataset) / max(total, 1)))
        return budget, fits[0], fits[1]

    def setup_train(self) -> None:
        """nerfstudio's ``setup_train``, with the training images cached as 8-bit (:class:`Uint8Images`) and
        the cache bounded (:meth:`image_cache_plan`); the loading's freed temporaries go back to the system."""
        budget, train_fit, eval_fit = self.image_cache_plan
        if train_fit != -1 or eval_fit != -1:
            num_train, num_eval = len(self.train_dataset), len(self.eval_dataset) if self.eval_dataset is not None else 0
            CONSOLE.log(
                f"image cache: {budget / 2**20:.3g} MiB (--pipeline.datamanager.image-cache-mib); caching "
                f"{num_train if train_fit == -1 else train_fit} of {num_train} training and "
                f"{num_eval if eval_fit == -1 else eval_fit} of {num_eval} eval images at a time, a new random subset "
                f"every {self.config.image_resample_every} steps"
            )
        assert self.train_dataset is not None
        CONSOLE.print("Setting up training dataset...")
        self.train_pixel_sampler = self._get_pixel_sampler(self.train_dataset, self.config.train_num_rays_per_batch)
        with self._cache_bounded("train", train_fit):
            config = self.config  # the bounded copy while the loader is built
            self.train_image_dataloader = CacheDataloader(
                Uint8Images(self.train_dataset) if self.caches_uint8 else self.train_dataset,  # type: ignore[arg-type]
                num_images_to_sample_from=config.train_num_images_to_sample_from,
                num_times_to_repeat_images=config.train_num_times_to_repeat_images,
                device=self.device,
                num_workers=self.world_size * 4,
                pin_memory=True,
                collate_fn=config.collate_fn,
                exclude_batch_keys_from_device=self.exclude_batch_keys_from_device,
            )
        self.iter_train_image_dataloader = iter(self.train_image_dataloader)
        self.train_ray_generator = RayGenerator(self.train_dataset.cameras.to(self.device))
        release_freed_memory()

    def release_train_images(self) -> None:
        """Drop the training loader and its cached images (and give their memory back to the system): the
        global model's images once its phase has ended, while the blocks train from their own. A later
        :meth:`next_train` loads them again."""
        self.train_image_dataloader = self.iter_train_image_dataloader = None  # type: ignore[assignment]
        gc.collect()
        release_freed_memory()

    def next_train(self, step: int) -> Tuple[RayBundle, Dict]:
        """nerfstudio's next training batch, the training images loaded again first if they were released."""
        if self.iter_train_image_dataloader is None:
            self.setup_train()
        return super().next_train(step)

    def setup_eval(self) -> None:
        """nerfstudio's set-up, with the eval image cache bounded (:meth:`image_cache_plan`)."""
        with self._cache_bounded("eval", self.image_cache_plan[2]):
            super().setup_eval()

    @contextmanager
    def _cache_bounded(self, split: str, fit: int) -> Iterator[None]:
        """nerfstudio's ``{split}_num_images_to_sample_from`` / ``..._num_times_to_repeat_images`` set
        to ``fit`` while its loader is built (unless set explicitly); the config itself is unchanged."""
        config = self.config
        if fit == -1 or getattr(config, f"{split}_num_images_to_sample_from") != -1:
            yield
            return
        with loader_options(self, **{
            f"{split}_num_images_to_sample_from": fit, f"{split}_num_times_to_repeat_images": config.image_resample_every,
        }):
            yield

    def record_train_errors(self, batch: Dict[str, Tensor], rgb: Tensor) -> None:
        """Give one training step's rendered colours ``rgb`` ``[N, 3]`` of ``batch``'s rays back to the pixel
        sampler (which draws by them with ``pixel-sampler.ray-choice error``)."""
        if isinstance(self.train_pixel_sampler, ScalarPixelSampler):
            self.train_pixel_sampler.record_errors(batch["indices"], rgb, batch["image"])

    def _with_background(self, dataset: ScalarInputDataset) -> ScalarInputDataset:
        dataset.alpha_background = tuple(float(c) for c in self.config.alpha_background)  # type: ignore[assignment]
        return dataset
