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


@pytest.mark.parametrize("budget_mib", [None, 0.3])
def test_datamanager_caches_a_subset_and_samples_every_image_over_time(scene: Path, budget_mib, capsys) -> None:
    """24 views of 96x72 (81 KiB each as float32): a 0.3 MiB budget holds 1 training image at a time
    (0.28 MiB for the 21 training images, half of it per subset); the default budget holds all."""
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
    assert "image cache: 0.3 MiB" in log and "1 of 21 training" in log and "1 of 3 eval images at a time" in log
    assert config.train_num_images_to_sample_from == -1, "the config itself is not changed"
    random.seed(0)  # nerfstudio draws each subset with the random module
    seen = set()
    for step in range(600):  # 300 subsets of 1 image: each image is missed with probability (20/21)^300 < 1e-6
        _, batch = datamanager.next_train(step)
        seen.update(torch.unique(batch["indices"][:, 0]).tolist())
    assert seen == set(range(num_train)), f"images never sampled: {sorted(set(range(num_train)) - seen)}"
