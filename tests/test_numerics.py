"""Numerical hard cases, property-based: contraction, hashing, volume rendering, bad rays, bf16."""

from __future__ import annotations

import math
import warnings

import pytest
import torch
from conftest import ray_bundle, small_scalar_model
from hypothesis import given, settings, strategies as st

from scalar_nerfstudio.encodings.hash_grid import HashGridEncoding
from scalar_nerfstudio.fields.scalar_field import contract, contract_to_unit_cube
from scalar_nerfstudio.model_components.rendering import render_weights
from scalar_nerfstudio.models.scalar_model import ScalarModel

EXTREME = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32),
    st.sampled_from([0.0, 1.0 - 1e-7, 1.0 + 1e-7, 1e6, 1e30, -1e30, 3.4e38]),
)
POINTS = st.lists(st.tuples(EXTREME, EXTREME, EXTREME), min_size=1, max_size=32)


@settings(max_examples=300, deadline=None)
@given(POINTS)
def test_contraction_is_finite_and_inside_the_ball(points) -> None:
    x = torch.tensor(points, dtype=torch.float32)
    out = contract(x)
    assert torch.isfinite(out).all()
    assert (torch.linalg.vector_norm(out, dim=-1) <= 2.0 + 1e-5).all()
    unit = contract_to_unit_cube(x)
    assert ((unit >= 0.0) & (unit <= 1.0)).all()


@settings(max_examples=60, deadline=None)
@given(POINTS)
def test_hash_encoding_of_any_point_is_finite_with_finite_gradients(points) -> None:
    encoding = _small_encoding()
    x = contract_to_unit_cube(torch.tensor(points, dtype=torch.float32)).requires_grad_(False)
    raw = torch.tensor(points, dtype=torch.float32).nan_to_num(0.5).clamp(-1e6, 1e6)  # outside [0, 1] too
    for inputs in (x, raw):
        out = encoding(inputs)
        assert torch.isfinite(out).all()
        out.square().sum().backward()
        assert all(torch.isfinite(p.grad).all() for p in encoding.parameters())
        encoding.zero_grad()


_ENCODING = None


def _small_encoding() -> HashGridEncoding:
    global _ENCODING  # one module for all examples (building the kernel once is the slow part)
    if _ENCODING is None:
        _ENCODING = HashGridEncoding(num_levels=4, features_per_level=2, log2_hashmap_size=12, base_resolution=16, max_resolution=4096)
    return _ENCODING


DENSITY = st.one_of(st.floats(min_value=0.0, max_value=1e6), st.sampled_from([0.0, 1e6, math.inf, math.nan]))
DELTA = st.one_of(st.floats(min_value=0.0, max_value=1e6), st.sampled_from([0.0, 1e-12, 1e6]))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(DENSITY, DELTA), min_size=1, max_size=24))
def test_volume_rendering_weights_are_a_sub_distribution(samples) -> None:
    densities = torch.tensor([[d for d, _ in samples]], dtype=torch.float32, requires_grad=True)
    deltas = torch.tensor([[t for _, t in samples]], dtype=torch.float32)
    weights, transmittance = render_weights(densities, deltas)
    assert torch.isfinite(weights).all() and (weights >= 0).all() and (weights <= 1).all()
    assert float(weights.sum()) <= 1.0 + 1e-5
    assert (transmittance[:, 1:] <= transmittance[:, :-1] + 1e-6).all()
    weights.sum().backward()
    assert torch.isfinite(densities.grad).all()


def _tiny_model() -> ScalarModel:
    return small_scalar_model(hidden_dim=32, num_samples_per_ray=16)


def test_rays_with_nan_or_inf_are_reported_and_render_background() -> None:
    model = _tiny_model().eval()
    origins = torch.tensor([[0.0, 0.0, 0.0], [math.nan, 0.0, 0.0], [0.0, 0.0, 0.0], [1e30, 0.0, 0.0]])
    directions = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [math.inf, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        outputs = model(ray_bundle(origins, directions))
    assert any("2 of 4 rays have a NaN/inf" in str(w.message) for w in caught)
    for value in outputs.values():
        assert torch.isfinite(value).all()
    assert torch.equal(outputs["accumulation"][1:3], torch.zeros(2, 1))
    assert torch.allclose(outputs["rgb"][1:3], torch.full((2, 3), 0.5))


def test_bf16_autocast_on_cpu_stays_finite() -> None:
    model = _tiny_model().train()
    origins = torch.zeros(64, 3)
    directions = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        outputs = model(ray_bundle(origins, directions))
        loss = outputs["rgb"].float().square().mean() + outputs["distortion"].float().mean()
    loss.backward()
    assert all(torch.isfinite(v).all() for v in outputs.values())
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in model.parameters())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (fp16 autocast)")
def test_fp16_autocast_on_cuda_stays_finite() -> None:
    model = _tiny_model().cuda().train()
    origins = torch.zeros(64, 3, device="cuda")
    directions = torch.nn.functional.normalize(torch.randn(64, 3, device="cuda"), dim=-1)
    with torch.autocast("cuda", dtype=torch.float16):
        outputs = model(ray_bundle(origins, directions))
    assert all(torch.isfinite(v).all() for v in outputs.values())
