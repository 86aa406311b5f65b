"""Blocks out of memory: only the training block and a bounded number of loaded ones hold weights,
finished blocks live in their own files, checkpoints hold no finished block, and rendering from the
files gives the image rendering from memory gives."""

from __future__ import annotations

from pathlib import Path
from typing import Dict

import pytest
import torch
from conftest import SMALL_FIELD, ray_bundle, small_scalar_model
from nerfstudio.data.scene_box import SceneBox

from scalar_nerfstudio.blocks.split import Block, BlockSplit
from scalar_nerfstudio.fields.scalar_field import ScalarFieldConfig
from scalar_nerfstudio.models.block_memory import (
    ResidentBlocks,
    install_tensors,
    is_released,
    load_block_file,
    release_tensors,
    tensor_specs,
)
from scalar_nerfstudio.models.block_store import BlockStore
from scalar_nerfstudio.models.scene_model import ScalarSceneModel, ScalarSceneModelConfig
from scalar_nerfstudio.runs import block_model_path

NUM_BLOCKS = 6


def _model(max_resident_blocks: int = 2, fusion: str = "idw") -> ScalarSceneModel:
    """Six small blocks along x; nothing started."""
    blocks = tuple(
        Block(index=k, image_indices=(0, 1), aabb_min=(x - 0.2, -0.3, -0.3), aabb_max=(x + 0.2, 0.3, 0.3), centre=(x, 0.0, 0.0))
        for k, x in enumerate(torch.linspace(-0.75, 0.75, NUM_BLOCKS).tolist())
    )
    config = ScalarSceneModelConfig(field=ScalarFieldConfig(**SMALL_FIELD), fusion=fusion, blocks_per_ray=2, num_samples_per_ray=24,
                                    render_normals="never", seed_block_occupancy=False, max_resident_blocks=max_resident_blocks,
                                    occupancy_resolution=16)
    return ScalarSceneModel(config=config, scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=2,
                            split=BlockSplit(blocks=blocks, aabb_scale=(1.0, 1.0, 1.0), seed=0))


def _train_blocks(model: ScalarSceneModel, store: Path) -> None:
    """Start every block in turn, give it distinct weights, and store it when its 'phase' ends (as
    the trainer does), leaving the last one in memory."""
    model.attach_block_store(store)
    torch.manual_seed(1)
    for block in range(NUM_BLOCKS):
        model.begin_block(block)
        with torch.no_grad():
            for parameter in model.phase_model(block).field.parameters():
                parameter.add_(torch.randn(parameter.shape) * 0.5)
        if block < NUM_BLOCKS - 1:
            model.store_block(block)


def _rays(num: int = 64):
    generator = torch.Generator().manual_seed(3)
    origins = torch.cat([torch.rand(num, 1, generator=generator) * 1.6 - 0.8, torch.full((num, 1), -0.9), torch.zeros(num, 1)], dim=-1)
    targets = torch.cat([torch.rand(num, 1, generator=generator) * 1.6 - 0.8, torch.full((num, 1), 0.9), torch.zeros(num, 1)], dim=-1)
    return ray_bundle(origins, torch.nn.functional.normalize(targets - origins, dim=-1))


def _resident_bytes(model: ScalarSceneModel) -> Dict[int, int]:
    return {b: sum(t.numel() * t.element_size() for t in model.blocks[str(b)].state_dict().values()) for b in model.block_ids}


# ------------------------------------------------------------------------------------ the pieces


def test_lru_keeps_at_most_the_limit_of_evictable_blocks_and_never_a_pinned_one() -> None:
    resident = ResidentBlocks(limit=2)
    resident.add(0, evictable=False)  # the block that trains
    resident.add(1, evictable=True)
    resident.add(2, evictable=True)
    assert resident.over_limit(keep=2) == []
    resident.add(3, evictable=True)
    assert resident.over_limit(keep=3) == [1]  # the least recently used loaded block, never block 0
    resident.touch(1)
    assert resident.over_limit(keep=3) == [2]
    with pytest.raises(ValueError, match="at least 1"):
        ResidentBlocks(limit=0)


def test_released_tensors_keep_their_objects_and_install_checks_shapes() -> None:
    module = torch.nn.Linear(4, 3)
    specs = tensor_specs(module)
    weight = module.weight
    saved = {k: v.clone() for k, v in module.state_dict().items()}
    release_tensors(module)
    assert is_released(module) and module.weight is weight  # an optimiser's reference stays valid
    install_tensors(module, saved, specs=specs, what="block 9")
    assert torch.equal(module.weight, saved["weight"]) and module.weight is weight
    with pytest.raises(ValueError, match=r"block 9: weight is \[3, 5\]"):
        install_tensors(module, {**saved, "weight": torch.zeros(3, 5)}, specs=specs, what="block 9")
    with pytest.raises(ValueError, match="1 tensors missing"):
        install_tensors(module, {"weight": saved["weight"]}, specs=specs, what="block 9")


def test_block_store_keeps_weights_in_files_loads_them_back_bounded_and_never_loses_a_trained_block(tmp_path: Path) -> None:
    blocks = torch.nn.ModuleDict()
    store = BlockStore(blocks, max_resident_blocks=1)
    for block in range(3):
        store.add_shell(block, small_scalar_model(num_train_data=2))
    assert all(is_released(blocks[str(b)]) for b in range(3))
    assert 0 < store.parameter_count(0, "encoder") < store.parameter_count(0)  # known without the weights
    weights = {k: v.clone() + 1.0 if v.is_floating_point() else v.clone() for k, v in small_scalar_model(num_train_data=2).state_dict().items()}
    store.install(0, weights, what="block 0", evictable=False)
    assert store.is_resident(0) and torch.equal(blocks["0"].field.encoder.table, weights["field.encoder.table"])
    with pytest.raises(RuntimeError, match="not saved to its file"):
        store.release(0, started=True)
    with pytest.raises(RuntimeError, match="no block store attached"):
        store.store(0)
    store.attach(tmp_path)
    assert store.store(0) == block_model_path(tmp_path, 0) and not store.is_resident(0) and is_released(blocks["0"])
    with pytest.raises(RuntimeError, match="has not started"):
        store.model(1)
    store.install(1, weights, what="block 1", evictable=False)
    store.store(1)
    assert torch.equal(store.model(0).field.encoder.table, weights["field.encoder.table"])  # loaded from its file
    store.model(1)  # a second loaded block: the least recently used one (0) leaves memory
    assert store.resident.blocks == [1] and is_released(blocks["0"])

    owner = torch.nn.Module()
    owner.blocks = blocks
    state = store.empty_stored(owner.state_dict())
    assert all(v.numel() == 0 for k, v in state.items() if k.startswith(("blocks.0.", "blocks.1.")))
    block_states, rest = BlockStore.split_state({"blocks.0.a": weights["field.encoder.table"], "blocks.7.b": torch.ones(1), "flag": torch.ones(1)}, [0, 2])
    assert list(block_states) == [0, 2] and list(block_states[0]) == ["a"] and block_states[2] == {} and sorted(rest) == ["blocks.7.b", "flag"]

    store.load({0: {}, 1: {k: v.new_empty(0) for k, v in weights.items()}, 2: weights}, started=[0, 1, 2])
    assert store.stored == {0, 1} and store.resident.blocks == [2] and not store.resident.is_evictable(2)  # 2 came with the checkpoint
    block_model_path(tmp_path, 1).unlink()
    with pytest.raises(FileNotFoundError, match="block 1 has trained"):
        store.load({1: {}}, started=[1])


# ------------------------------------------------------------------------------ the scene model


def test_only_started_blocks_hold_weights_and_a_stored_block_leaves_memory(tmp_path: Path) -> None:
    model = _model()
    assert all(size == 0 for size in _resident_bytes(model).values()), "no block holds weights before it starts"
    assert model.block_parameter_count(3) > 0  # its size is known all the same
    _train_blocks(model, tmp_path)
    sizes = _resident_bytes(model)
    assert [b for b, size in sizes.items() if size > 0] == [NUM_BLOCKS - 1], "only the last (training) block is in memory"
    for block in range(NUM_BLOCKS - 1):
        assert load_block_file(block_model_path(tmp_path, block), block).keys() == model.blocks[str(block)].state_dict().keys()


def test_rendering_loads_blocks_from_their_files_bounded_and_gives_the_same_image(tmp_path: Path) -> None:
    torch.manual_seed(0)  # the two models start from the same global model, whatever ran before in this process
    reference = _model(max_resident_blocks=NUM_BLOCKS, fusion="nearest")  # rays from x = -0.8 .. 0.8: every block
    reference.attach_block_store(tmp_path / "unused")
    torch.manual_seed(1)
    for block in range(NUM_BLOCKS):  # the same weights as _train_blocks, every block kept in memory
        reference.begin_block(block)
        with torch.no_grad():
            for parameter in reference.phase_model(block).field.parameters():
                parameter.add_(torch.randn(parameter.shape) * 0.5)
    torch.manual_seed(0)
    model = _model(max_resident_blocks=2, fusion="nearest")
    _train_blocks(model, tmp_path)
    rays = _rays()
    reference.eval(), model.eval()
    with torch.no_grad():
        expected = reference.get_outputs(rays)["rgb"]
        fused = model.get_outputs(rays)["rgb"]
    assert len(model.rays_rendered_by_block) == NUM_BLOCKS, "the rays need more blocks than the limit holds"
    assert torch.equal(fused, expected)
    resident = [b for b, size in _resident_bytes(model).items() if size > 0]
    assert NUM_BLOCKS - 1 in resident and len(resident) <= 1 + 2, resident


def test_checkpoint_holds_no_stored_block_and_loads_back_with_the_files(tmp_path: Path) -> None:
    model = _model()
    _train_blocks(model, tmp_path)
    state = model.state_dict()
    for block in range(NUM_BLOCKS - 1):
        assert all(state[k].numel() == 0 for k in state if k.startswith(f"blocks.{block}.")), f"block {block} is in its file"
    assert state[f"blocks.{NUM_BLOCKS - 1}.field.encoder.table"].numel() > 0, "the training block is in the checkpoint"
    block_bytes = sum(v.numel() * v.element_size() for k, v in state.items() if k.startswith("blocks."))
    assert block_bytes == sum(_resident_bytes(model).values())  # one block's cost, whatever K is

    loaded = _model()
    loaded.attach_block_store(tmp_path)
    loaded.load_state_dict(state)
    rays = _rays()
    model.eval(), loaded.eval()
    with torch.no_grad():
        assert torch.equal(loaded.get_outputs(rays)["rgb"], model.get_outputs(rays)["rgb"])

    block_model_path(tmp_path, 2).unlink()
    with pytest.raises(FileNotFoundError, match="block-0002.ckpt"):
        _with_store(tmp_path).load_state_dict(state)


def _with_store(store: Path) -> ScalarSceneModel:
    model = _model()
    model.attach_block_store(store)
    return model


def test_a_checkpoint_with_every_block_in_it_still_loads(tmp_path: Path) -> None:
    """Runs from before per-block files hold every started block in the checkpoint itself."""
    model = _model(max_resident_blocks=NUM_BLOCKS)
    model.attach_block_store(tmp_path)
    for block in range(NUM_BLOCKS):
        model.begin_block(block)
    state = model.state_dict()
    assert all(state[f"blocks.{b}.field.encoder.table"].numel() > 0 for b in range(NUM_BLOCKS))
    loaded = _model(max_resident_blocks=1)
    loaded.load_state_dict(state)
    assert all(loaded.block_is_resident(b) for b in range(NUM_BLOCKS)), "blocks only in the checkpoint are pinned, never dropped"
    with pytest.raises(RuntimeError, match="not saved to its file"):
        loaded.release_block(0)


def test_a_block_loaded_from_its_file_keeps_its_render_grid(tmp_path: Path, recwarn: pytest.WarningsRecorder) -> None:
    """A finished block's render grid (estimated from its final field) is in its file and is used
    again when the block is loaded to render, without a warning; it used to be dropped on every load
    (its empty shell was taken for a grid of another size), so stored blocks rendered with their
    training grid."""
    model = _model(max_resident_blocks=1)
    model.attach_block_store(tmp_path)
    model.begin_block(0)
    block = model.phase_model(0)
    block.seed_occupancy_from(model.global_model)  # past the warm-up: its last step builds the render grid
    block.finish_training()
    assert bool(block.render_occupancy_ready)
    grid = block.render_occupancy.occupied.clone()
    model.store_block(0)
    assert is_released(model.blocks["0"])
    loaded = model.resident_block(0)
    assert bool(loaded.render_occupancy_ready) and torch.equal(loaded.render_occupancy.occupied, grid)
    loaded.eval()
    assert loaded.samples_grid() is loaded.render_occupancy
    assert not [w for w in recwarn.list if "render grid" in str(w.message)]
