"""The rays per chunk of a camera render follow the device unless the user sets them: a GPU gets chunks
large enough to keep it busy, the CPU keeps its size, an explicit value wins, and the image never
depends on the chunk."""

from __future__ import annotations

import pytest
import torch
from conftest import small_scalar_model
from nerfstudio.cameras.cameras import Cameras

from scalar_nerfstudio.config_checks import OptionError, check_options
from scalar_nerfstudio.device_sizes import RENDER_RAYS_PER_CHUNK, render_rays_per_chunk
from scalar_nerfstudio.method_configs import scalar_nerf


def test_the_render_chunk_follows_the_device_unless_set() -> None:
    assert render_rays_per_chunk(None, "cpu") == RENDER_RAYS_PER_CHUNK["cpu"] == 1 << 16, "the CPU's chunk is unchanged"
    assert render_rays_per_chunk(None, torch.device("cuda", 1)) == RENDER_RAYS_PER_CHUNK["cuda"] > RENDER_RAYS_PER_CHUNK["cpu"]
    assert render_rays_per_chunk(None, "mps") == 1 << 16, "another device gets the CPU's size"
    assert render_rays_per_chunk(1000, "cuda") == 1000 and render_rays_per_chunk(512, "cpu") == 512


def test_the_method_leaves_the_chunk_to_the_device_and_refuses_one_below_one() -> None:
    import copy

    config = copy.deepcopy(scalar_nerf.config)
    assert config.pipeline.model.eval_num_rays_per_chunk is None
    check_options(config)  # None passes the option checks
    config.pipeline.model.eval_num_rays_per_chunk = 0
    with pytest.raises(OptionError, match="--pipeline.model.eval-num-rays-per-chunk 0"):
        check_options(config)


def test_a_camera_image_is_the_same_in_any_chunk_size() -> None:
    """The chunk size changes only how many rays go through the model at once, never the image."""
    model = small_scalar_model(num_samples_per_ray=16).eval()
    pose = torch.tensor([[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 2.5]]])  # [1, 3, 4] looking down -z at the box
    camera = Cameras(camera_to_worlds=pose, fx=20.0, fy=20.0, cx=12.0, cy=9.0, width=24, height=18)
    images = {}
    for chunk in (None, 1, 37, 24 * 18, 10**6):
        model.config.eval_num_rays_per_chunk = chunk
        images[chunk] = model.get_outputs_for_camera(camera)
    reference = images[None]
    assert reference["rgb"].shape == (18, 24, 3) and reference["depth"].shape == (18, 24, 1)
    assert reference["rgb"].std() > 1e-3, "an image with detail (the untrained field's colours vary over the view)"
    for chunk, outputs in images.items():
        assert outputs.keys() == reference.keys()
        for name in reference:
            torch.testing.assert_close(outputs[name], reference[name], rtol=1e-5, atol=1e-6, msg=f"chunk {chunk}: {name} differs")
