"""The fused bfloat16 MLP kernels (``csrc/mlp.cpp``, ``fields/fused_mlp.py``) against a float32 oracle.

The oracle is the same stack of layers in float32 torch with the inputs, weights and hidden
activations rounded to bfloat16, which is what the kernels compute (float32 sums of bfloat16
products). Gradients are compared with the oracle's autograd; the kernels also round each layer's
output gradient to bfloat16, so gradients agree to a few parts in a thousand, not exactly.
"""

from __future__ import annotations

import pytest
import torch
from conftest import SMALL_FIELD
from torch import Tensor, nn

from scalar_nerfstudio.fields import scalar_field
from scalar_nerfstudio.fields.fused_mlp import fused_mlp, fused_mlp_available, linear_layers
from scalar_nerfstudio.fields.scalar_field import ScalarField, ScalarFieldConfig

pytestmark = pytest.mark.skipif(not fused_mlp_available(), reason="no C++ extension or no AVX512-BF16 on this CPU")


def oracle(mlp: nn.Sequential, inputs: Tensor) -> Tensor:
    """float32 torch with bfloat16-rounded inputs, weights and hidden activations."""
    layers, relu = linear_layers(mlp)
    hidden = inputs.to(torch.bfloat16).float()
    for index, (layer, has_relu) in enumerate(zip(layers, relu)):
        hidden = hidden @ layer.weight.to(torch.bfloat16).float().t() + layer.bias
        if has_relu:
            hidden = torch.relu(hidden)
        if index + 1 < len(layers):
            hidden = hidden.to(torch.bfloat16).float()
    return hidden


def make_mlp(widths: tuple[int, ...], seed: int = 0) -> nn.Sequential:
    torch.manual_seed(seed)
    modules: list[nn.Module] = []
    for index, (inputs, outputs) in enumerate(zip(widths[:-1], widths[1:])):
        modules.append(nn.Linear(inputs, outputs))
        if index + 2 < len(widths):
            modules.append(nn.ReLU(inplace=True))
    with torch.no_grad():  # biases of a trained decoder's size, so that the ReLUs cut
        for module in modules:
            if isinstance(module, nn.Linear):
                module.bias.normal_(std=0.3)
    return nn.Sequential(*modules)


def relative_error(actual: Tensor, expected: Tensor) -> float:
    return float((actual - expected).norm() / expected.norm().clamp_min(1e-30))


# the decoder's two heads (hash-grid features -> density and geometry; geometry + direction +
# appearance -> RGB), the paper's 128-wide decoder, and widths that are not multiples of 16
SHAPES = [(64, 64, 16), (39, 64, 64, 3), (64, 128, 16), (5, 32, 3), (17, 80, 33, 1)]


@pytest.mark.parametrize("widths", SHAPES)
@pytest.mark.parametrize("num_rows", [1, 63, 64, 65, 1000])
def test_forward_and_gradients_agree_with_the_bfloat16_oracle(widths: tuple[int, ...], num_rows: int) -> None:
    mlp = make_mlp(widths)
    generator = torch.Generator().manual_seed(num_rows)
    inputs = torch.randn(num_rows, widths[0], generator=generator, requires_grad=True)
    output = fused_mlp(mlp, inputs)
    expected = oracle(mlp, inputs)
    assert output.dtype == torch.float32 and output.shape == (num_rows, widths[-1])
    assert relative_error(output, expected) < 1e-5

    grad_out = torch.randn(output.shape, generator=generator)
    got = torch.autograd.grad(output, [inputs, *mlp.parameters()], grad_out)
    want = torch.autograd.grad(expected, [inputs, *mlp.parameters()], grad_out)
    for name, actual, reference in zip(["inputs"] + [n for n, _ in mlp.named_parameters()], got, want):
        assert actual.shape == reference.shape and actual.dtype == torch.float32, name
        assert relative_error(actual, reference) < 1e-2, name


def test_bfloat16_inputs_give_bfloat16_input_gradients_and_the_same_result() -> None:
    mlp = make_mlp((39, 64, 64, 3))
    inputs = torch.randn(300, 39).to(torch.bfloat16).requires_grad_()
    output = fused_mlp(mlp, inputs)
    assert torch.allclose(output, oracle(mlp, inputs.float()), rtol=1e-5, atol=1e-6)
    output.square().sum().backward()
    assert inputs.grad is not None and inputs.grad.dtype == torch.bfloat16


def test_each_row_is_computed_alone_the_padding_rows_change_nothing() -> None:
    mlp = make_mlp((64, 64, 16))
    inputs = torch.randn(130, 64)
    inputs[7] = float("nan")  # a broken row spoils itself, not its tile
    with torch.no_grad():
        batch = fused_mlp(mlp, inputs)
        alone = torch.cat([fused_mlp(mlp, inputs[i : i + 1]) for i in range(inputs.shape[0])])
    assert torch.isnan(batch[7]).all()
    keep = torch.arange(130) != 7
    assert torch.equal(batch[keep], alone[keep])


def test_no_rows_give_an_empty_output_and_zero_gradients() -> None:
    mlp = make_mlp((64, 64, 16))
    inputs = torch.zeros(0, 64, requires_grad=True)
    output = fused_mlp(mlp, inputs)
    assert output.shape == (0, 16)
    output.sum().backward()
    assert inputs.grad is not None and inputs.grad.shape == (0, 64)
    assert all(p.grad is not None and not p.grad.any() for p in mlp.parameters())


def test_gradients_do_not_depend_on_the_thread_count() -> None:
    mlp = make_mlp((39, 64, 64, 3))
    inputs = torch.randn(5000, 39, generator=torch.Generator().manual_seed(5))
    threads = torch.get_num_threads()
    grads = []
    try:
        for count in (1, 2):
            torch.set_num_threads(count)
            mlp.zero_grad()
            fused_mlp(mlp, inputs).square().sum().backward()
            grads.append([p.grad.clone() for p in mlp.parameters()])
    finally:
        torch.set_num_threads(threads)
    for one, two in zip(*grads):
        assert relative_error(two, one) < 1e-5  # only the order of the per-thread sums differs


def test_layers_other_than_linear_and_relu_are_refused() -> None:
    with pytest.raises(TypeError, match="Sigmoid"):
        fused_mlp(nn.Sequential(nn.Linear(4, 8), nn.Sigmoid(), nn.Linear(8, 2)), torch.zeros(3, 4))
    with pytest.raises(TypeError, match="no ReLU after the last"):
        fused_mlp(nn.Sequential(nn.Linear(4, 8), nn.ReLU()), torch.zeros(3, 4))


def _field(fused: bool) -> ScalarField:
    torch.manual_seed(0)
    return ScalarFieldConfig(**SMALL_FIELD, decoder_precision="bfloat16", fused_decoder=fused).setup(num_images=3)


def test_the_field_trains_through_the_fused_kernels_with_autograd_s_results(monkeypatch: pytest.MonkeyPatch) -> None:
    fused, layered = _field(True), _field(False)
    layered.load_state_dict(fused.state_dict())
    with torch.no_grad():  # a trained-looking decoder: weights well away from their initial scale
        for field in (fused, layered):
            for parameter in field.decoder.parameters():
                parameter.mul_(3.0)
    calls: list[int] = []
    real = scalar_field.fused_mlp
    monkeypatch.setattr(scalar_field, "fused_mlp", lambda *args: calls.append(1) or real(*args))
    generator = torch.Generator().manual_seed(1)
    points = torch.rand(4096, 3, generator=generator)
    directions = torch.nn.functional.normalize(torch.randn(64, 3, generator=generator), dim=-1)
    ray_ids = torch.arange(4096) % 64
    camera_indices = torch.arange(64) % 3
    results = []
    for field in (fused, layered):
        field.train()
        density, geo = field.density_at_unit(points)
        rgb = field.colour(geo, directions, ray_ids, camera_indices=camera_indices)
        (density.log1p().sum() + rgb.square().sum()).backward()
        grads = {name: p.grad for name, p in field.named_parameters() if p.grad is not None}
        results.append((density, rgb, grads))
    assert len(calls) == 2  # density and colour heads of the fused field; none for the layered one
    (density_f, rgb_f, grads_f), (density_l, rgb_l, grads_l) = results
    assert density_f.dtype == rgb_f.dtype == torch.float32
    # the layered path rounds the density head's output to bfloat16; the fused one keeps float32
    assert torch.allclose(density_f, density_l, rtol=0.05, atol=1e-4)
    assert (rgb_f - rgb_l).abs().max() < 0.01
    assert grads_f.keys() == grads_l.keys() and any(name.startswith("encoder") for name in grads_f)
    for name in grads_f:
        cosine = torch.nn.functional.cosine_similarity(grads_f[name].flatten(), grads_l[name].flatten(), dim=0)
        assert cosine > 0.99, name


def test_without_autocast_or_without_autograd_the_field_does_not_take_the_training_kernels(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls: list[int] = []
    monkeypatch.setattr(scalar_field, "fused_mlp", lambda *args: calls.append(1))
    points = torch.rand(100, 3)
    float32 = ScalarFieldConfig(**SMALL_FIELD, decoder_precision="float32").setup(num_images=3)
    float32.density_at_unit(points)
    with torch.no_grad():
        _field(True).density_at_unit(points)
    assert not calls


def test_the_kernel_rejects_bad_inputs_with_a_message_that_names_the_sizes() -> None:
    """A bad call is a RuntimeError naming the numbers involved, not a crash (csrc/check.h)."""
    from scalar_nerfstudio.fields.fused_mlp import pack_weights

    weight = torch.randn(16, 32)
    forward_weight, _ = pack_weights(weight)
    bias = torch.zeros(16)
    with pytest.raises(RuntimeError, match="input has 48 columns, the first layer takes 32"):
        torch.ops.scalar_nerf_mlp.forward(torch.randn(4, 48), [forward_weight], [bias], [0], 16)
    with pytest.raises(RuntimeError, match="out_dim 17 out of range"):
        torch.ops.scalar_nerf_mlp.forward(torch.randn(4, 32), [forward_weight], [bias], [0], 17)
    with pytest.raises(RuntimeError, match=r"packed weight 0 must be .*got \[16, 16, 2\] Float"):
        torch.ops.scalar_nerf_mlp.forward(torch.randn(4, 32), [forward_weight.float()], [bias], [0], 16)
