"""Progressive rendering in nerfstudio's viewer for models that render on the CPU.

nerfstudio's viewer (``nerfstudio/viewer/render_state_machine.py``) renders a still camera at the
full "Max res" at once (state ``high``). On a CPU that render takes 45-90 s, and when the view is
opened (or after a render that was on screen at that size) nothing new appears until it is done.

:class:`ProgressiveRenderStateMachine` is nerfstudio's state machine with one change: a render in
state ``high`` of a model on the CPU first renders and shows a coarse image, sized from the measured
render time per pixel so that it takes about :attr:`~ProgressiveRenderStateMachine.coarse_budget_s`,
then renders the requested resolution. Moving the camera (and any other action) goes through
nerfstudio's unchanged code: a move interrupts either pass, and the low-resolution renders while
moving are sized by nerfstudio as before. GPU models keep nerfstudio's own state machine.

The hook: nerfstudio's ``Viewer.handle_new_client`` builds one ``RenderStateMachine`` per browser
client, puts it into ``viewer.render_statemachines`` and starts it from there.
:func:`install_progressive_render` replaces that (instance) dict by :class:`ProgressiveMachines`, which
puts a :class:`ProgressiveRenderStateMachine` in place of the machine nerfstudio built, before it is
started. Nothing in nerfstudio's modules is patched; only the one viewer object is changed. It is
called from ``viewer.CoarseFirstRender``, a ``ViewerControl`` (the viewer hands it the viewer object),
so it works for ``ns-train`` and ``ns-viewer`` alike. What of nerfstudio's render state machine and
viewer this relies on is in :mod:`scalar_nerfstudio.seam.render_state` and :mod:`scalar_nerfstudio.seam.viewer`.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from typing import Any, Deque, Dict, Optional, Tuple

from nerfstudio.viewer.utils import CameraState

from scalar_nerfstudio.seam.render_state import RenderStateMachineBase, SwappingMachines
from scalar_nerfstudio.seam.viewer import render_state_machines, set_render_state_machines, viewer_model_device

#: Seconds the coarse pass should take (measured render time per pixel x its pixels).
COARSE_BUDGET_S = 1.0
#: Bounds on the coarse pass's height in pixels.
COARSE_MIN_HEIGHT = 24
COARSE_MAX_HEIGHT = 96
#: Height of the coarse pass before any render time has been measured (the viewer's first render).
UNMEASURED_HEIGHT = 48


class RenderSpeed:
    """Render times of the last few renders of one viewer -> seconds per pixel.

    The estimate is total seconds / total pixels over the window, so the large renders (whose time is
    mostly per-pixel work) weigh most, and a small render's fixed costs or wait for the training lock
    do not make the estimate jump. Shared by the render threads of all browser clients.
    """

    def __init__(self, window: int = 8) -> None:
        self._records: Deque[Tuple[int, float]] = deque(maxlen=window)
        self._lock = threading.Lock()

    def record(self, pixels: int, seconds: float) -> None:
        if pixels > 0 and seconds > 0:
            with self._lock:
                self._records.append((int(pixels), float(seconds)))

    @property
    def seconds_per_pixel(self) -> Optional[float]:
        """Measured seconds per rendered pixel; None before any render."""
        with self._lock:
            pixels = sum(p for p, _ in self._records)
            seconds = sum(s for _, s in self._records)
        return seconds / pixels if pixels else None

    def seconds_for(self, pixels: int) -> Optional[float]:
        per_pixel = self.seconds_per_pixel
        return None if per_pixel is None else per_pixel * pixels


def coarse_resolution(
    aspect: float,
    seconds_per_pixel: Optional[float],
    *,
    budget_s: float = COARSE_BUDGET_S,
    min_height: int = COARSE_MIN_HEIGHT,
    max_height: int = COARSE_MAX_HEIGHT,
    unmeasured_height: int = UNMEASURED_HEIGHT,
) -> Tuple[int, int]:
    """(height, width) of the coarse pass: as many pixels as ``budget_s`` allows at the measured speed,
    height clamped to [min_height, max_height]; ``unmeasured_height`` while nothing is measured."""
    if seconds_per_pixel is None or seconds_per_pixel <= 0:
        height = unmeasured_height
    else:
        height = int(math.sqrt(budget_s / seconds_per_pixel / aspect) + 1e-6)
    height = max(min_height, min(max_height, height))
    return height, max(1, int(height * aspect))


class ProgressiveRenderStateMachine(RenderStateMachineBase):
    """nerfstudio's render state machine, plus a coarse first pass before a full-resolution CPU render.

    The coarse pass is made when all hold: the state is ``high`` (a still camera at "Max res"), the
    model is on the CPU, the image on screen is smaller than the coarse one would be (so a ``step``
    re-render during training, which replaces a full-size image, goes straight to full size), and the
    full-size render is expected to take longer than ``coarse_budget_s`` and is at least twice the
    coarse height.
    """

    coarse_budget_s: float = COARSE_BUDGET_S
    coarse_min_height: int = COARSE_MIN_HEIGHT
    coarse_max_height: int = COARSE_MAX_HEIGHT
    unmeasured_height: int = UNMEASURED_HEIGHT

    def __init__(self, viewer: Any, viser_scale_ratio: float, client: Any, *, speed: Optional[RenderSpeed] = None) -> None:
        super().__init__(viewer, viser_scale_ratio, client)
        self.speed = speed if speed is not None else RenderSpeed()
        self.shown_resolution: Optional[Tuple[int, int]] = None
        """(height, width) of the image last sent to the browser (None: nothing yet)."""
        self.coarse_passes = 0
        """How many coarse passes were shown."""
        self._forced_resolution: Optional[Tuple[int, int]] = None
        self._last_resolution: Optional[Tuple[int, int]] = None
        self._rendered_resolution: Optional[Tuple[int, int]] = None

    # ------------------------------------------------------------------ nerfstudio's steps, extended
    def image_resolution(self, aspect_ratio: float) -> Tuple[int, int]:
        resolution = self._forced_resolution or super().image_resolution(aspect_ratio)
        self._last_resolution = resolution
        return resolution

    def render_image(self, camera_state: CameraState) -> Dict[str, Any]:
        coarse = self.coarse_pass_resolution(camera_state.aspect)
        if coarse is not None:
            self._forced_resolution = coarse
            try:
                outputs = self._timed_render(camera_state)
            finally:
                self._forced_resolution = None
            # A move or rerender during this pass raised out of it (nerfstudio's interrupt); one that
            # comes while it is sent interrupts the full pass at its first line.
            self.show_output(outputs, static_render=True)
            self.coarse_passes += 1
        return self._timed_render(camera_state)

    def show_output(self, outputs: Dict[str, Any], *, static_render: bool = True) -> None:
        super().show_output(outputs, static_render=static_render)
        self.shown_resolution = self._rendered_resolution

    # --------------------------------------------------------------------------------- the additions
    def on_cpu(self) -> bool:
        return viewer_model_device(self.viewer) == "cpu"

    def coarse_pass_resolution(self, aspect: float) -> Optional[Tuple[int, int]]:
        """(height, width) of the coarse pass the next render makes first; None: no coarse pass."""
        if self.render_state != "high" or not self.on_cpu():
            return None
        full_height, full_width = self.nerfstudio_image_resolution(aspect)
        height, width = coarse_resolution(
            aspect, self.speed.seconds_per_pixel, budget_s=self.coarse_budget_s,
            min_height=self.coarse_min_height, max_height=self.coarse_max_height, unmeasured_height=self.unmeasured_height,
        )
        if width > full_width:  # a very wide view: Max res bounds the width
            height, width = max(1, int(full_width * height / width)), full_width
        if 2 * height > full_height:
            return None
        if self.shown_resolution is not None and self.shown_resolution[0] >= height:
            return None  # what is on screen is already at least as fine
        expected = self.speed.seconds_for(full_height * full_width)
        if expected is not None and expected <= self.coarse_budget_s:
            return None  # the full render is quick anyway
        return height, width

    def _timed_render(self, camera_state: CameraState) -> Dict[str, Any]:
        start = time.perf_counter()
        outputs = super().render_image(camera_state)
        seconds = time.perf_counter() - start
        self._rendered_resolution = self._last_resolution
        if self._last_resolution is not None:
            self.speed.record(self._last_resolution[0] * self._last_resolution[1], seconds)
        return outputs


class ProgressiveMachines(SwappingMachines):
    """``viewer.render_statemachines`` that turns each nerfstudio ``RenderStateMachine`` put into it
    into a :class:`ProgressiveRenderStateMachine` (one :class:`RenderSpeed` for the whole viewer;
    how the machines are swapped: :class:`~scalar_nerfstudio.seam.render_state.SwappingMachines`)."""

    def __init__(self, speed: Optional[RenderSpeed] = None) -> None:
        super().__init__()
        self.speed = speed if speed is not None else RenderSpeed()

    def build(self, viewer: Any, viser_scale_ratio: float, client: Any) -> ProgressiveRenderStateMachine:
        return ProgressiveRenderStateMachine(viewer, viser_scale_ratio, client, speed=self.speed)


def install_progressive_render(viewer: Any) -> bool:
    """Make ``viewer`` (nerfstudio's ``Viewer``) render still views of a CPU model coarse-then-full.

    Idempotent; does nothing (False) for a model that is not on the CPU or a viewer without
    ``render_statemachines`` (another nerfstudio version): there nerfstudio's behaviour is kept.
    """
    machines = render_state_machines(viewer)
    if isinstance(machines, ProgressiveMachines):
        return True
    if not isinstance(machines, dict):
        return False
    if viewer_model_device(viewer) != "cpu":
        return False
    progressive = ProgressiveMachines()
    set_render_state_machines(viewer, progressive)
    for client_id, machine in list(machines.items()):
        progressive[client_id] = machine
    return True
