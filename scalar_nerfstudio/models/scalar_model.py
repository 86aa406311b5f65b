"""The SCALAR-NeRF model: one class for the global model and for every block's local model.

Rendering path (per ray batch, flat tensors, no nerfstudio RaySamples on the hot path):

1. ``S`` intervals per ray, evenly spaced in Mip-NeRF 360's linear/disparity spacing (fewer,
   ``warmup_samples_per_ray``, for training rays while the occupancy grid warms up).
2. Samples in empty cells of the :class:`OccupancyGrid` are dropped, and so are (once the grid
   has warmed up) samples that the grid's density estimates around their cell make more
   transparent than ``alpha_threshold`` over their interval.
3. A no-grad density pass over the remaining samples finds where each ray's transmittance has
   fallen below ``transmittance_threshold``; those occluded samples are dropped too, and so are
   samples more transparent than ``alpha_threshold`` once the grid has warmed up. Steps 2 and 3 are
   the :class:`~scalar_nerfstudio.model_components.visibility.VisibilitySampler`.
4. The field (density and colour, with gradients) runs only on the surviving samples, which are
   volume-rendered from their own list (:func:`~scalar_nerfstudio.model_components.rendering.render_kept_samples`:
   one C++ pass when rendering on the CPU, the dense ``[R, S]`` layout otherwise).
5. Only when normals are wanted (see :class:`NormalsOutput`): the density's gradient with respect
   to the world position, by autograd on the samples that carry weight, gives each sample's normal
   ``-grad / |grad|``; their weighted sum, normalised, is the ray's ``normals`` output.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Dict, List, Literal, Optional, Tuple, Type

import torch
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.models.base_model import Model, ModelConfig
from torch import Tensor
from torch.nn import Parameter

from scalar_nerfstudio.fields.scalar_field import (
    ScalarField,
    ScalarFieldConfig,
    contract_rays_to_unit_cube,
    contract_to_unit_cube,
    to_region_frame,
    unit_cube_to_world,
)
from scalar_nerfstudio.metrics import ImageMetrics, depth_metrics, psnr
from scalar_nerfstudio.model_components.colliders import BoundedNearFarCollider
from scalar_nerfstudio.model_components.ray_samples import RaySamples, neutralise_bad_rays
from scalar_nerfstudio.model_components.rendering import (
    EVAL_BACKGROUND,
    dense_weights,
    distortion_loss,
    facing_normals,
    normals_to_unit_interval,
    render_depth,
    render_kept_samples,
    render_normals,
    render_weights,
    safe_normalise,
)
from scalar_nerfstudio.model_components.sampling import OccupancyGrid, lin_disp_spacing, sample_intervals
from scalar_nerfstudio.model_components.visibility import DENSITY_CHUNK, VisibilitySampler
from scalar_nerfstudio.models.normals import RENDER_NORMALS, NormalsOutput, RenderNormals, check_render_normals

__all__ = [
    "EVAL_BACKGROUND",
    "RENDER_NORMALS",
    "BoundedNearFarCollider",
    "NormalsOutput",
    "RenderNormals",
    "ScalarModel",
    "ScalarModelConfig",
    "check_render_normals",
    "near_far_collider",
]

#: Points per autograd pass of the normals (their graph holds ~1.5 kB per point at 16 levels x 4 features).
_NORMALS_CHUNK = 1 << 15
#: Samples lighter than this rendering weight get no normal (they add < 1e-4 each to the ray's sum).
NORMALS_MIN_WEIGHT = 1e-4


def near_far_collider(config: "ScalarModelConfig", *, scene_radius: Optional[float]) -> BoundedNearFarCollider:
    """Rays from ``config.near_plane`` to ``config.far_plane``, inside the sphere of ``scene_radius``
    when there is one (a model's: its config's ``scene_radius``, or the one the pipeline derived);
    outside training the near plane is kept, unless ``config.reset_near_plane`` (nerfstudio's default)
    starts rays at the camera."""
    return BoundedNearFarCollider(
        near_plane=config.near_plane, far_plane=config.far_plane, reset_near_plane=config.reset_near_plane,
        scene_radius=scene_radius,
    )


@dataclass
class ScalarModelConfig(ModelConfig):
    """SCALAR-NeRF model (global or local)."""

    _target: Type = field(default_factory=lambda: ScalarModel)
    field: ScalarFieldConfig = field(default_factory=ScalarFieldConfig)
    """Encoder / decoder hyper-parameters."""
    near_plane: float = 0.05
    """Ray start (world units of the normalised scene)."""
    # Off by default: no training camera sees the space within near_plane of itself, so a novel camera
    # starting its rays at 0 renders whatever the field left there as a veil in front of it.
    reset_near_plane: bool = False
    """Start rays at the camera (near 0) outside training, as nerfstudio's colliders do; off: rays
    start at ``near_plane`` in evaluation, ns-render and the viewer as in training."""
    far_plane: float = 1000.0
    """Ray end (world units); far points contract to the boundary of the unit cube."""
    # A bound keeps a small table from putting coloured haze far behind the surfaces; on a capture
    # with sky and far content, a bound set by hand can break training.
    scene_radius: Optional[float] = None
    """Keep rays inside the sphere of this radius around the origin (world units of the normalised
    scene); None: unbounded, unless ``--pipeline.scene-radius-from-depth`` fits one to the depth images
    (the pipeline holds it, and the run's blocks.json records it)."""
    num_samples_per_ray: int = 64
    """Intervals per ray before empty-space and occlusion skipping."""
    # A coarse start makes the warm-up steps cheaper and trains better; a block seeded from the global
    # model has no warm-up.
    warmup_samples_per_ray: int = 16
    """Intervals per training ray while the occupancy grid warms up (at most ``num_samples_per_ray``;
    0: ``num_samples_per_ray``)."""
    occupancy_resolution: int = 64
    """Occupancy-grid cells per axis of the contracted cube."""
    occupancy_update_every: int = 16
    """Steps between occupancy-grid updates."""
    occupancy_warmup_steps: int = 128
    """Steps during which every occupancy update re-evaluates all cells."""
    occupancy_opacity_threshold: float = 0.01
    """A cell is empty when its opacity (density over the cell's size) stays below min(this, mean)."""
    # The render grid is estimated at every cell's corners from the final field; the training grid is
    # coarser and remembers haze from earlier steps, so rendering evaluates fewer samples for the same image.
    render_occupancy_resolution: int = 128
    """Cells per axis of the render grid, estimated from the final field when training ends and used
    outside training instead of the training grid; 0: rendering uses the training grid."""
    transmittance_threshold: float = 1e-3
    """Samples behind the point where a ray's transmittance drops below this are not evaluated."""
    alpha_threshold: float = 0.01
    """Once the occupancy grid prunes, samples whose opacity in the no-grad density pass is below this
    are neither evaluated with gradients nor rendered (nerfacc's alpha_thre; 0 disables it)."""
    grid_alpha_skip: bool = True
    """Once the grid prunes, skip without a field evaluation the samples that the grid's density
    estimates (their cell and its 6 neighbours) make more transparent than ``alpha_threshold``."""
    distortion_loss_mult: float = 0.002
    """Weight of Mip-NeRF 360's distortion loss (0 disables it)."""
    background_color: Literal["random", "grey"] = "random"
    """Training background (random teaches opaque geometry); evaluation always uses grey."""
    eval_num_rays_per_chunk: Optional[int] = None
    """Rays per chunk of a camera render (eval, ns-render, the viewer); None: by the device it renders
    on (2^16 on the CPU, 2^18 on CUDA: ``scalar_nerfstudio.device_sizes``)."""
    # The position gradient runs through the hash grid in torch (the kernels give none): on all samples, +33 % a run.
    pose_gradient_share: float = 0.25
    """With pose refinement (``--pipeline.model.camera-optimizer.mode``): the share of a batch's rays (0-1] whose
    samples give the pose corrections their gradient."""
    render_normals: RenderNormals = "rays"
    """When the ``normals`` output (in [0, 1]) is computed outside training: "rays" for ray batches
    (ns-export) but not camera images, "always" also for camera images (the viewer), "never"."""


class ScalarModel(NormalsOutput, Model):
    """Hash-grid NeRF with an occupancy grid, a shared-decoder field and per-image appearance.

    Its collider is its own (:func:`near_far_collider`, held as ``collider``): nerfstudio's
    ``enable_collider`` and ``collider_params`` are not read, and its config is not changed.

    Keyword args (besides nerfstudio's ``scene_box`` / ``num_train_data``):
        scene_radius: rays end where they leave the sphere of this radius (default: the config's
            ``scene_radius``; the pipeline passes the radius it derived from the depth images).
        region_centre: [3] world point mapped to the origin before contraction (default 0).
        region_radius: world distance mapped to 1 before contraction (default 1). A block's local
            model gets its scaled AABB's centre and half-diagonal, so its hash grid spends its
            resolution on the block; the global model keeps the dataparser's normalised frame.
    """

    config: ScalarModelConfig
    region_centre: Tensor
    """[3] float32 world point mapped to the origin before contraction (buffer, not saved)."""
    render_occupancy_ready: Tensor
    """[] bool: whether ``render_occupancy`` holds the final field's estimates (buffer, saved)."""

    def populate_modules(self) -> None:
        """Build the field, the occupancy grid and the metrics (called by ``Model.__init__``)."""
        super().populate_modules()
        self.scene_radius: Optional[float] = self.kwargs.get("scene_radius", self.config.scene_radius)
        """Rays end where they leave the sphere of this radius (None: unbounded)."""
        self.collider = near_far_collider(self.config, scene_radius=self.scene_radius)
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
            [self.field.density_at_unit(chunk)[0].float() for chunk in torch.split(unit_positions, DENSITY_CHUNK)]
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
            sample_ids, encoding = self.visibility().visible(unit_positions, deltas)  # [M] flat indices into R*S, [M, L*F]
            kept = unit_positions[sample_ids]
            if origins.requires_grad or directions.requires_grad:  # refined poses: their gradient through kept samples
                kept, rows = self._with_pose_gradient(samples, sample_ids, kept)
                density, geo = self.field.density_at_unit(kept, encoding=encoding, gradient_rows=rows)
            else:
                density, geo = self.field.density_at_unit(kept, encoding=encoding)
        else:  # rendering: one field pass over the occupied samples serves the occlusion test and the colour
            sample_ids, density, geo = self.visibility().visible_with_features(unit_positions, deltas)
        ray_ids = torch.div(sample_ids, num_samples, rounding_mode="floor")
        rgb_points = self.field.colour(geo, directions, ray_ids, camera_indices=camera_indices)
        # Volume rendering in float32 also under autocast (bf16/fp16 cumulative sums drift).
        density, rgb_points = density.float(), rgb_points.float()
        background = self._background(num_rays, origins)
        # From the kept samples alone: each ray's come in front-to-back order from either branch above.
        rendered = render_kept_samples(sample_ids, density, rgb_points, deltas=deltas, t_mid=t_mid, fars=fars, background=background)
        rgb = rendered.rgb
        outputs = {"rgb": rgb, "depth": rendered.depth, "accumulation": rendered.accumulation}
        if self.training and self.config.distortion_loss_mult > 0:
            weights = dense_weights(rendered, sample_ids, num_rays, num_samples)
            outputs["distortion"] = distortion_loss(weights, lin_disp_spacing(t_starts), lin_disp_spacing(t_ends))
        samples_per_ray = torch.bincount(ray_ids, minlength=num_rays).to(rgb.dtype)[:, None]
        outputs["samples_per_ray"] = samples_per_ray
        if self.normals_wanted() if normals is None else normals:
            weights = dense_weights(rendered, sample_ids, num_rays, num_samples).detach()
            outputs["normals"] = normals_to_unit_interval(self._ray_normals(samples, sample_ids, weights))
        return outputs

    def _with_pose_gradient(self, samples: RaySamples, sample_ids: Tensor, kept: Tensor) -> Tuple[Tensor, Optional[Tensor]]:
        """``kept`` [M, 3] (kernel positions) with the samples of every (1 / ``pose_gradient_share``)-th ray recomputed
        from the rays, so that their poses get a gradient; and those rows [G] (None: all)."""
        stride = max(1, round(1.0 / self.config.pose_gradient_share))
        if stride == 1:
            return self.world_to_unit_cube(samples.world_positions(sample_ids)), None
        rows = torch.nonzero(torch.div(sample_ids, samples.t_mid.shape[1], rounding_mode="floor") % stride == 0).squeeze(-1)
        moved = self.world_to_unit_cube(samples.world_positions(sample_ids[rows]))
        return kept.index_put((rows,), moved), rows

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

    def _ray_samples(self, ray_bundle: RayBundle, jitter: bool) -> "RaySamples":
        """The samples along a (collided) batch of rays: bad rays neutralised, then
        ``num_samples_per_ray`` intervals from near to far (jittered if ``jitter``; while training
        during the occupancy warm-up, ``warmup_samples_per_ray``)."""
        origins = ray_bundle.origins.reshape(-1, 3)
        directions = ray_bundle.directions.reshape(-1, 3)
        num_rays = origins.shape[0]
        nears = ray_bundle.nears.reshape(-1, 1) if ray_bundle.nears is not None else origins.new_full((num_rays, 1), self.config.near_plane)
        fars = ray_bundle.fars.reshape(-1, 1) if ray_bundle.fars is not None else origins.new_full((num_rays, 1), self.config.far_plane)
        origins, directions, nears, fars = neutralise_bad_rays(origins, directions, nears=nears, fars=fars)
        num_samples = self.config.num_samples_per_ray
        if self.training and self.occupancy.warming_up and self.config.warmup_samples_per_ray > 0:
            num_samples = min(self.config.warmup_samples_per_ray, num_samples)
        t_starts, t_ends = sample_intervals(nears, fars, num_samples=num_samples, jitter=jitter)
        t_mid = (t_starts + t_ends) / 2.0
        unit_positions = contract_rays_to_unit_cube(origins, directions, t_mid, centre=self.region_centre,
                                                    radius=self.region_radius)  # [R*S, 3]
        return RaySamples(origins, directions, fars, t_starts, t_ends, t_mid, unit_positions)

    def _ray_normals(self, samples: "RaySamples", sample_ids: Tensor, weights: Tensor) -> Tensor:
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

    def visibility(self) -> VisibilitySampler:
        """The sampler that picks the samples the field evaluates now (:mod:`~scalar_nerfstudio.model_components.visibility`):
        :meth:`samples_grid`, this model's field, and the config's thresholds as they are now."""
        return VisibilitySampler(
            grid=self.samples_grid(), field=self.field, transmittance_threshold=self.config.transmittance_threshold,
            alpha_threshold=self.config.alpha_threshold, grid_alpha_skip=self.config.grid_alpha_skip,
        )

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
