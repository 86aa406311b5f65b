"""The SCALAR-NeRF model: one class for the global model and for every block's local model.

Rendering path (per ray batch, flat tensors, no nerfstudio RaySamples on the hot path):

1. ``S`` intervals per ray, evenly spaced in Mip-NeRF 360's linear/disparity spacing (fewer,
   ``warmup_samples_per_ray``, for training rays while the occupancy grid warms up).
2. Samples in empty cells of the :class:`OccupancyGrid` are dropped, and so are (once the grid
   has warmed up) samples that the grid's density estimates around their cell make more
   transparent than ``alpha_threshold`` over their interval.
3. A no-grad density pass over the remaining samples finds where each ray's transmittance has
   fallen below ``transmittance_threshold``; those occluded samples are dropped too, and so are
   samples more transparent than ``alpha_threshold`` once the grid has warmed up.
4. The field (density and colour, with gradients) runs only on the surviving samples, which are
   scattered back into a dense ``[R, S]`` layout for volume rendering.
5. Only when normals are wanted (see :class:`NormalsOutput`): the density's gradient with respect
   to the world position, by autograd on the samples that carry weight, gives each sample's normal
   ``-grad / |grad|``; their weighted sum, normalised, is the ray's ``normals`` output.
"""

from __future__ import annotations

import math
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Dict, Iterator, List, Literal, Optional, Tuple, Type, get_args

import torch
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.model_components.scene_colliders import NearFarCollider
from nerfstudio.models.base_model import Model, ModelConfig
from torch import Tensor
from torch.nn import Parameter

from scalar_nerfstudio.fields.scalar_field import ScalarField, ScalarFieldConfig, contract_rays_to_unit_cube, contract_to_unit_cube, to_region_frame, unit_cube_to_world
from scalar_nerfstudio.metrics import ImageMetrics, depth_metrics, psnr
from scalar_nerfstudio.model_components.rendering import (
    alphas_from_densities,
    composite,
    distortion_loss,
    facing_normals,
    normals_to_unit_interval,
    render_depth,
    render_normals,
    render_weights,
    safe_normalise,
    weights_from_alphas,
)
from scalar_nerfstudio.model_components.sampling import OccupancyGrid, lin_disp_spacing, sample_intervals, sphere_interval

_CHUNK = 1 << 16
#: Front-to-back segments of the samples at render time (rays that turned opaque stop being evaluated).
RENDER_SEGMENTS = 4
#: Points per autograd pass of the normals (their graph holds ~1.5 kB per point at 16 levels x 4 features).
_NORMALS_CHUNK = 1 << 15
#: Samples lighter than this rendering weight get no normal (they add < 1e-4 each to the ray's sum).
NORMALS_MIN_WEIGHT = 1e-4
#: Background colour outside training (evaluation, rendering, the viewer, exports).
EVAL_BACKGROUND = 0.5

RenderNormals = Literal["rays", "always", "never"]
RENDER_NORMALS: Tuple[str, ...] = get_args(RenderNormals)


def _neutralise_bad_rays(origins: Tensor, directions: Tensor, nears: Tensor, fars: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """Rays [R, 3] with a NaN/inf origin or direction (or near/far) are reported and made empty.

    They render as the background with zero accumulation instead of spreading NaN through the batch.
    """
    bad = ~(torch.isfinite(origins).all(-1) & torch.isfinite(directions).all(-1) & torch.isfinite(nears[:, 0]) & torch.isfinite(fars[:, 0]))
    if not bool(bad.any()):
        return origins, directions, nears, fars
    warnings.warn(f"{int(bad.sum())} of {bad.numel()} rays have a NaN/inf origin, direction or near/far; they render as background.")
    keep = ~bad[:, None]
    origins = torch.where(keep, origins, torch.zeros_like(origins))
    directions = torch.where(keep, directions, torch.tensor([0.0, 0.0, 1.0], dtype=directions.dtype, device=directions.device))
    nears = torch.where(keep, nears, torch.ones_like(nears))
    fars = torch.where(keep, fars, torch.ones_like(fars))
    return origins, directions, nears, fars


class BoundedNearFarCollider(NearFarCollider):
    """nerfstudio's NearFarCollider, and, with a ``scene_radius``, rays kept inside the sphere of that
    radius around the origin: a ray starts no earlier than where it enters the sphere and ends
    where it leaves it (or at the far plane, if that comes first); a ray that misses it is empty
    (near = far) and renders as the background."""

    def __init__(self, near_plane: float, far_plane: float, reset_near_plane: bool, scene_radius: Optional[float] = None) -> None:
        super().__init__(near_plane=near_plane, far_plane=far_plane, reset_near_plane=reset_near_plane)
        if scene_radius is not None and not (math.isfinite(scene_radius) and scene_radius > 0):
            raise ValueError(f"scene radius {scene_radius}: must be a finite number > 0 (None: unbounded)")
        self.scene_radius = scene_radius

    def set_nears_and_fars(self, ray_bundle: RayBundle) -> RayBundle:
        ray_bundle = super().set_nears_and_fars(ray_bundle)
        if self.scene_radius is None or ray_bundle.nears is None or ray_bundle.fars is None:
            return ray_bundle
        shape = ray_bundle.nears.shape
        t_entry, t_exit = sphere_interval(ray_bundle.origins.reshape(-1, 3), ray_bundle.directions.reshape(-1, 3), self.scene_radius)
        nears = torch.maximum(ray_bundle.nears.reshape(-1, 1), t_entry.to(ray_bundle.nears.dtype))
        fars = torch.maximum(torch.minimum(ray_bundle.fars.reshape(-1, 1), t_exit.to(ray_bundle.fars.dtype)), nears)
        ray_bundle.nears = nears.reshape(shape)
        ray_bundle.fars = fars.reshape(shape)
        return ray_bundle


def near_far_collider(config: "ScalarModelConfig") -> BoundedNearFarCollider:
    """Rays from ``config.near_plane`` to ``config.far_plane``, inside the sphere of
    ``config.scene_radius`` when there is one; outside training the near plane is kept, unless
    ``config.reset_near_plane`` (nerfstudio's default) starts rays at the camera. A config.yml from
    before 2026-11-26 has no ``scene_radius``: unbounded, as it was trained."""
    return BoundedNearFarCollider(
        near_plane=config.near_plane, far_plane=config.far_plane, reset_near_plane=config.reset_near_plane,
        scene_radius=getattr(config, "scene_radius", None),
    )


@dataclass
class ScalarModelConfig(ModelConfig):
    """SCALAR-NeRF model (global or local)."""

    _target: Type = field(default_factory=lambda: ScalarModel)
    field: ScalarFieldConfig = field(default_factory=ScalarFieldConfig)
    """Encoder / decoder hyper-parameters."""
    near_plane: float = 0.05
    """Ray start (world units of the normalised scene)."""
    reset_near_plane: bool = False
    """Start rays at the camera (near 0) when not training, as nerfstudio's colliders do by default.
    Off: evaluation, ns-render and the viewer start rays at ``near_plane`` like training does. No
    training camera ever sees the space within ``near_plane`` of itself, and a novel camera that
    stands where only distant cameras looked through would render whatever the field put there
    right in front of it as a veil (castle-P30's eval image 8, see docs/benchmarks.md)."""
    far_plane: float = 1000.0
    """Ray end; far points contract to the boundary of the unit cube."""
    scene_radius: Optional[float] = None
    """Rays end where they leave the sphere of this radius around the origin (world units of the
    normalised scene), if that comes before ``far_plane``; a ray from outside starts where it
    enters it. None: unbounded. Set by the pipeline from the scene's depth images when it has them
    (``--pipeline.scene-radius-from-depth``): a small table otherwise puts coloured haze far behind
    the surfaces, in the deep shell the far plane leaves it (docs/town.md). Set by hand on a capture
    with sky and far content, it can break training: castle-P30 scored 16.6-17.0 dB held out with
    radius 6 or 20 against 22.6 unbounded, unless the training background was grey (22.0; docs/town.md,
    "A bound on a real capture")."""
    num_samples_per_ray: int = 64
    """Intervals per ray before empty-space and occlusion skipping."""
    warmup_samples_per_ray: int = 16
    """Intervals per training ray while the occupancy grid warms up (at most ``num_samples_per_ray``;
    0: ``num_samples_per_ray``). Nothing is skipped then, so every interval runs with gradients. A
    coarse start (coarse to fine) makes those steps 4x cheaper and ended about 1 dB better on
    castle-P30 (docs/benchmarks.md). A block seeded from the global model has no warm-up."""
    occupancy_resolution: int = 64
    """Occupancy-grid cells per axis of the contracted cube."""
    occupancy_update_every: int = 16
    """Steps between occupancy-grid updates."""
    occupancy_warmup_steps: int = 128
    """Steps during which every occupancy update re-evaluates all cells."""
    occupancy_opacity_threshold: float = 0.01
    """A cell is empty when its opacity (density over the cell's size) stays below min(this, mean)."""
    render_occupancy_resolution: int = 128
    """Cells per axis of the render grid: when a model's training ends, a second occupancy grid is
    estimated from the final field at every cell's corners (129^3, about 2 M field evaluations at
    128, about 0.5 s on castle-P30 on 2 cores) and saved with the model; rendering outside training
    uses it instead of the training grid, which is coarser and remembers haze from earlier steps
    (castle-P30: 34 instead of 45 samples evaluated per ray, the same image; docs/benchmarks.md
    section 5). 0: rendering uses the training grid."""
    transmittance_threshold: float = 1e-3
    """Samples behind the point where a ray's transmittance drops below this are not evaluated."""
    alpha_threshold: float = 0.01
    """Once the occupancy grid marks cells empty (after its warm-up), samples whose opacity in the
    no-grad density pass is below this are not evaluated with gradients either (nerfacc's
    alpha_thre; 0 disables it). Skipped samples are not rendered, in training or evaluation."""
    grid_alpha_skip: bool = True
    """Under the same conditions, samples whose opacity over their interval, from the largest
    density estimate of their occupancy cell and the 6 cells beside it, is below ``alpha_threshold``
    are not evaluated at all (:meth:`OccupancyGrid.worth_evaluating`): the faint haze that keeps a
    cell occupied no longer costs a field evaluation per sample."""
    distortion_loss_mult: float = 0.002
    """Weight of Mip-NeRF 360's distortion loss (0 disables it)."""
    background_color: Literal["random", "grey"] = "random"
    """Training background (random teaches opaque geometry); evaluation always uses grey."""
    render_normals: RenderNormals = "rays"
    """When the ``normals`` output (density-gradient normals, in [0, 1] as (n + 1) / 2) is computed,
    never in training: "rays" (default) for ray batches rendered outside training (what
    ``ns-export pointcloud`` / ``poisson`` render) but not for camera images (eval, ns-render, the
    viewer), which then cost nothing extra; "always" also for camera images (the viewer lists
    ``normals``); "never"."""


def check_render_normals(mode: str) -> RenderNormals:
    """``mode`` if it is one of :data:`RENDER_NORMALS`, else a ValueError naming them."""
    if mode not in RENDER_NORMALS:
        raise ValueError(f"render_normals {mode!r}: expected one of {', '.join(RENDER_NORMALS)}")
    return mode  # type: ignore[return-value]


class NormalsOutput:
    """When a nerfstudio :class:`Model` adds the ``normals`` output; its RGBA image (mixin).

    ``render_normals`` (initialised from the config, settable at run time, or for a block of code
    with :meth:`rendering_normals`) is "rays", "always" or "never" (see
    :attr:`ScalarModelConfig.render_normals`). Camera images are told apart from ray batches by
    :meth:`get_outputs_for_camera_ray_bundle`, through which every camera render of nerfstudio
    (eval, ns-render, the viewer, the TSDF export) passes.
    """

    training: bool
    _render_normals: RenderNormals
    _camera_renders: int

    def _init_normals_output(self, mode: str) -> None:
        self._render_normals = check_render_normals(mode)
        self._camera_renders = 0

    @property
    def render_normals(self) -> RenderNormals:
        """"rays", "always" or "never": when rendering outside training adds ``normals``."""
        return self._render_normals

    @render_normals.setter
    def render_normals(self, mode: RenderNormals) -> None:
        self._render_normals = check_render_normals(mode)

    @contextmanager
    def rendering_normals(self, mode: RenderNormals = "always") -> Iterator[None]:
        """Use ``mode`` for :attr:`render_normals` inside the ``with`` block."""
        previous = self._render_normals
        self.render_normals = mode
        try:
            yield
        finally:
            self._render_normals = previous

    def normals_wanted(self) -> bool:
        """Whether the render running now adds ``normals`` (never in training)."""
        if self.training or self._render_normals == "never":
            return False
        return self._render_normals == "always" or self._camera_renders == 0

    @torch.no_grad()
    def get_outputs_for_camera_ray_bundle(self, camera_ray_bundle: RayBundle) -> Dict[str, Tensor]:
        """nerfstudio's chunked camera render, marked as a camera image (see :meth:`normals_wanted`)."""
        self._camera_renders += 1
        try:
            return super().get_outputs_for_camera_ray_bundle(camera_ray_bundle)  # type: ignore[misc]
        finally:
            self._camera_renders -= 1

    def get_rgba_image(self, outputs: Dict[str, Tensor], output_name: str = "rgb") -> Tensor:
        """[..., 4]: the colour without the background and the accumulation as alpha.

        Outside training the background is :data:`EVAL_BACKGROUND` grey, so ``rgb = c + (1 - a) grey``
        and the foreground colour is ``c / a``. nerfstudio's exporters keep the points / pixels of
        alpha > 0.5 (``ns-export pointcloud``) and texture meshes with this colour.
        """
        accumulation_name = output_name.replace("rgb", "accumulation")
        if output_name not in outputs or accumulation_name not in outputs:
            raise KeyError(f"get_rgba_image needs outputs {output_name!r} and {accumulation_name!r}; got {sorted(outputs)}")
        rgb = outputs[output_name]
        accumulation = outputs[accumulation_name]
        if accumulation.dim() < rgb.dim():
            accumulation = accumulation.unsqueeze(-1)
        foreground = (rgb - (1.0 - accumulation) * EVAL_BACKGROUND) / accumulation.clamp_min(1e-6)
        foreground = torch.where(accumulation > 1e-6, foreground, torch.full_like(foreground, EVAL_BACKGROUND))
        return torch.cat((torch.nan_to_num(foreground, nan=EVAL_BACKGROUND).clamp(0.0, 1.0), accumulation.clamp(0.0, 1.0)), dim=-1)


@dataclass(frozen=True)
class _RaySamples:
    """Samples along R rays, S per ray (:meth:`ScalarModel._ray_samples`)."""

    origins: Tensor  # [R, 3]
    directions: Tensor  # [R, 3]
    fars: Tensor  # [R, 1]
    t_starts: Tensor  # [R, S]
    t_ends: Tensor  # [R, S]
    t_mid: Tensor  # [R, S]
    unit_positions: Tensor  # [R*S, 3] contracted unit cube

    def world_positions(self, sample_ids: Tensor) -> Tensor:
        """[M] flat sample indices into [R*S] -> [M, 3] their world positions."""
        ray_ids = torch.div(sample_ids, self.t_mid.shape[1], rounding_mode="floor")
        return self.origins[ray_ids] + self.directions[ray_ids] * self.t_mid.reshape(-1)[sample_ids, None]


class ScalarModel(NormalsOutput, Model):
    """Hash-grid NeRF with an occupancy grid, a shared-decoder field and per-image appearance.

    Keyword args (besides nerfstudio's ``scene_box`` / ``num_train_data``):
        region_centre: [3] world point mapped to the origin before contraction (default 0).
        region_radius: world distance mapped to 1 before contraction (default 1). A block's local
            model gets its scaled AABB's centre and half-diagonal, so its hash grid spends its
            resolution on the block; the global model keeps the dataparser's normalised frame.
    """

    config: ScalarModelConfig

    def populate_modules(self) -> None:
        """Build the field, the occupancy grid and the metrics (called by ``Model.__init__``)."""
        self.config.enable_collider = True
        self.config.collider_params = {"near_plane": self.config.near_plane, "far_plane": self.config.far_plane}
        super().populate_modules()
        self.collider = near_far_collider(self.config)
        self._init_normals_output(self.config.render_normals)
        centre = torch.as_tensor(self.kwargs.get("region_centre", (0.0, 0.0, 0.0)), dtype=torch.float32).reshape(3)
        radius = float(self.kwargs.get("region_radius", 1.0))
        if not (torch.isfinite(centre).all() and radius > 0 and radius < float("inf")):
            raise ValueError(f"region centre {centre.tolist()} / radius {radius} must be finite with radius > 0")
        self.register_buffer("region_centre", centre, persistent=False)
        self.region_radius = radius
        self.field: ScalarField = self.config.field.setup(num_images=self.num_train_data)
        self.occupancy = OccupancyGrid(
            resolution=self.config.occupancy_resolution,
            update_every=self.config.occupancy_update_every,
            warmup_steps=self.config.occupancy_warmup_steps,
            opacity_threshold=self.config.occupancy_opacity_threshold,
            world_scale=radius,
        )
        self.render_occupancy: Optional[OccupancyGrid] = None
        if self.config.render_occupancy_resolution > 0:
            self.render_occupancy = OccupancyGrid(
                resolution=self.config.render_occupancy_resolution,
                opacity_threshold=self.config.occupancy_opacity_threshold,
                world_scale=radius,
                neighbourhood_alpha_test=False,
            )
        # whether render_occupancy holds the final field's estimates (built by finish_training, saved
        # with the model, cleared by the next training step)
        self.register_buffer("render_occupancy_ready", torch.zeros((), dtype=torch.bool))
        self.image_metrics = ImageMetrics()

    # ----------------------------------------------------------------------------------- training
    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        """Separate groups so the decoder can be fine-tuned with its own learning rate (or frozen)."""
        return {
            "encoder": list(self.field.encoder.parameters()),
            "decoder": list(self.field.decoder.parameters()),
            "appearance": list(self.field.appearance.parameters()),
        }

    def update_occupancy(self, step: int) -> None:
        """Update the occupancy grid at ``step`` of this model's phase (the pipeline calls it before
        each step). The field is about to change, so the render grid no longer describes it."""
        if bool(self.render_occupancy_ready):
            self.render_occupancy_ready.fill_(False)
        self.occupancy.update(step, self._density_no_grad)

    @torch.no_grad()
    def finish_training(self) -> None:
        """This model's training has ended (the pipeline calls it at the last step of its phase): its
        render grid is estimated from the final field (:meth:`OccupancyGrid.refresh`), unless the
        training grid is still in its warm-up (a field too young to tell empty space) or the config
        has no render grid."""
        if self.render_occupancy is None or self.occupancy.warming_up:
            return
        self.render_occupancy.refresh(self._density_no_grad)
        self.render_occupancy_ready.fill_(True)

    def samples_grid(self) -> OccupancyGrid:
        """The occupancy grid that decides which samples the field evaluates now: the render grid
        outside training once it is built (unless ``render_occupancy_resolution`` has been set to 0
        since, which a comparison of the two can do on a loaded model), the training grid otherwise."""
        if (self.render_occupancy is not None and not self.training and bool(self.render_occupancy_ready)
                and self.config.render_occupancy_resolution > 0):
            return self.render_occupancy
        return self.occupancy

    def complete_state(self, state: Dict[str, Tensor], prefix: str = "") -> Dict[str, Tensor]:
        """``state`` (this model's tensors under ``prefix``) with its render grid made to fit this
        model: where it lacks one (checkpoints and block files written before the render grid
        existed) or holds one of another resolution (the run's config edited since), the render
        grid is taken as not built, and renders use the training grid (a warning says so for a
        mismatch). Returns ``state`` itself, changed in place."""
        head = prefix + "render_occupancy."
        expected: Dict[str, torch.Size] = {}
        if self.render_occupancy is not None:  # the grid's shapes as built: a block's shell holds its tensors empty
            with torch.device("meta"):
                template = OccupancyGrid(resolution=self.render_occupancy.resolution)
            expected = {head + k: v.shape for k, v in template.state_dict().items()}
        given = {k: v for k, v in state.items() if k.startswith(head)}
        fits = set(given) == set(expected) and all(given[k].shape == expected[k] or given[k].numel() == 0 for k in given)
        if given and not fits:
            warnings.warn(f"the saved render grid ({len(next(iter(given.values())))} cells) does not fit this model's "
                          f"({'none' if self.render_occupancy is None else self.render_occupancy.resolution ** 3} cells): "
                          "rendering uses the training grid")
        if not fits or prefix + "render_occupancy_ready" not in state:
            for key in given:
                del state[key]
            state[prefix + "render_occupancy_ready"] = torch.zeros((), dtype=torch.bool)
            if self.render_occupancy is not None:
                fresh = OccupancyGrid(resolution=self.render_occupancy.resolution)
                state.update({head + k: v for k, v in fresh.state_dict().items()})
        return state

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        if prefix + "occupancy.density_ema" in state_dict:  # this model's own state (not a released block's)
            self.complete_state(state_dict, prefix)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @torch.no_grad()
    def seed_occupancy_from(self, other: "ScalarModel") -> None:
        """Mark this model's occupancy grid from ``other``'s density (a block from the global model):
        each cell centre is taken to the world, then into ``other``'s frame; no warm-up follows, but
        for the warm-up's length this model's own transparency drops no sample (its field settles,
        :attr:`OccupancyGrid.settling`)."""
        world = self.unit_cube_to_world(self.occupancy.cell_centres())
        self.occupancy.seed(other._density_no_grad(other.world_to_unit_cube(world)), settle=True)

    def world_to_unit_cube(self, positions: Tensor) -> Tensor:
        """[N, 3] world positions -> [N, 3] contracted unit-cube positions of this model's frame (what its field reads)."""
        return contract_to_unit_cube(self._to_region(positions))

    def unit_cube_to_world(self, unit_positions: Tensor) -> Tensor:
        """Inverse of :meth:`world_to_unit_cube`: [N, 3] in [0, 1]^3 -> [N, 3] world positions (finite)."""
        return self._from_region(unit_cube_to_world(unit_positions))

    def _from_region(self, positions: Tensor) -> Tensor:
        """[N, 3] positions in the model's region frame -> [N, 3] world positions."""
        return positions * self.region_radius + self.region_centre.to(positions.dtype)

    @torch.no_grad()
    def _density_no_grad(self, unit_positions: Tensor) -> Tensor:
        """[M, 3] contracted unit-cube positions -> [M] float32 density, evaluated in chunks without grad."""
        return torch.cat(
            [self.field.density_at_unit(chunk)[0].float() for chunk in torch.split(unit_positions, _CHUNK)]
        ) if unit_positions.shape[0] > 0 else unit_positions.new_zeros(0)

    # ---------------------------------------------------------------------------------- rendering
    def render_rays(self, ray_bundle: RayBundle, normals: Optional[bool] = None) -> Dict[str, Tensor]:
        """``forward`` (collider, then :meth:`get_outputs`) with an explicit choice of normals."""
        if self.collider is not None:
            ray_bundle = self.collider(ray_bundle)
        return self.get_outputs(ray_bundle, normals=normals)

    def get_outputs(self, ray_bundle: RayBundle, normals: Optional[bool] = None) -> Dict[str, Tensor]:
        """Render ``rgb`` [R, 3], ``depth`` [R, 1], ``accumulation`` [R, 1] for a batch of rays.

        Also ``normals`` [R, 3] in [0, 1] (``(n + 1) / 2`` of the unit world-frame normal) when
        ``normals`` is True, or when it is None and :meth:`normals_wanted`.
        """
        camera_indices = ray_bundle.camera_indices.reshape(-1) if ray_bundle.camera_indices is not None else None
        samples = self._ray_samples(ray_bundle, jitter=self.training)
        origins, directions, fars, t_starts, t_ends, t_mid = (
            samples.origins, samples.directions, samples.fars, samples.t_starts, samples.t_ends, samples.t_mid)
        unit_positions = samples.unit_positions
        num_rays, num_samples = t_mid.shape
        deltas = t_ends - t_starts

        if torch.is_grad_enabled():  # training: the density of the kept samples again, with gradients
            sample_ids, encoding = self._visible_samples(unit_positions, deltas)  # [M] flat indices into R*S, [M, L*F]
            density, geo = self.field.density_at_unit(unit_positions[sample_ids], encoding=encoding)
        else:  # rendering: one field pass over the occupied samples serves the occlusion test and the colour
            sample_ids, density, geo = self._visible_samples_with_features(unit_positions, deltas)
        ray_ids = torch.div(sample_ids, num_samples, rounding_mode="floor")
        rgb_points = self.field.colour(geo, directions, ray_ids, camera_indices)
        # Volume rendering in float32 also under autocast (bf16/fp16 cumulative sums drift).
        density, rgb_points = density.float(), rgb_points.float()

        densities = torch.zeros(num_rays * num_samples, dtype=density.dtype, device=density.device)
        densities = densities.index_put((sample_ids,), density).reshape(num_rays, num_samples)
        colours = torch.zeros(num_rays * num_samples, 3, dtype=rgb_points.dtype, device=rgb_points.device)
        colours = colours.index_put((sample_ids,), rgb_points).reshape(num_rays, num_samples, 3)

        weights, _ = render_weights(densities, deltas)
        accumulation = weights.sum(dim=-1, keepdim=True)
        background = self._background(num_rays, origins)
        rgb = composite(weights, colours) + (1.0 - accumulation) * background
        depth = render_depth(weights, t_mid, fars)
        outputs = {"rgb": rgb, "depth": depth, "accumulation": accumulation}
        if self.training and self.config.distortion_loss_mult > 0:
            outputs["distortion"] = distortion_loss(weights, lin_disp_spacing(t_starts), lin_disp_spacing(t_ends))
        samples_per_ray = torch.bincount(ray_ids, minlength=num_rays).to(rgb.dtype)[:, None]
        outputs["samples_per_ray"] = samples_per_ray
        if self.normals_wanted() if normals is None else normals:
            outputs["normals"] = normals_to_unit_interval(self._ray_normals(samples, sample_ids, weights.detach()))
        return outputs

    @torch.no_grad()
    def render_depth_only(self, ray_bundle: RayBundle, source: Literal["field", "grid"] = "field") -> Dict[str, Tensor]:
        """``depth`` [R, 1] and ``accumulation`` [R, 1] without colour: what choosing blocks per ray needs.

        ``field``: from the field's density at the occupied samples (no colour head, no appearance, no
        gradient: about half a render's cost). ``grid``: from the occupancy grid's density estimates
        alone (no field evaluation at all; each cell's estimate is the largest density seen in it, so
        the depth is coarser and tends to come early).
        """
        if self.collider is not None:
            ray_bundle = self.collider(ray_bundle)
        samples = self._ray_samples(ray_bundle, jitter=False)
        unit_positions = samples.unit_positions
        if source == "grid":
            densities = self.occupancy.density_estimates(unit_positions)
        else:
            occupied = torch.nonzero(self.samples_grid().is_occupied(unit_positions)).squeeze(-1)
            densities = torch.zeros(unit_positions.shape[0], device=unit_positions.device)
            densities[occupied] = self._density_no_grad(unit_positions[occupied])
        weights, _ = render_weights(densities.reshape(samples.t_mid.shape), samples.t_ends - samples.t_starts)
        return {"depth": render_depth(weights, samples.t_mid, samples.fars), "accumulation": weights.sum(dim=-1, keepdim=True)}

    def _ray_samples(self, ray_bundle: RayBundle, jitter: bool) -> "_RaySamples":
        """The samples along a (collided) batch of rays: bad rays neutralised, then
        ``num_samples_per_ray`` intervals from near to far (jittered if ``jitter``; while training
        during the occupancy warm-up, ``warmup_samples_per_ray``)."""
        origins = ray_bundle.origins.reshape(-1, 3)
        directions = ray_bundle.directions.reshape(-1, 3)
        num_rays = origins.shape[0]
        nears = ray_bundle.nears.reshape(-1, 1) if ray_bundle.nears is not None else origins.new_full((num_rays, 1), self.config.near_plane)
        fars = ray_bundle.fars.reshape(-1, 1) if ray_bundle.fars is not None else origins.new_full((num_rays, 1), self.config.far_plane)
        origins, directions, nears, fars = _neutralise_bad_rays(origins, directions, nears, fars)
        num_samples = self.config.num_samples_per_ray
        if self.training and self.occupancy.warming_up and self.config.warmup_samples_per_ray > 0:
            num_samples = min(self.config.warmup_samples_per_ray, num_samples)
        t_starts, t_ends = sample_intervals(nears, fars, num_samples, jitter=jitter)
        t_mid = (t_starts + t_ends) / 2.0
        unit_positions = contract_rays_to_unit_cube(origins, directions, t_mid, self.region_centre, self.region_radius)  # [R*S, 3]
        return _RaySamples(origins, directions, fars, t_starts, t_ends, t_mid, unit_positions)

    def _ray_normals(self, samples: "_RaySamples", sample_ids: Tensor, weights: Tensor) -> Tensor:
        """Expected unit normal per ray, [R, 3] in [-1, 1].

        Args:
            samples: the rays' samples; a ray without a normal (nothing hit, or zero density
                gradient everywhere) gets its reversed, normalised direction (it faces the camera).
            sample_ids: [M] flat indices of the evaluated samples.
            weights: [R, S] rendering weights.
        """
        num_rays, num_samples = weights.shape
        heavy = sample_ids[weights.reshape(-1)[sample_ids] > NORMALS_MIN_WEIGHT]
        sample_normals = weights.new_zeros(num_rays * num_samples, 3)
        sample_normals[heavy] = self.density_normals(samples.world_positions(heavy))
        facing = facing_normals(samples.directions)
        return render_normals(weights, sample_normals.reshape(num_rays, num_samples, 3), facing)

    def density_normals(self, positions: Tensor) -> Tensor:
        """Normals of the density field: ``-grad sigma / |grad sigma|`` at [N, 3] world positions -> [N, 3].

        The gradient is taken by autograd through the region transform, the contraction, the
        hash grid and the density head, in chunks, also when called under ``no_grad`` or
        ``inference_mode``. Where the gradient vanishes (or is not finite) the normal is 0.
        """
        if positions.shape[0] == 0:
            return positions.new_zeros(0, 3)
        chunks = []
        with torch.inference_mode(False), torch.enable_grad():
            for chunk in torch.split(positions, _NORMALS_CHUNK):
                points = chunk.detach().clone().float().requires_grad_(True)
                density, _ = self.field.density_at_unit(contract_to_unit_cube(self._to_region(points)))
                if not density.requires_grad:  # a density that does not depend on position
                    chunks.append(torch.zeros_like(points).detach())
                    continue
                (gradient,) = torch.autograd.grad(density.float().sum(), points, allow_unused=True)
                gradient = torch.zeros_like(points) if gradient is None else gradient
                chunks.append(safe_normalise(-gradient.detach(), torch.zeros(3, dtype=points.dtype, device=points.device)))
        return torch.cat(chunks).to(positions.dtype)

    def _to_region(self, positions: Tensor) -> Tensor:
        """[N, 3] world positions -> [N, 3] in the model's region frame (centre 0, radius 1)."""
        return to_region_frame(positions, self.region_centre, self.region_radius)

    @torch.no_grad()
    def _visible_samples(self, unit_positions: Tensor, deltas: Tensor) -> Tuple[Tensor, Optional[Tensor]]:
        """The samples that are in occupied cells and not occluded: ([M] flat indices into the [R*S]
        samples, [M, L*F] their hash-grid encoding from the no-grad pass, or None when there was no
        such pass), so that the pass with gradients does not encode them again."""
        if self.config.transmittance_threshold <= 0:
            return torch.nonzero(self.samples_grid().is_occupied(unit_positions)).squeeze(-1), None
        candidate_ids = torch.nonzero(self._worth_evaluating(unit_positions, deltas.reshape(-1))).squeeze(-1)
        if candidate_ids.numel() == 0:
            return candidate_ids, None
        candidates = unit_positions[candidate_ids]
        densities: List[Tensor] = []
        encodings: List[Tensor] = []
        for chunk in torch.split(candidates, _CHUNK):
            encodings.append(self.field.encoder(chunk))
            densities.append(self.field.density_at_unit(chunk, encoding=encodings[-1])[0].float())
        keep = self._kept_candidates(candidate_ids, torch.cat(densities), deltas)
        kept_encoding = torch.cat([encoding[chunk_keep] for encoding, chunk_keep in zip(encodings, torch.split(keep, _CHUNK))])
        return candidate_ids[keep], kept_encoding

    @torch.no_grad()
    def _visible_samples_with_features(self, unit_positions: Tensor, deltas: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        """:meth:`_visible_samples` without gradients, keeping what the field computed on the way:
        ([M] flat sample indices, [M] density, [M, F] geometry features).

        The samples are taken front to back in :data:`RENDER_SEGMENTS` segments along the rays: a
        segment evaluates only the rays whose transmittance is still above the threshold, so the
        occupied samples behind a surface are never evaluated (the kept samples and their values are
        those of one pass over every occupied sample)."""
        num_rays, num_samples = deltas.shape
        threshold = self.config.transmittance_threshold
        if threshold <= 0 or num_rays == 0:
            candidate_ids = torch.nonzero(self.samples_grid().is_occupied(unit_positions)).squeeze(-1)
            density, geo = self.field.density_at_unit(unit_positions[candidate_ids])
            return candidate_ids, density, geo
        occupied = self._worth_evaluating(unit_positions, deltas.reshape(-1)).reshape(num_rays, num_samples)
        log_threshold = math.log(threshold)
        depth_before = deltas.new_zeros(num_rays)  # [R] optical depth in front of the segment
        kept_ids: List[Tensor] = []
        kept_density: List[Tensor] = []
        kept_geo: List[Tensor] = []
        bounds = torch.linspace(0, num_samples, min(RENDER_SEGMENTS, num_samples) + 1).round().long().tolist()
        for start, end in zip(bounds[:-1], bounds[1:]):
            alive = -depth_before > log_threshold  # [R] light still reaches the segment
            rays, offsets = torch.nonzero(occupied[:, start:end] & alive[:, None], as_tuple=True)
            if rays.numel() == 0:
                if not bool(alive.any()):
                    break
                continue
            ids = rays * num_samples + start + offsets
            density, geo = self.field.density_at_unit(unit_positions[ids])
            densities = deltas.new_zeros(num_rays, end - start)
            densities[rays, offsets] = density.float()
            alphas = alphas_from_densities(densities, deltas[:, start:end])
            optical = -torch.log1p(-alphas.clamp(0.0, 1.0 - 1e-7))
            accumulated = torch.cumsum(optical, dim=-1) + depth_before[:, None]
            before = torch.cat([depth_before[:, None], accumulated[:, :-1]], dim=-1)  # [R, seg] in front of each sample
            keep = torch.exp(-before[rays, offsets]) > threshold
            if self._skips_transparent_samples():
                keep &= alphas[rays, offsets] > self.config.alpha_threshold
            kept_ids.append(ids[keep])
            kept_density.append(density[keep])
            kept_geo.append(geo[keep])
            depth_before = accumulated[:, -1]
        if not kept_ids:
            empty = unit_positions[:0]
            density, geo = self.field.density_at_unit(empty)
            return torch.zeros(0, dtype=torch.long, device=unit_positions.device), density, geo
        return torch.cat(kept_ids), torch.cat(kept_density), torch.cat(kept_geo)

    def _skips_transparent_samples(self) -> bool:
        """Whether samples more transparent than ``alpha_threshold`` are dropped now: once the
        occupancy grid marks cells empty (after its warm-up), unless the threshold is 0, and not
        while this model's field settles into a grid seeded from another model's
        (:attr:`OccupancyGrid.settling`)."""
        grid = self.samples_grid()
        return self.config.alpha_threshold > 0 and grid.pruning and not grid.settling

    @torch.no_grad()
    def _worth_evaluating(self, unit_positions: Tensor, deltas: Tensor) -> Tensor:
        """[R*S] bool: the samples (unit-cube positions [R*S, 3], world interval lengths [R*S]) the
        field evaluates: those in occupied cells and, once the grid prunes (as for the rendered
        samples' ``alpha_threshold``), only those the grid's estimates make opaque enough
        (``grid_alpha_skip``)."""
        grid = self.samples_grid()
        if self.config.grid_alpha_skip and self._skips_transparent_samples():
            return grid.worth_evaluating(unit_positions, deltas, self.config.alpha_threshold)
        return grid.is_occupied(unit_positions)

    @torch.no_grad()
    def _kept_candidates(self, candidate_ids: Tensor, density: Tensor, deltas: Tensor) -> Tensor:
        """[C] bool over the occupied samples ``candidate_ids`` (flat indices into [R*S]) with ``density``
        [C]: True where the transmittance before the sample is above the threshold and (once the grid
        prunes) its opacity above ``alpha_threshold``."""
        num_rays, num_samples = deltas.shape
        densities = torch.zeros(num_rays * num_samples, device=deltas.device)
        densities[candidate_ids] = density.float()
        alphas = alphas_from_densities(densities.reshape(num_rays, num_samples), deltas)
        _, transmittance = weights_from_alphas(alphas)
        keep = transmittance.reshape(-1)[candidate_ids] > self.config.transmittance_threshold
        if self._skips_transparent_samples():
            keep &= alphas.reshape(-1)[candidate_ids] > self.config.alpha_threshold
        return keep

    def _background(self, num_rays: int, like: Tensor) -> Tensor:
        """[R, 3] background colour: random while training (if configured), grey otherwise."""
        if self.training and self.config.background_color == "random":
            return torch.rand(num_rays, 3, dtype=like.dtype, device=like.device)
        return like.new_full((num_rays, 3), EVAL_BACKGROUND)

    # ------------------------------------------------------------------------------ loss, metrics
    @staticmethod
    def _target_rgb(batch: Dict[str, Tensor], like: Tensor) -> Tensor:
        image = batch["image"].to(like.device)
        return image[..., :3].to(like.dtype)

    def get_metrics_dict(self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """Training metrics: PSNR of the batch, samples evaluated per ray, occupied grid fraction."""
        target = self._target_rgb(batch, outputs["rgb"])
        return {
            "psnr": psnr(outputs["rgb"].detach(), target),
            "samples_per_ray": outputs["samples_per_ray"].mean(),
            "occupied_fraction": torch.tensor(self.occupancy.occupied_fraction()),
        }

    def get_loss_dict(self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor], metrics_dict: Optional[Dict[str, Tensor]] = None) -> Dict[str, Tensor]:
        """Photometric MSE (+ distortion loss while training)."""
        target = self._target_rgb(batch, outputs["rgb"])
        losses = {"rgb_loss": torch.mean((outputs["rgb"] - target) ** 2)}
        if "distortion" in outputs:
            losses["distortion_loss"] = self.config.distortion_loss_mult * outputs["distortion"].mean()
        return losses

    def get_image_metrics_and_images(
        self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        """PSNR, SSIM (and LPIPS when its weights are on disk) of a full rendered image [H, W, 3]; with
        the scene's true depth in the batch (``ray_depth`` [H, W, 1]), also :func:`depth_metrics`."""
        predicted = outputs["rgb"].clamp(0.0, 1.0)
        target = self._target_rgb(batch, predicted)
        metrics = self.image_metrics(predicted, target)
        if "ray_depth" in batch:  # the scene's true depth (eval images of a scene with depth images)
            metrics.update(depth_metrics(outputs["depth"], batch["ray_depth"]))
        images = {"img": torch.cat([target, predicted], dim=1), "depth": outputs["depth"], "accumulation": outputs["accumulation"]}
        if "normals" in outputs:
            images["normals"] = outputs["normals"]
        return metrics, images
