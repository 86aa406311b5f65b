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
from typing import Any, Dict, List, Literal, Optional, Tuple, Type

import torch
import tyro
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.utils.rich_utils import CONSOLE
from torch.cuda.amp.grad_scaler import GradScaler

from scalar_nerfstudio.blocks.capacity import BlockCapacity, LayoutScale, auto_num_blocks
from scalar_nerfstudio.blocks.length import LengthSettings, TrainingLength, parse_duration, plan_length
from scalar_nerfstudio.blocks.observation import split_observation
from scalar_nerfstudio.blocks.plan import BlockPlan, PlanSettings, load_plan, plan_blocks, recorded_scene_bound
from scalar_nerfstudio.blocks.split import BlockSplit, BlockSplitError, load_blocks_json
from scalar_nerfstudio.data.datamanager import (
    ScalarDataManager,
    ScalarDataManagerConfig,
    camera_centres,
    camera_layout,
    training_image_names,
)
from scalar_nerfstudio.data.depth import scene_radius_logged
from scalar_nerfstudio.engine.contract import Phase
from scalar_nerfstudio.engine.eval_progress import EvalProgress
from scalar_nerfstudio.engine.process_settings import apply_process_settings
from scalar_nerfstudio.models.scene_model import BlockInit, DecoderMode, ScalarSceneModel, ScalarSceneModelConfig
from scalar_nerfstudio.pipeline_text import format_eval_metrics, format_plan_report
from scalar_nerfstudio.runs import RUN_SCHEMA_VERSION, block_models_dir
from scalar_nerfstudio.seam.pipeline import PipelineBase
from scalar_nerfstudio.viewer import BlockOverlay, CoarseFirstRender, FinishedRunPanel, fusion_dropdown

LrSchedule = Literal["restart", "per-phase"]


@dataclass
class ScalarPipelineConfig(VanillaPipelineConfig):
    """Global phase, then one phase per block (Alg. 1)."""

    _target: Type = field(default_factory=lambda: ScalarPipeline)
    datamanager: ScalarDataManagerConfig = field(default_factory=ScalarDataManagerConfig)
    """Training/eval data (a block phase uses a copy restricted to the block's images)."""
    model: ScalarSceneModelConfig = field(default_factory=ScalarSceneModelConfig)
    """Model hyper-parameters, shared by the global and the local models, and the fusion."""
    num_blocks: Optional[int] = None
    """K, the number of blocks the training images are split into (KMeans on camera centres). None:
    automatic, ceil(R^2 / T) for a layout R training pixels across and tables of T rows; 1: one model."""
    max_auto_blocks: int = 64
    """Upper bound of the automatic K (blocks): a capture of thousands of photos may call for dozens."""
    auto_min_images_per_block: int = 6
    """The automatic K leaves at least this many training images per block (images)."""
    block_log2_hashmap_size: Optional[int] = None
    """log2 table rows of every block model. None: per block, from its extent in pixels and its
    images' pixel count, within block-log2-hashmap-bounds."""
    block_log2_hashmap_bounds: Tuple[int, int] = (14, 19)
    """Bounds LOW HIGH of the automatic block table size (log2 rows)."""
    block_max_resolution: Optional[int] = None
    """Finest grid resolution of every block model (cells per axis). None: per block, twice its
    extent in pixels, within block-max-resolution-bounds."""
    block_max_resolution_bounds: Tuple[int, int] = (64, 2048)
    """Bounds LOW HIGH of the automatic finest block resolution (cells per axis)."""
    aabb_scale: Tuple[float, float, float] = (1.2, 1.2, 1.2)
    """s_AABB: per-axis scale (x y z, >= 1) of each block's camera box; images inside a scaled box
    join the block, so blocks overlap when > 1."""
    min_overlap_images: int = 1
    """With aabb-scale > 1, a block whose scaled box takes in fewer images of other blocks is grown
    until it does (images; 0: never grown)."""
    split_seed: int = 0
    """KMeans seed of the split."""
    min_images_per_block: int = 2
    """A split that leaves a block with fewer training images is refused (images)."""
    global_steps: Optional[int] = None
    """Steps of the global phase. None: planned, from the capture (about rays-per-pixel rays for every training
    pixel, at least 2000 steps) or, with time-budget, to fit the budget."""
    block_steps: Optional[int] = None
    """Steps of each block's phase. None: planned, from the capture (about block-rays-per-pixel rays for every
    pixel of a block's images, at least 1000 steps) or, with time-budget, to fit the budget."""
    time_budget: Optional[str] = None
    """Wall-clock budget of the run's training (loading the scene is not counted), like 90s, 45m, 2h or 1h30m: the
    steps not given are planned to fit it at the pace measured in the run's first steps, and again as it trains.
    None: the steps are planned from the capture."""
    rays_per_pixel: float = 0.5
    """Without a budget, the global phase trains this many rays per training pixel (steps = this x pixels / rays
    per batch, 2000 to 200000)."""
    block_rays_per_pixel: float = 1.0
    """Without a budget, a block's phase trains this many rays per pixel of its images (1000 to 200000 steps)."""
    block_workers: int = 1
    """Blocks that will train at once (scalar-nerf-train-blocks on several processes or machines): a time budget
    then gives each block this many times the share it has on one machine."""
    decoder_mode: DecoderMode = "finetune"
    """Local decoders: finetune a copy of the global decoder (its rate: --optimizers.block-decoder),
    keep it frozen, or train a fresh one (independent)."""
    block_init: BlockInit = "global"
    """How a block's model starts: global: a copy of the trained global model; fresh: an empty table
    of its own over the block's region; fitted: like fresh, first fitted to the global model's encoding."""
    lr_schedule: LrSchedule = "restart"
    """restart: the global model holds its learning rates after its warm-up when blocks follow, each
    block warms up and decays over its phase; per-phase: every phase warms up and decays over its steps."""
    one_model_restart: float = 0.5
    """A run of one model (K = 1, lr-schedule restart) holds its rates for this share of its steps
    (0 to 1), then restarts them at the block templates' rates and decays; 0: one decay over the run."""
    scene_radius_from_depth: bool = True
    """A new run on a scene with depth images, without --pipeline.model.scene-radius, ends its rays at
    a sphere fitted to them (radius recorded in the run's blocks.json); False: rays run to the far plane."""
    train_blocks: bool = True
    """False: train the global phase only (blocks can then be trained with scalar-nerf-block)."""
    only_block: Optional[int] = None
    """Train this one block and nothing else (set by scalar-nerf-block)."""
    global_checkpoint: Optional[Path] = None
    """Checkpoint of a trained global run to start from (set by scalar-nerf-block)."""
    blocks_json: Optional[Path] = None
    """Use this split (a run's blocks.json) instead of computing one (set by scalar-nerf-block)."""
    run_plan: Optional[Path] = None
    """The run's own block plan (its blocks.json), recorded when training starts; every later load of
    the run reads K, the split and the block capacities from it."""
    scalar_schema_version: tyro.conf.Suppress[int] = RUN_SCHEMA_VERSION
    """Version of this config's layout in config.yml (runs.py: an older run is upgraded on load)."""

    def setup(self, **kwargs: Any) -> Any:
        """The pipeline (nerfstudio passes ``device``, ``test_mode`` ...), built after the process-wide
        settings for its device (``engine/process_settings.py``): every ns- verb loads a run through here."""
        apply_process_settings(kwargs.get("device", "cpu"))
        return super().setup(**kwargs)

    def plan_settings(self) -> PlanSettings:
        """The options a block plan is decided from (blocks/plan.py)."""
        return PlanSettings(
            num_blocks=self.num_blocks, log2_hashmap_size=self.model.field.log2_hashmap_size,
            max_auto_blocks=self.max_auto_blocks, auto_min_images_per_block=self.auto_min_images_per_block,
            aabb_scale=(*self.aabb_scale,), split_seed=self.split_seed, min_images_per_block=self.min_images_per_block,
            min_overlap_images=self.min_overlap_images, only_block=self.only_block,
            block_log2_hashmap_size=self.block_log2_hashmap_size, block_log2_hashmap_bounds=(*self.block_log2_hashmap_bounds,),
            block_max_resolution=self.block_max_resolution, block_max_resolution_bounds=(*self.block_max_resolution_bounds,),
            global_max_resolution=self.model.field.max_resolution if self.block_init == "global" else None,
        )

    def automatic_num_blocks(self, scale: LayoutScale, num_images: int) -> int:
        """The automatic K for a camera layout of ``num_images`` training images (blocks/capacity.py)."""
        return auto_num_blocks(scale, log2_hashmap_size=self.model.field.log2_hashmap_size, num_images=num_images,
                               min_images_per_block=self.auto_min_images_per_block, max_blocks=self.max_auto_blocks)

    def length_settings(self) -> LengthSettings:
        """The options a run's length is planned from (blocks/length.py); a scalar-nerf-block run plans its one block."""
        return LengthSettings(
            global_steps=0 if self.only_block is not None else self.global_steps, block_steps=self.block_steps,
            time_budget_s=None if self.time_budget is None else parse_duration(self.time_budget),
            rays_per_batch=self.datamanager.train_num_rays_per_batch, rays_per_pixel=self.rays_per_pixel,
            block_rays_per_pixel=self.block_rays_per_pixel, block_workers=self.block_workers,
        )

    def phases(self, num_blocks: int, length: TrainingLength, train_blocks: Optional[bool] = None) -> List[Phase]:
        """The training phases, in order, for a split into ``num_blocks`` blocks trained for ``length``
        (``train_blocks`` overrides the config's, e.g. False when the automatic K is 1)."""
        if self.only_block is not None:
            return [Phase(self.only_block, 0, length.block_steps)]
        phases = [Phase(None, 0, length.global_steps)]
        if self.train_blocks if train_blocks is None else train_blocks:
            for k in range(num_blocks):
                phases.append(Phase(k, phases[-1].end_step, length.steps_of_block(k)))
        return phases


class ScalarPipeline(PipelineBase):
    """Datamanager per phase -> :class:`ScalarSceneModel` (global model, block models, fusion)."""

    config: ScalarPipelineConfig
    datamanager: ScalarDataManager
    model: ScalarSceneModel

    def __init__(
        self,
        config: ScalarPipelineConfig,
        device: str,
        *,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler: Optional[GradScaler] = None,
    ) -> None:
        super().__init__(config, test_mode=test_mode, world_size=world_size, local_rank=local_rank)
        if world_size > 1:
            raise NotImplementedError("scalar-nerf trains on one device; use scalar-nerf-block to spread blocks over machines")
        self.datamanager = config.datamanager.setup(device=device, test_mode=test_mode, world_size=1, local_rank=0)
        self.datamanager.to(device)
        parsed = self.datamanager.train_dataparser_outputs
        self.plan: BlockPlan = self._block_plan(parsed)
        block_ids = self.plan.held_blocks
        self.phases: List[Phase] = self._phases()
        self.scene_radius: Optional[float] = self._scene_radius(parsed)
        """Rays end where they leave the sphere of this radius around the origin (None: unbounded)."""
        self.plan = self.plan.bounded(self.scene_radius)  # recorded in blocks.json
        model = config.model.setup(
            scene_box=self.datamanager.train_dataset.scene_box,
            num_train_data=len(self.datamanager.train_dataset),
            metadata=self.datamanager.train_dataset.metadata,
            device=device,
            grad_scaler=grad_scaler,
            split=self.split,
            block_ids=block_ids,
            block_capacities=self.plan.capacities,
            decoder_mode=config.decoder_mode,
            block_init=config.block_init,
            block_observation=split_observation(parsed.cameras, [block.image_indices for block in self.split.blocks]),
            scene_radius=self.scene_radius,
        )
        self.set_model(model)
        self.model.to(device)
        if config.run_plan is not None:  # a run that has started: its block_models/ are beside its plan
            self.attach_run_dir(Path(config.run_plan).parent)
        if config.global_checkpoint is not None:
            self._load_global_model(Path(config.global_checkpoint), device)
        # Viewer: fusion dropdown, block overlay, coarse-first renders, the panel of a finished run (found by
        # nerfstudio's viewer as attributes).
        self.fusion_dropdown = fusion_dropdown(str(self.model.fusion_mode), self.split.num_blocks, self.model.set_fusion)
        self.block_overlay = BlockOverlay(self.split, camera_centres(parsed).numpy())
        self.coarse_first_render = CoarseFirstRender()
        self.finished_run_panel = FinishedRunPanel()
        self._block_datamanager: Optional[ScalarDataManager] = None
        self._block_datamanager_index: Optional[int] = None
        self._device = device

    # ---------------------------------------------------------------------------- set-up
    def _block_plan(self, parsed) -> BlockPlan:
        """The run's own plan when it has one (``run_plan``), else one decided from the parsed cameras
        (its length planned from the capture: provisional when a time budget waits for the pace)."""
        names = training_image_names(parsed.image_filenames, self.config.datamanager.data)
        if self.config.run_plan is not None:
            plan = load_plan(Path(self.config.run_plan))
            if len(plan.image_names) != len(names):
                raise BlockSplitError(
                    f"{self.config.run_plan} was planned for {len(plan.image_names)} training images, but "
                    f"{len(names)} are parsed from {self.config.datamanager.data} (different scene or dataparser options)"
                )
            if plan.length is None:  # a run from before lengths were planned: its config.yml has the steps
                plan = replace(plan, length=TrainingLength(int(self.config.global_steps or 0), int(self.config.block_steps or 0), "given"))
            return plan
        given = None
        if self.config.blocks_json is not None:
            given, given_names = load_blocks_json(Path(self.config.blocks_json))
            if given_names != names:
                raise BlockSplitError(
                    f"{self.config.blocks_json} lists {len(given_names)} training images that differ from the "
                    f"{len(names)} parsed from {self.config.datamanager.data} (different scene or dataparser options)"
                )
        layout = camera_layout(parsed)
        plan = plan_blocks(layout.centres, layout.directions, layout.focal_px, image_pixels=layout.image_pixels, image_names=names,
                           settings=self.config.plan_settings(), given_split=given)
        pixels = [int(p) for p in layout.image_pixels]
        blocks = [plan.split.blocks[k] for k in plan.held_blocks] if not plan.single_model else []
        block_pixels = [sum(pixels[i] for i in block.image_indices) for block in blocks]
        return replace(plan, length=plan_length(self.config.length_settings(), train_pixels=sum(pixels), block_pixels=block_pixels))

    def _scene_radius(self, parsed) -> Optional[float]:
        """The radius rays end at: ``--pipeline.model.scene-radius`` (or a version-2 config.yml's fitted one); a
        started run's, in its plan; a ``scalar-nerf-block`` run's global run's; else one fitted to the depth images."""
        config = self.config
        if config.model.scene_radius is not None:
            return config.model.scene_radius
        if config.run_plan is not None:  # a plan from before bounds were recorded there: none (as before)
            return None if self.plan.scene_bound is None else self.plan.scene_bound.radius
        given = recorded_scene_bound(Path(config.blocks_json)) if config.blocks_json is not None else None
        if given is not None:
            return given.radius
        return scene_radius_logged(parsed) if config.scene_radius_from_depth else None

    def _phases(self) -> List[Phase]:
        assert self.plan.length is not None
        return self.config.phases(self.split.num_blocks, self.plan.length, train_blocks=False if self.plan.single_model else None)

    @property
    def length(self) -> TrainingLength:
        """How long the run trains (the plan's; a time budget's is provisional until the trainer measures the pace)."""
        assert self.plan.length is not None
        return self.plan.length

    def set_length(self, length: TrainingLength) -> None:
        """Train for ``length`` from now on (a time budget's plan, measured): the phases follow it. Only
        phases that have not started may change their start (the trainer re-plans the blocks before the
        first of them)."""
        self.plan = replace(self.plan, length=length)
        self.phases = self._phases()

    def length_settings(self) -> LengthSettings:
        """The options the run's length is planned from."""
        return self.config.length_settings()

    @property
    def num_blocks_following(self) -> int:
        """Blocks that train after the global model, in this run or in scalar-nerf-block runs (a time budget
        plans for them); a scalar-nerf-block run: its one block."""
        if self.config.only_block is not None:
            return 1
        return len(self.plan.held_blocks) if self._blocks_follow_global_model() else 0

    @property
    def split(self) -> BlockSplit:
        """The blocks of the training images."""
        return self.plan.split

    @property
    def image_names(self) -> List[str]:
        """Training image names, as stored in blocks.json."""
        return list(self.plan.image_names)

    @property
    def layout_scale(self) -> LayoutScale:
        """How large the camera layout looks at the training resolution."""
        return self.plan.layout

    @property
    def auto_num_blocks(self) -> Optional[int]:
        """The automatic K, when K was not given (and no split was)."""
        return self.plan.auto_num_blocks

    @property
    def block_capacities(self) -> Dict[int, BlockCapacity]:
        """Table size and finest resolution of each held block."""
        return self.plan.capacities

    def _load_global_model(self, checkpoint: Path, device: str) -> None:
        """Load the global model's weights (only those) from another run's checkpoint."""
        state = torch.load(checkpoint, map_location=device, weights_only=True)["pipeline"]
        global_state = ScalarSceneModel.global_state(state)
        if not global_state:
            raise ValueError(f"{checkpoint} holds no global model (is it a scalar-nerf checkpoint?)")
        self.model.global_model.load_state_dict(global_state, strict=True)
        poses = ScalarSceneModel.pose_state(state)
        if self.model.pose_refinement.enabled != bool(poses):
            raise ValueError(f"{checkpoint} {'holds' if poses else 'holds no'} pose corrections, and this run "
                             f"{'learns' if self.model.pose_refinement.enabled else 'learns none'} "
                             "(--pipeline.model.camera-optimizer.mode must be the global run's)")
        self.model.pose_refinement.load_state_dict(poses, strict=True)
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
            fit = self.model.begin_block(phase.block)
            if fit is not None:
                CONSOLE.log(f"phase {phase.name}: table fitted to the global model's encoding in {fit.steps} steps "
                            f"(mean squared error {fit.initial_error:.3g} -> {fit.final_error:.3g})")
        return phase

    def _train_datamanager(self, phase: Phase) -> ScalarDataManager:
        """The global datamanager, or (built once per phase) one over the block's images only."""
        if phase.block is None:
            return self.datamanager
        if self._block_datamanager_index != phase.block:
            self._release_block_datamanager()  # usually done already by finish_phase
            block = self.split.blocks[phase.block]
            CONSOLE.log(f"phase {phase.name}: loading its {len(block.image_indices)} training images")
            config = replace(self.config.datamanager, image_subset=tuple(block.image_indices))
            datamanager = config.setup(device=self._device, test_mode="val", world_size=1, local_rank=0)
            self._block_datamanager = datamanager
            datamanager.to(self._device)
            self._block_datamanager_index = phase.block
        assert self._block_datamanager is not None
        return self._block_datamanager

    def attach_run_dir(self, run_dir: Path) -> None:
        """Keep finished blocks in ``run_dir``'s block_models/ folder and load them from there."""
        self.model.attach_block_store(block_models_dir(run_dir))

    def end_training_of(self, phase: Phase) -> None:
        """The last step of ``phase`` has run: its model finishes its training (its occupancy grid is
        re-estimated from the final field, :meth:`ScalarModel.finish_training`). Called for every
        phase, the run's last one included, before :meth:`finish_phase` and the checkpoint."""
        self.model.phase_model(phase.block).finish_training()

    def finish_phase(self, phase: Phase) -> None:
        """A phase has ended: a block's weights go to their file and leave memory, with its images; the global
        model's training images leave memory when its phase ends (the blocks load their own)."""
        if phase.block is None:
            self.datamanager.release_train_images()
            return
        path = self.model.store_block(phase.block)
        CONSOLE.log(f"phase {phase.name} done: its model saved to {path} and released from memory")
        if self._block_datamanager_index == phase.block:
            self._release_block_datamanager()

    def _release_block_datamanager(self) -> None:
        """Drop the block datamanager, if one is held, with its images, and collect at once (a
        full collection per block change, so that nothing of them outlives it when the next block
        loads its own)."""
        if self._block_datamanager is None:
            return
        self._block_datamanager, self._block_datamanager_index = None, None
        gc.collect()

    def get_train_loss_dict(self, step: int):
        """One training batch of the phase at ``step`` (its rays moved by the pose corrections), through that
        phase's model."""
        phase = self._enter_phase(step)
        datamanager = self._train_datamanager(phase)
        ray_bundle, batch = datamanager.next_train(step)
        assert isinstance(ray_bundle, RayBundle), "scalar-nerf trains on ray batches (a pixel-sampling datamanager)"
        self.model.refine_training_rays(ray_bundle, phase.block)
        model = self.model.phase_model(phase.block)
        outputs = model(ray_bundle)
        datamanager.record_train_errors(batch, outputs["rgb"])
        metrics_dict = model.get_metrics_dict(outputs, batch)
        loss_dict = model.get_loss_dict(outputs, batch, metrics_dict)
        if phase.block is None:
            self.model.add_pose_terms(loss_dict, metrics_dict)
        metrics_dict["phase"] = torch.tensor(-1.0 if phase.block is None else float(phase.block))
        return outputs, loss_dict, metrics_dict

    def get_eval_loss_dict(self, step: int):
        """nerfstudio's eval ray batch during training, rendered without the ``normals`` output (its loss
        and metrics do not use it; ray batches outside training otherwise get it, for ``ns-export``)."""
        with self.model.rendering_normals("never"):
            return super().get_eval_loss_dict(step)

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        """Before each step: update the occupancy grid of the phase's model (at its phase-local step)."""
        return [TrainingCallback(where_to_run=[TrainingCallbackLocation.BEFORE_TRAIN_ITERATION],
                                 update_every_num_iters=1, func=self._before_train_step)]

    def _before_train_step(self, step: int) -> None:
        phase = self._enter_phase(step)
        self.model.phase_model(phase.block).update_occupancy(step - phase.start_step)

    def plan_report(self) -> str:
        """The split, the automatic K, the block capacities and the phases, for the training log."""
        return format_plan_report(self.plan, self.phases, log2_hashmap_size=self.config.model.field.log2_hashmap_size,
                                  block_init=self.config.block_init, device_type=torch.device(self.device).type)

    def get_average_eval_image_metrics(
        self, step: Optional[int] = None, output_path: Optional[Path] = None, get_std: bool = False
    ) -> Dict[str, float]:
        """nerfstudio's average over the eval images, with a line per image (images done, time left: nerfstudio's
        bar has neither), and the average printed (``ns-eval`` itself only says where it saved them)."""
        loader = EvalProgress(self.datamanager.fixed_indices_eval_dataloader, report=CONSOLE.print)
        metrics = self.get_average_image_metrics(loader, "eval", step=step, output_path=output_path, get_std=get_std)
        CONSOLE.print(format_eval_metrics(metrics, str(self.model.fusion_mode)))
        return metrics

    def param_group_phases(self) -> Dict[str, Tuple[str, Optional[Phase]]]:
        """For each optimiser parameter group: (template key in ``optimizers``, the phase it trains in).

        A block's groups use the ``block_encoder`` (its table) and ``appearance`` templates, and
        ``block_decoder`` for a fine-tuned decoder copy."""
        phase_of_block = {phase.block: phase for phase in self.phases}
        templates = {}
        for group, _ in self.model.param_groups_by_model():
            template = group.part
            if group.block is not None and group.part == "encoder":
                template = "block_encoder"
            elif group.block is not None and group.part == "decoder" and self.config.decoder_mode == "finetune":
                template = "block_decoder"
            templates[group.name] = (template, phase_of_block.get(group.block))
        return templates

    @property
    def holds_global_learning_rate(self) -> bool:
        """With ``lr_schedule`` restart, the global model's groups hold their rate after the warm-up
        when blocks follow it, in this run or in scalar-nerf-block runs (K > 1, or K = 1 with
        train_blocks); each block decays over its phase. One model (automatic K = 1, or K = 1 without
        blocks) does not hold to its end: see :attr:`global_restart_fraction`."""
        return self.config.lr_schedule == "restart" and self._blocks_follow_global_model()

    @property
    def global_restart_fraction(self) -> float:
        """Share of the global model's steps after which its rates restart at the block templates'
        (:attr:`ScalarPipelineConfig.one_model_restart`): only in a run of one model, with
        ``lr_schedule`` restart; 0 otherwise (no restart)."""
        if self.config.lr_schedule != "restart" or self._blocks_follow_global_model():
            return 0.0
        return float(self.config.one_model_restart)

    def _blocks_follow_global_model(self) -> bool:
        """Whether blocks train from the global model, in this run or in scalar-nerf-block runs."""
        return not self.plan.single_model and (self.split.num_blocks > 1 or self.config.train_blocks)
