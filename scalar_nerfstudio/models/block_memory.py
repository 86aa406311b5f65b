"""Block models that are not in memory: their tensors released, kept on disk, loaded back on demand.

A run of K blocks holds every block's :class:`~scalar_nerfstudio.models.scalar_model.ScalarModel` as
a *shell*: the module, its parameters and buffers exist (optimiser groups, checkpoint keys and
``frozen`` flags keep working), but a released tensor holds no elements (``numel() == 0``). Only the
block that trains, and a bounded number loaded for rendering, hold their weights; a finished block's
weights are in its own file (``runs.block_model_path``), written atomically when its phase ends.

Releasing keeps each tensor *object* and swaps its storage (``tensor.data = empty``), so references
held elsewhere (an optimiser's parameter list) stay valid.
"""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import Dict, Iterable, List, Optional, Tuple

import torch
from torch import Tensor, nn

from scalar_nerfstudio.atomic_io import atomic_torch_save

TensorSpec = Tuple[torch.Size, torch.dtype]


def tensor_specs(module: nn.Module) -> Dict[str, TensorSpec]:
    """Shape and dtype of every tensor in ``module``'s state dict (recorded while it holds its weights)."""
    return {key: (tensor.shape, tensor.dtype) for key, tensor in module.state_dict(keep_vars=True).items()}


def release_tensors(module: nn.Module) -> None:
    """Free the storage of every state-dict tensor of ``module`` (and the parameters' gradients)."""
    for tensor in module.state_dict(keep_vars=True).values():
        tensor.data = torch.empty(0, dtype=tensor.dtype, device=tensor.device)
        if isinstance(tensor, nn.Parameter):
            tensor.grad = None


def is_released(module: nn.Module) -> bool:
    """True when ``module``'s state-dict tensors hold no elements (:func:`release_tensors`)."""
    return all(tensor.numel() == 0 for tensor in module.state_dict(keep_vars=True).values())


def is_released_state(state: Dict[str, Tensor]) -> bool:
    """True when a saved state (one block's) holds only released, empty tensors."""
    return all(tensor.numel() == 0 for tensor in state.values())


def install_tensors(module: nn.Module, state: Dict[str, Tensor], *, specs: Dict[str, TensorSpec], what: str) -> None:
    """Give ``module``'s tensors the values in ``state`` (its own state-dict keys), in place.

    Raises:
        ValueError: ``state`` lacks a key, has an extra one, or a shape or dtype differs from ``specs``
            (``what`` names the block and where ``state`` came from).
    """
    missing, extra = sorted(set(specs) - set(state)), sorted(set(state) - set(specs))
    if missing or extra:
        raise ValueError(f"{what}: {len(missing)} tensors missing (e.g. {missing[:1]}), {len(extra)} unexpected (e.g. {extra[:1]})")
    for key, (shape, dtype) in specs.items():
        if state[key].shape != shape or state[key].dtype != dtype:
            raise ValueError(f"{what}: {key} is {list(state[key].shape)} {state[key].dtype}, the model expects {list(shape)} {dtype}")
    targets = module.state_dict(keep_vars=True)
    for key, value in state.items():
        target = targets[key]
        target.data = value.detach().to(device=target.device)


def spec_numel(specs: Dict[str, TensorSpec], keys: Optional[Iterable[str]] = None) -> int:
    """Elements of the tensors ``keys`` (default: all) of a recorded spec."""
    chosen = specs if keys is None else {k: specs[k] for k in keys}
    return sum(int(torch.Size(shape).numel()) for shape, _ in chosen.values())


class ResidentBlocks:
    """Which blocks hold their weights in memory, in least-recently-used order.

    A block is *evictable* when an up-to-date copy is on disk (it was loaded from its file, or saved
    to it); other resident blocks (the one training, one loaded from a full checkpoint) are pinned.
    """

    def __init__(self, limit: int) -> None:
        if limit < 1:
            raise ValueError(f"max_resident_blocks must be at least 1, got {limit}")
        self.limit = limit
        self._order: "OrderedDict[int, bool]" = OrderedDict()  # block -> evictable

    def __contains__(self, block: int) -> bool:
        return block in self._order

    def add(self, block: int, evictable: bool) -> None:
        """Mark ``block`` resident and most recently used."""
        self._order[block] = evictable
        self._order.move_to_end(block)

    def touch(self, block: int) -> None:
        """Mark ``block`` most recently used."""
        self._order.move_to_end(block)

    def discard(self, block: int) -> None:
        self._order.pop(block, None)

    def is_evictable(self, block: int) -> bool:
        return self._order.get(block, False)

    def over_limit(self, keep: int) -> List[int]:
        """Evictable blocks to release (oldest first) so that at most ``limit`` evictable ones stay;
        ``keep`` is never among them."""
        evictable = [b for b, ok in self._order.items() if ok and b != keep]
        excess = len(evictable) + (1 if self.is_evictable(keep) else 0) - self.limit
        return evictable[:max(excess, 0)]

    @property
    def blocks(self) -> List[int]:
        """Resident blocks, least recently used first."""
        return list(self._order)


def save_block_file(path: Path, block: int, state: Dict[str, Tensor]) -> None:
    """Write one block's state dict to ``path`` atomically (:func:`~scalar_nerfstudio.atomic_io.atomic_torch_save`)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_torch_save({"block": block, "state": {k: v.detach().cpu() for k, v in state.items()}}, path)


def load_block_file(path: Path, block: int) -> Dict[str, Tensor]:
    """One block's state dict from its file (CPU tensors).

    Raises:
        FileNotFoundError: the file is missing (the message says which block needs it).
        ValueError: the file holds another block.
    """
    if not path.is_file():
        raise FileNotFoundError(
            f"block {block}'s weights are not in memory and its file {path} is missing "
            "(the run folder was copied without its block_models/ folder?)"
        )
    saved = torch.load(path, map_location="cpu", weights_only=True)
    if int(saved.get("block", -1)) != block:
        raise ValueError(f"{path} holds block {saved.get('block')}, not block {block}")
    return saved["state"]
