"""The model nerfstudio's trainer, viewer, ``ns-eval`` and ``ns-render`` see: global + blocks + fusion.

:class:`ScalarSceneModel` holds one :class:`ScalarModel` for the coarse global model and one per
block (the same class: a block differs only by its region, its images and where its decoder came
from). Training runs one of them at a time (the pipeline picks it by step); rendering renders the
global model and the blocks that have started training, and fuses them per pixel.

It is a composition of

* :class:`~scalar_nerfstudio.models.block_store.BlockStore`: which block weights are in memory, in
  their files, in checkpoints;
* ``block_start.py``: how a block's model is built and how its phase starts (copied from, seeded
  from or fitted to the global model);
* ``block_selection.py``: which block renders which ray;
* :class:`~scalar_nerfstudio.models.fused_render.FusedRenderer`: the fused render of a ray batch.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple, Type

import torch
from nerfstudio.cameras.camera_optimizers import CameraOptimizerConfig
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.models.base_model import Model
from torch import Tensor, nn
from torch.nn import Parameter

from scalar_nerfstudio.blocks.capacity import BlockCapacity
from scalar_nerfstudio.blocks.split import BlockSplit
from scalar_nerfstudio.engine.memory import HeapRelease
from scalar_nerfstudio.fusion import ParsedFusionMode, parse_fusion_mode
from scalar_nerfstudio.metrics import psnr
from scalar_nerfstudio.models.block_fit import EncodingFit
from scalar_nerfstudio.models.block_selection import BlockRegions, blocks_for
from scalar_nerfstudio.models.block_start import (
    BLOCK_INITS,
    MIN_REGION_RADIUS,
    BlockInit,
    DecoderMode,
    block_region,
    check_block_start,
    fit_block,
    new_block_model,
    start_block,
)
from scalar_nerfstudio.models.block_store import BlockStore
from scalar_nerfstudio.models.fused_render import FusedRenderer, FusionSettings
from scalar_nerfstudio.models.normals import NormalsOutput
from scalar_nerfstudio.models.pose_refinement import PoseRefinement
from scalar_nerfstudio.models.scalar_model import ScalarModel, ScalarModelConfig, near_far_collider
from scalar_nerfstudio.seam import PIPELINE_MODEL_KEY_PREFIX

__all__ = [
    "BLOCK_INITS",
    "MIN_REGION_RADIUS",
    "BlockInit",
    "DecoderMode",
    "ParamGroup",
    "ScalarSceneModel",
    "ScalarSceneModelConfig",
    "block_region",
]


@dataclass
class ScalarSceneModelConfig(ScalarModelConfig):
    """Global model + one local model per block, fused per pixel (paper Sec. 3.4)."""

    _target: Type = field(default_factory=lambda: ScalarSceneModel)
    # nearest-guarded gives nearest's image wherever the blocks learnt what the global model shows, and
    # the global model's where a block learnt nothing; it renders the global model only on those rays.
    fusion: str = "nearest-guarded"
    """How block renders are fused per ray: nearest-guarded, nearest, nearest-idw, global (the paper's),
    surface, idw, global-only or block:<k> (see scalar_nerfstudio/fusion)."""
    idw_gamma: float = 1.0
    """Exponent of inverse distance weighting (``idw``, and ``surface`` between its blocks)."""
    guard_accumulation: float = 0.5
    """``nearest-guarded``: accumulation (0-1) below which a block counts as transparent on a ray, and at
    or above which the global model's render replaces it there."""
    nearest_idw_gamma: float = 2.0
    """Exponent of the inverse camera distance that weights the ``blocks_per_ray`` nearest blocks in
    ``nearest-idw``."""
    seed_block_occupancy: bool = True
    """Start a block's occupancy grid from the global model's density (empty space skipped from its
    first step) instead of a warm-up that evaluates every sample."""
    selection_depth: Literal["field", "grid"] = "field"
    """Where choosing blocks per ray reads the global depth: ``field`` (a density-only pass of the global
    field) or ``grid`` (its occupancy grid's estimates: no field evaluation, coarser)."""
    blocks_per_ray: int = 2
    """Blocks rendered per ray: those whose region best holds the global surface point (global, idw,
    surface) or whose centres are nearest the ray's origin (nearest-idw); 0: every block on every ray."""
    # Off, every block's region competes: on inward-looking captures that picks blocks whose cameras look away.
    observed_blocks_only: bool = True
    """Choosing blocks per ray, consider only blocks whose training cameras observe the global surface
    point; a ray no block observes is the global model's."""
    block_fit_steps: int = 100
    """``block_init`` fitted: Adam steps fitting a block's table to the global model's encoding before
    the block trains (hash grids only, no rendering)."""
    block_fit_points: int = 1 << 15
    """``block_init`` fitted: world points per fitting step."""
    max_resident_blocks: int = 8
    """Finished blocks kept in memory at most (the others are on disk in RUN/block_models/ and loaded
    when a render needs them); the training block comes on top."""
    camera_optimizer: CameraOptimizerConfig = field(default_factory=lambda: CameraOptimizerConfig(mode="off"))
    """Pose refinement (nerfstudio's camera optimiser; its rate: --optimizers.camera-opt): a correction per
    training image learnt in the global phase and applied, as learnt, in the blocks' phases; held-out views
    keep their poses. mode SO3xR3 or SE3 turns it on."""


@dataclass(frozen=True)
class ParamGroup:
    """An optimiser parameter group: which model it belongs to and which part of that model it is."""

    block: Optional[int]
    """None: the global model; k: block k's model."""
    part: str
    """``encoder``, ``decoder`` or ``appearance``; ``camera_opt`` (block None): the pose corrections."""

    @property
    def name(self) -> str:
        """The group's name (a key of the optimisers): ``decoder``, ``block3.decoder``, ..."""
        return self.part if self.block is None else f"block{self.block}.{self.part}"


class ScalarSceneModel(NormalsOutput, Model):
    """Global model, block models and their fusion.

    Rendering outside training adds a fused ``normals`` output (see
    :attr:`ScalarModelConfig.render_normals`): each pixel's normal comes from the model that gave its
    colour (the same winner, or the same IDW weights), so ``ns-export pointcloud`` writes one merged
    cloud of what the fused render shows.

    Keyword args (from the pipeline):
        split: the :class:`BlockSplit` of the training images (indices into them).
        block_ids: which blocks this model holds (all of them, or one in a ``scalar-nerf-block`` run).
        block_capacities: {k: BlockCapacity} table size and finest resolution of block k's model
            (default: the config's field settings).
        decoder_mode: ``finetune`` / ``frozen`` (start from the global decoder) or ``independent``.
        block_init: ``global``: a block model lives in the global model's frame and starts as a copy of
            it (:meth:`begin_block`); ``fresh``: its own frame over its scaled AABB, an empty table;
            ``fitted``: as fresh, with the table fitted to the global model first (``block_start.fit_block``).
        block_observation: [K, G^3] bool, the cells each block's cameras observe
            (``blocks/observation.py``); None: blocks are chosen by their regions alone.
    """

    config: ScalarSceneModelConfig
    blocks_started: Tensor
    """[K] bool: which blocks have started training (buffer, saved in checkpoints)."""
    block_centres: Tensor
    """[K, 3] float32 the blocks' centres (buffer, not saved)."""
    block_radii: Tensor
    """[K] float32 the blocks' region radii (buffer, not saved)."""
    block_observation: Optional[Tensor]
    """[K, G^3] bool: the cells each block's cameras observe; None: not known (buffer, not saved)."""

    def populate_modules(self) -> None:
        """Build the global model and the block models (their colliders are their own, as
        :class:`ScalarModel`'s: the config is not changed)."""
        super().populate_modules()
        self.scene_radius: Optional[float] = self.kwargs.get("scene_radius", self.config.scene_radius)
        """Every model's rays end where they leave the sphere of this radius (None: unbounded)."""
        self.collider = near_far_collider(self.config, scene_radius=self.scene_radius)
        self._init_normals_output(self.config.render_normals)
        self.heap_release = HeapRelease()
        """Gives the memory camera renders freed back to the operating system (CPU; see get_outputs_for_camera)."""
        self.split: BlockSplit = self.kwargs["split"]
        self.block_ids: Tuple[int, ...] = tuple(self.kwargs.get("block_ids", range(self.split.num_blocks)))
        self.decoder_mode: DecoderMode = self.kwargs.get("decoder_mode", "finetune")
        self.block_init: BlockInit = self.kwargs.get("block_init", "fresh")
        check_block_start(self.decoder_mode, self.block_init)
        self.fusion_mode: ParsedFusionMode = parse_fusion_mode(self.config.fusion, self.split.num_blocks)
        self.rendered_models: set = set()
        """Models (block indices, "global") rendered since the last camera started (for reports)."""
        self.rays_rendered_by_block: Dict[int, int] = {}
        """Rays each block rendered since the last camera started (for reports)."""
        self.global_model = ScalarModel(config=self.config, scene_box=self.scene_box, num_train_data=self.num_train_data,
                                        scene_radius=self.scene_radius)
        self._block_capacities: Dict[int, BlockCapacity] = self.kwargs.get("block_capacities") or {}
        self._num_block_images = {b.index: len(b.image_indices) for b in self.split.blocks}  # sizes appearance embeddings
        self.blocks = nn.ModuleDict()
        """Block k's model under ``str(k)``: a shell whose tensors are empty unless :attr:`store` holds it in memory."""
        self.store = BlockStore(self.blocks, self.config.max_resident_blocks)
        """Where each block's weights are: in memory, in its file (:class:`BlockStore`)."""
        for index in self.block_ids:
            model = self._new_block_model(index)
            self.store.add_shell(index, model)  # one block at a time in memory: built, measured, emptied
            if self.decoder_mode == "frozen":
                model.field.decoder.requires_grad_(False)
        # Which blocks have started training (their decoder was initialised); saved in checkpoints.
        self.register_buffer("blocks_started", torch.zeros(self.split.num_blocks, dtype=torch.bool))
        # The blocks' regions (not in checkpoints); :meth:`renderer` passes them on as one :class:`BlockRegions`.
        self.register_buffer(
            "block_centres", torch.tensor([b.centre for b in self.split.blocks], dtype=torch.float32), persistent=False
        )
        self.register_buffer(
            "block_radii", torch.tensor([block_region(b)[1] for b in self.split.blocks], dtype=torch.float32), persistent=False
        )
        self.pose_refinement = PoseRefinement(self.config.camera_optimizer, num_images=self.num_train_data)
        """The training images' pose corrections (:mod:`~scalar_nerfstudio.models.pose_refinement`)."""
        self._block_images = {b.index: torch.as_tensor(b.image_indices, dtype=torch.long) for b in self.split.blocks}
        observation = self.kwargs.get("block_observation")
        self.register_buffer("block_observation", None if observation is None else observation.bool(), persistent=False)
        """[K, G^3] bool: the cells of a coarse grid each block's cameras observe (None: not known)."""

    def _new_block_model(self, index: int) -> ScalarModel:
        """Block ``index``'s model, freshly initialised (its own frame, or the global one)."""
        return new_block_model(self.config, capacity=self._block_capacities.get(index), block=self.split.blocks[index],
                               block_init=self.block_init, scene_box=self.scene_box, num_images=self._num_block_images[index],
                               scene_radius=self.scene_radius)

    # -------------------------------------------------------------- checkpoint layout
    #: Where the pipeline keeps this model in its state dict (nerfstudio's ``_model.``: ``scalar_nerfstudio.seam``).
    PIPELINE_KEY_PREFIX = PIPELINE_MODEL_KEY_PREFIX

    @classmethod
    def global_state(cls, pipeline_state: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """The global model's own state dict, out of a pipeline checkpoint's ``pipeline`` state."""
        return cls._submodule_state(pipeline_state, "global_model")

    @classmethod
    def pose_state(cls, pipeline_state: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """The pose corrections' state dict (empty: the run learnt none), out of a pipeline checkpoint's state."""
        return cls._submodule_state(pipeline_state, "pose_refinement")

    @classmethod
    def _submodule_state(cls, pipeline_state: Dict[str, Tensor], name: str) -> Dict[str, Tensor]:
        """The state dict of this model's submodule ``name``, out of a pipeline checkpoint's state."""
        prefix = f"{cls.PIPELINE_KEY_PREFIX}{name}."
        return {k[len(prefix):]: v for k, v in pipeline_state.items() if k.startswith(prefix)}

    @classmethod
    def block_keys(cls, pipeline_state: Dict[str, Tensor], block: int) -> List[str]:
        """The keys of block ``block``'s model in a pipeline checkpoint's ``pipeline`` state."""
        prefix = f"{cls.PIPELINE_KEY_PREFIX}blocks.{block}."
        return [k for k in pipeline_state if k.startswith(prefix)]

    @classmethod
    def started_key(cls) -> str:
        """The key of the ``blocks_started`` flags in a pipeline checkpoint's ``pipeline`` state."""
        return f"{cls.PIPELINE_KEY_PREFIX}blocks_started"

    # ------------------------------------------------------------------- blocks in memory and on disk
    @property
    def block_store(self) -> Optional[Path]:
        """The run's block_models/ folder (:meth:`attach_block_store`); None: blocks are never stored."""
        return self.store.directory

    def attach_block_store(self, directory: Path) -> None:
        """Keep finished blocks in ``directory`` (the run's ``block_models/``) and load them from there."""
        self.store.attach(directory)

    def block_is_resident(self, block: int) -> bool:
        """Whether block ``block``'s weights are in memory (else its shell's tensors are empty)."""
        return self.store.is_resident(block)

    def block_parameter_count(self, block: int, part: Optional[str] = None) -> int:
        """Parameters of block ``block``'s model (of its ``encoder``/``decoder``/``appearance`` when
        ``part`` is given), whether or not they are in memory."""
        return self.store.parameter_count(block, part)

    def release_block(self, block: int) -> None:
        """Free block ``block``'s weights from memory (it must be in its file, or not started)."""
        self.store.release(block, started=bool(self.blocks_started[block]))

    def store_block(self, block: int) -> Path:
        """Write block ``block``'s weights to its file (atomically) and free them from memory: its
        phase is over. Returns the file."""
        return self.store.store(block)

    def resident_block(self, block: int) -> ScalarModel:
        """Block ``block``'s model with its weights in memory: loaded from its file if they are not
        (then at most :attr:`max_resident_blocks` loaded blocks stay, least recently used released)."""
        return self.store.model(block)

    def state_dict(self, *args: Any, destination: Any = None, prefix: str = "", keep_vars: bool = False) -> Dict[str, Any]:
        """nn.Module's, with the tensors of blocks kept in their files empty: a checkpoint holds the
        global model and the blocks that live only in memory (one block's cost, whatever K is)."""
        state = super().state_dict(*args, destination=destination, prefix=prefix, keep_vars=keep_vars)
        return self.store.empty_stored(state, prefix)

    def load_state_dict(self, state_dict: Dict[str, Tensor], strict: bool = True, assign: bool = False):  # type: ignore[override]
        """Load a checkpoint: the global model and the flags as nn.Module does; a block whose weights
        are in the checkpoint becomes resident, a started block whose tensors are empty there is read
        from its file when a render needs it (the file must exist: checked here)."""
        block_states, rest = BlockStore.split_state(state_dict, self.block_ids)
        block_prefixes = tuple(f"blocks.{b}." for b in self.block_ids)
        result = super().load_state_dict(rest, strict=False)
        missing = [k for k in result.missing_keys if not k.startswith(block_prefixes)]
        if strict and (missing or result.unexpected_keys):
            raise RuntimeError(f"the checkpoint does not fit the model: missing {missing[:3]}, unexpected {result.unexpected_keys[:3]}")
        self.store.load(block_states, started=self.started_block_ids())
        return result

    # ------------------------------------------------------------------------------ phases
    def phase_model(self, block: Optional[int]) -> ScalarModel:
        """The model trained in a phase: the global model (block None) or block ``block``'s (with its
        weights in memory once :meth:`begin_block` has started it)."""
        if block is None:
            return self.global_model
        if str(block) not in self.blocks:
            raise KeyError(f"block {block} is not held by this model (it holds {list(self.block_ids)})")
        return self.resident_block(block) if bool(self.blocks_started[block]) else self.store.shell(block)

    @torch.no_grad()
    def begin_block(self, block: int) -> Optional[EncodingFit]:
        """Start block ``block``'s phase once: give it freshly initialised weights in memory and start
        it from the global model (``block_start.start_block``: decoder, and with ``block_init`` global
        the whole model; else its occupancy grid seeded when :attr:`seed_block_occupancy`); with
        ``fitted``, fit its table to the global model's encoding (``block_start.fit_block``; the fit is
        returned, None otherwise)."""
        if bool(self.blocks_started[block]):
            return None
        fresh = self._new_block_model(block).to(self.blocks_started.device)
        self.store.install(block, fresh.state_dict(), what=f"block {block} (fresh)", evictable=False)
        del fresh
        model = self.store.shell(block)
        images = self.split.blocks[block].image_indices
        start_block(model, self.global_model, image_indices=images, decoder_mode=self.decoder_mode, block_init=self.block_init,
                    seed_occupancy=self.config.seed_block_occupancy)
        fit = None
        if self.block_init == "fitted":
            fit = fit_block(
                model, self.global_model, image_indices=images,
                observation=None if self.block_observation is None else self.block_observation[block : block + 1],
                centre=self.block_centres[block], radius=float(self.block_radii[block]), seed=block,
                steps=self.config.block_fit_steps, points_per_step=self.config.block_fit_points,
            )
        self.blocks_started[block] = True
        return fit

    def started_block_ids(self) -> List[int]:
        """Blocks held here whose training has started (the ones rendering fuses)."""
        return [b for b in self.block_ids if bool(self.blocks_started[b])]

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        """``encoder`` / ``decoder`` / ``appearance`` of the global model, ``block{k}.*`` of each block."""
        return {group.name: params for group, params in self.param_groups_by_model()}

    def param_groups_by_model(self) -> List[Tuple[ParamGroup, List[Parameter]]]:
        """Every parameter group with the model it belongs to (:class:`ParamGroup`), in
        :meth:`get_param_groups` order."""
        groups = [(ParamGroup(None, part), params) for part, params in self.global_model.get_param_groups().items()]
        if self.pose_refinement.enabled:
            groups.append((ParamGroup(None, "camera_opt"), list(self.pose_refinement.parameters_to_learn())))
        for index in self.block_ids:
            groups += [(ParamGroup(index, part), params) for part, params in self.store.shell(index).get_param_groups().items()]
        return groups

    def refine_training_rays(self, ray_bundle: RayBundle, block: Optional[int]) -> None:
        """Move a training batch of the phase of ``block`` (None: the global phase, whose batch indexes the
        capture's images; k: block k's, indexing its images) by the pose corrections, in place: learnt in
        the global phase, applied as they are in a block's."""
        images = None if block is None else self._block_images[block]
        self.pose_refinement.apply(ray_bundle, image_indices=images, learn=block is None)

    def add_pose_terms(self, loss_dict: Dict[str, Tensor], metrics_dict: Dict[str, Tensor]) -> None:
        """The pose corrections' regulariser and metrics, for a global phase's step (none when disabled)."""
        if self.pose_refinement.enabled:
            self.pose_refinement.add_losses(loss_dict)
            self.pose_refinement.add_metrics(metrics_dict)

    # --------------------------------------------------------------------------- rendering
    def set_fusion(self, mode: str | ParsedFusionMode) -> None:
        """Switch the fusion mode used by rendering (checked against the number of blocks)."""
        self.fusion_mode = parse_fusion_mode(mode, self.split.num_blocks)

    @torch.no_grad()
    def get_outputs_for_camera(self, camera: Cameras, obb_box=None) -> Dict[str, Tensor]:
        """nerfstudio's camera render; :attr:`rendered_models` then lists the models it rendered. On the
        CPU the memory its chunks freed is given back to the operating system once resident memory
        has grown by 2 GiB (:class:`~scalar_nerfstudio.engine.memory.HeapRelease`): without it,
        resident memory climbs with every image of an evaluation."""
        self.rendered_models = set()
        self.rays_rendered_by_block = {}
        outputs = super().get_outputs_for_camera(camera, obb_box=obb_box)
        if self.device.type == "cpu":
            self.heap_release()
        return outputs

    def renderer(self) -> FusedRenderer:
        """The fused renderer of this model as it is now (its models, block regions, fusion options);
        it adds to :attr:`rendered_models` and :attr:`rays_rendered_by_block`."""
        config = self.config
        settings = FusionSettings(
            blocks_per_ray=config.blocks_per_ray, idw_gamma=config.idw_gamma, nearest_idw_gamma=config.nearest_idw_gamma,
            guard_accumulation=config.guard_accumulation, selection_depth=config.selection_depth,
            observed_blocks_only=config.observed_blocks_only,
        )
        return FusedRenderer(
            self.global_model, block_model=self.resident_block, block_shell=self.store.shell, settings=settings,
            regions=BlockRegions(self.block_centres, self.block_radii, self.block_observation),
            rendered_models=self.rendered_models, rays_rendered_by_block=self.rays_rendered_by_block,
        )

    def get_outputs(self, ray_bundle: RayBundle) -> Dict[str, Tensor]:
        """Fused ``rgb`` [R, 3], ``depth`` [R, 1], ``accumulation`` [R, 1], ``block_winner`` [R, 1],
        ``block_colour`` [R, 3]; ``normals`` [R, 3] in [0, 1] when :meth:`normals_wanted`
        (:meth:`FusedRenderer.render` with the current fusion mode and the started blocks)."""
        normals = self.normals_wanted()
        mode = self.fusion_mode
        return self.renderer().render(ray_bundle, mode, self._blocks_for(mode), normals=normals)

    @torch.no_grad()
    def select_rays(
        self, mode: ParsedFusionMode, block_ids: List[int], ray_bundle: RayBundle, *, global_outputs: Optional[Dict[str, Tensor]] = None
    ) -> Tuple[Tensor, Optional[Tensor]]:
        """Which block renders which ray: ``([K', R] bool, [K', R] region scores or None)``
        (:func:`~scalar_nerfstudio.models.block_selection.select_rays`)."""
        return self.renderer().select_rays(mode, block_ids, ray_bundle, global_outputs=global_outputs)

    def _blocks_for(self, mode: ParsedFusionMode) -> List[int]:
        """Blocks that may render for ``mode`` (none for global-only or before any block has trained)."""
        return blocks_for(mode, self.started_block_ids())

    # ------------------------------------------------------------------------- loss, metrics
    def get_metrics_dict(self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """PSNR of the fused render."""
        return {"psnr": psnr(outputs["rgb"].detach(), self._target_rgb(batch, outputs["rgb"]))}

    def get_loss_dict(
        self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor], metrics_dict: Optional[Dict[str, Tensor]] = None
    ) -> Dict[str, Tensor]:
        """Photometric MSE of the fused render (evaluation only; training uses the phase's model)."""
        return {"rgb_loss": torch.mean((outputs["rgb"] - self._target_rgb(batch, outputs["rgb"])) ** 2)}

    _target_rgb = staticmethod(ScalarModel._target_rgb)

    def get_image_metrics_and_images(
        self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        """PSNR, SSIM (LPIPS when available) of the fused image; images incl. the block winner map."""
        metrics, images = self.global_model.get_image_metrics_and_images(outputs, batch)  # (normals too, if rendered)
        if "block_winner" in outputs:
            images["block_winner"] = outputs["block_winner"]
        return metrics, images
