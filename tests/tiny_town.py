"""The tiny town the town tests share."""

from __future__ import annotations

from pathlib import Path

from scalar_nerfstudio.scenes.town import TownConfig, write_town

#: A 2 x 1-block town, 17 frames (eval interval 8 holds out frames 0, 8 and 16) of 40 x 30 pixels.
TINY = TownConfig(num_images=17, width=40, height=30, blocks_x=2, blocks_y=1, seed=3)


def write_tiny_town(folder: Path) -> Path:
    """Write :data:`TINY` into ``folder``; returns ``folder``."""
    write_town(folder, TINY, progress=False)
    return folder
