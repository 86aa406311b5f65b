"""Atomic file writes (standard library only at import, so light processes such as Ray workers can use
it; :func:`atomic_torch_save` imports torch when it is called)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any, Dict

#: Suffix of the hidden file :func:`atomic_torch_save` writes before renaming it into place.
PARTIAL_SUFFIX = ".ckpt.partial"


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that ``path`` is either its old self or complete, never half-written.

    The bytes go to a hidden temporary file beside ``path`` (mode 0644, readable by other users'
    processes), are fsynced, then renamed over ``path``. The parent folder is created if needed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o644)  # mkstemp creates 0600
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    """:func:`atomic_write_bytes` of ``text`` encoded as UTF-8."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_torch_save(state: Dict[str, Any], path: Path) -> None:
    """Write ``state`` to ``path`` so that ``path`` is either absent or complete, never half-written.

    The bytes go to a hidden file in ``path``'s parent's parent (outside the checkpoint folder, whose
    every file nerfstudio's loaders parse as ``step-N.ckpt``), are fsynced, then renamed into place.
    """
    import torch  # here, not at import: light processes (Ray workers) read run folders without torch

    path = Path(path)
    staging = path.parent.parent / f".{path.stem}{PARTIAL_SUFFIX}"
    with open(staging, "wb") as handle:
        torch.save(state, handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(staging, path)
