"""The fused float32 MLP kernels (``csrc/mlp_f32.cpp``, ``fields/fused_mlp_float32.py``) against torch's
float32 layers, and the choice of the decoder's CPU training kernel (``fields/decoder_kernels.py``).

Both builds of the kernels are checked where they run: ``"avx2"`` (AVX2 + FMA) and ``"portable"``
(the compiler's baseline target, the fallback on CPUs without AVX2 and off x86). They sum in
another order than torch and with fused multiply-adds, so results agree to float32 rounding over
the sums: relative error (Frobenius norm) below 1e-5 for outputs, 1e-4 for gradients.
"""

from __future__ import annotations

import pytest
import torch
from conftest import SMALL_FIELD
from torch import Tensor, nn

from scalar_nerfstudio.fields import scalar_field
from scalar_nerfstudio.fields.decoder_kernels import choose_cpu_decoder_kernel
from scalar_nerfstudio.fields.fused_mlp import fused_mlp_available
from scalar_nerfstudio.fields.fused_mlp_float32 import float32_mlp_isa, fused_mlp_float32, mlp_float32_inference
from scalar_nerfstudio.fields.scalar_field import ScalarFieldConfig

OUTPUT_TOLERANCE = 1e-5
GRADIENT_TOLERANCE = 1e-4

needs_extension = pytest.mark.skipif(float32_mlp_isa() is None, reason="the C++ extension did not build")
ISAS = [
    pytest.param("portable", marks=needs_extension),
    pytest.param("avx2", marks=pytest.mark.skipif(float32_mlp_isa() != "avx2", reason="no AVX2 and FMA on this CPU")),
]


def make_mlp(widths: tuple[int, ...], relu: bool = True, seed: int = 0) -> nn.Sequential:
    torch.manual_seed(seed)
    modules: list[nn.Module] = []
    for index, (inputs, outputs) in enumerate(zip(widths[:-1], widths[1:])):
        modules.append(nn.Linear(inputs, outputs))
        if relu and index + 2 < len(widths):
            modules.append(nn.ReLU(inplace=True))
    with torch.no_grad():  # biases of a trained decoder's size, so that the ReLUs cut
        for module in modules:
            if isinstance(module, nn.Linear):
                module.bias.normal_(std=0.3)
    return nn.Sequential(*modules)


def relative_error(actual: Tensor, expected: Tensor) -> float:
    return float((actual - expected).detach().norm() / expected.detach().norm().clamp_min(1e-30))


# the decoder's two heads at widths 64 and 128, widths that are not multiples of 8 or 16, one layer
SHAPES = [(64, 64, 16), (39, 64, 64, 3), (64, 128, 16), (5, 32, 3), (17, 80, 33, 1), (9, 4)]


@pytest.mark.parametrize("isa", ISAS)
@pytest.mark.parametrize("widths", SHAPES)
@pytest.mark.parametrize("num_rows", [1, 63, 65, 300])
@pytest.mark.parametrize("relu", [True, False])
def test_forward_and_gradients_agree_with_torch_float32(isa: str, widths: tuple[int, ...], num_rows: int, relu: bool) -> None:
    mlp = make_mlp(widths, relu)
    generator = torch.Generator().manual_seed(num_rows)
    inputs = torch.randn(num_rows, widths[0], generator=generator, requires_grad=True)
    output = fused_mlp_float32(mlp, inputs, isa)
    expected = mlp(inputs)
    assert output.dtype == torch.float32 and output.shape == (num_rows, widths[-1])
    assert relative_error(output, expected) < OUTPUT_TOLERANCE
    assert torch.equal(mlp_float32_inference(mlp, inputs.detach(), isa), output.detach())  # same tiles, no activations kept

    grad_out = torch.randn(output.shape, generator=generator)
    got = torch.autograd.grad(output, [inputs, *mlp.parameters()], grad_out)
    want = torch.autograd.grad(expected, [inputs, *mlp.parameters()], grad_out)
    for name, actual, reference in zip(["inputs"] + [n for n, _ in mlp.named_parameters()], got, want):
        assert actual.shape == reference.shape and actual.dtype == torch.float32, name
        assert relative_error(actual, reference) < GRADIENT_TOLERANCE, name


@needs_extension
def test_avx2_and_portable_builds_agree_and_rows_are_computed_alone() -> None:
    mlp = make_mlp((39, 64, 64, 3))
    inputs = torch.randn(130, 39, generator=torch.Generator().manual_seed(3))
    inputs[7] = float("nan")  # a broken row spoils itself, not its tile
    with torch.no_grad():
        portable = fused_mlp_float32(mlp, inputs, "portable")
        alone = torch.cat([fused_mlp_float32(mlp, inputs[i : i + 1], "portable") for i in range(inputs.shape[0])])
        if float32_mlp_isa() == "avx2":
            avx2 = fused_mlp_float32(mlp, inputs, "avx2")
            keep = torch.arange(130) != 7
            assert relative_error(avx2[keep], portable[keep]) < OUTPUT_TOLERANCE
    assert torch.isnan(portable[7]).all()
    keep = torch.arange(130) != 7
    assert torch.equal(portable[keep], alone[keep])


@needs_extension
def test_only_the_requested_parameters_get_gradients_and_no_rows_give_zeros() -> None:
    mlp = make_mlp((17, 32, 5))
    mlp[0].weight.requires_grad_(False)
    inputs = torch.randn(70, 17)  # no input gradient asked for
    fused_mlp_float32(mlp, inputs).sum().backward()
    assert mlp[0].weight.grad is None and mlp[0].bias.grad is not None and mlp[2].weight.grad is not None
    empty = torch.zeros(0, 17, requires_grad=True)
    output = fused_mlp_float32(mlp, empty)
    assert output.shape == (0, 5)
    output.sum().backward()
    assert empty.grad is not None and empty.grad.shape == (0, 17)


@needs_extension
def test_gradients_do_not_depend_on_the_thread_count() -> None:
    mlp = make_mlp((39, 64, 64, 3))
    inputs = torch.randn(5000, 39, generator=torch.Generator().manual_seed(5))
    threads = torch.get_num_threads()
    grads = []
    try:
        for count in (1, 2):
            torch.set_num_threads(count)
            mlp.zero_grad()
            fused_mlp_float32(mlp, inputs).square().sum().backward()
            grads.append([p.grad.clone() for p in mlp.parameters()])
    finally:
        torch.set_num_threads(threads)
    for one, two in zip(*grads):
        assert relative_error(two, one) < 1e-5  # only the order of the per-thread sums differs


@needs_extension
def test_bad_calls_are_refused_with_messages_that_name_the_problem() -> None:
    mlp = make_mlp((4, 8, 2))
    with pytest.raises(TypeError, match="float32"):
        fused_mlp_float32(mlp, torch.zeros(3, 4, dtype=torch.float64))
    with pytest.raises(TypeError, match="Sigmoid"):
        fused_mlp_float32(nn.Sequential(nn.Linear(4, 8), nn.Sigmoid(), nn.Linear(8, 2)), torch.zeros(3, 4))
    with pytest.raises(RuntimeError, match="isa must be 'avx2' .* or 'portable', got 'sse9'"):
        torch.ops.scalar_nerf_mlp_f32.forward(torch.zeros(3, 8), [torch.zeros(8, 8)], [torch.zeros(8)], [0], 2, "sse9")
    with pytest.raises(RuntimeError, match="input has 16 columns, the first layer takes 8"):
        torch.ops.scalar_nerf_mlp_f32.forward(torch.zeros(3, 16), [torch.zeros(8, 8)], [torch.zeros(8)], [0], 2, "portable")
    inputs = torch.ones(3, 4, requires_grad=True)
    output = fused_mlp_float32(mlp, inputs)
    (grad,) = torch.autograd.grad(output, inputs, torch.ones_like(output).requires_grad_(), create_graph=True)
    with pytest.raises(RuntimeError, match="differentiate twice"):  # not silently wrong second derivatives
        grad.sum().backward()


# --- the choice of kernel (pure: every CPU is described by the flags) -------------------------------

ALL = dict(bfloat16_is_fast=True, has_avx512bf16=True, has_avx2=True)
AVX2_ONLY = dict(bfloat16_is_fast=False, has_avx512bf16=False, has_avx2=True)
NEITHER = dict(bfloat16_is_fast=False, has_avx512bf16=False, has_avx2=False)


def choose(requested: str, precision: str = "auto", fused: bool = True, **cpu: bool):
    choice = choose_cpu_decoder_kernel(requested, precision, fused=fused, **cpu)  # type: ignore[arg-type]
    return choice.kernel, choice.bfloat16, choice.note


def test_auto_takes_avx512bf16_where_it_runs_else_avx2_in_float32_else_torch() -> None:
    assert choose("auto", **ALL) == ("avx512bf16", True, None)  # unchanged on an AVX512-BF16 CPU
    assert choose("auto", **AVX2_ONLY) == ("avx2", False, None)
    assert choose("auto", **NEITHER) == ("torch", False, None)
    assert choose("auto", "float32", **ALL) == ("avx2", False, None)
    assert choose("auto", "bfloat16", **AVX2_ONLY) == ("torch", True, None)  # bfloat16 asked for: autocast, layer by layer
    assert choose("auto", fused=False, **ALL) == ("torch", True, None)  # fused_decoder=False, as before
    assert choose("torch", **AVX2_ONLY) == ("torch", False, None)


def test_a_forced_kernel_is_taken_where_it_runs_and_otherwise_falls_back_with_a_note() -> None:
    assert choose("avx2", **ALL) == ("avx2", False, None)  # the AVX2 path on an AVX512-BF16 CPU: float32 products
    assert choose("avx512bf16", **ALL) == ("avx512bf16", True, None)
    kernel, bfloat16, note = choose("avx512bf16", **AVX2_ONLY)
    assert (kernel, bfloat16) == ("avx2", False)
    assert note is not None and "'avx512bf16' cannot run here" in note and "'avx2' in float32 instead" in note
    kernel, bfloat16, note = choose("avx2", **NEITHER)
    assert (kernel, bfloat16) == ("torch", False) and note is not None and "no AVX2 and FMA" in note


def test_contradictory_settings_are_refused() -> None:
    with pytest.raises(ValueError, match="'avx512bf16' multiplies in bfloat16, but decoder_precision='float32'"):
        choose("avx512bf16", "float32", **ALL)
    with pytest.raises(ValueError, match="'avx2' multiplies in float32, but decoder_precision='bfloat16'"):
        choose("avx2", "bfloat16", **ALL)
    with pytest.raises(ValueError, match="fused_decoder=False"):
        choose("avx2", fused=False, **ALL)


# --- the field ------------------------------------------------------------------------------------


@pytest.mark.skipif(float32_mlp_isa() != "avx2", reason="no AVX2 and FMA on this CPU")
def test_the_field_with_the_avx2_kernel_forced_trains_and_renders_in_float32_with_torch_s_results(monkeypatch: pytest.MonkeyPatch) -> None:
    torch.manual_seed(0)
    forced = ScalarFieldConfig(**SMALL_FIELD, cpu_decoder_kernel="avx2").setup(num_images=3)
    torch.manual_seed(0)
    layered = ScalarFieldConfig(**SMALL_FIELD, decoder_precision="float32", cpu_decoder_kernel="torch").setup(num_images=3)
    layered.load_state_dict(forced.state_dict())
    assert forced.cpu_decoder_kernel == "avx2" and not forced.cpu_bfloat16
    assert layered.cpu_decoder_kernel == "torch" and not layered.cpu_bfloat16
    calls: list[int] = []
    real = scalar_field.fused_mlp_float32
    monkeypatch.setattr(scalar_field, "fused_mlp_float32", lambda *args: calls.append(1) or real(*args))
    generator = torch.Generator().manual_seed(1)
    points = torch.rand(2000, 3, generator=generator)
    directions = torch.nn.functional.normalize(torch.randn(50, 3, generator=generator), dim=-1)
    ray_ids, camera_indices = torch.arange(2000) % 50, torch.arange(50) % 3
    results = []
    for field in (forced, layered):
        field.train()
        density, geo = field.density_at_unit(points)
        rgb = field.colour(geo, directions, ray_ids, camera_indices=camera_indices)
        (density.log1p().sum() + rgb.square().sum()).backward()
        results.append((density, rgb, {name: p.grad for name, p in field.named_parameters() if p.grad is not None}))
    assert len(calls) == 2  # density and colour heads of the forced field; none for the layered one
    (density_f, rgb_f, grads_f), (density_l, rgb_l, grads_l) = results
    assert relative_error(density_f, density_l) < OUTPUT_TOLERANCE and relative_error(rgb_f, rgb_l) < OUTPUT_TOLERANCE
    assert grads_f.keys() == grads_l.keys() and any(name.startswith("encoder") for name in grads_f)
    for name in grads_f:
        assert relative_error(grads_f[name], grads_l[name]) < GRADIENT_TOLERANCE, name
    inference: list[int] = []
    real_inference = scalar_field.mlp_float32_inference
    monkeypatch.setattr(scalar_field, "mlp_float32_inference", lambda *args: inference.append(1) or real_inference(*args))
    with torch.no_grad():  # evaluation takes the inference kernels, with the training kernels' results
        density_i, geo_i = forced.density_at_unit(points)
        rgb_i = forced.colour(geo_i, directions, ray_ids, camera_indices=camera_indices)
        layered.density_at_unit(points)
    assert len(calls) == 2 and len(inference) == 2
    assert torch.equal(density_i, density_f.detach()) and torch.equal(rgb_i, rgb_f.detach())


@pytest.mark.skipif(not fused_mlp_available(), reason="no AVX512-BF16 on this CPU")
def test_the_default_on_an_avx512bf16_cpu_is_the_bfloat16_kernel() -> None:
    field = ScalarFieldConfig(**SMALL_FIELD).setup(num_images=3)
    assert field.cpu_decoder_kernel == "avx512bf16" and field.cpu_bfloat16
    assert field.decoder.fused_cpu_training and not field.decoder.float32_cpu_training


def test_a_forced_kernel_the_cpu_lacks_falls_back_with_one_warning(monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setattr(scalar_field, "float32_mlp_isa", lambda: "portable")  # a CPU without AVX2
    monkeypatch.setattr(scalar_field, "fused_mlp_available", lambda: False)
    monkeypatch.setattr(scalar_field, "cpu_bfloat16_is_fast", lambda: False)
    scalar_field._warn_once.cache_clear()
    with caplog.at_level("WARNING", logger=scalar_field.__name__):
        fields = [ScalarFieldConfig(**SMALL_FIELD, cpu_decoder_kernel="avx2").setup(num_images=3) for _ in range(2)]
    assert all(f.cpu_decoder_kernel == "torch" and not f.cpu_bfloat16 for f in fields)
    warnings = [r.getMessage() for r in caplog.records if "cpu_decoder_kernel='avx2' cannot run here" in r.getMessage()]
    assert len(warnings) == 1 and "'torch' in float32 instead" in warnings[0]
    scalar_field._warn_once.cache_clear()


def test_ns_train_refuses_contradictory_kernel_settings_up_front() -> None:
    from scalar_nerfstudio.config_checks import OptionError, check_pipeline_options
    from scalar_nerfstudio.models.scene_model import ScalarSceneModelConfig
    from scalar_nerfstudio.pipeline import ScalarPipelineConfig

    def pipeline(**field: object) -> ScalarPipelineConfig:
        return ScalarPipelineConfig(model=ScalarSceneModelConfig(field=ScalarFieldConfig(**field)))

    check_pipeline_options(pipeline(cpu_decoder_kernel="avx2"))  # fine whatever the CPU (it falls back where it must)
    with pytest.raises(OptionError, match=r"--pipeline.model.field.cpu-decoder-kernel: .*'avx2' multiplies in float32"):
        check_pipeline_options(pipeline(cpu_decoder_kernel="avx2", decoder_precision="bfloat16"))
    with pytest.raises(OptionError, match="fused_decoder=False"):
        check_pipeline_options(pipeline(cpu_decoder_kernel="avx512bf16", fused_decoder=False))
