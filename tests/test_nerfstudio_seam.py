"""The seam with nerfstudio (``scalar_nerfstudio/seam/``): each hook against the nerfstudio installed here.

Every test names the hook it guards and fails when nerfstudio no longer has what the hook relies on
(a method, its parameters, an attribute its code sets or reads); where it is cheap, the hook is run
against nerfstudio's own code. No model is trained and no viewer is started.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable, Dict, List, Optional

import pytest
import torch

from scalar_nerfstudio.seam import PIPELINE_MODEL_KEY_PREFIX


def _parameters(function: Callable[..., Any]) -> List[str]:
    return list(inspect.signature(function).parameters)


def _source(obj: Any) -> str:
    return inspect.getsource(obj)


# ------------------------------------------------------------------------------- seam/trainer.py
def test_progress_total_is_the_writer_buffers_max_iter(monkeypatch: pytest.MonkeyPatch) -> None:
    """``set_progress_total``: nerfstudio's step log counts to ``writer.GLOBAL_BUFFER["max_iter"]``."""
    from nerfstudio.utils import writer

    from scalar_nerfstudio.seam.trainer import set_progress_total

    assert isinstance(writer.GLOBAL_BUFFER, dict)
    source = _source(writer)  # (its functions are wrapped by a decorator that hides their source)
    assert 'GLOBAL_BUFFER["max_iter"] = max_iter' in source  # setup_local_writer
    assert 'remain_iter = GLOBAL_BUFFER["max_iter"] - step' in source  # put_time's ETA
    assert 'fraction_done = step / GLOBAL_BUFFER["max_iter"]' in source  # the local writer's % done
    monkeypatch.setattr(writer, "GLOBAL_BUFFER", {})
    set_progress_total(123)
    assert writer.GLOBAL_BUFFER == {"max_iter": 123}


def _trainer_config(tmp_path: Path) -> Any:
    from nerfstudio.engine.trainer import TrainerConfig

    config = TrainerConfig(method_name="seam-test", experiment_name="seam", output_dir=tmp_path, vis="tensorboard")
    config.machine.device_type = "cuda"
    config.mixed_precision = True
    return config


def test_trainer_init_reads_the_device_and_mixed_precision_there_only(tmp_path: Path) -> None:
    """``TrainerBase.__init__``: nerfstudio's ``Trainer.__init__`` reads ``machine.device_type`` and
    ``mixed_precision`` from the config, and nothing else of the Trainer reads them."""
    from nerfstudio.engine.trainer import Trainer

    from scalar_nerfstudio.seam.trainer import TrainerBase

    assert _parameters(Trainer.__init__) == ["self", "config", "local_rank", "world_size"]
    init = _source(Trainer.__init__)
    assert "config.machine.device_type" in init and "self.config.mixed_precision" in init
    whole = _source(Trainer)
    assert whole.count("machine.device_type") == 1 and whole.count("config.mixed_precision") == 1
    config = _trainer_config(tmp_path)
    trainer = TrainerBase(config, device_type="cpu", mixed_precision=False)
    assert trainer.device == "cpu" and trainer.mixed_precision is False and not trainer.grad_scaler.is_enabled()
    assert trainer.config is config
    assert (config.machine.device_type, config.mixed_precision) == ("cuda", True)  # as it was given


def test_trainer_loop_length_is_read_from_max_num_iterations_as_it_starts(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """``TrainerBase.train_for``: ``Trainer.train`` runs ``config.max_num_iterations`` steps from
    ``_start_step``, one ``train_iteration`` each; the config holds its own value at every step."""
    from nerfstudio.engine.trainer import Trainer
    from nerfstudio.utils import writer

    from scalar_nerfstudio.seam.trainer import TrainerBase, set_progress_total, start_step

    train = _source(Trainer.train)
    assert "num_iterations = self.config.max_num_iterations" in train
    assert "range(self._start_step, self._start_step + num_iterations)" in train
    assert "self.train_iteration(step)" in train
    assert "self._start_step" in _source(Trainer.__init__)

    monkeypatch.setattr(writer, "GLOBAL_BUFFER", {"events": {}, "max_buffer_size": 20})
    monkeypatch.setattr(writer, "EVENT_STORAGE", [])
    set_progress_total(3)
    seen: List[tuple] = []

    def train_iteration(self: Any, step: int) -> tuple:
        seen.append((step, self.config.max_num_iterations))
        return torch.tensor(0.0), {}, {}

    monkeypatch.setattr(Trainer, "train_iteration", train_iteration)
    config = _trainer_config(tmp_path)
    config.max_num_iterations = 0  # as asked ("every phase")
    trainer = TrainerBase(config, device_type="cpu", mixed_precision=False)
    datamanager = SimpleNamespace(train_dataset=[0], eval_dataset=None, get_train_rays_per_batch=lambda: 1)
    trainer.pipeline = SimpleNamespace(datamanager=datamanager, train=lambda: None)  # type: ignore[assignment]
    trainer.callbacks = []
    monkeypatch.setattr(trainer, "save_checkpoint", lambda step: None)
    assert start_step(trainer) == 0
    trainer.train_for(3)
    assert seen == [(0, 0), (1, 0), (2, 0)]
    assert config.max_num_iterations == 0


def test_trainer_checkpoint_is_loaded_by_its_private_load_checkpoint(tmp_path: Path) -> None:
    """``TrainerBase._load_checkpoint``: ``Trainer.setup`` calls the private ``_load_checkpoint``, which
    loads ``load_dir/step-{load_step:09d}.ckpt`` and sets ``_start_step`` to the step after it."""
    from nerfstudio.engine.trainer import Trainer

    from scalar_nerfstudio.seam.trainer import TrainerBase, start_step

    assert "self._load_checkpoint()" in _source(Trainer.setup)
    assert _parameters(Trainer._load_checkpoint) == ["self"]
    load = _source(Trainer._load_checkpoint)
    assert "self.config.load_step" in load and 'f"step-{load_step:09d}.ckpt"' in load and "self._start_step =" in load

    loaded: Dict[str, Any] = {}

    class Resuming(TrainerBase):
        def resume_step(self, load_dir: Path) -> Optional[int]:
            return 4

        def checkpoint_loaded(self, step: Optional[int]) -> None:
            loaded["step"], loaded["load_step"] = step, self.config.load_step

    checkpoints = tmp_path / "checkpoints"
    checkpoints.mkdir()
    state = {"step": 4, "pipeline": {"w": torch.ones(1)}, "optimizers": {}, "scalers": {}}
    torch.save(state, checkpoints / "step-000000004.ckpt")
    (checkpoints / "step-000000009.ckpt.partial").write_text("not a checkpoint")  # nerfstudio's own choice: 9
    config = _trainer_config(tmp_path)
    config.load_dir = checkpoints
    trainer = Resuming(config, device_type="cpu", mixed_precision=False)
    trainer.pipeline = SimpleNamespace(load_pipeline=lambda state, step: loaded.update(pipeline=state))  # type: ignore[assignment]
    trainer.optimizers = SimpleNamespace(load_optimizers=lambda state: None)  # type: ignore[assignment]
    trainer._load_checkpoint()
    assert start_step(trainer) == 5 and loaded["step"] == 4 and torch.equal(loaded["pipeline"]["w"], torch.ones(1))
    assert loaded["load_step"] is None and config.load_step is None  # chosen for nerfstudio's load only


# ------------------------------------------------------------------------------ seam/pipeline.py
def test_pipeline_base_sets_what_vanilla_pipelines_methods_use() -> None:
    """``PipelineBase``: ``Pipeline.__init__`` takes no argument; ``VanillaPipeline.__init__`` sets the
    attributes its methods use, the model as the private ``_model``, saved under ``_model.``."""
    from nerfstudio.pipelines.base_pipeline import Pipeline, VanillaPipeline, VanillaPipelineConfig

    from scalar_nerfstudio.seam.pipeline import PipelineBase

    assert Pipeline.__init__ is torch.nn.Module.__init__
    init = _source(VanillaPipeline.__init__)
    for attribute in ("self.config = config", "self.test_mode = test_mode", "self.world_size = world_size",
                      "self.datamanager", "self._model = config.model.setup("):
        assert attribute in init, attribute
    assert "_model" in Pipeline.__annotations__ and "self._model" in _source(Pipeline.model.fget)
    assert f'"{PIPELINE_MODEL_KEY_PREFIX}"' in _source(Pipeline.load_state_dict)

    pipeline = PipelineBase(VanillaPipelineConfig(), test_mode="test")
    assert (pipeline.test_mode, pipeline.world_size, pipeline.local_rank) == ("test", 1, 0)
    model = torch.nn.Linear(2, 1)
    pipeline.set_model(model)  # type: ignore[arg-type]
    assert pipeline.model is model
    state = pipeline.state_dict()
    assert sorted(state) == [f"{PIPELINE_MODEL_KEY_PREFIX}bias", f"{PIPELINE_MODEL_KEY_PREFIX}weight"]
    pipeline.load_state_dict({key: torch.zeros_like(value) for key, value in state.items()})
    assert float(model.weight.detach().abs().sum()) == 0.0


# ---------------------------------------------------------------------------------- seam/data.py
def test_dataset_keeps_its_parsed_outputs_and_loaders_read_the_datamanagers_config() -> None:
    """``dataparser_outputs``: ``InputDataset`` keeps its outputs as the private ``_dataparser_outputs``;
    ``loader_options``: ``VanillaDataManager.setup_train`` / ``setup_eval`` read their image sampling
    options from ``self.config`` as they build their loaders."""
    from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
    from nerfstudio.data.datasets.base_dataset import InputDataset

    from scalar_nerfstudio.seam.data import dataparser_outputs, loader_options

    assert "self._dataparser_outputs = dataparser_outputs" in _source(InputDataset.__init__)
    for split in ("train", "eval"):
        setup = _source(getattr(VanillaDataManager, f"setup_{split}"))
        for option in ("num_images_to_sample_from", "num_times_to_repeat_images"):
            assert f"self.config.{split}_{option}" in setup, (split, option)
    dataset = InputDataset.__new__(InputDataset)
    dataset._dataparser_outputs = outputs = SimpleNamespace()  # type: ignore[assignment]
    assert dataparser_outputs(dataset) is outputs
    config = VanillaDataManagerConfig()
    datamanager = SimpleNamespace(config=config)
    with loader_options(datamanager, train_num_images_to_sample_from=3):
        assert datamanager.config.train_num_images_to_sample_from == 3 and datamanager.config is not config
    assert datamanager.config is config and config.train_num_images_to_sample_from == -1


# -------------------------------------------------------------------------------- seam/viewer.py
def test_viewer_control_is_set_up_by_the_viewer() -> None:
    """``ViewerHook``: the viewer calls ``ViewerControl._setup(viewer)`` on every control of the pipeline,
    which sets ``viewer`` and ``viser_server``."""
    from nerfstudio.viewer.viewer import Viewer
    from nerfstudio.viewer.viewer_elements import ViewerControl

    from scalar_nerfstudio.seam.viewer import ViewerHook

    assert _parameters(ViewerControl._setup) == ["self", "viewer"]
    assert "._setup(self)" in _source(Viewer.__init__)
    ready: List[Any] = []

    class Hook(ViewerHook):
        def viewer_ready(self, viewer: Any) -> None:
            ready.append(viewer)

    viewer = SimpleNamespace(viser_server=object())
    hook = Hook()
    hook._setup(viewer)
    assert ready == [viewer] and hook.viewer is viewer and hook.viser_server is viewer.viser_server


def test_viewer_attributes_read_by_the_controls() -> None:
    """``viewer_trains``, ``hide_training_buttons``, ``show_step``, ``viewer_model_device``,
    ``render_state_machines``, ``viser_scale_ratio``: the viewer's undocumented attributes."""
    import nerfstudio.viewer.viewer as viewer_module
    from nerfstudio.viewer.viewer import Viewer

    from scalar_nerfstudio.seam.viewer import (
        hide_training_buttons,
        show_step,
        viewer_model_device,
        viewer_trains,
        viser_scale_ratio,
    )

    init = _source(Viewer.__init__)
    for attribute in ("self.trainer = trainer", "self.pause_train = ", "self.resume_train = ",
                      "self.render_statemachines"):
        assert attribute in init, attribute
    source = _source(viewer_module)  # (some of its methods are decorated: their own source is hidden)
    for code in ("self.step = step", "def update_step(self, step)", "def get_model(self)"):  # update_scene, ...
        assert code in source, code
    assert viser_scale_ratio() == float(viewer_module.VISER_NERFSTUDIO_SCALE_RATIO) > 0

    steps: List[int] = []
    viewer = SimpleNamespace(trainer=None, pause_train=SimpleNamespace(visible=True),
                             resume_train=SimpleNamespace(visible=True), step=7, update_step=steps.append,
                             get_model=lambda: SimpleNamespace(device=torch.device("cpu")))
    assert not viewer_trains(viewer) and viewer_model_device(viewer) == "cpu"
    hide_training_buttons(viewer)
    show_step(viewer)
    assert not viewer.pause_train.visible and not viewer.resume_train.visible and steps == [7]


# -------------------------------------------------------------------------- seam/render_state.py
def test_render_state_machine_steps_are_its_private_methods() -> None:
    """``RenderStateMachineBase``: nerfstudio's render thread renders with ``_render_img`` (sized by
    ``_calculate_image_res``) and shows it with ``_send_output_to_viewer``; the base routes them to its
    public methods."""
    import threading

    from nerfstudio.viewer.render_state_machine import RenderStateMachine

    from scalar_nerfstudio.seam.render_state import RenderStateMachineBase

    assert issubclass(RenderStateMachine, threading.Thread)
    assert _parameters(RenderStateMachine.__init__) == ["self", "viewer", "viser_scale_ratio", "client"]
    assert _parameters(RenderStateMachine._render_img) == ["self", "camera_state"]
    assert _parameters(RenderStateMachine._calculate_image_res) == ["self", "aspect_ratio"]
    assert _parameters(RenderStateMachine._send_output_to_viewer) == ["self", "outputs", "static_render"]
    run = _source(RenderStateMachine.run)
    assert "self._render_img(" in run and "self._send_output_to_viewer(" in run and "while self.running" in run
    assert "self._calculate_image_res(" in _source(RenderStateMachine._render_img)
    init = _source(RenderStateMachine.__init__)
    for attribute in ("self.state", "self.running", "self.interrupt_render_flag", "self.viewer = viewer",
                      "self.viser_scale_ratio = viser_scale_ratio", "self.client = client"):
        assert attribute in init, attribute

    class Sized(RenderStateMachineBase):
        def image_resolution(self, aspect_ratio: float) -> tuple:
            return 3, int(3 * aspect_ratio)

    machine = Sized(SimpleNamespace(), 1.0, SimpleNamespace())
    assert machine._calculate_image_res(2.0) == (3, 6) and machine.render_state == "low_static"


def test_viewer_starts_the_machine_it_finds_under_the_clients_id() -> None:
    """``SwappingMachines``: ``Viewer.handle_new_client`` puts a new ``RenderStateMachine`` into
    ``render_statemachines`` and starts the one found there."""
    import nerfstudio.viewer.viewer as viewer_module

    source = _source(viewer_module)  # (handle_new_client is decorated: its own source is hidden)
    new_client = source[source.index("def handle_new_client("):]
    assert new_client.index("self.render_statemachines[client.client_id] = RenderStateMachine(") < new_client.index(
        "self.render_statemachines[client.client_id].start()") < new_client.index("\n    def ")


# ------------------------------------------------------------------------ seam/render_command.py
def test_render_commands_load_runs_with_their_modules_eval_setup(monkeypatch: pytest.MonkeyPatch) -> None:
    """``after_each_load``: ``ns-render``'s commands load the run with the ``eval_setup`` name of their module."""
    from nerfstudio.scripts import render as ns_render
    from nerfstudio.utils.eval_utils import eval_setup

    from scalar_nerfstudio.seam.render_command import after_each_load

    assert ns_render.eval_setup is eval_setup
    for command in (ns_render.RenderCameraPath, ns_render.RenderInterpolated, ns_render.SpiralRender,
                    ns_render.DatasetRender):
        assert "eval_setup(" in _source(command.main), command.__name__

    def fake_eval_setup(path: Path, **kwargs: Any) -> tuple:
        return "config", SimpleNamespace(path=path), "checkpoint", 3

    monkeypatch.setattr(ns_render, "eval_setup", fake_eval_setup)
    changed: List[tuple] = []
    with after_each_load(lambda config, pipeline: changed.append((config, pipeline.path))):
        assert ns_render.eval_setup("run.yml")[3] == 3
    assert changed == [("config", "run.yml")] and ns_render.eval_setup is fake_eval_setup


# --------------------------------------------------------------------------- seam/method_list.py
def test_the_method_list_reads_only_frame_names_and_still_offers_to_install_an_external_method(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """``list_methods_without_reading_sources``: nerfstudio's external-method configs read ``inspect`` as a
    module global and only ``inspect.stack()[2].function`` of it; with the hook, listing them reads no source
    file, and one made anywhere else still prints its install instructions and exits."""
    from nerfstudio.configs import external_methods
    from nerfstudio.configs.method_configs import all_methods

    from scalar_nerfstudio.seam.method_list import list_methods_without_reading_sources, stack_without_sources

    assert "inspect.stack()[2].function" in _source(external_methods.ExternalMethodDummyTrainerConfig.__post_init__)
    assert "scalar-nerf" in all_methods  # nerfstudio loaded this package's methods, which set the hook up
    assert external_methods.inspect is not inspect and external_methods.inspect.stack is stack_without_sources
    list_methods_without_reading_sources()  # again: a no-op
    assert external_methods.inspect.stack is stack_without_sources and external_methods.inspect.signature is inspect.signature

    def named_chain() -> List[Any]:
        return inner()

    def inner() -> List[Any]:
        return stack_without_sources()

    fast, slow = named_chain(), inspect.stack()
    assert [f.function for f in fast[:3]] == ["inner", "named_chain", "test_the_method_list_reads_only_frame_names_and_still_offers_to_install_an_external_method"]
    assert [(f.function, f.filename) for f in fast[2:]] == [(f.function, f.filename) for f in slow]

    def no_source(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the method list read a source file")

    monkeypatch.setattr(inspect, "findsource", no_source)
    monkeypatch.setattr(inspect, "getmodule", no_source)
    configs, descriptions = external_methods.get_external_methods()
    assert len(configs) == len(descriptions) >= 10 and capsys.readouterr().out == ""
    method = next(m for m in external_methods.external_methods if m.pip_package is None)
    with pytest.raises(SystemExit) as exited:
        external_methods.ExternalMethodDummyTrainerConfig(method_name="x", method=method)
    assert exited.value.code == 0 and "For more information visit" in capsys.readouterr().out  # its instructions
