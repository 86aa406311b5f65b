"""SCALAR-NeRF pipeline: the global phase, then one phase per block, in one run (paper Alg. 1).

Training steps are laid out as phases: ``[0, G)`` trains the global model on all images, then
``[G + k B, G + (k + 1) B)`` trains block k's local model on block k's images. The phase is a
function of the step alone, so a run resumed from any checkpoint continues in the phase it was
killed in. Only the current phase's images are loaded (the global datamanager, or one block's).
"""

from __future__ import annotations

import gc
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Dict, List, Literal, Optional, Sequence, Tuple, Type

import torch
from nerfstudio.data.datamanagers.base_datamanager import DataManager
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.pipelines.base_pipeline import Pipeline, VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils.rich_utils import CONSOLE
from torch.cuda.amp.grad_scaler import GradScaler

from scalar_nerfstudio.blocks.capacity import BlockCapacity, LayoutScale, auto_num_blocks, block_capacity, layout_scale
from scalar_nerfstudio.blocks.split import BlockSplit, BlockSplitError, load_blocks_json, split_cameras
from scalar_nerfstudio.data.datamanager import ScalarDataManagerConfig, camera_centres
from scalar_nerfstudio.viewer import BlockOverlay, fusion_dropdown
from scalar_nerfstudio.models.scene_model import DecoderMode, ScalarSceneModel, ScalarSceneModelConfig, held_blocks


@dataclass(frozen=True)
class Phase:
    """A contiguous range of training steps that trains one model."""

    block: Optional[int]
    """None: the global model; k: block k's local model."""
    start_step: int
    num_steps: int

    @property
    def end_step(self) -> int:
        """First step after the phase."""
        return self.start_step + self.num_steps

    @property
    def name(self) -> str:
        return "global" if self.block is None else f"block {self.block}"


@dataclass
class ScalarPipelineConfig(VanillaPipelineConfig):
    """Global phase, then one phase per block (Alg. 1)."""

    _target: Type = field(default_factory=lambda: ScalarPipeline)
    datamanager: ScalarDataManagerConfig = field(default_factory=ScalarDataManagerConfig)
    """Training/eval data (a block phase uses a copy restricted to the block's images)."""
    model: ScalarSceneModelConfig = field(default_factory=ScalarSceneModelConfig)
    """Model hyper-parameters, shared by the global and the local models, and the fusion."""
    num_blocks: Optional[int] = None
    """K: blocks the training images are split into (KMeans on camera centres). None (default):
    chosen from the camera layout, ceil(R^2 / T) for a layout R training pixels across and tables of
    T rows (blocks/capacity.py); automatic K = 1 trains the global model only."""
    max_auto_blocks: int = 8
    """Upper bound of the automatic K."""
    auto_min_images_per_block: int = 6
    """The automatic K leaves at least this many training images per block."""
    block_log2_hashmap_size: Optional[int] = None
    """log2 table rows of every block model. None (default): per block, from its extent in pixels
    and its images' pixel count, within block_log2_hashmap_bounds."""
    block_log2_hashmap_bounds: Tuple[int, int] = (14, 19)
    """Bounds of the automatic block table size (log2 rows)."""
    block_max_resolution: Optional[int] = None
    """Finest grid resolution of every block model. None (default): twice the block's extent in
    pixels, within block_max_resolution_bounds."""
    block_max_resolution_bounds: Tuple[int, int] = (64, 2048)
    """Bounds of the automatic finest block resolution."""
    aabb_scale: Tuple[float, float, float] = (1.2, 1.2, 1.2)
    """s_AABB: per-axis scale of each block's camera AABB; images inside a scaled AABB join the
    block, so blocks overlap when > 1 (1.2 is the paper's best)."""
    min_overlap_images: int = 1
    """With aabb_scale > 1, a block whose scaled AABB takes in fewer images of other blocks is grown
    until it does (sparse layouts such as castle-P30's ring; 0: Alg. 1 verbatim)."""
    split_seed: int = 0
    """KMeans seed of the split."""
    min_images_per_block: int = 2
    """A split that leaves a block with fewer training images is refused (use fewer blocks)."""
    global_steps: int = 2000
    """Steps of the global phase."""
    block_steps: int = 1000
    """Steps of each block's phase."""
    decoder_mode: DecoderMode = "finetune"
    """Local decoders: finetune a copy of the global decoder (its lr: --optimizers.block-decoder), keep
    it frozen, or train a fresh one (independent, the paper's "w/o SD" ablation)."""
    train_blocks: bool = True
    """False: train the global phase only (blocks can then be trained with scalar-nerf-block)."""
    only_block: Optional[int] = None
    """Train this one block and nothing else (set by scalar-nerf-block)."""
    global_checkpoint: Optional[Path] = None
    """Checkpoint of a trained global run to start from (set by scalar-nerf-block)."""
    blocks_json: Optional[Path] = None
    """Use this split (a run's blocks.json) instead of computing one (set by scalar-nerf-block)."""

    def automatic_num_blocks(self, scale: LayoutScale, num_images: int) -> int:
        """The automatic K for a camera layout of ``num_images`` training images (blocks/capacity.py)."""
        return auto_num_blocks(scale, self.model.field.log2_hashmap_size, num_images, self.auto_min_images_per_block, self.max_auto_blocks)

    def phases(self, num_blocks: int, train_blocks: Optional[bool] = None) -> List[Phase]:
        """The training phases, in order, for a split into ``num_blocks`` blocks (``train_blocks``
        overrides the config's, e.g. False when the automatic K is 1)."""
        if self.only_block is not None:
            return [Phase(self.only_block, 0, self.block_steps)]
        phases = [Phase(None, 0, self.global_steps)]
        if self.train_blocks if train_blocks is None else train_blocks:
            phases += [Phase(k, self.global_steps + k * self.block_steps, self.block_steps) for k in range(num_blocks)]
        return phases


class ScalarPipeline(VanillaPipeline):
    """Datamanager per phase -> :class:`ScalarSceneModel` (global model, block models, fusion)."""

    config: ScalarPipelineConfig
    model: ScalarSceneModel

    def __init__(
        self,
        config: ScalarPipelineConfig,
        device: str,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler: Optional[GradScaler] = None,
    ) -> None:
        Pipeline.__init__(self)
        if world_size > 1:
            raise NotImplementedError("scalar-nerf trains on one device; use scalar-nerf-block to spread blocks over machines")
        self.config = config
        self.test_mode = test_mode
        self.world_size = world_size
        self.local_rank = local_rank
        self.datamanager: DataManager = config.datamanager.setup(device=device, test_mode=test_mode, world_size=1, local_rank=0)
        self.datamanager.to(device)
        parsed = self.datamanager.train_dataparser_outputs
        self.image_names: List[str] = _image_names(parsed.image_filenames, config.datamanager.data)
        self.layout_scale: LayoutScale = _layout_scale(parsed)
        self.auto_num_blocks: Optional[int] = None
        """The automatic K, when K was not given (and no split was)."""
        if config.num_blocks is None and config.blocks_json is None and config.only_block is None:
            self.auto_num_blocks = config.automatic_num_blocks(self.layout_scale, len(parsed.image_filenames))
        self.split: BlockSplit = self._block_split(camera_centres(parsed).double().numpy())
        # Automatic K = 1: one block would repeat the global model, so none is allocated or trained.
        single_model = self.auto_num_blocks == 1
        self.phases: List[Phase] = config.phases(self.split.num_blocks, train_blocks=False if single_model else None)
        block_ids = () if single_model else held_blocks(self.split, config.only_block)
        self.block_capacities: Dict[int, BlockCapacity] = self._block_capacities(parsed, block_ids)
        self._model = config.model.setup(
            scene_box=self.datamanager.train_dataset.scene_box,
            num_train_data=len(self.datamanager.train_dataset),
            metadata=self.datamanager.train_dataset.metadata,
            device=device,
            grad_scaler=grad_scaler,
            split=self.split,
            block_ids=block_ids,
            block_capacities=self.block_capacities,
            decoder_mode=config.decoder_mode,
        )
        self.model.to(device)
        if config.global_checkpoint is not None:
            self._load_global_model(Path(config.global_checkpoint), device)
        # Viewer: fusion dropdown and block overlay (found by nerfstudio's viewer as attributes).
        self.fusion_dropdown = fusion_dropdown(str(self.model.fusion_mode), self.split.num_blocks, self.model.set_fusion)
        self.block_overlay = BlockOverlay(self.split, camera_centres(parsed).numpy())
        self._block_datamanager: Optional[DataManager] = None
        self._block_datamanager_index: Optional[int] = None
        self._device = device

    # ---------------------------------------------------------------------------- set-up
    def _block_split(self, centres) -> BlockSplit:
        if self.config.blocks_json is not None:
            split, names = load_blocks_json(Path(self.config.blocks_json))
            if names != self.image_names:
                raise BlockSplitError(
                    f"{self.config.blocks_json} lists {len(names)} training images that differ from the "
                    f"{len(self.image_names)} parsed from {self.config.datamanager.data} (different scene or dataparser options)"
                )
            return split
        return split_cameras(
            centres,
            self.config.num_blocks if self.auto_num_blocks is None else self.auto_num_blocks,
            aabb_scale=self.config.aabb_scale,
            seed=self.config.split_seed,
            min_images_per_block=self.config.min_images_per_block,
            min_overlap_images=self.config.min_overlap_images,
        )

    def _block_capacities(self, parsed, block_ids: Sequence[int]) -> Dict[int, BlockCapacity]:
        """Table size and finest resolution of each held block (automatic unless set in the config)."""
        cameras = parsed.cameras
        pixels = (cameras.width * cameras.height).reshape(-1).tolist()
        capacities = {}
        for index in block_ids:
            block = self.split.blocks[index]
            extent = max(hi - lo for lo, hi in zip(block.aabb_min, block.aabb_max))
            auto = block_capacity(
                self.layout_scale, extent, int(sum(pixels[i] for i in block.image_indices)),
                self.config.block_log2_hashmap_bounds, self.config.block_max_resolution_bounds,
            )
            capacities[index] = BlockCapacity(
                log2_hashmap_size=auto.log2_hashmap_size if self.config.block_log2_hashmap_size is None else self.config.block_log2_hashmap_size,
                max_resolution=auto.max_resolution if self.config.block_max_resolution is None else self.config.block_max_resolution,
            )
        return capacities

    def _load_global_model(self, checkpoint: Path, device: str) -> None:
        """Load the global model's weights (only those) from another run's checkpoint."""
        state = torch.load(checkpoint, map_location=device, weights_only=True)["pipeline"]
        prefix = "_model.global_model."
        global_state = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
        if not global_state:
            raise ValueError(f"{checkpoint} holds no global model (is it a scalar-nerf checkpoint?)")
        self.model.global_model.load_state_dict(global_state, strict=True)
        CONSOLE.log(f"global model loaded from {checkpoint}")

    @property
    def total_steps(self) -> int:
        """Steps of all phases together."""
        return self.phases[-1].end_step

    def phase_at(self, step: int) -> Phase:
        """The phase that trains at ``step`` (the last phase for steps past the end)."""
        for phase in self.phases:
            if step < phase.end_step:
                return phase
        return self.phases[-1]

    # --------------------------------------------------------------------------- training
    def _enter_phase(self, step: int) -> Phase:
        """The phase at ``step``; a block's phase starts (its decoder is copied) on its first step."""
        phase = self.phase_at(step)
        if phase.block is not None:
            self.model.begin_block(phase.block)
        return phase

    def _train_datamanager(self, phase: Phase) -> DataManager:
        """The global datamanager, or (built once per phase) one over the block's images only."""
        if phase.block is None:
            return self.datamanager
        if self._block_datamanager_index != phase.block:
            self._block_datamanager = None
            gc.collect()
            block = self.split.blocks[phase.block]
            CONSOLE.log(f"phase {phase.name}: loading its {len(block.image_indices)} training images")
            config = replace(self.config.datamanager, image_subset=tuple(block.image_indices))
            self._block_datamanager = config.setup(device=self._device, test_mode="val", world_size=1, local_rank=0)
            self._block_datamanager.to(self._device)
            self._block_datamanager_index = phase.block
        assert self._block_datamanager is not None
        return self._block_datamanager

    def get_train_loss_dict(self, step: int):
        """One training batch of the phase at ``step``, through that phase's model."""
        phase = self._enter_phase(step)
        ray_bundle, batch = self._train_datamanager(phase).next_train(step)
        model = self.model.phase_model(phase.block)
        outputs = model(ray_bundle)
        metrics_dict = model.get_metrics_dict(outputs, batch)
        loss_dict = model.get_loss_dict(outputs, batch, metrics_dict)
        metrics_dict["phase"] = torch.tensor(-1.0 if phase.block is None else float(phase.block))
        return outputs, loss_dict, metrics_dict

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        """Before each step: update the occupancy grid of the phase's model (at its phase-local step)."""
        return [
            TrainingCallback(
                where_to_run=[TrainingCallbackLocation.BEFORE_TRAIN_ITERATION],
                update_every_num_iters=1,
                func=self._before_train_step,
            )
        ]

    def _before_train_step(self, step: int) -> None:
        phase = self._enter_phase(step)
        self.model.phase_model(phase.block)._update_occupancy(step - phase.start_step)

    def param_group_phases(self) -> dict:
        """For each optimiser parameter group: (template key in ``optimizers``, its phase)."""
        phase_of_block = {phase.block: phase for phase in self.phases}
        templates = {}
        for group in self.model.get_param_groups():
            if group.startswith("block"):
                prefix, name = group.split(".", 1)
                block = int(prefix[len("block"):])
                template = "block_decoder" if name == "decoder" and self.config.decoder_mode == "finetune" else name
                templates[group] = (template, phase_of_block.get(block))
            else:
                templates[group] = (group, phase_of_block.get(None))
        return templates


def _layout_scale(parsed) -> LayoutScale:
    """:class:`LayoutScale` of the parsed training cameras (optical axis: -z of the OpenGL pose)."""
    poses = parsed.cameras.camera_to_worlds.double()
    return layout_scale(poses[:, :3, 3].numpy(), (-poses[:, :3, 2]).numpy(), parsed.cameras.fx.reshape(-1).double().numpy())


def _image_names(filenames: List[Path], data: Optional[Path]) -> List[str]:
    """Training image names as stored in blocks.json: paths relative to the scene folder when possible."""
    root = None
    if data is not None:
        root = Path(data).resolve()
        root = root.parent if root.suffix == ".json" else root
    names = []
    for path in filenames:
        resolved = Path(path).resolve()
        names.append(str(resolved.relative_to(root)) if root is not None and resolved.is_relative_to(root) else resolved.name)
    return names
