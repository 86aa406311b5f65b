"""The colours of the blocks: the viewer's overlay and the model's ``block_colour`` output share them."""

from __future__ import annotations

from typing import Tuple

import numpy as np

#: RGB in [0, 1] per block (tab10), cycling for K > 10.
BLOCK_PALETTE = np.array(
    [
        [0.122, 0.467, 0.706], [1.000, 0.498, 0.055], [0.173, 0.627, 0.173], [0.839, 0.153, 0.157],
        [0.580, 0.404, 0.741], [0.549, 0.337, 0.294], [0.890, 0.467, 0.761], [0.737, 0.741, 0.133],
        [0.090, 0.745, 0.812], [0.498, 0.498, 0.498],
    ],
    dtype=np.float32,
)
#: RGB in [0, 1] of the global model (grey).
GLOBAL_COLOUR = (0.35, 0.35, 0.35)


def block_colour(index: int) -> Tuple[float, float, float]:
    """RGB in [0, 1] of block ``index`` (``-1``: the global model)."""
    if index < 0:
        return GLOBAL_COLOUR
    red, green, blue = BLOCK_PALETTE[index % len(BLOCK_PALETTE)]  # [3]
    return float(red), float(green), float(blue)
