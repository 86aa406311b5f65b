"""nerfstudio's viser viewer, where scalar-nerf reaches past its documented elements
(``nerfstudio/viewer/viewer_elements.py`` and ``nerfstudio/viewer/viewer.py`` of nerfstudio 1.1.5).

A ``ViewerControl`` among the pipeline's attributes is handed the viewer object by the viewer
(``Viewer.__init__`` calls ``control._setup(viewer)``, marked "internal use only"), which sets its
``viewer`` and ``viser_server``. The viewer's attributes read here are undocumented: ``trainer`` (None
for ``ns-viewer``), the ``pause_train`` / ``resume_train`` buttons, ``step`` and ``update_step``,
``get_model()``, ``render_statemachines`` and the module's ``VISER_NERFSTUDIO_SCALE_RATIO``. Each is
checked by ``tests/test_nerfstudio_seam.py``.
"""

from __future__ import annotations

from typing import Any, Optional

from nerfstudio.viewer.viewer_elements import ViewerControl

__all__ = [
    "ViewerHook",
    "hide_training_buttons",
    "render_state_machines",
    "set_render_state_machines",
    "show_step",
    "viewer_model_device",
    "viewer_trains",
    "viser_scale_ratio",
]


class ViewerHook(ViewerControl):
    """A ``ViewerControl`` (found by the viewer among the pipeline's attributes) that is told, by
    :meth:`viewer_ready`, once the viewer has set it up; ``self.viewer`` and ``self.viser_server`` are set then."""

    def _setup(self, viewer: Any) -> None:  # called by nerfstudio's Viewer once the server runs
        super()._setup(viewer)
        self.viewer_ready(viewer)

    def viewer_ready(self, viewer: Any) -> None:
        """The viewer (nerfstudio's ``Viewer``) has set this control up."""


def viewer_trains(viewer: Any) -> bool:
    """Whether the viewer shows a training run (``ns-train``; ``ns-viewer`` builds it without a trainer)."""
    return getattr(viewer, "trainer", None) is not None


def hide_training_buttons(viewer: Any) -> None:
    """Hide the viewer's "Pause Training" and "Resume Training" buttons (where it has them)."""
    for name in ("pause_train", "resume_train"):
        button = getattr(viewer, name, None)
        if button is not None:
            button.visible = False


def show_step(viewer: Any) -> None:
    """Write the step the viewer was last given (``ns-viewer``: the checkpoint's) into its stats line."""
    viewer.update_step(int(viewer.step))


def viewer_model_device(viewer: Any) -> Optional[str]:
    """The device type ("cpu", "cuda") of the model the viewer renders (None: it has no device)."""
    device = getattr(viewer.get_model(), "device", None)
    return None if device is None else str(device).split(":")[0]


def render_state_machines(viewer: Any) -> Optional[Any]:
    """The viewer's per-client render threads, client id -> machine (None: a viewer without them)."""
    return getattr(viewer, "render_statemachines", None)


def set_render_state_machines(viewer: Any, machines: Any) -> None:
    """Give the viewer ``machines`` (a dict) to put its per-client render threads in."""
    viewer.render_statemachines = machines


def viser_scale_ratio() -> float:
    """How many viser scene units the viewer draws per world unit (imports nerfstudio's viewer)."""
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

    return float(VISER_NERFSTUDIO_SCALE_RATIO)
