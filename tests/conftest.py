"""Shared fixtures: the real scenes beside the repo and the short trained runs every verb, fusion,
viewer, export and assembly test reuses.

The suite runs on several pytest-xdist workers (README: ``pytest -n auto``). A session fixture that
trains is built once for all of them (:func:`built_once`: the first worker to ask builds it under a
file lock, the others wait and read its result); the runs it returns are read-only for the tests
(a test that changes a run copies it first). Each worker's torch, and every command it starts, uses
one thread per worker so that the workers do not fight over the cores.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, TypeVar

import numpy as np
import pytest
import torch
from filelock import FileLock
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import SceneBox
from prerequisites import CASTLE, apply_needs_markers, need_castle

from scalar_nerfstudio.fields.scalar_field import ScalarFieldConfig
from scalar_nerfstudio.models.scalar_model import ScalarModel, ScalarModelConfig
from scalar_nerfstudio.runs import latest_checkpoint_step
from scalar_nerfstudio.scenes.courtyard import write_scene

#: This pytest-xdist worker's name ("gw0", ...); None when pytest runs without workers.
XDIST_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
if XDIST_WORKER is not None:
    # One thread per worker, for this process and every command it starts: two workers of 2 threads
    # each on 2 cores spin-wait for each other at every OpenMP barrier.
    _workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    _cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, _cores // max(1, _workers))))
    os.environ.setdefault("MKL_NUM_THREADS", os.environ["OMP_NUM_THREADS"])
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))


# A short run that fits the suite's budget on 2 cores (see README "Tests").
TRAIN_STEPS = int(os.environ.get("SCALAR_TEST_TRAIN_STEPS", "200"))


T = TypeVar("T")

#: Fixtures that hand a test a trained run: a test that asks for one is marked slow (it trains, or
#: waits for the run to be trained) whether or not it says so itself.
TRAINED_RUN_FIXTURES = frozenset({"full_run", "trained_castle_run", "auto_runs", "global_run"})


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "needs(what, present, provided_by): skip without it; fail under CI=true (prerequisites.py)")


def pytest_runtest_setup(item: pytest.Item) -> None:
    apply_needs_markers(item)


@pytest.hookimpl(tryfirst=True)  # before ``-m "not slow"`` deselects
def pytest_collection_modifyitems(config: pytest.Config, items: List[pytest.Item]) -> None:
    """Mark the tests of trained runs slow, and put the files with slow tests first: the workers
    (``pytest -n auto --dist loadfile``) take files in this order, so the long ones start at once
    and the short ones fill the gaps at the end."""
    for item in items:
        if TRAINED_RUN_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.slow)
    slow_files = {item.path for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: item.path not in slow_files)  # stable: the order inside a file is kept


def built_once(tmp_path_factory: pytest.TempPathFactory, name: str, build: Callable[[Path], T]) -> T:
    """``build(folder)`` run once per test session, whichever xdist worker asks first; the others
    wait for it and get the same result. ``build`` returns a Path or a dict of Paths (stored as JSON
    beside the folder). A build that failed fails every later request with its message, at once.
    """
    base = tmp_path_factory.getbasetemp()
    if XDIST_WORKER is not None:
        base = base.parent  # shared by the workers of this session
    folder, result_file, failure_file = base / name, base / f"{name}.result.json", base / f"{name}.failed"
    with FileLock(str(base / f"{name}.lock")):
        if failure_file.exists():
            pytest.fail(f"building the shared {name!r} failed in another worker:\n{failure_file.read_text()}")
        if not result_file.exists():
            if folder.exists():
                shutil.rmtree(folder)
            folder.mkdir(parents=True)
            try:
                result = build(folder)
            except BaseException as exc:
                failure_file.write_text(f"{type(exc).__name__}: {exc}"[-6000:])
                raise
            encoded = {k: str(v) for k, v in result.items()} if isinstance(result, dict) else str(result)
            result_file.write_text(json.dumps(encoded))
        stored = json.loads(result_file.read_text())
    return {k: Path(v) for k, v in stored.items()} if isinstance(stored, dict) else Path(stored)  # type: ignore[return-value]


#: A field small enough for unit tests: 4 hash levels of 2^12 rows, finest resolution 128.
SMALL_FIELD = dict(num_levels=4, log2_hashmap_size=12, max_resolution=128, hidden_dim=64)


def small_scalar_model(hidden_dim: int = 64, num_train_data: int = 2, **config: object) -> ScalarModel:
    """A fresh :class:`ScalarModel` (seed 0) with :data:`SMALL_FIELD` in the [-1, 1]^3 scene box;
    ``config`` sets other :class:`ScalarModelConfig` fields (e.g. ``num_samples_per_ray``)."""
    torch.manual_seed(0)
    field = ScalarFieldConfig(**{**SMALL_FIELD, "hidden_dim": hidden_dim})
    model_config = ScalarModelConfig(field=field, **config)
    return ScalarModel(config=model_config, scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=num_train_data)


def ray_bundle(origins: torch.Tensor, directions: torch.Tensor) -> RayBundle:
    """Rays [N, 3] origins and directions of training image 0, unit pixel area, no near/far set, on the
    origins' device."""
    n, device = origins.shape[0], origins.device
    return RayBundle(origins=origins, directions=directions, pixel_area=torch.ones(n, 1, device=device),
                     camera_indices=torch.zeros(n, 1, dtype=torch.long, device=device))


def with_torch_code(monkeypatch: pytest.MonkeyPatch, kernels: str, fn: Callable[[], T]) -> T:
    """``fn()`` with one group of the C++ kernels hidden, so that the torch code runs: ``kernels`` names its loader
    in ``scalar_nerfstudio.encodings._cpp`` (``sampling_ops``, ``march_ops``)."""
    from scalar_nerfstudio.encodings import _cpp

    with monkeypatch.context() as patch:
        patch.setattr(_cpp, kernels, lambda: None)
        return fn()


def free_port() -> int:
    """A TCP port that is free right now on localhost."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def ns_train_command(data: Path, output_dir: Path, *extra: str, method: str = "scalar-nerf", step_log: bool = False) -> List[str]:
    """``ns-train METHOD`` as a user runs it, with a private viewer port, ending when training ends;
    nerfstudio's step log (its default) only with ``step_log``, every 5 steps."""
    log = ["--logging.steps-per-log", "5"] if step_log else ["--logging.local-writer.enable", "False"]
    return [
        sys.executable, "-m", "nerfstudio.scripts.train", method,
        "--data", str(data),
        "--output-dir", str(output_dir),
        "--viewer.websocket-port", str(free_port()),
        "--viewer.quit-on-train-completion", "True",
        *log,
        *extra,
    ]


def run_dirs(output_dir: Path, method: str = "scalar-nerf") -> List[Path]:
    """Run folders (``.../METHOD/TIMESTAMP``) under ``output_dir``."""
    return sorted(p.parent for p in output_dir.glob(f"*/{method}/*/config.yml"))


def ns_eval(run: Path, output: Path, cwd: Optional[Path] = None) -> subprocess.CompletedProcess:
    """``ns-eval`` of a run folder as a user runs it, writing ``output`` (JSON), started in ``cwd``
    (a run trained with a relative ``--data`` is evaluated from the directory it was trained in)."""
    return subprocess.run(
        [sys.executable, "-m", "nerfstudio.scripts.eval", "--load-config", str(run / "config.yml"), "--output-path", str(output)],
        capture_output=True, text=True, timeout=600, cwd=cwd, check=False
    )


def sigkill_after_checkpoint(process: subprocess.Popen, output_dir: Path, min_step: int, method: str = "scalar-nerf") -> Optional[int]:
    """SIGKILL ``process`` once its run under ``output_dir`` has a checkpoint at step >= ``min_step``.

    Returns the newest checkpoint step seen before the kill (None if none appeared in 600 s).
    """
    deadline = time.time() + 600
    step = None
    while time.time() < deadline and process.poll() is None:
        runs = run_dirs(output_dir, method)
        step = latest_checkpoint_step(runs[0] / "nerfstudio_models") if runs else None
        if step is not None and step >= min_step:
            break
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.wait()
    return step


@contextmanager
def running_viewer(config: Path, timeout: float = 300.0) -> Iterator[int]:
    """Start ``ns-viewer`` on a run's config.yml as a user does and yield its port once it serves its page.

    Fails the calling test if the viewer exits, serves nothing within ``timeout`` seconds, or logs a
    traceback or a checkpoint that does not fit its model while loading the run."""
    port = free_port()
    viewer = subprocess.Popen(
        [sys.executable, "-m", "nerfstudio.scripts.viewer.run_viewer", "--load-config", str(config), "--viewer.websocket-port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    try:
        deadline = time.time() + timeout
        served = False
        while time.time() < deadline and viewer.poll() is None and not served:
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5).close()
                served = True
            except OSError:
                time.sleep(1.0)
        assert viewer.poll() is None, viewer.stdout.read()[-3000:] if viewer.stdout else ""
        assert served, f"the viewer served nothing on port {port} within {timeout:.0f} s"
        yield port
    finally:
        viewer.terminate()
        viewer.wait(timeout=60)
    log = viewer.stdout.read() if viewer.stdout else ""
    assert "Traceback" not in log and "size mismatch" not in log, log[-3000:]


def viewer_image(config: Path, *, c2w: torch.Tensor, fov: float, aspect: float, timeout: float = 300.0,
                 max_res: int = 512) -> np.ndarray:
    """The image ``ns-viewer`` sends a browser that looks through one camera: ``[H, W, 3]`` uint8.

    Connects to the running viewer's websocket as the browser does (viser's messages), sends the camera
    (``c2w`` ``[3, 4]`` in the run's frame, vertical ``fov`` in radians, ``aspect`` width / height, turned into
    viser's pose the inverse way nerfstudio's viewer reads it back) and returns the first background image at
    full size, ``max_res`` pixels on its longer side (nerfstudio's "Max res"; a CPU run sends a coarse one first)."""
    import io

    import msgspec
    import viser.transforms as vtf
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO
    from PIL import Image
    from viser._messages import ViewerCameraMessage
    from websockets.sync.client import connect

    rotation = c2w[:3, :3].double().cpu().numpy() @ vtf.SO3.from_x_radians(np.pi).as_matrix()  # nerfstudio's c2w -> viser's
    position = c2w[:3, 3].double().cpu().numpy() * VISER_NERFSTUDIO_SCALE_RATIO
    forward = -c2w[:3, 2].double().cpu().numpy()  # nerfstudio's cameras look down -z
    message = ViewerCameraMessage(
        wxyz=tuple(float(v) for v in vtf.SO3.from_matrix(rotation).wxyz), position=tuple(float(v) for v in position),
        fov=float(fov), aspect=float(aspect), look_at=tuple(float(v) for v in position + forward),
        up_direction=tuple(float(v) for v in c2w[:3, 1].double().cpu().numpy()),
    )
    with running_viewer(config, timeout) as port, connect(f"ws://127.0.0.1:{port}", max_size=None) as socket_:
        socket_.send(msgspec.msgpack.encode(message.as_serializable_dict()))
        deadline, sizes = time.time() + timeout, []
        while time.time() < deadline:
            try:
                raw = socket_.recv(timeout=1.0)
            except TimeoutError:
                continue
            batch = msgspec.msgpack.decode(raw)
            for item in batch if isinstance(batch, list) else [batch]:
                if isinstance(item, dict) and item.get("type") == "BackgroundImageMessage":
                    image = np.asarray(Image.open(io.BytesIO(item["rgb_bytes"])).convert("RGB"))
                    if max(image.shape[:2]) == max_res:
                        return image
                    sizes.append(image.shape[:2])
    raise AssertionError(f"the viewer sent no image of {max_res} pixels within {timeout:.0f} s (sizes sent: {sizes})")


def castle_args() -> List[str]:
    return ["nerfstudio-data", "--downscale-factor", "4"]


@pytest.fixture(scope="session")
def trained_castle_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Train the global model on castle-P30 (downscale 4) for TRAIN_STEPS steps; returns the run folder."""
    need_castle()

    def train(output_dir: Path) -> Path:
        command = ns_train_command(CASTLE, output_dir, "--max-num-iterations", str(TRAIN_STEPS), "--steps-per-save", str(TRAIN_STEPS), *castle_args())
        result = subprocess.run(command, capture_output=True, text=True, timeout=1200, check=False)
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
        (run,) = run_dirs(output_dir)
        return run

    return built_once(tmp_path_factory, "castle_run", train)


# --------------------------------------------------------- the bad-input tests' scenes (bad_scenes.py)


@pytest.fixture(scope="module")
def good_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The 6-image courtyard the bad-input tests break, one per test module."""
    from bad_scenes import write_good_scene

    return write_good_scene(tmp_path_factory.mktemp("good"))


@pytest.fixture(scope="module")
def mixed_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 10-image scene with grayscale, RGBA, palette and 16-bit images among the RGB ones."""
    from bad_scenes import write_mixed_scene

    return write_mixed_scene(tmp_path_factory.mktemp("mixed"))


# ------------------------------------------------- a tiny run through every phase (blocks, fusion)

GLOBAL_STEPS, BLOCK_STEPS, NUM_BLOCKS = 100, 30, 2  # the time goes into starting ns-train, not into these steps
TOTAL_STEPS = GLOBAL_STEPS + NUM_BLOCKS * BLOCK_STEPS
# A small field and batch so that a whole run (global + 2 blocks) takes well under a minute.
TINY = [
    "--pipeline.model.field.log2-hashmap-size", "14",
    "--pipeline.model.field.max-resolution", "256",
    "--pipeline.model.num-samples-per-ray", "32",
    "--pipeline.datamanager.train-num-rays-per-batch", "512",
    "--pipeline.model.occupancy-warmup-steps", "8",
    "--pipeline.num-blocks", str(NUM_BLOCKS),
    "--pipeline.global-steps", str(GLOBAL_STEPS),
    "--pipeline.block-steps", str(BLOCK_STEPS),
]


@pytest.fixture(scope="session")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    def write(folder: Path) -> Path:
        write_scene(folder, num_images=24, width=96, height=72)
        return folder

    return built_once(tmp_path_factory, "courtyard", write)


@pytest.fixture(scope="session")
def full_run(scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``ns-train scalar-nerf`` through the global phase and both blocks, with nerfstudio's step log
    on (its default); what the command printed is kept beside the run (:func:`full_run_log`)."""
    def train(output_dir: Path) -> Path:
        result = subprocess.run(ns_train_command(scene, output_dir, *TINY, step_log=True), capture_output=True, text=True, timeout=900, check=False)
        (output_dir / "ns-train.log").write_text(result.stdout + result.stderr)
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
        (run,) = run_dirs(output_dir)
        phases = (f"phases: global: steps 0-{GLOBAL_STEPS - 1}, block 0: steps {GLOBAL_STEPS}-{GLOBAL_STEPS + BLOCK_STEPS - 1}, "
                  f"block 1: steps {GLOBAL_STEPS + BLOCK_STEPS}-{TOTAL_STEPS - 1}")
        assert phases in " ".join(result.stdout.split()), result.stdout[-3000:]
        return run

    return built_once(tmp_path_factory, "full_run", train)


def full_run_log(run: Path) -> str:
    """What ``ns-train`` printed while training :func:`full_run` (stdout, then stderr)."""
    return (run.parents[2] / "ns-train.log").read_text()


def tiny_trainer(scene: Path, output_dir: Path, log2_hashmap_size: int = 14, rays_per_batch: int = 512,
                 configure: Optional[Callable[[Any], None]] = None, **pipeline: object):
    """An in-process scalar-nerf trainer on ``scene`` with tiny settings, set up but not trained.

    ``pipeline`` sets attributes of the pipeline config (e.g. ``num_blocks=2``, ``decoder_mode=...``);
    defaults: 2 blocks, 20 global and 8 block steps. ``configure`` may change the trainer config
    further before it is set up.
    """
    import copy

    from scalar_nerfstudio.method_configs import scalar_nerf

    config = copy.deepcopy(scalar_nerf.config)
    config.data = scene
    config.pipeline.datamanager.data = scene
    config.output_dir = output_dir
    config.vis = "tensorboard"
    config.logging.local_writer.enable = False
    config.steps_per_save = 1000
    config.pipeline.model.field.log2_hashmap_size = log2_hashmap_size
    config.pipeline.model.field.max_resolution = 256
    config.pipeline.model.num_samples_per_ray = 32
    config.pipeline.model.occupancy_warmup_steps = 8
    config.pipeline.datamanager.train_num_rays_per_batch = rays_per_batch
    settings = {"num_blocks": NUM_BLOCKS, "global_steps": 20, "block_steps": 8, **pipeline}
    for key, value in settings.items():
        setattr(config.pipeline, key, value)
    if configure is not None:
        configure(config)
    config.set_timestamp()
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def trained_block_tensors(run: Path, block: int) -> Dict[str, torch.Tensor]:
    """Block ``block``'s weights as a run holds them (keys ``field.encoder.table`` ...): from its newest
    checkpoint when they are there, else from the run's per-block file (a finished block)."""
    from scalar_nerfstudio.runs import block_model_path, block_models_dir

    step = latest_checkpoint_step(run / "nerfstudio_models")
    assert step is not None, f"{run}: no checkpoint"
    state = torch.load(run / "nerfstudio_models" / f"step-{step:09d}.ckpt", map_location="cpu", weights_only=True)["pipeline"]
    head = f"_model.blocks.{block}."
    tensors = {k[len(head):]: v for k, v in state.items() if k.startswith(head)}
    if any(v.numel() > 0 for v in tensors.values()):
        return tensors
    saved = torch.load(block_model_path(block_models_dir(run), block), map_location="cpu", weights_only=True)
    assert saved["block"] == block
    return saved["state"]
