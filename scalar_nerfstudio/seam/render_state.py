"""nerfstudio's per-client render thread, extended (``nerfstudio/viewer/render_state_machine.py`` and
``nerfstudio/viewer/viewer.py`` of nerfstudio 1.1.5).

What is relied on, each checked by ``tests/test_nerfstudio_seam.py``:

* ``RenderStateMachine(viewer, viser_scale_ratio, client)`` is a ``threading.Thread`` whose ``run``
  renders with the private ``_render_img(camera_state)`` (which sizes the image with the private
  ``_calculate_image_res(aspect_ratio)``) and shows it with the private
  ``_send_output_to_viewer(outputs, static_render=...)``; it keeps its arguments as ``viewer``,
  ``viser_scale_ratio`` and ``client``, its state ("low_move", "low_static", "high") as ``state``, and
  stops when ``running`` is False (a render in progress when ``interrupt_render_flag`` is set);
* ``Viewer.handle_new_client`` puts a new ``RenderStateMachine`` into ``viewer.render_statemachines``
  and then starts the one found there under the client's id.
"""

from __future__ import annotations

from typing import Any, Dict, Tuple

from nerfstudio.viewer.render_state_machine import RenderStateMachine
from nerfstudio.viewer.utils import CameraState

__all__ = ["RenderStateMachineBase", "SwappingMachines"]


class RenderStateMachineBase(RenderStateMachine):
    """nerfstudio's ``RenderStateMachine`` whose private steps are public methods a subclass extends:
    :meth:`image_resolution` (the size of the next image), :meth:`render_image` (one render; its size from
    :meth:`image_resolution`) and :meth:`show_output` (send it to the browser)."""

    def __init__(self, viewer: Any, viser_scale_ratio: float, client: Any) -> None:
        super().__init__(viewer, viser_scale_ratio, client)

    # ------------------------------------------------------------------ what nerfstudio calls
    def _calculate_image_res(self, aspect_ratio: float) -> Tuple[int, int]:
        return self.image_resolution(aspect_ratio)

    def _render_img(self, camera_state: CameraState) -> Dict[str, Any]:
        return self.render_image(camera_state)

    def _send_output_to_viewer(self, outputs: Dict[str, Any], static_render: bool = True) -> None:
        self.show_output(outputs, static_render=static_render)

    # ------------------------------------------------------------------ what a subclass extends
    def image_resolution(self, aspect_ratio: float) -> Tuple[int, int]:
        """(height, width) of the next render at ``aspect_ratio`` (default: :meth:`nerfstudio_image_resolution`)."""
        return self.nerfstudio_image_resolution(aspect_ratio)

    def nerfstudio_image_resolution(self, aspect_ratio: float) -> Tuple[int, int]:
        """The (height, width) nerfstudio chooses for the current :attr:`render_state` and the viewer's settings."""
        return RenderStateMachine._calculate_image_res(self, aspect_ratio)

    def render_image(self, camera_state: CameraState) -> Dict[str, Any]:
        """Render the view of ``camera_state`` (nerfstudio's render, sized by :meth:`image_resolution`)."""
        return RenderStateMachine._render_img(self, camera_state)

    def show_output(self, outputs: Dict[str, Any], *, static_render: bool = True) -> None:
        """Send a render's ``outputs`` to the browser (nerfstudio's)."""
        RenderStateMachine._send_output_to_viewer(self, outputs, static_render=static_render)

    @property
    def render_state(self) -> str:
        """nerfstudio's state of this machine: "high" for a still camera at full size, "low_move", "low_static"."""
        return str(self.state)


class SwappingMachines(dict):
    """A viewer's ``render_statemachines`` that puts, in place of each plain nerfstudio ``RenderStateMachine``
    put into it, the machine :meth:`build` makes from the same arguments.

    nerfstudio's ``handle_new_client`` does ``machines[id] = RenderStateMachine(...)`` and then
    ``machines[id].start()``: the machine it built is never started, the replacement is. A machine that
    is already running (a browser connected before the swap) is stopped, and its replacement started in
    its state.
    """

    def build(self, viewer: Any, viser_scale_ratio: float, client: Any) -> RenderStateMachine:
        """The replacement of nerfstudio's machine for ``client`` (a subclass says which)."""
        raise NotImplementedError

    def __setitem__(self, client_id: int, machine: RenderStateMachine) -> None:
        if type(machine) is RenderStateMachine:
            running = machine.ident is not None
            replacement = self.build(machine.viewer, machine.viser_scale_ratio, machine.client)
            if running:
                machine.running = False
                machine.interrupt_render_flag = True
                replacement.state = machine.state
                replacement.start()
            machine = replacement
        super().__setitem__(client_id, machine)
