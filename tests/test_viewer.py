"""The viewer (fusion dropdown, block overlay and block colours, checked in a real headless browser), and
what the fusion modes render on a trained run of two blocks."""

from __future__ import annotations

import io
import shutil
import subprocess
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import tyro
from conftest import NUM_BLOCKS, running_viewer
from prerequisites import needs
from quality import (
    FUSION_TOLERANCE_DB,
    TRAINED_MARGIN_DB,
    eval_renders,
    image_difference,
    load_pipeline,
    untrained_psnr,
)

from scalar_nerfstudio.blocks.palette import BLOCK_PALETTE, block_colour
from scalar_nerfstudio.blocks.split import split_cameras
from scalar_nerfstudio.fusion_eval import evaluate_fusion_modes, markdown_table
from scalar_nerfstudio.models.fused_render import winner_colours
from scalar_nerfstudio.viewer import BlockOverlay, CoarseFirstRender, FinishedRunPanel, box_edges, fusion_options

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")


# ------------------------------------------------------------------------- pure pieces


def test_fusion_options_list_modes_and_blocks() -> None:
    assert fusion_options(2) == ["global", "surface", "idw", "nearest", "nearest-guarded", "nearest-idw", "global-only", "block:0", "block:1"]


def test_box_edges_are_the_twelve_unit_edges() -> None:
    edges = box_edges((0, 0, 0), (1, 2, 3))
    assert edges.shape == (12, 2, 3)
    lengths = sorted(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1).round(6).tolist())
    assert lengths == [1.0] * 4 + [2.0] * 4 + [3.0] * 4


class _FakeNode:
    def __init__(self, name: str, kwargs: dict) -> None:
        self.name, self.kwargs, self.visible, self.removed = name, kwargs, kwargs.get("visible", True), False

    def remove(self) -> None:
        self.removed = True


class _FakeScene:
    """viser's scene API as the overlay uses it: every add_* returns a node handle."""

    def __init__(self) -> None:
        self.nodes: list = []

    def _add(self, name: str, **kwargs) -> _FakeNode:
        self.nodes.append(_FakeNode(name, kwargs))
        return self.nodes[-1]

    add_spline_catmull_rom = add_point_cloud = _add


class _FakeViewer:
    def __init__(self) -> None:
        self.viser_server = type("Server", (), {"scene": _FakeScene()})()


def test_block_overlay_keeps_its_scene_nodes_to_hide_restyle_and_remove() -> None:
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

    centres = np.stack([np.linspace(-1, 1, 8), np.zeros(8), np.zeros(8)], axis=1)
    overlay = BlockOverlay(split_cameras(centres, 2, aabb_scale=(1.2, 1.2, 1.2)), centres)
    assert overlay.handles == []
    overlay.set_visible(False)  # before the viewer runs: remembered for the drawing
    viewer = _FakeViewer()
    overlay._setup(viewer)
    nodes = list(viewer.viser_server.scene.nodes)
    assert len(nodes) == 2 * 12 + 1 and overlay.handles == nodes
    assert not any(node.visible for node in nodes)
    cameras = overlay.camera_handle
    assert np.allclose(cameras.kwargs["points"], centres * VISER_NERFSTUDIO_SCALE_RATIO)
    assert tuple(cameras.kwargs["colors"][0]) == pytest.approx(block_colour(0)) and block_colour(1) == tuple(BLOCK_PALETTE[1].tolist())
    overlay.set_visible(True)
    assert all(node.visible for node in nodes)
    overlay.restyle(line_width=5.0)
    assert all(node.removed for node in nodes), "the old nodes are replaced"
    assert {h.kwargs["line_width"] for block in overlay.edge_handles.values() for h in block} == {5.0}
    drawn = overlay.handles
    overlay.remove()
    assert overlay.handles == [] and all(node.removed for node in drawn)


def test_coarse_first_render_control_makes_the_viewer_render_cpu_models_coarse_first() -> None:
    """The pipeline's CoarseFirstRender control is handed the viewer: it installs viewer_render.py's
    machines for a CPU model and leaves a GPU model's viewer as nerfstudio made it."""
    from scalar_nerfstudio.viewer_render import ProgressiveMachines

    for device, progressive in (("cpu", True), ("cuda", False)):
        viewer = _FakeViewer()
        viewer.render_statemachines = {}
        viewer.get_model = lambda device=device: type("Model", (), {"device": torch.device(device)})()
        CoarseFirstRender()._setup(viewer)
        assert isinstance(viewer.render_statemachines, ProgressiveMachines) is progressive


def test_finished_run_panel_hides_the_train_buttons_and_shows_the_runs_step_on_ns_viewer() -> None:
    """ns-viewer builds nerfstudio's Viewer without a trainer: no "Pause Training", and "Step:" is the run's
    step once a browser connects. Under ns-train (a trainer) nerfstudio's buttons are left alone."""
    from nerfstudio.viewer.viewer import Viewer

    for trainer in (None, object()):
        connect_callbacks: list = []
        viewer = _FakeViewer()
        viewer.viser_server.on_client_connect = connect_callbacks.append
        viewer.trainer, viewer.step = trainer, 0
        viewer.pause_train, viewer.resume_train = SimpleNamespace(visible=True), SimpleNamespace(visible=False)
        viewer.stats_markdown = SimpleNamespace(content="Step: 0  \nResolution: 0x0px")
        viewer.make_stats_markdown = lambda step, res, viewer=viewer: Viewer.make_stats_markdown(viewer, step, res)
        viewer.update_step = lambda step, viewer=viewer: Viewer.update_step(viewer, step)
        FinishedRunPanel()._setup(viewer)
        viewer.step = 499  # ns-viewer's update_scene(step=...) after the controls are set up
        for callback in connect_callbacks:
            callback(SimpleNamespace(client_id=1))
        if trainer is None:
            assert not viewer.pause_train.visible and not viewer.resume_train.visible
            assert viewer.stats_markdown.content.startswith("Step: 499")
        else:
            assert viewer.pause_train.visible and connect_callbacks == []


# --------------------------------------------------------------------- the trained run


@pytest.mark.slow
def test_dropdown_switches_fusion_and_block_colours(full_run: Path) -> None:
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(full_run / "config.yml", test_mode="test")
    model = pipeline.model
    camera, _ = next(iter(pipeline.datamanager.fixed_indices_eval_dataloader))
    dropdown = pipeline.fusion_dropdown
    assert dropdown.value == "nearest-guarded" and dropdown.options == fusion_options(NUM_BLOCKS)  # the default fusion
    fused = model.get_outputs_for_camera(camera)
    winners = set(fused["block_winner"].unique().long().tolist())
    assert winners <= set(range(NUM_BLOCKS)) and winners
    dropdown.cb_hook(type("Element", (), {"value": "block:1"})())
    assert str(model.fusion_mode) == "block:1"
    single = model.get_outputs_for_camera(camera)
    assert set(single["block_winner"].unique().long().tolist()) == {1}
    # every pixel of block_colour is the colour of the block that won it
    block1_colour = winner_colours(torch.tensor([[1.0]], device=model.device))[0]
    colours = single["block_colour"].reshape(-1, 3)
    assert torch.allclose(colours, block1_colour.expand_as(colours))
    assert not torch.allclose(block1_colour, winner_colours(torch.tensor([[-1.0]], device=model.device))[0])


# ------------------------------------------------------------------------ the browser


def _screenshot(driver) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"), dtype=np.float32)


def _choose(driver, label_text: str, option: str) -> None:
    """Pick ``option`` in the viewer's dropdown labelled ``label_text``."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions
    from selenium.webdriver.support.ui import WebDriverWait

    label = driver.find_element(By.XPATH, f"//label[text()='{label_text}']")
    field = driver.find_element(By.ID, label.get_attribute("for"))
    driver.execute_script("arguments[0].scrollIntoView({block: 'center'});", field)
    field.click()
    # The list opens when the browser gets to it: on a loaded machine that can take seconds.
    item = (By.XPATH, f"//*[@role='option'][normalize-space()='{option}']")
    WebDriverWait(driver, 60).until(expected_conditions.element_to_be_clickable(item)).click()
    WebDriverWait(driver, 30).until(lambda _: field.get_attribute("value") == option)


def _wait_for_change(driver, viewport, before: np.ndarray, timeout: float = 180.0) -> None:
    """Wait until the render area differs from ``before`` (the new render has arrived)."""
    deadline = time.time() + timeout
    while time.time() < deadline and np.abs(_screenshot(driver)[viewport] - before).mean() <= 2.0:
        time.sleep(1.0)


def _wait_for(driver, viewport, condition, timeout: float = 180.0) -> None:
    """Wait until ``condition(render area)`` holds (or the time-out; the caller asserts what it needs)."""
    deadline = time.time() + timeout
    while time.time() < deadline and not condition(_screenshot(driver)[viewport]):
        time.sleep(1.0)


def _colourfulness(image: np.ndarray) -> float:
    """Mean spread between an RGB pixel's largest and smallest channel (0 for greys)."""
    return float((image.max(axis=-1) - image.min(axis=-1)).mean())


def _settled(driver, viewport, timeout: float = 240.0) -> np.ndarray:
    """The render area once two screenshots 3 s apart agree (progressive refinement is over)."""
    deadline = time.time() + timeout
    previous = None
    while time.time() < deadline:
        image = _screenshot(driver)[viewport]
        if previous is not None and np.abs(image - previous).mean() < 0.05:
            return image
        previous = image
        time.sleep(3.0)
    raise AssertionError("the viewer's render did not settle")


@pytest.mark.slow
@needs("chromium and chromedriver", CHROMIUM is not None and CHROMEDRIVER is not None)
def test_browser_shows_a_render_that_changes_with_fusion(full_run: Path) -> None:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu", "--window-size=1000,700", "--enable-unsafe-swiftshader"):
        options.add_argument(argument)
    with running_viewer(full_run / "config.yml") as port:
        driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
        try:
            driver.get(f"http://127.0.0.1:{port}/")
            viewport = (slice(80, 520), slice(20, 660))  # the 3D view, left of the control panel
            rgb_render = _settled(driver, viewport)
            assert rgb_render.std() > 5.0, "the render area is blank"

            # The block_colour output paints each pixel in the colour of the block that won it:
            # under global fusion that is block colours (tab10 blue/orange), under global-only grey.
            _choose(driver, "Output type", "block_colour")
            _wait_for_change(driver, viewport, rgb_render)
            blocks_render = _settled(driver, viewport)
            _choose(driver, "Fusion", "global-only")
            # A render of the global model and both blocks can take longer than _settled's 3 s window,
            # so wait for the grey of global-only (or the time-out) before taking the settled image.
            _wait_for(driver, viewport, lambda image: _colourfulness(image) <= _colourfulness(blocks_render) - 10.0)
            global_only_render = _settled(driver, viewport)
            assert _colourfulness(blocks_render) > _colourfulness(global_only_render) + 10.0, "fusion did not change the block colours"
            assert np.abs(global_only_render - blocks_render).mean() > 5.0, "switching the fusion did not change the image"
        finally:
            driver.quit()


# ------------------------------------------------------------------ render and eval commands


def test_render_command_refuses_an_unknown_fusion_before_loading_anything(tmp_path: Path) -> None:
    from scalar_nerfstudio.scripts.render import Commands

    command = tyro.cli(Commands, args=["dataset", "--load-config", str(tmp_path / "no-run" / "config.yml"), "--fusion", "median",
                                       "--output-path", str(tmp_path / "x")])
    with pytest.raises(SystemExit, match="unknown fusion mode 'median'"):
        command.main()
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_render_command_writes_the_runs_own_render_under_the_fusion_asked(full_run: Path, tmp_path: Path) -> None:
    """``scalar-nerf-render dataset --fusion block:1`` writes, for every held-out view, what the run
    renders in-process for that camera under block:1 (to the 8-bit level), which is not what its
    global model renders."""
    output = tmp_path / "block_1"
    result = subprocess.run(
        ["scalar-nerf-render", "dataset", "--fusion", "block:1", "--load-config", str(full_run / "config.yml"), "--output-path", str(output),
         "--split", "test", "--rendered-output-names", "rgb", "--image-format", "png"],
        capture_output=True, text=True, timeout=600, check=False
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    saved = sorted((output / "test" / "rgb").rglob("*.png"))
    pipeline = load_pipeline(full_run)
    names = [Path(f).name for f in pipeline.datamanager.eval_dataset.image_filenames]
    assert [p.stem for p in saved] == sorted(Path(n).stem for n in names)
    _, block_1 = eval_renders(pipeline, "block:1")
    _, global_only = eval_renders(pipeline, "global-only")
    differences = []
    for name, render, other in zip(names, block_1, global_only):
        (path,) = [p for p in saved if p.stem == Path(name).stem]
        assert image_difference(path, render) < 1.0, f"{path.name} is not the run's block:1 render of that camera"
        differences.append(image_difference(path, other))
    assert np.mean(differences) > 1.0, f"block:1 renders what the global model renders: {differences}"


@pytest.mark.slow
def test_every_fusion_mode_scores_at_least_the_global_model_and_beats_step_0(full_run: Path) -> None:
    """The fusion table (``scalar-nerf-eval-fusion``'s, computed in-process): every fusion of the
    trained blocks scores at least the global model alone (within FUSION_TOLERANCE_DB) and beats the
    run's untrained model by TRAINED_MARGIN_DB; the table's bookkeeping is consistent."""
    modes = ("global", "surface", "idw", "nearest", "nearest-guarded", "nearest-idw", "global-only")
    table = evaluate_fusion_modes(load_pipeline(full_run), modes)
    step_0 = untrained_psnr(full_run)
    print({mode: round(table[mode]["psnr"], 2) for mode in modes}, f"step 0: {step_0:.2f} dB")
    for mode in modes:
        assert table[mode]["psnr"] >= table["global-only"]["psnr"] - FUSION_TOLERANCE_DB, (mode, table[mode]["psnr"], table["global-only"]["psnr"])
        assert table[mode]["psnr"] > step_0 + TRAINED_MARGIN_DB, (mode, table[mode]["psnr"], step_0)
        assert 0.0 < table[mode]["ssim"] <= 1.0 and table[mode]["ms_per_image"] > 0
    for mode in ("global", "surface", "idw"):
        assert table["selection:" + mode]["num_images"] == table[mode]["num_images"] > 0
    assert table["global-only"]["global_pixel_share"] == 1.0 and table["nearest"]["global_pixel_share"] == 0.0
    assert 0.0 <= table["nearest-guarded"]["global_pixel_share"] < 1.0  # the global model only where its block is transparent
    markdown = markdown_table(table)
    assert "| global |" in markdown and "| idw |" in markdown
