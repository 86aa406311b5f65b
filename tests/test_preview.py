"""The training preview: one held-out view beside its ground truth, bounded in size."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Dict, List

import numpy as np
import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from PIL import Image

from scalar_nerfstudio.engine.preview import PREVIEW_DIR, PREVIEW_NAME, preview_scale, write_preview


class _FlatModel(torch.nn.Module):
    """Renders every pixel in one colour and records the size of each camera it was asked for."""

    def __init__(self, colour: float) -> None:
        super().__init__()
        self.colour = colour
        self.sizes: List[tuple] = []

    def get_outputs_for_camera(self, camera: Cameras) -> Dict[str, torch.Tensor]:
        height, width = int(camera.height[0, 0]), int(camera.width[0, 0])
        self.sizes.append((width, height))
        return {"rgb": torch.full((height, width, 3), self.colour)}  # [H, W, 3]


def _pipeline(width: int, height: int, truth: float, rendered: float) -> SimpleNamespace:
    cameras = Cameras(camera_to_worlds=torch.eye(4)[:3][None], fx=float(width), fy=float(width), cx=width / 2, cy=height / 2,
                      width=width, height=height, camera_type=CameraType.PERSPECTIVE)
    images = [{"image": torch.full((height, width, 3), truth)}]  # [H, W, 3]

    class _Dataset:
        def __init__(self) -> None:
            self.cameras = cameras

        def __getitem__(self, index: int) -> Dict[str, torch.Tensor]:
            return images[index]

    return SimpleNamespace(datamanager=SimpleNamespace(eval_dataset=_Dataset()), device="cpu", model=_FlatModel(rendered))


@pytest.mark.parametrize("width, height, max_size, expected", [
    (4000, 3000, 512, 512 / 4000), (3000, 4000, 512, 512 / 4000), (500, 375, 512, 1.0), (4000, 3000, 0, 1.0),
])
def test_preview_scale_bounds_the_longer_side(width: int, height: int, max_size: int, expected: float) -> None:
    assert preview_scale(width, height, max_size) == pytest.approx(expected)


def test_a_full_resolution_view_is_previewed_at_the_bound(tmp_path: Path) -> None:
    """A 4000 x 3000 eval photo is rendered at 512 x 384, not in full; the dataset's camera keeps its size."""
    pipeline = _pipeline(4000, 3000, truth=0.5, rendered=0.6)
    path, score = write_preview(pipeline, tmp_path, step=499, max_size=512)
    assert pipeline.model.sizes == [(512, 384)]
    assert int(pipeline.datamanager.eval_dataset.cameras.width[0, 0]) == 4000
    assert score == pytest.approx(20.0, abs=1e-3)  # a flat error of 0.1 is 20 dB at any size
    image = np.asarray(Image.open(path))
    assert image.shape == (384, 2 * 512, 3)  # render | ground truth
    assert path == tmp_path / PREVIEW_NAME and (tmp_path / PREVIEW_DIR / "step-000000499.png").is_file()


def test_max_size_zero_previews_at_the_eval_size(tmp_path: Path) -> None:
    pipeline = _pipeline(640, 480, truth=0.5, rendered=0.5)
    _, score = write_preview(pipeline, tmp_path, step=0, max_size=0)
    assert pipeline.model.sizes == [(640, 480)]
    assert score == pytest.approx(100.0)  # identical images: the metric's cap
