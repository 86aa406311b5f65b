"""``--pipeline.datamanager.pixel-sampler.ray-choice error``: training pixels drawn more where the model's colour
error is high (data/ray_choice.py), fed by the pipeline after every step."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from scalar_nerfstudio.data.ray_choice import ErrorMap, ScalarPixelSampler, ScalarPixelSamplerConfig

H, W, TILE = 37, 50, 16  # edge tiles of 5 x 16, 16 x 2 and 5 x 2 pixels


def sampler(**options: object) -> ScalarPixelSampler:
    config = ScalarPixelSamplerConfig(ray_choice="error", tile_px=TILE, **options)  # type: ignore[arg-type]
    return config.setup(num_rays_per_batch=4096)


def image_batch(image_idx: list) -> dict:
    """Images whose every pixel holds its training index / 10 (so a ray's colour names its image)."""
    images = torch.stack([torch.full((H, W, 3), i / 10.0) for i in image_idx])
    return {"image": images, "image_idx": torch.tensor(image_idx)}


def test_an_even_map_draws_every_pixel_alike_edge_tiles_included() -> None:
    torch.manual_seed(0)
    error_map = ErrorMap(height=H, width=W, tile_px=TILE, decay=0.8)
    drawn = error_map.draw(torch.tensor([5, 9]), 300_000)  # [N, 3] (position in the batch, y, x)
    which, y, x = drawn.unbind(-1)
    assert which.min() == 0 and which.max() == 1 and y.min() == 0 and y.max() == H - 1 and x.min() == 0 and x.max() == W - 1
    counts = torch.bincount((which * H + y) * W + x, minlength=2 * H * W).float()
    assert counts.min() > 0, "every pixel of both images is drawn"
    expected = len(drawn) / (2 * H * W)
    assert abs(counts.mean() / expected - 1) < 1e-6 and counts.std() / expected < 0.2  # about Poisson noise (0.11)
    assert abs(float((y >= 32).float().mean()) - 5 / H) < 0.005  # the last row of tiles is 5 pixels tall
    assert abs(float((x >= 48).float().mean()) - 2 / W) < 0.003


def test_rays_follow_the_error_that_steps_report() -> None:
    torch.manual_seed(0)
    pixel_sampler = sampler(uniform_share=0.5)
    batch = image_batch([3, 7])
    first = pixel_sampler.sample(batch)
    assert first["indices"].shape == (4096, 3)
    # The model is wrong only in image 7's tile (1, 2): pixels y 16-31, x 32-47.
    ys, xs = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    for image in (3, 7):
        indices = torch.stack([torch.full((H * W,), image), ys.reshape(-1), xs.reshape(-1)], dim=-1)
        target = torch.zeros(H * W, 3)
        wrong = (image == 7) & (indices[:, 1] // TILE == 1) & (indices[:, 2] // TILE == 2)
        predicted = torch.where(wrong[:, None], 0.5, 0.0) + 0.001
        for _ in range(60):  # enough visits for the running means to forget their start (0.8^60)
            pixel_sampler.record_errors(indices, predicted, target)
    rays = torch.cat([pixel_sampler.sample(batch)["indices"] for _ in range(20)])
    in_tile = (rays[:, 0] == 7) & (rays[:, 1] // TILE == 1) & (rays[:, 2] // TILE == 2)
    area_share = TILE * TILE / (2 * H * W)
    weight_share = 0.501 * TILE * TILE / (0.501 * TILE * TILE + 0.001 * (2 * H * W - TILE * TILE))
    expected = 0.5 * area_share + 0.5 * weight_share
    assert abs(float(in_tile.float().mean()) - expected) < 0.01, (float(in_tile.float().mean()), expected)
    assert float(in_tile.float().mean()) > 5 * area_share


def test_rays_carry_their_own_images_colours_and_training_indices() -> None:
    torch.manual_seed(1)
    collated = sampler(uniform_share=0.25).sample(image_batch([3, 7]))
    indices, colours = collated["indices"], collated["image"]
    assert set(indices[:, 0].tolist()) == {3, 7}
    assert torch.allclose(colours[:, 0], indices[:, 0].float() / 10.0)
    assert bool((indices[:, 1] < H).all() and (indices[:, 2] < W).all())


def test_a_tile_keeps_a_running_mean_of_its_rays_errors() -> None:
    """One noisy step moves a tile by 1 - decay of the way: a single bad ray does not take over the draw."""
    error_map = ErrorMap(height=H, width=W, tile_px=TILE, decay=0.75)
    error_map.ensure(2)
    rays = torch.tensor([[1, 20, 40], [1, 21, 41], [1, 0, 0]])  # two rays in tile (1, 2) of image 1, one in (0, 0)
    error_map.record(rays[:, 0], rays[:, 1], rays[:, 2], torch.tensor([3.0, 5.0, 0.0]))
    assert error_map.values[1, 1, 2] == pytest.approx(0.75 * 1.0 + 0.25 * 4.0)
    assert error_map.values[1, 0, 0] == pytest.approx(0.75)
    assert float(error_map.values[0].sum()) == pytest.approx(error_map.values[0].numel())  # untouched tiles keep theirs


def test_non_finite_errors_are_ignored_and_a_zero_map_draws_by_area() -> None:
    error_map = ErrorMap(height=H, width=W, tile_px=TILE, decay=0.5)
    error_map.ensure(1)
    pixel = torch.zeros(3, dtype=torch.long)
    error_map.record(pixel, pixel, pixel, torch.tensor([float("nan"), float("inf"), -float("inf")]))
    assert torch.equal(error_map.values, torch.ones_like(error_map.values))
    error_map.values.zero_()
    drawn = error_map.draw(torch.tensor([0]), 50_000)
    assert abs(float((drawn[:, 1] >= 32).float().mean()) - 5 / H) < 0.01


def test_uniform_choice_keeps_nerfstudios_sampler_and_ignores_errors() -> None:
    pixel_sampler = ScalarPixelSamplerConfig().setup(num_rays_per_batch=256)
    collated = pixel_sampler.sample(image_batch([0, 1]))
    assert collated["indices"].shape == (256, 3)
    pixel_sampler.record_errors(collated["indices"], torch.ones(256, 3), collated["image"])
    assert pixel_sampler.error_map is None


def test_a_share_outside_zero_to_one_is_refused() -> None:
    with pytest.raises(ValueError, match="uniform-share"):
        sampler(uniform_share=1.5)


@pytest.mark.slow  # trains 30 tiny steps
def test_training_feeds_the_error_map_that_draws_its_rays(scene: Path, tmp_path: Path) -> None:
    """Through the pipeline: every step's rendered colours reach the sampler, whose map then draws more rays from
    the tiles where the model is furthest from the photos."""
    from conftest import tiny_trainer

    def error_rays(config) -> None:
        config.pipeline.datamanager.pixel_sampler.ray_choice = "error"
        config.pipeline.datamanager.pixel_sampler.tile_px = 8

    trainer = tiny_trainer(scene, tmp_path, configure=error_rays, num_blocks=1, train_blocks=False, global_steps=30)
    trainer.train()
    pixel_sampler = trainer.pipeline.datamanager.train_pixel_sampler
    assert isinstance(pixel_sampler, ScalarPixelSampler) and pixel_sampler.error_map is not None
    values = pixel_sampler.error_map.values  # [images, Ty, Tx]
    assert values.shape[0] == len(trainer.pipeline.datamanager.train_dataset)
    assert bool(torch.isfinite(values).all()) and float(values.std()) > 0.01, "the steps' errors reached the map"
    worst = values.reshape(-1) >= values.reshape(-1).quantile(0.9)
    share = float(values.reshape(-1)[worst].sum() / values.sum())  # the scene's 96 x 72 images hold whole 8 x 8 tiles
    assert share > 0.13, "the worst tenth of the tiles holds well over a tenth of the error"
    drawn = pixel_sampler.error_map.draw(torch.arange(values.shape[0]), 100_000)
    tiles = (drawn[:, 0] * values.shape[1] + drawn[:, 1] // 8) * values.shape[2] + drawn[:, 2] // 8
    assert abs(float(worst[tiles].float().mean()) - share) < 0.01, "it gets that share of the rays"
