"""What scalar-nerf adds to nerfstudio's viser viewer.

* a "Fusion" dropdown (every fusion mode of ``scalar_nerfstudio.fusion``, then block:k) that switches how
  the rendered image is fused, live, during training and on a trained run;
* the scene overlay: each block's scaled AABB as a wire box, and the training cameras as points
  coloured by block (a camera in several blocks takes its first block's colour);
* the ``block_colour`` output (chosen in the viewer's output dropdown) is made by the model: each
  pixel in the colour of the block that won it (grey: the global model).

* :class:`CoarseFirstRender`: a still view of a CPU model is rendered coarse first, then at full
  size (``viewer_render.py``).
* :class:`FinishedRunPanel`: on ``ns-viewer`` of a trained run, the panel shows the run's step and no
  "Pause Training" button (nerfstudio's viewer shows "Pause Training" and "Step: 0" there).

All are found by nerfstudio's viewer because they are attributes of the pipeline (the controls are
handed the viewer object: :class:`scalar_nerfstudio.seam.viewer.ViewerHook`).
"""

from __future__ import annotations

from typing import Any, Callable, Dict, List, Optional, Sequence

import numpy as np
from nerfstudio.viewer.viewer_elements import ViewerDropdown

from scalar_nerfstudio.blocks.palette import block_colour
from scalar_nerfstudio.blocks.split import BlockSplit
from scalar_nerfstudio.fusion import FUSION_MODES
from scalar_nerfstudio.seam.viewer import ViewerHook, hide_training_buttons, show_step, viewer_trains, viser_scale_ratio

#: Scene node under which the overlay is drawn.
OVERLAY_NODE = "/scalar_blocks"


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
    # corner i has bit a set where it is at the max on axis a
    corners = np.array([[(aabb_max if (i >> a) & 1 else aabb_min)[a] for a in range(3)] for i in range(8)], dtype=np.float64)
    edges = [(i, i | (1 << a)) for i in range(8) for a in range(3) if not (i >> a) & 1]
    return np.stack([corners[[i, j]] for i, j in edges])


class CoarseFirstRender(ViewerHook):
    """Makes the viewer render a still view of a CPU model coarse first, then at full size (GPU models
    keep nerfstudio's renders); see ``viewer_render.py``."""

    def viewer_ready(self, viewer: Any) -> None:
        from scalar_nerfstudio.viewer_render import install_progressive_render  # imports nerfstudio's viewer (slow)

        install_progressive_render(viewer)


class FinishedRunPanel(ViewerHook):
    """On a viewer without a trainer (``ns-viewer`` of a trained run) hides nerfstudio's "Pause Training" and
    "Resume Training" buttons (there is no training to pause) and shows the run's step in the stats line.

    nerfstudio's ``ns-viewer`` builds its viewer with no trainer, so the buttons show "Pause Training", and
    it passes the checkpoint's step to ``Viewer.update_scene``, which stores it in ``viewer.step`` but
    writes "Step:" only while training. The step is written when a browser connects (``update_scene``
    runs after the viewer's controls are set up).
    """

    def viewer_ready(self, viewer: Any) -> None:
        if viewer_trains(viewer):
            return  # ns-train: nerfstudio's buttons pause and resume the training
        hide_training_buttons(viewer)
        self.viser_server.on_client_connect(lambda client: self.show_step())

    def show_step(self) -> None:
        """Write the run's step (the viewer's) into the viewer's stats line."""
        show_step(self.viewer)


class BlockOverlay(ViewerHook):
    """Draws the blocks' scaled AABBs and the training cameras coloured by block into the viewer.

    The scene nodes viser returns are kept, so the overlay can be hidden (:meth:`set_visible`), drawn
    again in another style (:meth:`restyle`) or taken away (:meth:`remove`) while the viewer runs.

    Args:
        split: the block split (AABBs in the dataparser frame).
        camera_centres: [N, 3] training camera centres, dataparser frame.
        line_width: width of the AABB edges (pixels).
        point_size: size of the camera points (viewer scene units).
    """

    def __init__(self, split: BlockSplit, camera_centres: np.ndarray, *, line_width: float = 2.0, point_size: float = 0.4) -> None:
        self.split = split
        self.camera_centres = np.asarray(camera_centres, dtype=np.float32)
        self.line_width = line_width
        self.point_size = point_size
        self.visible = True
        self.edge_handles: Dict[int, List[Any]] = {}
        """Block index -> the scene nodes of its AABB's edges."""
        self.camera_handle: Optional[Any] = None
        """The scene node of the camera points."""

    def viewer_ready(self, viewer: Any) -> None:
        self.draw()

    @property
    def handles(self) -> List[Any]:
        """Every scene node of the overlay (empty before the viewer has set it up)."""
        edges = [handle for block in self.edge_handles.values() for handle in block]
        return edges + ([self.camera_handle] if self.camera_handle is not None else [])

    def camera_owners(self) -> np.ndarray:
        """[N] the block whose colour each training camera takes (its first block; -1: none)."""
        owner = np.full(len(self.camera_centres), -1)
        for block in reversed(self.split.blocks):
            owner[list(block.image_indices)] = block.index
        return owner

    def draw(self) -> None:
        """(Re)draw the overlay into the viewer's scene, in the current style and visibility."""
        scale = viser_scale_ratio()
        self.remove()
        scene = self.viser_server.scene
        for block in self.split.blocks:
            red, green, blue = (int(255 * c) for c in block_colour(block.index))
            self.edge_handles[block.index] = [
                scene.add_spline_catmull_rom(
                    f"{OVERLAY_NODE}/block_{block.index}/edge_{e}",
                    positions=(tuple(start * scale), tuple(end * scale)),
                    color=(red, green, blue), line_width=self.line_width, visible=self.visible,
                )
                for e, (start, end) in enumerate(box_edges(block.aabb_min, block.aabb_max))
            ]
        colours = np.stack([block_colour(int(o)) for o in self.camera_owners()]).astype(np.float32)
        self.camera_handle = scene.add_point_cloud(
            f"{OVERLAY_NODE}/cameras", points=self.camera_centres * scale, colors=colours,
            point_size=self.point_size, point_shape="circle", visible=self.visible,
        )

    def set_visible(self, visible: bool) -> None:
        """Show or hide the whole overlay (kept for later; nothing is drawn again)."""
        self.visible = bool(visible)
        for handle in self.handles:
            handle.visible = self.visible

    def restyle(self, line_width: Optional[float] = None, point_size: Optional[float] = None) -> None:
        """Change the edges' width and the camera points' size; drawn again at once if the viewer runs."""
        if line_width is not None:
            self.line_width = line_width
        if point_size is not None:
            self.point_size = point_size
        if self.handles:
            self.draw()

    def remove(self) -> None:
        """Take the overlay out of the viewer's scene (:meth:`draw` puts it back)."""
        for handle in self.handles:
            handle.remove()
        self.edge_handles, self.camera_handle = {}, None
