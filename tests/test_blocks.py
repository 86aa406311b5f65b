"""Blocks: the split in the run, phases, decoder modes, resume inside a block phase, what
``scalar-nerf-block`` checks, and assembling block runs (block processes in parallel, assembled and
fused, are tested end to end in test_train_blocks.py and test_scale.py)."""

from __future__ import annotations

import copy
import json
import math
import sys
from pathlib import Path
from typing import Dict, List

import numpy as np
import pytest
import torch
import yaml
from conftest import BLOCK_STEPS, NUM_BLOCKS, tiny_trainer, trained_block_tensors
from fake_runs import fake_run
from nerfstudio.cameras.rays import RayBundle
from prerequisites import CASTLE, requires_castle

from scalar_nerfstudio.blocks.split import load_blocks_json, split_cameras
from scalar_nerfstudio.method_configs import scalar_nerf
from scalar_nerfstudio.runs import RUN_SCHEMA_VERSION, latest_checkpoint_step


def _pipeline_state(run: Path) -> Dict[str, torch.Tensor]:
    step = latest_checkpoint_step(run / "nerfstudio_models")
    assert step is not None
    return torch.load(run / "nerfstudio_models" / f"step-{step:09d}.ckpt", map_location="cpu", weights_only=True)["pipeline"]


def _decoder(state: Dict[str, torch.Tensor], model: str) -> Dict[str, torch.Tensor]:
    prefix = f"_model.{model}.field.decoder."
    return {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}


# ------------------------------------------------------------------------------ the split


@requires_castle
@pytest.mark.parametrize("num_blocks", [2, 3, 4])
def test_castle_split_in_the_training_frame(num_blocks: int) -> None:
    """In the frame the models train in: full cover, overlap exactly when s > 1, deterministic."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    parser = NerfstudioDataParserConfig(data=CASTLE, eval_mode="interval", eval_interval=8).setup()
    centres = parser.get_dataparser_outputs("train").cameras.camera_to_worlds[:, :3, 3].double().numpy()
    defaults = scalar_nerf.config.pipeline
    shared = {}
    for scale in (1.0, 1.2):
        split = split_cameras(centres, num_blocks, aabb_scale=(scale,) * 3, seed=defaults.split_seed,
                              min_images_per_block=defaults.min_images_per_block, min_overlap_images=defaults.min_overlap_images)
        counts = np.bincount(np.concatenate([b.image_indices for b in split.blocks]), minlength=len(centres))
        assert split.num_blocks == num_blocks and (counts >= 1).all()
        shared[scale] = int((counts > 1).sum())
        again = split_cameras(centres, num_blocks, aabb_scale=(scale,) * 3, seed=defaults.split_seed,
                              min_images_per_block=defaults.min_images_per_block, min_overlap_images=defaults.min_overlap_images)
        assert again == split
    assert shared[1.0] == 0 and shared[1.2] > 0


# ------------------------------------------------------------------------ one full run


@pytest.mark.slow
def test_full_run_writes_split_and_trains_every_block(full_run: Path, scene: Path) -> None:
    split, names = load_blocks_json(full_run / "blocks.json")
    assert split.num_blocks == NUM_BLOCKS
    assert sorted(set(i for b in split.blocks for i in b.image_indices)) == list(range(len(names)))
    assert all(name.startswith("images/") and (scene / name).is_file() for name in names)
    state = _pipeline_state(full_run)
    assert state["_model.blocks_started"].tolist() == [True] * NUM_BLOCKS
    global_decoder = _decoder(state, "global_model")
    # the finished block 0 lives in its own file, the last one (block 1) in the checkpoint
    assert state["_model.blocks.0.field.encoder.table"].numel() == 0 and (full_run / "block_models" / "block-0000.ckpt").is_file()
    assert state["_model.blocks.1.field.encoder.table"].numel() > 0 and not (full_run / "block_models" / "block-0001.ckpt").exists()
    for block in range(NUM_BLOCKS):
        tensors = trained_block_tensors(full_run, block)
        block_decoder = {k[len("field.decoder."):]: v for k, v in tensors.items() if k.startswith("field.decoder.")}
        # fine-tuned from the global decoder at lr 5e-5: moved, but only a little
        difference = max(float((block_decoder[k] - global_decoder[k]).abs().max()) for k in global_decoder)
        assert 0.0 < difference < 0.05
        assert tensors["field.encoder.table"].shape != state["_model.global_model.field.encoder.table"].shape or not torch.equal(
            tensors["field.encoder.table"], state["_model.global_model.field.encoder.table"])


# ------------------------------------------------------------- in-process runs (decoder modes)


def _trainer(scene: Path, output_dir: Path, configure=None, **pipeline: object):
    """A scalar-nerf trainer on ``scene`` with the TINY settings, set up but not trained."""
    return tiny_trainer(scene, output_dir, configure=configure, **pipeline)


def _decoder_params(model) -> List[torch.Tensor]:
    return [p.detach().clone() for p in model.field.decoder.parameters()]


@pytest.mark.slow  # trains
@pytest.mark.parametrize("mode", ["frozen", "finetune", "independent"])
def test_decoder_modes(scene: Path, tmp_path: Path, mode: str, monkeypatch: pytest.MonkeyPatch) -> None:
    trainer = _trainer(scene, tmp_path, decoder_mode=mode)
    model = trainer.pipeline.model
    started: Dict[str, List[torch.Tensor]] = {}
    begin_block = model.begin_block

    def begin_and_record(index: int) -> None:  # the decoder block 0 starts its phase with
        first = not bool(model.blocks_started[index])
        begin_block(index)
        if first and index == 0:
            started["fresh"] = _decoder_params(model.phase_model(0))

    monkeypatch.setattr(model, "begin_block", begin_and_record)
    trainer.train()
    fresh = started["fresh"]
    global_decoder = _decoder_params(model.global_model)
    block = model.resident_block(0)  # loaded back from its file
    trained = _decoder_params(block)
    if mode == "frozen":
        assert all(torch.equal(a, b) for a, b in zip(trained, global_decoder)), "a frozen decoder stays the global one"
        assert all(not p.requires_grad for p in block.field.decoder.parameters())
    elif mode == "finetune":
        assert not all(torch.equal(a, b) for a, b in zip(trained, global_decoder)), "a fine-tuned decoder moves"
        assert max(float((a - b).abs().max()) for a, b in zip(trained, global_decoder)) < 0.05
    else:
        assert not all(torch.equal(a, b) for a, b in zip(fresh, global_decoder)), "an independent decoder starts fresh"
        assert max(float((a - b).abs().max()) for a, b in zip(trained, fresh)) > 0.0


def test_block_starts_from_global_decoder_and_only_its_images(scene: Path, tmp_path: Path) -> None:
    trainer = _trainer(scene, tmp_path, decoder_mode="finetune")
    pipeline = trainer.pipeline
    pipeline.model.begin_block(1)
    global_decoder = _decoder_params(pipeline.model.global_model)
    assert all(torch.equal(a, b) for a, b in zip(_decoder_params(pipeline.model.phase_model(1)), global_decoder))
    phase = pipeline.phase_at(pipeline.phases[2].start_step)
    assert phase.block == 1
    datamanager = pipeline._train_datamanager(phase)
    expected = [pipeline.datamanager.train_dataparser_outputs.image_filenames[i] for i in pipeline.split.blocks[1].image_indices]
    assert list(datamanager.train_dataset.image_filenames) == expected
    assert len(datamanager.train_dataset) < len(pipeline.datamanager.train_dataset)


@pytest.mark.slow  # trains
def test_run_stopped_in_a_block_phase_resumes_there(scene: Path, tmp_path: Path) -> None:
    stop_at = 20 + 8 + 3  # inside block 1's phase (steps 28-35)
    first = _trainer(scene, tmp_path)
    first.config.max_num_iterations = stop_at
    first.train()
    assert first.pipeline.datamanager.train_image_dataloader is None, "the global model's images leave memory with its phase"
    run = first.base_dir
    assert latest_checkpoint_step(run / "nerfstudio_models") == stop_at - 1
    saved = torch.load(run / "nerfstudio_models" / f"step-{stop_at - 1:09d}.ckpt", map_location="cpu", weights_only=True)
    assert saved["pipeline"]["_model.blocks_started"].tolist() == [True, True]

    config = yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader)
    config.load_dir = run / "nerfstudio_models"
    config.max_num_iterations = 0  # every phase
    resumed = config.setup(local_rank=0, world_size=1)
    resumed.setup()
    assert resumed._start_step == stop_at and resumed.pipeline.phase_at(stop_at).block == 1
    block1_table = saved["pipeline"]["_model.blocks.1.field.encoder.table"]
    assert torch.equal(resumed.pipeline.model.phase_model(1).field.encoder.table.detach().cpu(), block1_table)
    resumed.train()
    assert latest_checkpoint_step(run / "nerfstudio_models") == 20 + 2 * 8 - 1


def _lr_factor(trainer, group: str, step: int) -> float:
    """The learning-rate multiplier of parameter group ``group`` at global step ``step``."""
    return float(trainer.optimizers.schedulers[group].lr_lambdas[0](step))


@pytest.mark.parametrize("lr_schedule", ["restart", "per-phase"])
def test_global_phase_holds_its_learning_rate_only_when_blocks_follow(scene: Path, tmp_path: Path, lr_schedule: str) -> None:
    """restart (default): the global model warms up and keeps its rate to the end of its phase, each
    block warms up again and decays 10x over its own phase; per-phase: the global phase decays too.
    A run of one model decays over its whole run either way."""
    global_steps, block_steps = 20, 8  # tiny_trainer's
    trainer = _trainer(scene, tmp_path / "blocks", lr_schedule=lr_schedule)
    groups = [g for g in trainer.optimizers.schedulers if not g.startswith("block")]
    assert {"encoder", "decoder"} <= set(groups)
    for group in groups:  # (20 steps are too few to warm up)
        end_of_global = _lr_factor(trainer, group, global_steps - 1)
        assert end_of_global == 1.0 if lr_schedule == "restart" else end_of_global < 0.15
    for block in range(NUM_BLOCKS):
        start = global_steps + block * block_steps
        for part in ("encoder", "decoder"):
            group = f"block{block}.{part}"
            assert _lr_factor(trainer, group, start) == pytest.approx(1.0)  # too short a phase to warm up
            assert _lr_factor(trainer, group, start + block_steps) == pytest.approx(0.1)
    decay = _trainer(scene, tmp_path / "decay", lr_schedule=lr_schedule, num_blocks=1, train_blocks=False, one_model_restart=0.0)
    assert _lr_factor(decay, "encoder", global_steps) == pytest.approx(0.1)


def test_one_model_holds_then_restarts_at_the_block_rates(scene: Path, tmp_path: Path) -> None:
    """A run of one model follows the blocks' schedule: warm-up and hold for ``one_model_restart`` of its
    steps, then its table restarts at the block table's rate, its decoder at the block decoder's, its
    appearance at its own, each decaying 10x over the rest; ``lr_schedule`` per-phase decays throughout."""
    steps = 200
    trainer = _trainer(scene, tmp_path / "restart", num_blocks=1, train_blocks=False, global_steps=steps, one_model_restart=0.5)
    optimizers = trainer.config.optimizers
    assert trainer.pipeline.global_restart_fraction == 0.5
    rate = {part: lambda step, part=part: _lr_factor(trainer, part, step) * optimizers[part]["optimizer"].lr
            for part in ("encoder", "decoder", "appearance")}
    for part, restart_template in (("encoder", "block_encoder"), ("decoder", "block_decoder"), ("appearance", "appearance")):
        base, restarted = optimizers[part]["optimizer"].lr, optimizers[restart_template]["optimizer"].lr
        assert rate[part](1) < base  # warming up
        assert rate[part](40) == pytest.approx(base) and rate[part](99) == pytest.approx(base)  # held
        assert rate[part](100) < restarted  # warming up again
        assert rate[part](103) == pytest.approx(restarted, rel=0.05)  # warmed up, decaying from here
        assert rate[part](steps) == pytest.approx(0.1 * restarted)
    assert optimizers["block_encoder"]["optimizer"].lr > optimizers["encoder"]["optimizer"].lr
    per_phase = _trainer(scene, tmp_path / "per-phase", num_blocks=1, train_blocks=False, global_steps=steps, lr_schedule="per-phase")
    assert per_phase.pipeline.global_restart_fraction == 0.0
    assert _lr_factor(per_phase, "encoder", steps) == pytest.approx(0.1)
    with_blocks = _trainer(scene, tmp_path / "blocks", one_model_restart=0.5)
    assert with_blocks.pipeline.global_restart_fraction == 0.0  # the blocks restart instead

    def frozen_table(config) -> None:  # a table at lr 0 stays frozen, before and after the restart
        config.optimizers["encoder"]["optimizer"].lr = 0.0
        config.optimizers["block_encoder"]["optimizer"].lr = 0.0

    frozen = _trainer(scene, tmp_path / "frozen", configure=frozen_table, num_blocks=1, train_blocks=False, global_steps=steps)
    assert frozen.optimizers.optimizers["encoder"].param_groups[0]["lr"] == 0.0
    assert all(math.isfinite(_lr_factor(frozen, "encoder", step)) for step in (0, 50, 150, steps))


def test_block_tables_train_at_the_block_encoder_rate(scene: Path, tmp_path: Path) -> None:
    """A block's table takes ``--optimizers.block-encoder`` (the global table ``encoder``); a config.yml
    from before that template existed trains its block tables at the ``encoder`` rate, as it did."""

    def initial_lr(trainer, group: str) -> float:
        return float(trainer.optimizers.optimizers[group].param_groups[0]["initial_lr"])

    trainer = _trainer(scene, tmp_path / "now")
    optimizers = trainer.config.optimizers
    assert optimizers["block_encoder"]["optimizer"].lr != optimizers["encoder"]["optimizer"].lr
    assert initial_lr(trainer, "encoder") == pytest.approx(optimizers["encoder"]["optimizer"].lr)
    for block in range(NUM_BLOCKS):
        assert initial_lr(trainer, f"block{block}.encoder") == pytest.approx(optimizers["block_encoder"]["optimizer"].lr)
        assert initial_lr(trainer, f"block{block}.decoder") == pytest.approx(optimizers["block_decoder"]["optimizer"].lr)

    def without_block_encoder(config) -> None:  # as a config.yml from before the template loads
        del config.optimizers["block_encoder"]
        text = yaml.dump(config).replace(f"  scalar_schema_version: {RUN_SCHEMA_VERSION}\n", "")
        config.__dict__.update(vars(yaml.load(text, Loader=yaml.Loader)))

    older = _trainer(scene, tmp_path / "older", configure=without_block_encoder)
    assert initial_lr(older, "block0.encoder") == pytest.approx(older.config.optimizers["encoder"]["optimizer"].lr)


# ------------------------------------------------------------- assembling (assembly.py), in-process


def test_assemble_takes_each_block_from_its_run_and_keeps_blocks_in_files(tmp_path: Path) -> None:
    """The global run's finished block 0 (in its block file) and block 1 from a block run become one
    run: both started, their weights in the new run's block_models/, the checkpoint's block tensors
    empty, the plan copied beside it; a block run of another split, or a block given twice, is refused."""
    from scalar_nerfstudio.assembly import AssembleError, assemble
    from scalar_nerfstudio.models.block_memory import load_block_file, save_block_file
    from scalar_nerfstudio.runs import block_model_path, block_models_dir, load_run_config

    empty = torch.empty(0)
    global_run = fake_run(tmp_path / "global", {"_model.global_model.w": torch.ones(2), "_model.blocks.0.t": empty,
                                                 "_model.blocks.1.t": empty, "_model.blocks_started": torch.tensor([True, False])})
    save_block_file(block_model_path(block_models_dir(global_run), 0), 0, {"t": torch.full((3,), 2.0)})
    block_run = fake_run(tmp_path / "block1", {"_model.global_model.w": torch.ones(2), "_model.blocks.1.t": torch.full((3,), 5.0),
                                                "_model.blocks_started": torch.tensor([False, True])}, only_block=1)
    run = assemble(global_run, [block_run], tmp_path / "assembled")
    state = torch.load(run / "nerfstudio_models" / "step-000000027.ckpt", weights_only=True)["pipeline"]
    assert state["_model.blocks_started"].tolist() == [True, True] and torch.equal(state["_model.global_model.w"], torch.ones(2))
    assert state["_model.blocks.0.t"].numel() == 0 and state["_model.blocks.1.t"].numel() == 0
    assert load_block_file(block_model_path(block_models_dir(run), 0), 0)["t"].tolist() == [2.0] * 3
    assert load_block_file(block_model_path(block_models_dir(run), 1), 1)["t"].tolist() == [5.0] * 3
    assert load_run_config(run).pipeline.run_plan == (run / "blocks.json").resolve()
    assert json.loads((run / "assembled_from.json").read_text())["blocks"] == {"1": str(block_run)}
    with pytest.raises(AssembleError, match="given twice"):
        assemble(global_run, [block_run, block_run], tmp_path / "twice")
    with pytest.raises(AssembleError, match="not a scalar-nerf-block run"):
        assemble(global_run, [global_run], tmp_path / "not-a-block")


# ------------------------------------------------------- scalar-nerf-block, in parallel


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ([], "--global-run is required"),
        (["--global-run", "/nonexistent/run"], "no config.yml"),
    ],
)
def test_block_command_explains_bad_arguments(tmp_path: Path, extra: List[str], message: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """``ns-train scalar-nerf-block`` (nerfstudio's entry point, in-process) ends in one line naming
    the problem (a SystemExit with a message: no traceback), and writes nothing."""
    from nerfstudio.scripts import train as ns_train

    monkeypatch.setattr(sys, "argv", ["ns-train", "scalar-nerf-block", "--output-dir", str(tmp_path / "out"), *extra])
    with pytest.raises(SystemExit) as exit_info:
        ns_train.entrypoint()
    assert isinstance(exit_info.value.code, str) and message in exit_info.value.code
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_block_command_refuses_missing_block_and_unfinished_global(full_run: Path, tmp_path: Path) -> None:
    """What ``ns-train scalar-nerf-block`` checks before it writes anything (the command line's own
    error path is test_block_command_explains_bad_arguments)."""
    from scalar_nerfstudio.method_configs import scalar_nerf_block
    from scalar_nerfstudio.runs import RunError

    config = copy.deepcopy(scalar_nerf_block.config)
    config.global_run, config.block = full_run, 7
    with pytest.raises(RunError, match="--block 7 does not exist"):
        config.adopt_global_run()
    unfinished = tmp_path / "unfinished"
    (unfinished / "nerfstudio_models").mkdir(parents=True)
    (unfinished / "config.yml").write_text((full_run / "config.yml").read_text())
    (unfinished / "blocks.json").write_text((full_run / "blocks.json").read_text())
    config = copy.deepcopy(scalar_nerf_block.config)
    config.global_run, config.block = unfinished, 0
    with pytest.raises(RunError, match="global phase of .* is not finished"):
        config.adopt_global_run()


@pytest.mark.slow
def test_block_run_takes_unset_block_settings_from_the_global_run(full_run: Path) -> None:
    """``scalar-nerf-block`` without --pipeline.block-steps trains as many steps as the global run's
    blocks did (not the method default), with its ray batch; explicit values win."""
    from scalar_nerfstudio.method_configs import scalar_nerf_block

    config = copy.deepcopy(scalar_nerf_block.config)
    config.global_run = full_run
    config.adopt_global_run()
    assert config.pipeline.block_steps == BLOCK_STEPS
    assert config.pipeline.datamanager.train_num_rays_per_batch == 512
    explicit = copy.deepcopy(scalar_nerf_block.config)
    explicit.global_run = full_run
    explicit.pipeline.block_steps = 7
    explicit.pipeline.decoder_mode = "frozen"
    explicit.adopt_global_run()
    assert explicit.pipeline.block_steps == 7 and explicit.pipeline.decoder_mode == "frozen"


def test_fused_rendering_starts_rays_at_the_training_near_plane(scene: Path, tmp_path: Path) -> None:
    """The scene model collides rays before the global and block models see them: it keeps the near plane too."""
    model = _trainer(scene, tmp_path).pipeline.model.eval()
    rays = RayBundle(origins=torch.zeros(2, 3), directions=torch.eye(3)[:2], pixel_area=torch.ones(2, 1))
    assert torch.equal(model.collider(rays).nears, torch.full((2, 1), model.config.near_plane))
