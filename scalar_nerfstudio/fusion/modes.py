"""Fusion mode names and their parsing (standard library only)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

FusionMode = Literal["global", "surface", "idw", "nearest", "nearest-guarded", "nearest-idw", "global-only"]
FUSION_MODES: tuple[str, ...] = get_args(FusionMode)


class FusionModeError(ValueError):
    """Unknown or malformed fusion mode string."""


@dataclass(frozen=True)
class ParsedFusionMode:
    """A parsed fusion mode: ``kind`` is a :data:`FusionMode` or ``"block"`` with ``block_index``."""

    kind: Literal["global", "surface", "idw", "nearest", "nearest-guarded", "nearest-idw", "global-only", "block"]
    block_index: int | None = None

    def __str__(self) -> str:
        return f"block:{self.block_index}" if self.kind == "block" else self.kind


def parse_fusion_mode(mode: str | ParsedFusionMode, num_blocks: int | None = None) -> ParsedFusionMode:
    """Parse ``"global" | "surface" | "idw" | "nearest" | "nearest-guarded" | "nearest-idw" | "global-only" | "block:<k>"``.

    Args:
        mode: The mode string (case-insensitive, surrounding blanks ignored) or an already parsed mode.
        num_blocks: If given, ``block:<k>`` must satisfy ``0 <= k < num_blocks``.

    Raises:
        FusionModeError: For an unknown mode or a bad block index.
    """
    if isinstance(mode, ParsedFusionMode):
        parsed = mode
    else:
        text = str(mode).strip().lower()
        if text in FUSION_MODES:
            return ParsedFusionMode(kind=text)  # type: ignore[arg-type]
        if not text.startswith("block:"):
            valid = ", ".join(repr(m) for m in FUSION_MODES)
            raise FusionModeError(f"unknown fusion mode {mode!r}; expected one of {valid} or 'block:<k>'")
        index_text = text.split(":", 1)[1]
        if not index_text.isdigit():
            raise FusionModeError(f"bad fusion mode {mode!r}: 'block:<k>' needs a non-negative integer k")
        parsed = ParsedFusionMode(kind="block", block_index=int(index_text))
    if parsed.kind == "block" and num_blocks is not None and not 0 <= (parsed.block_index or 0) < num_blocks:
        raise FusionModeError(f"fusion mode {str(parsed)!r}: block index out of range, there are {num_blocks} blocks")
    return parsed
