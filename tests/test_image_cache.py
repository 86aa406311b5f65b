"""A bounded image cache (issue 17): when the decoded images do not fit the budget, a random subset
that fits is cached and replaced over time, so every image is still trained on."""

from __future__ import annotations

import random
from pathlib import Path

import pytest
import torch
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

from scalar_nerfstudio.data.datamanager import ScalarDataManagerConfig, images_that_fit

MIB = 2**20


def test_images_that_fit_counts_two_subsets_at_a_resample() -> None:
    assert images_that_fit(10, MIB, 10 * MIB) == -1, "everything fits: cache all, as nerfstudio does"
    assert images_that_fit(10, MIB, 9 * MIB) == 4, "half the budget per subset (old and new are both held while loading)"
    assert images_that_fit(10, MIB, 0.1 * MIB) == 1, "at least one image"
    assert images_that_fit(0, MIB, 0) == -1


@pytest.mark.parametrize("budget_mib", [None, 0.07])
def test_datamanager_caches_a_subset_and_samples_every_image_over_time(scene: Path, budget_mib, capsys) -> None:
    """24 views of 96x72 (20 KiB each as the training loader's 8-bit, 81 KiB as the eval loader's float32): a
    0.07 MiB budget holds 1 training image at a time (61 KiB for the 21 training images, half of it per subset)
    and 1 eval image; the default budget holds all."""
    config = ScalarDataManagerConfig(
        data=scene, dataparser=NerfstudioDataParserConfig(eval_mode="interval", eval_interval=8),
        image_cache_mib=budget_mib, image_resample_every=2, train_num_rays_per_batch=256,
    )
    datamanager = config.setup(device="cpu", test_mode="val")
    loader = datamanager.train_image_dataloader
    num_train = len(datamanager.train_dataset)
    if budget_mib is None:
        assert loader.cache_all_images and loader.num_images_to_sample_from == num_train
        return
    assert not loader.cache_all_images and loader.num_images_to_sample_from == 1
    assert datamanager.eval_image_dataloader.num_images_to_sample_from == 1
    log = " ".join(capsys.readouterr().out.split())
    assert "image cache: 0.07 MiB" in log and "1 of 21 training" in log and "1 of 3 eval images at a time" in log
    assert config.train_num_images_to_sample_from == -1, "the config itself is not changed"
    random.seed(0)  # nerfstudio draws each subset with the random module
    seen = set()
    for step in range(600):  # 300 subsets of 1 image: each image is missed with probability (20/21)^300 < 1e-6
        _, batch = datamanager.next_train(step)
        seen.update(torch.unique(batch["indices"][:, 0]).tolist())
    assert seen == set(range(num_train)), f"images never sampled: {sorted(set(range(num_train)) - seen)}"


def test_training_images_are_cached_as_8_bit_and_drawn_as_nerfstudios_float32(scene: Path) -> None:
    """The training loader holds uint8 images (a quarter of float32's memory); every pixel a step draws is
    exactly the float32 value nerfstudio's dataset gives for it, by either ray choice. Eval stays float32."""
    for ray_choice in ("uniform", "error"):
        config = ScalarDataManagerConfig(
            data=scene, dataparser=NerfstudioDataParserConfig(eval_mode="interval", eval_interval=8), train_num_rays_per_batch=512,
        )
        config.pixel_sampler.ray_choice = ray_choice
        datamanager = config.setup(device="cpu", test_mode="val")
        cached = datamanager.train_image_dataloader.cached_collated_batch["image"]
        assert cached.dtype == torch.uint8 and cached.shape[-1] == 3
        _, batch = datamanager.next_train(0)
        assert batch["image"].dtype == torch.float32
        images = {}
        for k, (image, y, x) in enumerate(batch["indices"].tolist()):
            if image not in images:
                images[image] = datamanager.train_dataset[image]["image"]  # [H, W, 3] float32, as nerfstudio reads it
            assert torch.equal(batch["image"][k], images[image][y, x]), (ray_choice, k)
        assert datamanager.eval_image_dataloader.cached_collated_batch["image"].dtype == torch.float32


def test_released_training_images_load_again_when_a_batch_is_asked_for(scene: Path) -> None:
    """The global model's images are released when its phase ends; a later batch (a run that goes back to it)
    loads them again instead of failing."""
    config = ScalarDataManagerConfig(data=scene, dataparser=NerfstudioDataParserConfig(eval_mode="interval", eval_interval=8),
                                     train_num_rays_per_batch=128)
    datamanager = config.setup(device="cpu", test_mode="val")
    datamanager.release_train_images()
    assert datamanager.train_image_dataloader is None and datamanager.iter_train_image_dataloader is None
    _, batch = datamanager.next_train(0)
    assert batch["image"].shape == (128, 3) and datamanager.train_image_dataloader is not None
