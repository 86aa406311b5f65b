"""Depth metrics against a scene's true depth (scalar_nerfstudio/metrics.py: depth_metrics), hand-made maps."""

from __future__ import annotations

import math

import pytest
import torch

from scalar_nerfstudio.metrics import DEPTH_DELTA1_FACTOR, depth_metrics


def _map(*values: float) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float32).reshape(1, -1, 1)  # [H=1, W, 1]


def test_exact_depth_scores_perfectly() -> None:
    truth = _map(1.0, 2.0, 40.0)
    assert depth_metrics(truth.clone(), truth) == {"depth_delta1": 1.0, "depth_median_rel_error": 0.0, "depth_known_pixels": 3.0}


def test_fog_at_the_far_plane_scores_as_wrong_as_it_is() -> None:
    """A render that puts every surface at its far plane (colour from haze) gets none within 25 %."""
    truth = _map(5.0, 10.0, 20.0)
    metrics = depth_metrics(torch.full_like(truth, 1000.0), truth)
    assert metrics["depth_delta1"] == 0.0
    assert metrics["depth_median_rel_error"] == pytest.approx(99.0)


def test_the_25_percent_threshold_holds_both_ways() -> None:
    truth = _map(10.0, 10.0, 10.0, 10.0)
    predicted = _map(10.0 * 1.2, 10.0 / 1.2, 10.0 * 1.3, 10.0 / 1.3)  # in, in, out, out
    metrics = depth_metrics(predicted, truth)
    assert metrics["depth_delta1"] == 0.5
    assert DEPTH_DELTA1_FACTOR == 1.25


def test_unknown_truth_is_left_out_and_bad_predictions_count_as_wrong() -> None:
    truth = _map(0.0, -1.0, math.inf, math.nan, 10.0, 10.0, 10.0, 10.0)  # sky (0) and garbage: unknown
    predicted = _map(123.0, 5.0, 1.0, 1.0, 10.0, math.nan, math.inf, -3.0)
    metrics = depth_metrics(predicted, truth)
    assert metrics["depth_known_pixels"] == 4.0
    assert metrics["depth_delta1"] == 0.25, "NaN, inf and negative depths are never right"
    assert math.isfinite(metrics["depth_median_rel_error"])


def test_an_image_of_sky_gives_nan_not_a_missing_key() -> None:
    metrics = depth_metrics(_map(1.0, 2.0), _map(0.0, 0.0))
    assert set(metrics) == {"depth_delta1", "depth_median_rel_error", "depth_known_pixels"}
    assert math.isnan(metrics["depth_delta1"]) and metrics["depth_known_pixels"] == 0.0


def test_shapes_must_match() -> None:
    with pytest.raises(ValueError, match="differ in shape"):
        depth_metrics(torch.ones(4, 4, 1), torch.ones(4, 4))
