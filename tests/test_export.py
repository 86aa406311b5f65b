"""Surface normals of the density field and ``ns-export pointcloud`` of a fused run.

The fast tests check the normals on hand-made density fields whose normals are known (a half-space,
a sphere) and that they stay finite where the gradient vanishes or is undefined; the slow test trains
a tiny two-block run on the project's courtyard scene (known geometry) and exports its point cloud
with nerfstudio's own ``ns-export pointcloud``.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Optional, Tuple

import numpy as np
import pytest
import torch
from conftest import ns_train_command, ray_bundle, run_dirs, small_scalar_model, tiny_trainer
from nerfstudio.cameras.cameras import Cameras, CameraType
from torch import Tensor

from scalar_nerfstudio.fields.scalar_field import encode_with_position_gradients
from scalar_nerfstudio.model_components.rendering import (
    normals_from_unit_interval,
    normals_to_unit_interval,
    render_normals,
    safe_normalise,
)
from scalar_nerfstudio.models.scalar_model import ScalarModel
from scalar_nerfstudio.scenes.courtyard import DEFAULT_BOXES, write_scene

DensityFn = Callable[[Tensor], Tensor]


# ------------------------------------------------------------------------------ hand-made fields


def _world(unit_positions: Tensor) -> Tensor:
    """Contracted unit-cube positions -> world positions (inverse of ``contract_to_unit_cube`` below radius 2)."""
    contracted = (unit_positions - 0.5) * 4.0
    norm = torch.linalg.vector_norm(contracted, dim=-1, keepdim=True)
    outside = contracted / norm.clamp_min(1.0) / (2.0 - norm.clamp(1.0, 2.0 - 1e-6))
    return torch.where(norm <= 1.0, contracted, outside)


def _model_with_density(density: DensityFn, **config: object) -> ScalarModel:
    """A fresh small model (eval mode) whose density is ``density(world positions [N, 3]) -> [N]``."""
    model = small_scalar_model(num_train_data=1, **config)
    density_at_unit = model.field.density_at_unit

    def field_density(unit_positions: Tensor, encoding: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
        _, geo_features = density_at_unit(unit_positions)
        return density(_world(unit_positions)), geo_features

    model.field.density_at_unit = field_density
    return model.eval()


def _half_space(world: Tensor) -> Tensor:
    """Solid below z = -0.3 (a smooth step 0.02 wide): its outward normal is +z everywhere."""
    return 400.0 * torch.sigmoid(-(world[:, 2] + 0.3) / 0.02)


SPHERE_RADIUS = 0.4


def _sphere(centre: Tuple[float, float, float]) -> DensityFn:
    """Solid ball of radius 0.4 around ``centre`` (a smooth step 0.01 wide): normals point radially outwards."""

    def density(world: Tensor) -> Tensor:
        distance = torch.linalg.vector_norm(world - torch.tensor(centre), dim=-1)
        return 400.0 * torch.sigmoid((SPHERE_RADIUS - distance) / 0.01)

    return density


def _decoded(outputs: dict) -> Tensor:
    assert "normals" in outputs
    encoded = outputs["normals"]
    assert torch.isfinite(encoded).all() and encoded.min() >= 0.0 and encoded.max() <= 1.0  # what ns-export asserts
    normals = normals_from_unit_interval(encoded)
    assert torch.allclose(torch.linalg.vector_norm(normals, dim=-1), torch.ones(normals.shape[0], device=normals.device), atol=1e-5)
    return normals


def _rays_down(num: int) -> Tuple[Tensor, Tensor]:
    """Rays from z = 0.5 looking down at varied angles, all hitting z = -0.3 within the unit ball."""
    generator = torch.Generator().manual_seed(0)
    origins = torch.cat([(torch.rand(num, 2, generator=generator) - 0.5) * 0.6, torch.full((num, 1), 0.5)], dim=-1)
    targets = torch.cat([(torch.rand(num, 2, generator=generator) - 0.5) * 0.6, torch.full((num, 1), -0.3)], dim=-1)
    return origins, torch.nn.functional.normalize(targets - origins, dim=-1)


def test_position_differentiable_encoding_matches_the_kernel_and_finite_differences() -> None:
    model = small_scalar_model()
    field = model.field
    field.cpu_bfloat16 = False  # compare gradients with float32 finite differences
    with torch.no_grad():
        field.encoder.table.normal_(0.0, 0.5)
    points = torch.rand(2000, 3, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(encode_with_position_gradients(field.encoder, points), field.encoder(points), atol=1e-6)

    points = 0.3 + 0.4 * torch.rand(16, 3, generator=torch.Generator().manual_seed(1))
    points.requires_grad_(True)
    density, _ = field.density_at_unit(points)
    (gradient,) = torch.autograd.grad(density.sum(), points)
    step = 1e-4
    with torch.no_grad():
        finite = torch.stack(
            [(field.density_at_unit(points + step * e)[0] - field.density_at_unit(points - step * e)[0]) / (2 * step) for e in torch.eye(3)],
            dim=-1,
        )
    # the interpolation is linear within a cell: central differences agree unless they straddle a cell face
    close = torch.isclose(gradient, finite, rtol=0.02, atol=1e-3 * float(finite.abs().max())).all(dim=-1)
    assert close.float().mean() >= 0.8
    assert field.encoder.table.grad is None  # normals never touch the table's gradient


def test_half_space_normals_are_the_plane_normal() -> None:
    model = _model_with_density(_half_space)
    origins, directions = _rays_down(64)
    with torch.no_grad():  # as ns-export renders: plain forward, outside training, under no_grad
        outputs = model(ray_bundle(origins, directions))
    assert (outputs["accumulation"] > 0.99).all()
    normals = _decoded(outputs)
    assert (normals[:, 2] > 0.9999).all(), normals[normals[:, 2] <= 0.9999]


@pytest.mark.parametrize("centre", [(0.0, 0.0, 0.0), (1.6, 0.0, 0.5)], ids=["unit-ball", "contracted"])
def test_sphere_normals_are_radial(centre: Tuple[float, float, float]) -> None:
    """Also beyond radius 1, where the hash grid lives in contracted space: the gradient is taken
    through the contraction, so the normals are the world-space ones."""
    model = _model_with_density(_sphere(centre), num_samples_per_ray=128)
    generator = torch.Generator().manual_seed(0)
    angles = torch.rand(64, generator=generator) * 2 * math.pi
    offsets = torch.stack([0.9 * torch.cos(angles), 0.9 * torch.sin(angles), 0.3 * (torch.rand(64, generator=generator) - 0.5)], dim=-1)
    origins = torch.tensor(centre) + offsets
    targets = torch.tensor(centre) + 0.2 * (torch.rand(64, 3, generator=generator) - 0.5)  # aimed near the centre: no grazing rays
    directions = torch.nn.functional.normalize(targets - origins, dim=-1)
    with torch.no_grad():
        outputs = model(ray_bundle(origins, directions))
    assert (outputs["accumulation"] > 0.99).all()
    normals = _decoded(outputs)
    hits = origins + directions * outputs["depth"] - torch.tensor(centre)
    assert (torch.linalg.vector_norm(hits, dim=-1) - SPHERE_RADIUS).abs().max() < 0.05
    expected = torch.nn.functional.normalize(hits, dim=-1)
    assert (normals * expected).sum(-1).min() > 0.98


@pytest.mark.parametrize(
    "density",
    [
        lambda w: torch.full_like(w[:, 0], 50.0),  # no dependence on position at all
        lambda w: 50.0 + 0.0 * w.sum(-1),  # depends on position, gradient exactly zero
        lambda w: 50.0 + torch.sqrt(0.0 * w[:, 0]),  # gradient 0 * inf = NaN at every point
        lambda w: torch.where(w[:, 2] < -0.3, 1e3, 0.0),  # a hard step: zero gradient almost everywhere
    ],
    ids=["constant", "zero-gradient", "nan-gradient", "hard-step"],
)
def test_zero_or_undefined_gradients_give_finite_normals_facing_the_camera(density: DensityFn) -> None:
    model = _model_with_density(density)
    origins, directions = _rays_down(32)
    with torch.no_grad():
        normals = _decoded(model(ray_bundle(origins, directions)))
    assert torch.allclose(normals, -directions, atol=1e-5)


def test_rays_with_nan_or_inf_get_finite_normals() -> None:
    model = _model_with_density(_half_space)
    origins = torch.tensor([[0.0, 0.0, 0.5], [math.nan, 0.0, 0.0], [0.0, 0.0, 0.5], [1e30, 0.0, 0.0]])
    directions = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [math.inf, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with pytest.warns(UserWarning, match="2 of 4 rays"), torch.no_grad():
        outputs = model(ray_bundle(origins, directions))
    normals = _decoded(outputs)
    assert normals[0, 2] > 0.9999


def test_safe_normalise_and_render_normals_edge_cases() -> None:
    fallback = torch.tensor([0.0, 0.0, 1.0])
    vectors = torch.tensor(
        [[0.0, 0.0, 0.0], [1e-30, 0.0, 0.0], [1e30, 1e30, 0.0], [math.nan, 1.0, 0.0], [math.inf, 0.0, 0.0], [3.0, 4.0, 0.0], [-1e-9, 0.0, 0.0]]
    )
    unit = safe_normalise(vectors, fallback)
    assert torch.isfinite(unit).all()
    assert torch.allclose(torch.linalg.vector_norm(unit, dim=-1), torch.ones(len(vectors)))
    for row in (0, 1, 3, 4):
        assert torch.equal(unit[row], fallback)
    assert torch.allclose(unit[2], torch.tensor([1.0, 1.0, 0.0]) / math.sqrt(2.0))
    assert torch.allclose(unit[5], torch.tensor([0.6, 0.8, 0.0]))
    assert torch.allclose(unit[6], torch.tensor([-1.0, 0.0, 0.0]))

    weights = torch.tensor([[0.0, 0.0], [0.2, 0.6], [0.5, 0.5]])
    sample_normals = torch.tensor([[[1.0, 0, 0], [0, 1.0, 0]], [[0, 0, 0], [0, 1.0, 0]], [[1.0, 0, 0], [-1.0, 0, 0]]])
    ray_fallback = torch.tensor([[0.0, 0.0, 1.0]] * 3)
    rendered = render_normals(weights, sample_normals, ray_fallback)
    assert torch.equal(rendered[0], ray_fallback[0])  # nothing hit
    assert torch.allclose(rendered[1], torch.tensor([0.0, 1.0, 0.0]))  # a sample without normal does not count
    assert torch.equal(rendered[2], ray_fallback[2])  # opposite normals cancel
    encoded = normals_to_unit_interval(rendered)
    assert encoded.min() >= 0.0 and encoded.max() <= 1.0
    assert torch.allclose(normals_from_unit_interval(encoded), rendered)


# --------------------------------------------------------------------- when normals are rendered


def _camera(width: int = 8, height: int = 6) -> Cameras:
    pose = torch.tensor([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0.5]])  # at z = 0.5 looking down (-z)
    return Cameras(camera_to_worlds=pose[None], fx=4.0, fy=4.0, cx=width / 2, cy=height / 2, width=width, height=height, camera_type=CameraType.PERSPECTIVE)


def test_normals_only_outside_training_and_not_for_camera_images_unless_asked() -> None:
    model = _model_with_density(_half_space)
    rays = ray_bundle(*_rays_down(8))
    with torch.no_grad():
        assert "normals" in model(rays)  # a ray batch outside training (ns-export)
        assert "normals" not in model.get_outputs_for_camera(_camera())  # eval / ns-render / viewer: no cost
        with model.rendering_normals("always"):
            image = model.get_outputs_for_camera(_camera())
        assert image["normals"].shape == (6, 8, 3) and (normals_from_unit_interval(image["normals"])[..., 2] > 0.999).all()
        assert "normals" not in model.get_outputs_for_camera(_camera())  # the block restored the mode
        model.render_normals = "never"
        assert "normals" not in model(rays)
    model.render_normals = "rays"
    model.train()
    assert "normals" not in model(rays)  # never in training
    with pytest.raises(ValueError, match="render_normals"):
        model.render_normals = "sometimes"  # type: ignore[assignment]
    never = _model_with_density(_half_space, render_normals="never")
    with torch.no_grad():
        assert "normals" not in never(rays)


def test_exporter_probe_ray_with_grad_enabled() -> None:
    """nerfstudio's validate_pipeline: one ray, direction (1, 1, 1), float camera index, grad mode on."""
    model = _model_with_density(_half_space)
    rays = ray_bundle(torch.zeros(1, 3), torch.ones(1, 3))
    rays.camera_indices = torch.zeros(1, 1)
    outputs = model(rays)
    assert outputs["normals"].shape == (1, 3)


def test_rgba_image_takes_the_grey_background_out() -> None:
    model = small_scalar_model()
    colour = torch.tensor([[0.9, 0.2, 0.1], [0.3, 0.6, 0.8], [0.1, 0.1, 0.1]])
    accumulation = torch.tensor([[1.0], [0.25], [0.0]])
    rgb = colour * accumulation + (1.0 - accumulation) * 0.5  # grey background outside training
    rgba = model.get_rgba_image({"rgb": rgb, "accumulation": accumulation})
    assert torch.allclose(rgba[:2, :3], colour[:2], atol=1e-5)
    assert torch.equal(rgba[:, 3:], accumulation)
    assert torch.isfinite(rgba).all()


# ------------------------------------------------------------------------- the fused scene model


def test_fused_normals_follow_the_fusion(scene: Path, tmp_path: Path) -> None:
    trainer = tiny_trainer(scene, tmp_path)
    model = trainer.pipeline.model
    for block in model.block_ids:
        model.begin_block(block)
    model.eval()
    generator = torch.Generator().manual_seed(0)
    origins = (torch.rand(64, 3, generator=generator) - 0.5) * 0.5
    directions = torch.nn.functional.normalize(torch.randn(64, 3, generator=generator), dim=-1)
    rays = ray_bundle(origins.to(model.device), directions.to(model.device))  # the trainer's device: CUDA where present
    with torch.no_grad():
        own = {b: model.blocks[str(b)].render_rays(rays, normals=True)["normals"] for b in model.block_ids}
        own[-1] = model.global_model.render_rays(rays, normals=True)["normals"]  # nearest-guarded's fallback
        for mode in ("global", "nearest", "nearest-guarded", "block:1", "idw", "nearest-idw", "global-only"):
            model.set_fusion(mode)
            outputs = model(rays)
            normals = _decoded(outputs)
            if mode == "global-only":
                assert torch.allclose(outputs["normals"], model.global_model.render_rays(rays, normals=True)["normals"])
            elif mode not in ("idw", "surface", "nearest-idw"):
                winner = outputs["block_winner"].reshape(-1).long()
                assert (winner >= (-1 if mode == "nearest-guarded" else 0)).all()
                expected = torch.stack([own[int(w)][i] for i, w in enumerate(winner)])
                if expected.device.type == "cpu":
                    assert torch.equal(outputs["normals"], expected), mode  # the winner's normal, bit for bit
                else:  # on CUDA the block renders a subset of the rays with other kernel sizes: float32 rounding apart
                    assert torch.allclose(outputs["normals"], expected, rtol=0.0, atol=1e-4), mode
            else:
                assert torch.isfinite(normals).all()
        assert "normals" not in model.get_outputs_for_camera(trainer.pipeline.datamanager.train_dataset.cameras[0:1])
    outputs, _, _ = trainer.pipeline.get_eval_loss_dict(0)  # the eval batch during training: no normals
    assert "normals" not in outputs and "rgb" in outputs and model.render_normals == "rays"


# ---------------------------------------------------------------------- ns-export on a trained run

#: A two-block run on the courtyard that forms geometry in about a minute on one core: small tables,
#: 32 samples per ray, a stronger distortion loss (compact surfaces) and enough steps per block
#: (a block's hash grid starts empty: after 100 steps it is still a haze).
# The paper's blocks and fusion (fresh blocks, `global`), with which the threshold below was measured.
# With the defaults (blocks copied from the global model, `nearest`) this one-minute run's ground
# normals agree less: |dot| > 0.7 for 0.44-0.46 of the ground points (two runs), and 0.41-0.52 with
# fresh blocks and `nearest` (two runs).
EXPORT_RUN = [
    "--pipeline.block-init", "fresh",
    "--pipeline.model.fusion", "global",
    "--pipeline.num-blocks", "2",
    "--pipeline.global-steps", "300",
    "--pipeline.block-steps", "400",
    "--pipeline.model.field.log2-hashmap-size", "14",
    "--pipeline.model.field.max-resolution", "256",
    "--pipeline.block-log2-hashmap-size", "14",
    "--pipeline.block-max-resolution", "256",
    "--pipeline.model.num-samples-per-ray", "32",
    "--pipeline.model.distortion-loss-mult", "0.02",
    "--pipeline.datamanager.train-num-rays-per-batch", "1024",
    # The paper's 128-wide decoder, which the normals' threshold below was measured with. After this
    # one-minute run the default 64-wide one's normals beat isotropic ones by less than two standard
    # errors in some runs (0.36 and 0.40, passing at 0.43; docs/notebook/defaults.md, "A narrower decoder").
    "--pipeline.model.field.hidden-dim", "128",
    "--steps-per-save", "100000",
]
#: The courtyard's walled area (world metres) with a margin: the export's oriented box.
COURTYARD_MIN, COURTYARD_MAX = np.array([-6.8, -6.8, -0.3]), np.array([6.8, 6.8, 3.3])


def _surface_distance_and_normal(points: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[N, 3] world points -> distance (m) to the nearest surface of the courtyard (ground plane z = 0 or
    a face of a box of DEFAULT_BOXES), that surface's unit normal [N, 3], and which surface (-1: ground)."""
    distance = np.abs(points[:, 2])
    normal = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    surface = np.full(len(points), -1)
    rows = np.arange(len(points))
    for index, box in enumerate(DEFAULT_BOXES):
        lo, hi = np.array(box.lo), np.array(box.hi)
        to_faces = np.concatenate([points - lo, hi - points], axis=1)  # [N, 6] signed distance to each face plane
        inside = (to_faces > 0).all(axis=1)
        box_distance = np.where(inside, to_faces.min(axis=1), np.linalg.norm(np.maximum(np.maximum(lo - points, points - hi), 0.0), axis=1))
        face = np.argmin(np.abs(to_faces), axis=1)
        face_normal = np.zeros_like(points)
        face_normal[rows, face % 3] = np.where(face < 3, -1.0, 1.0)
        closer = box_distance < distance
        distance = np.where(closer, box_distance, distance)
        normal[closer], surface[closer] = face_normal[closer], index
    return distance, normal, surface


def _rpy(rotation: np.ndarray) -> Tuple[float, float, float]:
    """Roll, pitch, yaw (radians) of a [3, 3] rotation R = Rz(yaw) Ry(pitch) Rx(roll) (OrientedBox.from_params' convention)."""
    pitch = -math.asin(float(np.clip(rotation[2, 0], -1.0, 1.0)))
    return math.atan2(rotation[2, 1], rotation[2, 2]), pitch, math.atan2(rotation[1, 0], rotation[0, 0])


@pytest.mark.slow
def test_ns_export_pointcloud_of_a_fused_run_lies_on_the_courtyard(tmp_path: Path) -> None:
    """``ns-export pointcloud --save-world-frame True`` (nerfstudio's own command, default
    ``--normal-method model_output``) of a global + 2-block run: one merged cloud of the fused render,
    in the capture's own frame (the dataparser's transform and scale undone), near the scene's known
    surfaces there, with unit normals that on the ground mostly point along its normal."""
    import open3d as o3d
    import torch as _torch

    start = time.time()
    scene = tmp_path / "scene"
    write_scene(scene, num_images=40, width=160, height=120)
    trained = subprocess.run(ns_train_command(scene, tmp_path / "outputs", *EXPORT_RUN), capture_output=True, text=True, timeout=900, check=False)
    assert trained.returncode == 0, trained.stdout[-3000:] + trained.stderr[-3000:]
    (run,) = run_dirs(tmp_path / "outputs")
    (checkpoint,) = (run / "nerfstudio_models").glob("step-*.ckpt")
    assert _torch.load(checkpoint, map_location="cpu", weights_only=True)["pipeline"]["_model.blocks_started"].tolist() == [True, True]
    trained_at = time.time()

    # The oriented box: the courtyard mapped into the dataparser's normalised frame, p' = s (R p + t).
    transforms = json.loads((run / "dataparser_transforms.json").read_text())
    transform, scale = np.array(transforms["transform"]), float(transforms["scale"])
    rotation, translation = transform[:, :3], transform[:, 3]
    centre = scale * (rotation @ ((COURTYARD_MIN + COURTYARD_MAX) / 2.0) + translation)
    exported = subprocess.run(
        [sys.executable, "-m", "nerfstudio.scripts.exporter", "pointcloud", "--load-config", str(run / "config.yml"),
         "--output-dir", str(tmp_path / "export"), "--num-points", "6000", "--remove-outliers", "False", "--num-rays-per-batch", "8192",
         "--save-world-frame", "True",
         "--obb-center", *map(str, centre), "--obb-rotation", *map(str, _rpy(rotation)), "--obb-scale", *map(str, scale * (COURTYARD_MAX - COURTYARD_MIN))],
        capture_output=True, text=True, timeout=600, check=False
    )
    assert exported.returncode == 0, exported.stdout[-3000:] + exported.stderr[-3000:]
    cloud = o3d.io.read_point_cloud(str(tmp_path / "export" / "point_cloud.ply"))
    points, normals = np.asarray(cloud.points), np.asarray(cloud.normals)
    assert len(points) >= 6000 and cloud.has_normals() and normals.shape == points.shape
    assert np.isfinite(normals).all() and np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-3)

    world_points = points  # already in the scene's frame (--save-world-frame); the normals are not
    world_normals = normals @ rotation  # R^T n, as row vectors
    distance, surface_normal, surface = _surface_distance_and_normal(world_points)
    random_points = np.random.default_rng(0).uniform(COURTYARD_MIN, COURTYARD_MAX, size=(len(points), 3))
    chance = float(np.median(_surface_distance_and_normal(random_points)[0]))
    summary = (
        f"distance to the nearest surface (m): median {np.median(distance):.3f} (uniform points in the box: {chance:.3f}), "
        f"within 0.25 m: {np.mean(distance < 0.25):.2f}; "
    )
    assert np.median(distance) < 0.25 and np.mean(distance < 0.25) > 0.5 and np.median(distance) < chance / 2, summary

    on_ground = (surface == -1) & (distance < 0.1)
    agreement = np.abs(np.sum(world_normals * surface_normal, axis=1))
    summary += f"{on_ground.sum()} points on the ground, |dot| > 0.7 for {np.mean(agreement[on_ground] > 0.7):.2f} (isotropic: 0.30)"
    # Measured 0.41-0.52 over configurations and runs with the 128-wide decoder (0.54-0.69 earlier),
    # 0.36-0.43 with the 64-wide one (hence the 128-wide decoder of EXPORT_RUN); a one-minute run: the density is still
    # noisy. The normals must beat isotropic ones (0.30) by two standard errors of that fraction over
    # the ground points; 6000 exported points (about 150 on the ground) keep that margin near 0.075.
    isotropic = 0.30
    margin = 2.0 * float(np.sqrt(isotropic * (1.0 - isotropic) / max(int(on_ground.sum()), 1)))
    assert on_ground.sum() >= 30 and np.mean(agreement[on_ground] > 0.7) > isotropic + margin, summary
    print(f"{summary}; trained in {trained_at - start:.0f} s, exported in {time.time() - trained_at:.0f} s")
