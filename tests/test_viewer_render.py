"""Progressive viewer renders of CPU models (viewer_render.py), driven through nerfstudio's own render
state machine and viewer code with a fake browser client and a fake model whose render time is known."""

from __future__ import annotations

import time
from types import SimpleNamespace
from typing import List, Optional, Tuple

import pytest
import torch
from nerfstudio.cameras.cameras import CameraType
from nerfstudio.utils import writer
from nerfstudio.utils.colormaps import ColormapOptions
from nerfstudio.viewer.render_state_machine import RenderAction, RenderStateMachine
from nerfstudio.viewer.utils import CameraState
from nerfstudio.viewer.viewer import Viewer

from scalar_nerfstudio.viewer_render import (
    ProgressiveMachines,
    ProgressiveRenderStateMachine,
    RenderSpeed,
    coarse_resolution,
    install_progressive_render,
)

ASPECT = 1.5
MAX_RES = 256  # full size at this aspect: 170 x 256
FULL = (170, 256)


class _FakeModel(torch.nn.Module):
    """Renders a grey image in ``seconds_per_pixel`` x its pixels, in small Python steps (so nerfstudio's
    line-trace interrupt can stop it), and logs the (height, width) of every render it starts."""

    def __init__(self, seconds_per_pixel: float, device: str = "cpu") -> None:
        super().__init__()
        self.seconds_per_pixel = seconds_per_pixel
        self._device = torch.device(device)
        self.started: List[Tuple[int, int]] = []

    @property
    def device(self) -> torch.device:
        return self._device

    def get_outputs_for_camera(self, camera, obb_box=None):
        height, width = int(camera.height.item()), int(camera.width.item())
        self.started.append((height, width))
        deadline = time.perf_counter() + self.seconds_per_pixel * height * width
        while time.perf_counter() < deadline:
            time.sleep(0.005)
        return {"rgb": torch.full((height, width, 3), 0.5)}


class _FakeClient:
    """A browser client as the state machine uses it: its camera's aspect, and the background image."""

    def __init__(self, client_id: int = 1) -> None:
        self.client_id = client_id
        self.camera = SimpleNamespace(aspect=ASPECT, on_update=lambda callback: callback)
        self.images: List[Tuple[Tuple[int, int], float]] = []
        self.scene = SimpleNamespace(set_background_image=self._show)

    def _show(self, image, format, jpeg_quality, depth) -> None:
        self.images.append((tuple(image.shape[:2]), time.perf_counter()))

    def wait_for_images(self, count: int, timeout: float = 20.0) -> List[Tuple[int, int]]:
        deadline = time.time() + timeout
        while len(self.images) < count and time.time() < deadline:
            time.sleep(0.01)
        return [shape for shape, _ in self.images]


def _camera_state() -> CameraState:
    return CameraState(fov=1.0, aspect=ASPECT, c2w=torch.eye(4, dtype=torch.float64)[:3], camera_type=CameraType.PERSPECTIVE)


class _FakeViewer:
    """What nerfstudio's RenderStateMachine reads from its Viewer."""

    def __init__(self, model: _FakeModel, ready: bool = True) -> None:
        self.model = model
        self.ready = ready
        self.include_time = False
        self.train_lock = None
        self.step = 0
        self.config = SimpleNamespace(jpeg_quality=75, image_format="jpeg")
        self.render_tab_state = SimpleNamespace(preview_render=False)
        self.stats_markdown = SimpleNamespace(content="Step: 0  \nResolution: 0x0px")
        self.control_panel = SimpleNamespace(
            max_res=MAX_RES, crop_viewport=False, layer_depth=False, output_render="rgb", split=False,
            colormap_options=ColormapOptions(), background_color=(0, 0, 0), update_output_options=lambda keys: None,
        )
        self.render_statemachines: dict = {}

    def get_model(self) -> _FakeModel:
        return self.model

    def get_camera_state(self, client) -> CameraState:
        return _camera_state()

    def make_stats_markdown(self, step: Optional[int], res: Optional[str]) -> str:
        return f"Step: {self.step}  \nResolution: {res}"

    def update_colormap_options(self, dimensions: int, dtype: type) -> None:
        pass


@pytest.fixture(autouse=True)
def _no_nerfstudio_event_writer(monkeypatch: pytest.MonkeyPatch) -> None:
    """nerfstudio sizes move renders from its logged rays/s when its writer is set up (global state other
    tests may have set): off here, so nerfstudio's move resolution is its fixed default."""
    monkeypatch.setattr(writer, "is_initialized", lambda: False)


def _machine(model: _FakeModel, speed: RenderSpeed, budget_s: float) -> Tuple[ProgressiveRenderStateMachine, _FakeClient]:
    client = _FakeClient()
    machine = ProgressiveRenderStateMachine(_FakeViewer(model), 1.0, client, speed=speed)
    machine.coarse_budget_s = budget_s
    return machine, client


def _stop(machine: RenderStateMachine) -> None:
    machine.running = False
    machine.interrupt_render_flag = True
    if machine.ident is not None:
        machine.join(timeout=10)


def _measured(seconds_per_pixel: float) -> RenderSpeed:
    speed = RenderSpeed()
    speed.record(10_000, 10_000 * seconds_per_pixel)
    return speed


# ------------------------------------------------------------------------ choosing the coarse size


def test_coarse_height_comes_from_measured_render_time() -> None:
    assert RenderSpeed().seconds_per_pixel is None
    speed = RenderSpeed(window=3)
    speed.record(1_000, 2.0)  # a slow first render (warm-up) ...
    for _ in range(3):
        speed.record(100_000, 10.0)  # ... drops out of the window of recent renders
    assert speed.seconds_per_pixel == pytest.approx(1e-4)
    assert speed.seconds_for(5_000) == pytest.approx(0.5)
    # the budget buys budget / (seconds per pixel) pixels at the view's aspect
    assert coarse_resolution(ASPECT, 1.0 / 6144, budget_s=1.0) == (64, 96)
    assert coarse_resolution(ASPECT, 4.0 / 6144, budget_s=1.0) == (32, 48)  # 4x slower: half the height
    assert coarse_resolution(ASPECT, 4.0 / 6144, budget_s=4.0) == (64, 96)
    assert coarse_resolution(ASPECT, None) == (48, 72)  # nothing measured yet
    assert coarse_resolution(ASPECT, 1e-9) == (96, 144)  # fast: capped
    assert coarse_resolution(ASPECT, 1.0) == (24, 36)  # hopeless: floored


def test_when_a_coarse_pass_is_made() -> None:
    model = _FakeModel(seconds_per_pixel=1.0 / 6144)
    machine, _ = _machine(model, _measured(1.0 / 6144), budget_s=1.0)
    machine.state = "low_move"
    assert machine.coarse_pass_resolution(ASPECT) is None  # nerfstudio's low renders stay as they are
    machine.state = "high"
    assert machine.coarse_pass_resolution(ASPECT) == (64, 96)
    machine.shown_resolution = FULL  # a full-size image on screen (a training step re-render): no coarse
    assert machine.coarse_pass_resolution(ASPECT) is None
    machine.shown_resolution = (30, 45)  # nerfstudio's move-sized image on screen: coarse first
    assert machine.coarse_pass_resolution(ASPECT) == (64, 96)
    quick, _ = _machine(model, _measured(1e-7), budget_s=1.0)
    quick.state = "high"
    assert quick.coarse_pass_resolution(ASPECT) is None  # the full render takes less than the budget
    gpu, _ = _machine(_FakeModel(1e-4, device="cuda"), _measured(1e-4), budget_s=1.0)
    gpu.state = "high"
    assert gpu.coarse_pass_resolution(ASPECT) is None


# ------------------------------------------------------------- nerfstudio's state machine, running


def test_static_view_shows_coarse_image_then_full_resolution() -> None:
    seconds_per_pixel = 0.1 / 6144  # measured speed: 0.1 s buys a 64 x 96 coarse image
    model = _FakeModel(seconds_per_pixel)
    machine, client = _machine(model, _measured(seconds_per_pixel), budget_s=0.1)
    machine.start()  # state low_static; with no camera move the machine asks itself for a static render
    try:
        assert client.wait_for_images(2) == [(64, 96), FULL]
        assert model.started == [(64, 96), FULL] and machine.coarse_passes == 1
        coarse_shown, full_shown = client.images[0][1], client.images[1][1]
        full_seconds = FULL[0] * FULL[1] * seconds_per_pixel
        assert full_shown - coarse_shown >= 0.9 * full_seconds  # the coarse image was up while the full one rendered
        # A training step re-renders at full size over the full-size image: no coarse pass again.
        machine.action(RenderAction("step", _camera_state()))
        assert client.wait_for_images(3)[2] == FULL and machine.coarse_passes == 1
        # the machine measured its own renders: the speed now reflects them
        assert machine.speed.seconds_per_pixel == pytest.approx(seconds_per_pixel, rel=0.5)
    finally:
        _stop(machine)


def test_moving_the_camera_interrupts_and_renders_like_nerfstudio() -> None:
    seconds_per_pixel = 1e-4  # the full image would take 4.4 s
    model = _FakeModel(seconds_per_pixel)
    machine, client = _machine(model, _measured(seconds_per_pixel), budget_s=0.1)
    nerfstudio = RenderStateMachine(_FakeViewer(model), 1.0, _FakeClient())
    nerfstudio.state = "low_move"
    move_resolution = nerfstudio._calculate_image_res(ASPECT)
    assert move_resolution == (50, 75)
    machine.start()
    try:
        assert client.wait_for_images(1) == [(25, 37)]  # coarse: 0.1 s at the measured speed
        deadline = time.time() + 5
        while FULL not in model.started and time.time() < deadline:
            time.sleep(0.005)
        started = time.perf_counter()
        machine.action(RenderAction("move", _camera_state()))
        # the full render is interrupted; the move, then the still camera, render at nerfstudio's size
        assert client.wait_for_images(3) == [(25, 37), move_resolution, move_resolution]
        assert client.images[1][1] - started < 2.0
        assert model.started[:3] == [(25, 37), FULL, move_resolution]
    finally:
        _stop(machine)


# ----------------------------------------------------------------------- the hook into the viewer


def test_viewer_builds_progressive_machines_once_installed() -> None:
    viewer = _FakeViewer(_FakeModel(1e-4), ready=False)
    early_client = _FakeClient(client_id=1)
    Viewer.handle_new_client(viewer, early_client)  # a browser that connected before the set-up
    early = viewer.render_statemachines[1]
    assert type(early) is RenderStateMachine and early.is_alive()
    try:
        assert install_progressive_render(viewer)
        machines = viewer.render_statemachines
        assert isinstance(machines, ProgressiveMachines)
        assert isinstance(machines[1], ProgressiveRenderStateMachine) and machines[1].client is early_client
        early.join(timeout=5)
        assert not early.is_alive()  # nerfstudio's machine for that client has stopped
        # nerfstudio's own handle_new_client now builds and starts ours
        Viewer.handle_new_client(viewer, _FakeClient(client_id=2))
        assert isinstance(machines[2], ProgressiveRenderStateMachine) and machines[2].is_alive()
        assert machines[1].speed is machines[2].speed is machines.speed  # one measured speed per viewer
        assert install_progressive_render(viewer) and viewer.render_statemachines is machines  # idempotent
    finally:
        for machine in [early, *viewer.render_statemachines.values()]:
            _stop(machine)


def test_gpu_model_keeps_nerfstudio_machines() -> None:
    viewer = _FakeViewer(_FakeModel(1e-4, device="cuda"), ready=False)
    assert not install_progressive_render(viewer)
    Viewer.handle_new_client(viewer, _FakeClient())
    try:
        assert type(viewer.render_statemachines) is dict and type(viewer.render_statemachines[1]) is RenderStateMachine
    finally:
        _stop(viewer.render_statemachines[1])

