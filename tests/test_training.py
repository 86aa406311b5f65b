"""Training makes the render measurably better on held-out castle-P30 views."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from conftest import TRAIN_STEPS
from nerfstudio.utils.eval_utils import eval_setup
from prerequisites import requires_castle
from quality import mean_image_psnr


@pytest.mark.slow
@requires_castle
def test_training_improves_heldout_psnr(trained_castle_run: Path) -> None:
    config_path = trained_castle_run / "config.yml"
    config, trained, _, step = eval_setup(config_path, test_mode="test")
    assert step == TRAIN_STEPS - 1
    trained_metrics = trained.get_average_eval_image_metrics()

    untrained_config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    untrained = untrained_config.pipeline.setup(device="cpu", test_mode="test")
    untrained.eval()
    untrained_metrics = untrained.get_average_eval_image_metrics()
    baseline = mean_image_psnr(trained)

    print(f"held-out PSNR: step 0 {untrained_metrics['psnr']:.2f} dB, step {step} {trained_metrics['psnr']:.2f} dB, "
          f"mean training image {baseline:.2f} dB; SSIM {untrained_metrics['ssim']:.3f} -> {trained_metrics['ssim']:.3f}")
    assert trained_metrics["psnr"] > untrained_metrics["psnr"] + 3.0
    assert trained_metrics["psnr"] > baseline
    assert trained_metrics["ssim"] > untrained_metrics["ssim"]
