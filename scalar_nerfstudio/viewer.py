"""What scalar-nerf adds to nerfstudio's viser viewer.

* a "Fusion" dropdown (global / idw / nearest / global-only / block:k) that switches how the
  rendered image is fused, live, during training and on a trained run;
* the scene overlay: each block's scaled AABB as a wire box, and the training cameras as points
  coloured by block (a camera in several blocks takes its first block's colour);
* the ``block_colour`` output (chosen in the viewer's output dropdown) is made by the model: each
  pixel in the colour of the block that won it (grey: the global model).

Both are found by nerfstudio's viewer because they are attributes of the pipeline.
"""

from __future__ import annotations

from typing import Callable, List, Sequence

import numpy as np
from nerfstudio.viewer.viewer_elements import ViewerControl, ViewerDropdown

from scalar_nerfstudio.blocks.split import BlockSplit
from scalar_nerfstudio.blocks.visibility import box_corners
from scalar_nerfstudio.fusion import FUSION_MODES

#: nerfstudio draws the scene at 10x the dataparser frame (viewer.VISER_NERFSTUDIO_SCALE_RATIO).
VISER_SCALE = 10.0
#: RGB in [0, 1] per block (tab10), cycling for K > 10; the global model is grey.
BLOCK_PALETTE = np.array(
    [
        [0.122, 0.467, 0.706], [1.000, 0.498, 0.055], [0.173, 0.627, 0.173], [0.839, 0.153, 0.157],
        [0.580, 0.404, 0.741], [0.549, 0.337, 0.294], [0.890, 0.467, 0.761], [0.737, 0.741, 0.133],
        [0.090, 0.745, 0.812], [0.498, 0.498, 0.498],
    ],
    dtype=np.float32,
)
GLOBAL_COLOUR = (0.35, 0.35, 0.35)


def block_colour(index: int) -> tuple:
    """RGB in [0, 1] of block ``index`` (``-1``: the global model)."""
    return GLOBAL_COLOUR if index < 0 else tuple(float(v) for v in BLOCK_PALETTE[index % len(BLOCK_PALETTE)])


def fusion_options(num_blocks: int) -> List[str]:
    """The dropdown's entries: the fusion modes, then one ``block:k`` per block."""
    return [*FUSION_MODES, *(f"block:{k}" for k in range(num_blocks))]


def fusion_dropdown(current: str, num_blocks: int, on_change: Callable[[str], None]) -> ViewerDropdown:
    """The "Fusion" dropdown; ``on_change`` gets the chosen mode."""
    options = fusion_options(num_blocks)
    return ViewerDropdown(
        name="Fusion",
        default_value=current if current in options else options[0],
        options=options,
        cb_hook=lambda element: on_change(element.value),
        hint="How block renders are combined: global = closest to the global model's colour (SCALAR-NeRF).",
    )


def box_edges(aabb_min: Sequence[float], aabb_max: Sequence[float]) -> np.ndarray:
    """[12, 2, 3] the edges of an axis-aligned box."""
    corners = box_corners(aabb_min, aabb_max)  # corner i has bit a set where it is at the max on axis a
    edges = [(i, i | (1 << a)) for i in range(8) for a in range(3) if not (i >> a) & 1]
    return np.stack([corners[[i, j]] for i, j in edges])


class BlockOverlay(ViewerControl):
    """Draws the blocks' scaled AABBs and the training cameras coloured by block into the viewer.

    Args:
        split: the block split (AABBs in the dataparser frame).
        camera_centres: [N, 3] training camera centres, dataparser frame.
    """

    def __init__(self, split: BlockSplit, camera_centres: np.ndarray) -> None:
        self.split = split
        self.camera_centres = np.asarray(camera_centres, dtype=np.float32)

    def _setup(self, viewer) -> None:  # called by nerfstudio's Viewer once the server runs
        super()._setup(viewer)
        scene = self.viser_server.scene
        owner = np.full(len(self.camera_centres), -1)
        for block in reversed(self.split.blocks):
            owner[list(block.image_indices)] = block.index
        for block in self.split.blocks:
            colour = tuple(int(255 * c) for c in block_colour(block.index))
            for e, (start, end) in enumerate(box_edges(block.aabb_min, block.aabb_max)):
                scene.add_spline_catmull_rom(
                    f"/scalar_blocks/block_{block.index}/edge_{e}",
                    positions=(tuple(start * VISER_SCALE), tuple(end * VISER_SCALE)),
                    color=colour, line_width=2.0,
                )
        colours = np.stack([block_colour(int(o)) for o in owner]).astype(np.float32)
        scene.add_point_cloud(
            "/scalar_blocks/cameras", points=self.camera_centres * VISER_SCALE, colors=colours, point_size=0.4, point_shape="circle"
        )
