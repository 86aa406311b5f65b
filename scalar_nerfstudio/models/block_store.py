"""Where each block model's weights are: in memory (a bounded number), in its file, or nowhere yet.

:class:`BlockStore` keeps the block models of a scene model as *shells* (see ``block_memory.py``):
only the block that trains and at most ``max_resident_blocks`` blocks loaded for rendering hold
their weights. A finished block's weights are written to its own file in the run's
``block_models/`` folder (:meth:`BlockStore.store`) and read back when a render needs them
(:meth:`BlockStore.model`). A checkpoint holds the tensors of a stored block empty
(:meth:`BlockStore.empty_stored`); loading one (:meth:`BlockStore.load`) installs the blocks whose
weights it holds and checks that the others' files exist.

The store does not own the block models: it works on the owner's ``nn.ModuleDict`` (so that their
state-dict keys stay the owner's ``blocks.<k>.*``) and is told which blocks have started training.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Collection, Dict, Iterable, Optional, Set, Tuple, cast

from torch import Tensor, nn

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
from scalar_nerfstudio.models.scalar_model import ScalarModel
from scalar_nerfstudio.runs import block_model_path

#: State-dict prefix of the block models in their owner (``blocks.<k>.``).
BLOCKS_PREFIX = "blocks."


class BlockStore:
    """The weights of the block models in ``blocks`` (``str(k)`` -> :class:`ScalarModel`): in memory or on disk.

    Args:
        blocks: the owner's module dict of block models; :meth:`add_shell` fills it.
        max_resident_blocks: at most this many blocks loaded from their files stay in memory
            (least recently used ones are released); blocks not in a file are never released.
    """

    def __init__(self, blocks: nn.ModuleDict, max_resident_blocks: int) -> None:
        self.blocks = blocks
        self.resident = ResidentBlocks(max_resident_blocks)
        """Blocks whose weights are in memory (the others' tensors are empty)."""
        self.specs: Dict[int, Dict[str, TensorSpec]] = {}
        """Shape and dtype of each block model's tensors (its shell holds them empty until needed)."""
        self.directory: Optional[Path] = None
        """The run's block_models/ folder (:meth:`attach`); None: blocks are never stored."""
        self.stored: Set[int] = set()
        """Blocks whose current weights are in their file in :attr:`directory`."""

    def add_shell(self, block: int, model: ScalarModel) -> None:
        """Hold ``model`` (freshly built, with its weights) as block ``block``'s: its tensor shapes are
        recorded, then its weights released (one block at a time in memory: built, measured, emptied)."""
        self.specs[block] = tensor_specs(model)
        release_tensors(model)
        self.blocks[str(block)] = model

    def shell(self, block: int) -> ScalarModel:
        """Block ``block``'s model as :attr:`blocks` holds it (its tensors empty unless it is resident)."""
        return cast(ScalarModel, self.blocks[str(block)])  # only add_shell fills blocks, with ScalarModels

    def attach(self, directory: Path) -> None:
        """Keep finished blocks in ``directory`` (the run's ``block_models/``) and load them from there."""
        self.directory = Path(directory)

    def path(self, block: int) -> Path:
        """Block ``block``'s file in :attr:`directory` (which must be attached)."""
        assert self.directory is not None
        return block_model_path(self.directory, block)

    def is_resident(self, block: int) -> bool:
        """Whether block ``block``'s weights are in memory (else its shell's tensors are empty)."""
        return block in self.resident

    def parameter_count(self, block: int, part: Optional[str] = None) -> int:
        """Parameters of block ``block``'s model (of its ``encoder``/``decoder``/``appearance`` when
        ``part`` is given), whether or not they are in memory."""
        head = "field." if part is None else f"field.{part}."
        specs = self.specs[block]
        return spec_numel(specs, [k for k in specs if k.startswith(head)])

    def install(self, block: int, state: Dict[str, Tensor], *, what: str, evictable: bool) -> None:
        """Give block ``block``'s model the weights ``state`` (its own state-dict keys; ``what`` names
        where they come from in errors); then release the least recently used loaded blocks over the limit."""
        model = self.shell(block)
        install_tensors(model, model.complete_state(dict(state)), specs=self.specs[block], what=what)
        self.resident.add(block, evictable)
        for other in self.resident.over_limit(keep=block):
            self._free(other)  # evictable: its weights are in its file

    def release(self, block: int, started: bool) -> None:
        """Free block ``block``'s weights from memory (``started``: whether it has started training;
        then it must be in its file)."""
        if started and block not in self.stored:
            raise RuntimeError(f"block {block} is trained but not saved to its file: releasing it would lose it")
        self._free(block)

    def _free(self, block: int) -> None:
        release_tensors(self.blocks[str(block)])
        self.resident.discard(block)

    def store(self, block: int) -> Path:
        """Write block ``block``'s weights to its file (atomically) and free them from memory: its
        phase is over. Returns the file."""
        if self.directory is None:
            raise RuntimeError("no block store attached (attach_block_store): the block's weights would be lost")
        path = self.path(block)
        save_block_file(path, block, self.blocks[str(block)].state_dict())
        self.stored.add(block)
        self._free(block)
        return path

    def model(self, block: int) -> ScalarModel:
        """Block ``block``'s model with its weights in memory: loaded from its file if they are not
        (then at most ``max_resident_blocks`` loaded blocks stay, least recently used released)."""
        if block in self.resident:
            self.resident.touch(block)
        elif block in self.stored:
            path = self.path(block)
            self.install(block, load_block_file(path, block), what=f"block {block} from {path}", evictable=True)
        else:
            raise RuntimeError(f"block {block} has no weights: it has not started training")
        return self.shell(block)

    def empty_stored(self, state: Dict[str, Any], prefix: str = "") -> Dict[str, Any]:
        """``state`` (the owner's state dict, keys under ``prefix``) with the tensors of the blocks kept
        in their files made empty, in place: a checkpoint holds only the blocks that live in memory."""
        for block in self.stored:
            head = f"{prefix}{BLOCKS_PREFIX}{block}."
            for key in [k for k in state if k.startswith(head)]:
                state[key] = state[key].new_empty(0)
        return state

    @staticmethod
    def split_state(state_dict: Dict[str, Tensor], block_ids: Iterable[int]) -> Tuple[Dict[int, Dict[str, Tensor]], Dict[str, Tensor]]:
        """The owner's ``state_dict`` split into each held block's own state (its keys without
        ``blocks.<k>.``) and the rest (the owner's other keys, and blocks it does not hold)."""
        block_states: Dict[int, Dict[str, Tensor]] = {b: {} for b in block_ids}
        rest = {}
        for key, value in state_dict.items():
            parts = key.split(".", 2)
            if parts[0] == BLOCKS_PREFIX[:-1] and len(parts) == 3 and parts[1].isdigit() and int(parts[1]) in block_states:
                block_states[int(parts[1])][parts[2]] = value
            else:
                rest[key] = value
        return block_states, rest

    def load(self, block_states: Dict[int, Dict[str, Tensor]], started: Collection[int]) -> None:
        """After the owner loaded a checkpoint: every block in ``block_states`` (:meth:`split_state`) is
        released; a block in ``started`` whose weights are in its state becomes resident (pinned), one
        whose tensors are empty there is read from its file when a render needs it.

        Raises:
            FileNotFoundError: a started block's weights are neither in its state nor in its file.
        """
        for block, state in block_states.items():
            self.resident.discard(block)
            self.stored.discard(block)
            release_tensors(self.blocks[str(block)])
            if block not in started:
                continue
            if state and not is_released_state(state):
                self.install(block, state, what=f"block {block} in the checkpoint", evictable=False)
            elif self.directory is not None and not self.path(block).is_file():
                raise FileNotFoundError(
                    f"the checkpoint says block {block} has trained, but its weights are neither in it nor in "
                    f"{self.path(block)}"
                )
            else:
                self.stored.add(block)
