"""The one error process-data raises for bad input: its message names the problem and the files."""

from __future__ import annotations


class ProcessDataError(Exception):
    """Bad input or a capture that cannot be reconstructed; the message says which and what to do.

    Raised before anything of the scene is written (the COLMAP database under ``SCENE/colmap`` is
    kept for a re-run once structure-from-motion has started).
    """
