"""The model nerfstudio's trainer, viewer, ``ns-eval`` and ``ns-render`` see: global + blocks + fusion.

:class:`ScalarSceneModel` holds one :class:`ScalarModel` for the coarse global model and one per
block (the same class: a block differs only by its region, its images and where its decoder came
from). Training runs one of them at a time (the pipeline picks it by step); rendering renders the
global model and the blocks that have started training, and fuses them per pixel.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple, Type, get_args

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.models.base_model import Model
from torch import Tensor, nn
from torch.nn import Parameter

from scalar_nerfstudio.blocks.capacity import BlockCapacity
from scalar_nerfstudio.blocks.observation import observed_at
from scalar_nerfstudio.blocks.split import Block, BlockSplit
from scalar_nerfstudio.engine.memory import HeapRelease
from scalar_nerfstudio.fusion import (
    FUSED_KEYS,
    ParsedFusionMode,
    fuse_weighted,
    fusion_weights,
    guard_transparent,
    nearest_block,
    nearest_blocks,
    parse_fusion_mode,
    region_scores,
    select_blocks,
    surface_points,
    transparent_pixels,
    weights_winner,
)
from scalar_nerfstudio.metrics import psnr
from scalar_nerfstudio.models.block_fit import EncodingFit, fit_encoding, occupied_cell_sampler
from scalar_nerfstudio.models.block_memory import (
    ResidentBlocks,
    TensorSpec,
    install_tensors,
    is_released_state,
    load_block_file,
    release_tensors,
    save_block_file,
    spec_numel,
    tensor_specs,
)
from scalar_nerfstudio.runs import block_model_path
from scalar_nerfstudio.model_components.rendering import facing_normals, normals_from_unit_interval, normals_to_unit_interval, safe_normalise
from scalar_nerfstudio.models.scalar_model import NormalsOutput, ScalarModel, ScalarModelConfig, near_far_collider
from scalar_nerfstudio.blocks.palette import BLOCK_PALETTE, GLOBAL_COLOUR

DecoderMode = Literal["finetune", "frozen", "independent"]
BlockInit = Literal["global", "fresh", "fitted"]
BLOCK_INITS: Tuple[str, ...] = get_args(BlockInit)
#: A block's region radius never drops below this (normalised scene units; cameras span [-1, 1]).
MIN_REGION_RADIUS = 0.05


@dataclass
class ScalarSceneModelConfig(ScalarModelConfig):
    """Global model + one local model per block, fused per pixel (paper Sec. 3.4)."""

    _target: Type = field(default_factory=lambda: ScalarSceneModel)
    fusion: str = "nearest-guarded"
    """How block renders are fused: nearest-guarded (default: nearest, but the global model's render
    where the block is transparent and the global model opaque; the global model renders only the rays
    whose block is transparent: the same images as nearest on every trained run measured, and the global
    model's where a block learnt nothing, docs/fusion.md), nearest (per ray the block whose cameras are
    nearest the ray's origin; one block per ray, no global render: the best and cheapest on castle-P30
    with blocks started from the global model), nearest-idw (the ``blocks_per_ray`` nearest
    blocks weighted by inverse distance), global (closest to the global model's colour, the
    paper's), surface (the block whose region holds the surface the global depth points to), idw
    (Block-NeRF's inverse distance weighting), global-only, or block:<k>."""
    idw_gamma: float = 1.0
    """Exponent of inverse distance weighting (``idw``, and ``surface`` between its blocks)."""
    guard_accumulation: float = 0.5
    """``nearest-guarded``: a block whose accumulation on a ray is below this counts as transparent
    there, and the global model's render is used where its own accumulation is at least this."""
    nearest_idw_gamma: float = 2.0
    """Exponent of the inverse camera distance that weights the ``blocks_per_ray`` nearest blocks in
    ``nearest-idw`` (2 scored best on the town, docs/town.md)."""
    seed_block_occupancy: bool = True
    """A block's occupancy grid starts from the global model's density (empty space is skipped from
    its first step) instead of a warm-up that evaluates every sample."""
    selection_depth: Literal["field", "grid"] = "field"
    """Where choosing blocks per ray reads the global model's depth when the fusion does not render the
    global colour: ``field`` (a density-only pass of the global field) or ``grid`` (its occupancy
    grid's density estimates: no field evaluation, coarser)."""
    blocks_per_ray: int = 2
    """Per ray, render only this many blocks: those whose region best holds the point the global
    model's depth gives (``global``, ``idw``, ``surface``), or those whose centres are nearest the ray's
    origin (``nearest-idw``; ``nearest`` renders one). The render cost is
    then the global model's plus this many blocks', whatever the number of blocks. 0: every block on
    every ray (the paper's ``global`` rule over all blocks; cost grows with K)."""
    observed_blocks_only: bool = True
    """Choosing blocks per ray, consider only the blocks whose training cameras observe the point at the
    global depth (blocks/observation.py); a ray no block observes is the global model's. Off: every
    block's region competes (on inward-looking captures that picks blocks whose cameras look away)."""
    block_fit_steps: int = 100
    """``block_init`` fitted: Adam steps fitting a block's table to the global model's encoding before the
    block trains (models/block_fit.py; hash grids only, no rendering)."""
    block_fit_points: int = 1 << 15
    """``block_init`` fitted: world points per fitting step."""
    max_resident_blocks: int = 8
    """Finished blocks are kept on disk (RUN/block_models/) and loaded when a render needs them; at
    most this many loaded blocks stay in memory at once (least recently used ones are released).
    The block that trains is always in memory besides them."""


def block_region(block: Block) -> Tuple[Tuple[float, float, float], float]:
    """Centre and radius of a block's local model frame: its scaled AABB's centre and largest half-extent.

    The global model maps the camera layout's largest half-extent to 1 (nerfstudio's pose
    normalisation); a block does the same with its own scaled AABB, so its hash grid resolves the
    block as finely as the global grid resolves the whole scene.
    """
    half_extent = max((hi - lo) / 2.0 for lo, hi in zip(block.aabb_min, block.aabb_max))
    return block.centre, max(half_extent, MIN_REGION_RADIUS)


@dataclass(frozen=True)
class ParamGroup:
    """An optimiser parameter group: which model it belongs to and which part of that model it is."""

    block: Optional[int]
    """None: the global model; k: block k's model."""
    part: str
    """``encoder``, ``decoder`` or ``appearance``."""

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
            ``fitted``: as fresh, with the table fitted to the global model first (:meth:`_fit_block`).
        block_observation: [K, G^3] bool, the cells each block's cameras observe
            (``blocks/observation.py``); None: blocks are chosen by their regions alone.
    """

    config: ScalarSceneModelConfig

    def populate_modules(self) -> None:
        """Build the global model and the block models."""
        self.config.enable_collider = True
        self.config.collider_params = {"near_plane": self.config.near_plane, "far_plane": self.config.far_plane}
        super().populate_modules()
        self.collider = near_far_collider(self.config)
        self._init_normals_output(self.config.render_normals)
        self.heap_release = HeapRelease()
        """Gives the memory camera renders freed back to the operating system (CPU; see get_outputs_for_camera)."""
        self.split: BlockSplit = self.kwargs["split"]
        self.block_ids: Tuple[int, ...] = tuple(self.kwargs.get("block_ids", range(self.split.num_blocks)))
        self.decoder_mode: DecoderMode = self.kwargs.get("decoder_mode", "finetune")
        if self.decoder_mode not in ("finetune", "frozen", "independent"):
            raise ValueError(f"decoder_mode {self.decoder_mode!r}: expected finetune, frozen or independent")
        self.block_init: BlockInit = self.kwargs.get("block_init", "fresh")
        if self.block_init not in BLOCK_INITS:
            raise ValueError(f"block_init {self.block_init!r}: expected one of {', '.join(BLOCK_INITS)}")
        if self.block_init == "fitted" and self.decoder_mode == "independent":
            raise ValueError("block_init fitted fits a block's table to the global model through the global decoder, "
                             "which decoder_mode independent does not copy: use decoder_mode finetune or frozen, or block_init fresh")
        num_images: Dict[int, int] = {b.index: len(b.image_indices) for b in self.split.blocks}  # sizes appearance embeddings
        self.fusion_mode: ParsedFusionMode = parse_fusion_mode(self.config.fusion, self.split.num_blocks)
        self.rendered_models: set = set()
        """Models (block indices, "global") rendered since the last camera started (for reports)."""
        self.rays_rendered_by_block: Dict[int, int] = {}
        """Rays each block rendered since the last camera started (for reports)."""
        self.global_model = ScalarModel(config=self.config, scene_box=self.scene_box, num_train_data=self.num_train_data)
        self._block_capacities: Dict[int, BlockCapacity] = self.kwargs.get("block_capacities") or {}
        self._num_block_images = num_images
        self._block_specs: Dict[int, Dict[str, TensorSpec]] = {}
        """Shape and dtype of each block model's tensors (its shell holds them empty until needed)."""
        blocks = {}
        for index in self.block_ids:
            model = self._new_block_model(index)
            self._block_specs[index] = tensor_specs(model)
            release_tensors(model)  # one block at a time in memory: built, measured, emptied
            if self.decoder_mode == "frozen":
                model.field.decoder.requires_grad_(False)
            blocks[str(index)] = model
        self.blocks = nn.ModuleDict(blocks)
        # Which blocks have started training (their decoder was initialised); saved in checkpoints.
        self.register_buffer("blocks_started", torch.zeros(self.split.num_blocks, dtype=torch.bool))
        self.register_buffer(
            "block_centres", torch.tensor([b.centre for b in self.split.blocks], dtype=torch.float32), persistent=False
        )
        self.register_buffer(
            "block_radii", torch.tensor([block_region(b)[1] for b in self.split.blocks], dtype=torch.float32), persistent=False
        )
        observation = self.kwargs.get("block_observation")
        self.register_buffer("block_observation", None if observation is None else observation.bool(), persistent=False)
        """[K, G^3] bool: the cells of a coarse grid each block's cameras observe (None: not known)."""
        self.resident = ResidentBlocks(self.config.max_resident_blocks)
        """Blocks whose weights are in memory (the others' tensors are empty; see block_memory.py)."""
        self.block_store: Optional[Path] = None
        """The run's block_models/ folder (:meth:`attach_block_store`); None: blocks are never stored."""
        self._stored: set = set()
        """Blocks whose current weights are in their file in :attr:`block_store`."""

    def _new_block_model(self, index: int) -> ScalarModel:
        """Block ``index``'s model, freshly initialised (its own frame, or the global one)."""
        centre, radius = ((0.0, 0.0, 0.0), 1.0) if self.block_init == "global" else block_region(self.split.blocks[index])
        return ScalarModel(
            config=self._block_config(self._block_capacities.get(index)), scene_box=self.scene_box,
            num_train_data=self._num_block_images[index], region_centre=centre, region_radius=radius,
        )

    def _block_config(self, capacity: Optional[BlockCapacity]) -> ScalarModelConfig:
        """The model config of a block: the shared one, with the block's table size and resolution."""
        if capacity is None:
            return self.config
        field_config = replace(self.config.field, log2_hashmap_size=capacity.log2_hashmap_size, max_resolution=capacity.max_resolution)
        return replace(self.config, field=field_config)

    # -------------------------------------------------------------- checkpoint layout
    #: Where the pipeline keeps this model in its state dict (nerfstudio's ``Pipeline._model``).
    PIPELINE_KEY_PREFIX = "_model."

    @classmethod
    def global_state(cls, pipeline_state: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """The global model's own state dict, out of a pipeline checkpoint's ``pipeline`` state."""
        prefix = f"{cls.PIPELINE_KEY_PREFIX}global_model."
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
    def attach_block_store(self, directory: Path) -> None:
        """Keep finished blocks in ``directory`` (the run's ``block_models/``) and load them from there."""
        self.block_store = Path(directory)

    def block_is_resident(self, block: int) -> bool:
        """Whether block ``block``'s weights are in memory (else its shell's tensors are empty)."""
        return block in self.resident

    def block_parameter_count(self, block: int, part: Optional[str] = None) -> int:
        """Parameters of block ``block``'s model (of its ``encoder``/``decoder``/``appearance`` when
        ``part`` is given), whether or not they are in memory."""
        head = "field." if part is None else f"field.{part}."
        specs = self._block_specs[block]
        return spec_numel(specs, [k for k in specs if k.startswith(head)])

    def _install_block(self, block: int, state: Dict[str, Tensor], what: str, evictable: bool) -> None:
        model = self.blocks[str(block)]
        install_tensors(model, model.complete_state(dict(state)), self._block_specs[block], what)
        self.resident.add(block, evictable)
        for other in self.resident.over_limit(keep=block):
            self.release_block(other)

    def release_block(self, block: int) -> None:
        """Free block ``block``'s weights from memory (it must be in its file, or not started)."""
        if bool(self.blocks_started[block]) and block not in self._stored:
            raise RuntimeError(f"block {block} is trained but not saved to its file: releasing it would lose it")
        release_tensors(self.blocks[str(block)])
        self.resident.discard(block)

    def store_block(self, block: int) -> Path:
        """Write block ``block``'s weights to its file (atomically) and free them from memory: its
        phase is over. Returns the file."""
        if self.block_store is None:
            raise RuntimeError("no block store attached (attach_block_store): the block's weights would be lost")
        path = block_model_path(self.block_store, block)
        save_block_file(path, block, self.blocks[str(block)].state_dict())
        self._stored.add(block)
        self.release_block(block)
        return path

    def resident_block(self, block: int) -> ScalarModel:
        """Block ``block``'s model with its weights in memory: loaded from its file if they are not
        (then at most :attr:`max_resident_blocks` loaded blocks stay, least recently used released)."""
        if block in self.resident:
            self.resident.touch(block)
        elif block in self._stored:
            assert self.block_store is not None
            path = block_model_path(self.block_store, block)
            self._install_block(block, load_block_file(path, block), f"block {block} from {path}", evictable=True)
        else:
            raise RuntimeError(f"block {block} has no weights: it has not started training")
        return self.blocks[str(block)]

    def state_dict(self, *args: Any, destination: Any = None, prefix: str = "", keep_vars: bool = False) -> Dict[str, Any]:
        """nn.Module's, with the tensors of blocks kept in their files empty: a checkpoint holds the
        global model and the blocks that live only in memory (one block's cost, whatever K is)."""
        state = super().state_dict(*args, destination=destination, prefix=prefix, keep_vars=keep_vars)
        for block in self._stored:
            head = f"{prefix}blocks.{block}."
            for key in [k for k in state if k.startswith(head)]:
                state[key] = state[key].new_empty(0)
        return state

    def load_state_dict(self, state_dict: Dict[str, Tensor], strict: bool = True, assign: bool = False):  # type: ignore[override]
        """Load a checkpoint: the global model and the flags as nn.Module does; a block whose weights
        are in the checkpoint becomes resident, a started block whose tensors are empty there is read
        from its file when a render needs it (the file must exist: checked here)."""
        block_states: Dict[int, Dict[str, Tensor]] = {b: {} for b in self.block_ids}
        rest = {}
        for key, value in state_dict.items():
            parts = key.split(".", 2)
            if parts[0] == "blocks" and len(parts) == 3 and parts[1].isdigit() and int(parts[1]) in block_states:
                block_states[int(parts[1])][parts[2]] = value
            else:
                rest[key] = value
        block_prefixes = tuple(f"blocks.{b}." for b in self.block_ids)
        result = super().load_state_dict(rest, strict=False)
        missing = [k for k in result.missing_keys if not k.startswith(block_prefixes)]
        if strict and (missing or result.unexpected_keys):
            raise RuntimeError(f"the checkpoint does not fit the model: missing {missing[:3]}, unexpected {result.unexpected_keys[:3]}")
        for block, state in block_states.items():
            self.resident.discard(block)
            self._stored.discard(block)
            release_tensors(self.blocks[str(block)])
            if not bool(self.blocks_started[block]):
                continue
            if state and not is_released_state(state):
                self._install_block(block, state, f"block {block} in the checkpoint", evictable=False)
            elif self.block_store is not None and not block_model_path(self.block_store, block).is_file():
                raise FileNotFoundError(
                    f"the checkpoint says block {block} has trained, but its weights are neither in it nor in "
                    f"{block_model_path(self.block_store, block)}"
                )
            else:
                self._stored.add(block)
        return result

    # ------------------------------------------------------------------------------ phases
    def phase_model(self, block: Optional[int]) -> ScalarModel:
        """The model trained in a phase: the global model (block None) or block ``block``'s (with its
        weights in memory once :meth:`begin_block` has started it)."""
        if block is None:
            return self.global_model
        if str(block) not in self.blocks:
            raise KeyError(f"block {block} is not held by this model (it holds {list(self.block_ids)})")
        return self.resident_block(block) if bool(self.blocks_started[block]) else self.blocks[str(block)]

    @torch.no_grad()
    def begin_block(self, block: int) -> Optional[EncodingFit]:
        """Start block ``block``'s phase once: give it freshly initialised weights in memory and copy
        the global decoder into it (finetune / frozen); with ``block_init`` global, also the global
        table, occupancy grid and the block's images' appearance embeddings (the block starts as the
        global model); else, with :attr:`seed_block_occupancy`, mark its occupancy grid from the
        global model's density, and with ``fitted`` fit its table to the global model's encoding
        (:meth:`_fit_block`; the fit is returned, None otherwise)."""
        if bool(self.blocks_started[block]):
            return None
        fit = None
        fresh = self._new_block_model(block).to(self.blocks_started.device)
        self._install_block(block, fresh.state_dict(), f"block {block} (fresh)", evictable=False)
        del fresh
        model = self.blocks[str(block)]
        if self.decoder_mode != "independent":
            model.field.decoder.load_state_dict(self.global_model.field.decoder.state_dict())
        if self.block_init == "global":
            model.field.encoder.load_state_dict(self.global_model.field.encoder.state_dict())
            self._copy_appearance(block, model)
            model.occupancy.load_state_dict(self.global_model.occupancy.state_dict())
            model.occupancy.seeded.fill_(True)
        else:
            if self.config.seed_block_occupancy:
                model.seed_occupancy_from(self.global_model)
            if self.block_init == "fitted":
                fit = self._fit_block(block, model)
        self.blocks_started[block] = True
        return fit

    def _fit_block(self, block: int, model: ScalarModel) -> EncodingFit:
        """``block_init`` fitted: block ``block``'s table fitted to the global model's encoding over the
        global model's occupied cells that the block's cameras observe (all its occupied cells near the
        block when that is not known; every cell when none is occupied), and its images' appearance
        embeddings copied."""
        global_model = self.global_model
        grid = global_model.occupancy
        cells = torch.nonzero(grid.occupied).squeeze(-1)
        if cells.numel() == 0:
            cells = torch.arange(grid.occupied.numel(), device=grid.occupied.device)
        centres = global_model.unit_cube_to_world(grid.cell_centres()[cells])  # [C, 3] world
        if self.block_observation is not None:
            near_block = observed_at(self.block_observation[block : block + 1], centres)[0].to(cells.device)
        else:
            near_block = torch.linalg.vector_norm(centres - self.block_centres[block], dim=-1) <= 2.0 * float(self.block_radii[block])
        if bool(near_block.any()):
            cells = cells[near_block]
        generator = torch.Generator(device=cells.device).manual_seed(block)
        sampler = occupied_cell_sampler(cells, grid.resolution, global_model.unit_cube_to_world, generator)
        self._copy_appearance(block, model)
        return fit_encoding(
            model.field.encoder, model.world_to_unit_cube, global_model.field.encoder, global_model.world_to_unit_cube,
            sampler, steps=self.config.block_fit_steps, points_per_step=self.config.block_fit_points,
        )

    def _copy_appearance(self, block: int, model: ScalarModel) -> None:
        """Give block ``block``'s model the global model's appearance embeddings of the block's images."""
        rows = torch.tensor(self.split.blocks[block].image_indices, dtype=torch.long, device=model.field.appearance.weight.device)
        model.field.appearance.weight.copy_(self.global_model.field.appearance.weight[rows])

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
        for index in self.block_ids:
            groups += [(ParamGroup(index, part), params) for part, params in self.blocks[str(index)].get_param_groups().items()]
        return groups

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

    def get_outputs(self, ray_bundle: RayBundle) -> Dict[str, Tensor]:
        """Fused ``rgb`` [R, 3], ``depth`` [R, 1], ``accumulation`` [R, 1], ``block_winner`` [R, 1],
        ``block_colour`` [R, 3]; ``normals`` [R, 3] in [0, 1] when :meth:`normals_wanted`.

        Each block renders only the rays it is selected for (:meth:`select_rays`); the fusion sees
        NaN where a block was not rendered, which every rule treats as "not available". The global
        model renders colour for ``global`` / ``global-only`` (and the rays no block could give), its
        depth alone where only the selection needs it. ``block_winner`` is the index of the block that
        gave the pixel (-1: the global model); ``block_colour`` shows it in the block's viewer colour.
        """
        normals = self.normals_wanted()
        mode = self.fusion_mode
        block_ids = self._blocks_for(mode)
        if mode.kind == "global" and self.config.blocks_per_ray == 1:
            # One block chosen per ray: it is the closest to the global colour by itself, so the global
            # colour is not rendered (the same image as "surface" with one block per ray).
            mode = ParsedFusionMode(kind="surface")
        origins = ray_bundle.origins.reshape(-1, 3)
        global_outputs: Optional[Dict[str, Tensor]] = None
        if mode.kind in ("global", "global-only") or not block_ids:
            # Its normals only where it is the output (with blocks, "global" takes every pixel from a block).
            global_outputs = self.global_model.render_rays(ray_bundle, normals=normals and not block_ids)
            self.rendered_models.add("global")
        if block_ids:
            selected, scores = self.select_rays(mode, block_ids, ray_bundle, global_outputs)  # [K', R]
            used = selected.any(dim=1)  # blocks no ray chose take no part at all: the cost is O(chosen), not O(K)
            if not bool(used.all()):
                rows = torch.nonzero(used).squeeze(-1)
                block_ids = [block_ids[i] for i in rows.tolist()]
                selected = selected[rows]
                scores = None if scores is None else scores[rows]
        if not block_ids:  # no block, or none chosen by any ray: the global model's render
            if global_outputs is None or (normals and "normals" not in global_outputs):
                global_outputs = self.global_model.render_rays(ray_bundle, normals=normals)
                self.rendered_models.add("global")
            winner = torch.full_like(global_outputs["accumulation"], -1.0)
            return {**global_outputs, "block_winner": winner, "block_colour": self._winner_colours(winner)}
        block_outputs = [self._render_block_rays(b, ray_bundle, selected[i], normals) for i, b in enumerate(block_ids)]
        self.rendered_models.update(b for i, b in enumerate(block_ids) if bool(selected[i].any()))
        rgb_stack = torch.stack([o["rgb"] for o in block_outputs])  # [K', R, 3]
        weights = fusion_weights(
            ParsedFusionMode(kind="block", block_index=0) if mode.kind == "block" else mode,
            rgb_stack, None if global_outputs is None else global_outputs["rgb"], origins,
            self.block_centres[block_ids].to(origins.device),
            self.config.nearest_idw_gamma if mode.kind == "nearest-idw" else self.config.idw_gamma, scores,
            self.config.blocks_per_ray or None,
        )
        if mode.kind == "nearest-guarded":
            weights, global_outputs = self._guard_transparent_blocks(weights, block_outputs, ray_bundle, normals)
        orphans = ~(weights > 0).any(dim=0)  # [R] rays no block could give: the global model's
        if bool(orphans.any()) and global_outputs is None:
            global_outputs = self._render_global_rays(ray_bundle, orphans, normals)
            self.rendered_models.add("global")
        fused = {
            key: fuse_weighted(torch.stack([o[key] for o in block_outputs]), weights,
                               None if global_outputs is None or key not in global_outputs else global_outputs[key])
            for key in FUSED_KEYS
        }
        if normals:
            fallback = (global_outputs["normals"] if global_outputs is not None and "normals" in global_outputs
                        else normals_to_unit_interval(facing_normals(ray_bundle.directions.reshape(-1, 3))))
            stacked = torch.stack([o["normals"] for o in block_outputs])  # [K', R, 3] in [0, 1]
            if mode.kind in ("global", "nearest", "nearest-guarded", "block"):  # one winner per ray: its normal, bit for bit
                fused["normals"] = fuse_weighted(stacked, weights, fallback)
            else:  # a weighted mix of unit normals, normalised again
                mixed = fuse_weighted(normals_from_unit_interval(stacked), weights, normals_from_unit_interval(fallback))
                fused["normals"] = normals_to_unit_interval(safe_normalise(mixed, normals_from_unit_interval(fallback)))
        position_to_id = torch.tensor([-1, *block_ids], dtype=torch.float32, device=origins.device)
        fused["block_winner"] = position_to_id[weights_winner(weights) + 1][:, None]
        fused["block_colour"] = self._winner_colours(fused["block_winner"])
        return fused

    @torch.no_grad()
    def select_rays(
        self, mode: ParsedFusionMode, block_ids: List[int], ray_bundle: RayBundle, global_outputs: Optional[Dict[str, Tensor]] = None
    ) -> Tuple[Tensor, Optional[Tensor]]:
        """Which block renders which ray: ``([K', R] bool, [K', R] region scores or None)``.

        ``block``: every ray. ``nearest``: the block whose centre is nearest to the ray's origin;
        ``nearest-idw``: the :attr:`blocks_per_ray` blocks nearest to it (every block with 0).
        ``global`` / ``idw`` / ``surface``: the :attr:`blocks_per_ray` blocks whose region best holds
        the point at the global model's depth (:func:`region_scores`); with ``blocks_per_ray`` 0 or
        at least K', every block (``surface`` still weights them by score). The global depth is taken
        from ``global_outputs`` when given, else rendered from the density alone.
        """
        origins = ray_bundle.origins.reshape(-1, 3)
        num_rays, num_blocks = origins.shape[0], len(block_ids)
        every = torch.ones(num_blocks, num_rays, dtype=torch.bool, device=origins.device)
        if mode.kind == "block":
            return every, None
        centres = self.block_centres[block_ids].to(origins.device)
        if mode.kind in ("nearest", "nearest-guarded"):
            nearest = nearest_block(origins, centres)
            return torch.arange(num_blocks, device=origins.device)[:, None] == nearest[None], None
        limit = self.config.blocks_per_ray
        if mode.kind == "nearest-idw":  # the blocks the weights will use: the `limit` nearest the origin
            return nearest_blocks(origins, centres, limit if limit > 0 else num_blocks), None
        if mode.kind != "surface" and (limit <= 0 or limit >= num_blocks):
            return every, None
        if global_outputs is None:
            global_outputs = self.global_model.render_depth_only(ray_bundle, source=self.config.selection_depth)
            self.rendered_models.add("global")
        points = surface_points(origins, ray_bundle.directions.reshape(-1, 3), global_outputs["depth"])
        scores = region_scores(points, centres, self.block_radii[block_ids].to(origins.device))
        usable = None
        if self.config.observed_blocks_only and self.block_observation is not None:
            usable = observed_at(self.block_observation[block_ids], points).to(scores.device)  # [K', R]
            scores = torch.where(usable, scores, torch.full_like(scores, float("inf")))
        return select_blocks(scores, limit if limit > 0 else num_blocks, usable), scores

    def _guard_transparent_blocks(
        self, weights: Tensor, block_outputs: List[Dict[str, Tensor]], ray_bundle: RayBundle, normals: bool
    ) -> Tuple[Tensor, Dict[str, Tensor]]:
        """``nearest-guarded``: the global model renders the rays whose block is transparent (and those
        no block gave); where it is opaque, the ray takes its render (:func:`guard_transparent`).

        Returns the ``[K', R]`` weights, zero on the guarded rays, and the global model's outputs (NaN
        on the rays it did not render)."""
        threshold = self.config.guard_accumulation
        block_accumulation = torch.stack([o["accumulation"] for o in block_outputs])  # [K', R, 1]
        suspects = transparent_pixels(weights, block_accumulation, threshold)  # [R]
        global_outputs = self._render_global_rays(ray_bundle, suspects, normals)
        if bool(suspects.any()):
            self.rendered_models.add("global")
        return guard_transparent(weights, block_accumulation, global_outputs["accumulation"], threshold), global_outputs

    def _render_block_rays(self, block: int, ray_bundle: RayBundle, rays: Tensor, normals: bool) -> Dict[str, Tensor]:
        """Block ``block``'s render of the rays where ``rays`` [R] is True; NaN on the others."""
        if not bool(rays.any()):
            return self._render_subset(self.blocks[str(block)], ray_bundle, rays, normals, block)  # NaN, no weights needed
        return self._render_subset(self.resident_block(block), ray_bundle, rays, normals, block)

    def _render_global_rays(self, ray_bundle: RayBundle, rays: Tensor, normals: bool) -> Dict[str, Tensor]:
        """The global model's render of the rays where ``rays`` [R] is True; NaN on the others."""
        return self._render_subset(self.global_model, ray_bundle, rays, normals, None)

    def _render_subset(self, model: ScalarModel, ray_bundle: RayBundle, rays: Tensor, normals: bool, block: Optional[int]) -> Dict[str, Tensor]:
        num_rays = rays.shape[0]
        keys = [*FUSED_KEYS, *(["normals"] if normals else [])]
        widths = {"rgb": 3, "normals": 3}
        device = ray_bundle.origins.device
        full = {k: torch.full((num_rays, widths.get(k, 1)), float("nan"), device=device) for k in keys}
        count = int(rays.sum())
        if block is not None:
            self.rays_rendered_by_block[block] = self.rays_rendered_by_block.get(block, 0) + count
        if count == 0:
            return full
        if count == num_rays:
            outputs = model.render_rays(ray_bundle.reshape((num_rays,)), normals=normals)
            return {k: outputs[k].reshape(num_rays, -1) for k in keys}
        outputs = model.render_rays(ray_bundle.reshape((num_rays,))[rays], normals=normals)
        for key in keys:
            full[key][rays] = outputs[key].reshape(count, -1).to(full[key].dtype)
        return full

    def _winner_colours(self, winner: Tensor) -> Tensor:
        """[R, 1] block indices (-1: global) -> [R, 3] viewer colours."""
        palette = torch.tensor([GLOBAL_COLOUR, *BLOCK_PALETTE.tolist()], dtype=torch.float32, device=winner.device)
        index = winner.reshape(-1).long()
        return palette[torch.where(index < 0, 0, 1 + index % len(BLOCK_PALETTE))]

    def _blocks_for(self, mode: ParsedFusionMode) -> List[int]:
        """Blocks that may render for ``mode`` (none for global-only or before any block has trained)."""
        if mode.kind == "global-only":
            return []
        started = self.started_block_ids()
        if mode.kind == "block":
            return [mode.block_index] if mode.block_index in started else []
        return started

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

