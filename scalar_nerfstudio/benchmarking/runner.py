"""One variant of ``scalar-nerf-benchmark``, in its own process: train, evaluate along the way, report.

    python -m scalar_nerfstudio.benchmarking.runner SPEC.json

SPEC (written by :func:`.schedule.variant_spec`) holds: ``method`` ("scalar-nerf" or "nerfacto"), ``data``,
``downscale``, ``overrides`` (dotted trainer-config attributes -> values), ``eval_every`` (evaluate
every this many steps; 0: never during training), ``eval_at_end``, ``time_limit_s`` (stop training after this much training
wall-clock; 0: none), ``fusions`` (fusion modes to evaluate at the end; the first is the run's),
``output_dir``, ``result`` (where to write the JSON).

Training time excludes evaluation and the run's checkpoint, written once after its last step.
Lines ``PROGRESS <done> <total>`` on stdout drive the benchmark's progress bar.
"""

from __future__ import annotations

import json
import sys
import time
from copy import deepcopy
from pathlib import Path
from typing import TYPE_CHECKING, Any, Dict, List, Tuple, cast

import torch

from scalar_nerfstudio.atomic_io import atomic_write_text
from scalar_nerfstudio.engine.device import resolve_machine
from scalar_nerfstudio.engine.report import MIB, peak_memory_mib, tensor_bytes
from scalar_nerfstudio.engine.timing import StepClock, time_train_iterations
from scalar_nerfstudio.fusion import parse_fusion_mode

if TYPE_CHECKING:
    from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManagerConfig

    from scalar_nerfstudio.models.scene_model import ScalarSceneModelConfig


def _disable_lpips() -> None:
    """nerfacto builds LPIPS, which downloads AlexNet weights: offline that dies, so stub it out."""
    from torchmetrics.image import lpip

    class NoLPIPS(torch.nn.Module):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__()

        def forward(self, *args, **kwargs) -> torch.Tensor:
            return torch.tensor(float("nan"))

    lpip.LearnedPerceptualImagePatchSimilarity = NoLPIPS


def _set(config: Any, dotted: str, value: Any) -> None:
    """Set ``config.a.b.c = value`` for ``dotted == "a.b.c"`` (lists become tuples; a dict's part is a
    key, e.g. ``optimizers.block_decoder.optimizer.lr``)."""
    *parents, name = dotted.split(".")
    target = config
    for part in parents:
        if isinstance(target, dict):
            if part not in target:
                raise KeyError(f"benchmark override {dotted!r}: no key {part!r} (keys: {sorted(target)})")
            target = target[part]
        else:
            target = getattr(target, part)
    if not hasattr(target, name):
        raise AttributeError(f"benchmark override {dotted!r}: {type(target).__name__} has no attribute {name!r}")
    setattr(target, name, tuple(value) if isinstance(value, list) else value)


def trainer_config(spec: Dict[str, Any]):
    """The trainer config of a benchmark run: the method's defaults on ``spec["data"]`` with every
    8th image held out, no evaluation, checkpoints or local log while training, then ``spec["overrides"]``."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    if spec["method"] == "nerfacto":
        _disable_lpips()
        from nerfstudio.configs.method_configs import all_methods

        config = deepcopy(all_methods["nerfacto"])
        config.pipeline.model.implementation = "torch"
        config.machine.device_type, config.mixed_precision = "auto", True
        resolve_machine(config)  # nerfstudio's Trainer does not settle "auto" itself (scalar-nerf's does)
    else:
        from scalar_nerfstudio.method_configs import scalar_nerf

        config = deepcopy(scalar_nerf.config)
    config.pipeline.datamanager.data = Path(spec["data"])
    # nerfacto's (parallel) and scalar-nerf's datamanagers are both vanilla ones, with a dataparser
    cast("VanillaDataManagerConfig", config.pipeline.datamanager).dataparser = NerfstudioDataParserConfig(
        downscale_factor=spec["downscale"], eval_mode="interval", eval_interval=8
    )
    config.vis = "tensorboard"
    config.logging.local_writer.enable = False
    config.steps_per_eval_batch = config.steps_per_eval_image = config.steps_per_eval_all_images = 10**9
    config.steps_per_save = 10**9
    config.output_dir = Path(spec["output_dir"])
    if spec["method"] != "nerfacto" and spec.get("fusions"):
        # The run's own fusion (its curve and first result) is the first one listed, whatever the default.
        cast("ScalarSceneModelConfig", config.pipeline.model).fusion = spec["fusions"][0]  # scalar-nerf's model
    for key, value in spec.get("overrides", {}).items():
        _set(config, key, value)
    return config


def setup_trainer(config):
    """The set-up trainer of ``config``, as ns-train builds it (nerfstudio's ``train_loop``): Python's,
    NumPy's and torch's random generators seeded with ``config.machine.seed`` first. Unseeded, two
    runs of one spec started from different initial weights and rays (NGP_10 on the 256 x 192 town:
    18.38 and 17.67 dB at 6400 steps, docs/notebook/defaults.md)."""
    import random

    import numpy as np

    seed = int(config.machine.seed)
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    return trainer


def _planned_steps(trainer: Any) -> int:
    """The steps ``trainer`` trains in all: a scalar-nerf trainer's (planned from its phases unless
    ``--max-num-iterations`` is given), nerfstudio's ``max_num_iterations`` for nerfstudio's own trainer."""
    from scalar_nerfstudio.engine.trainer import ScalarTrainer  # imports nerfstudio's trainer

    return trainer.total_steps if isinstance(trainer, ScalarTrainer) else int(trainer.config.max_num_iterations)


def _evaluate(pipeline) -> Dict[str, float]:
    """Mean PSNR / SSIM (/ LPIPS; / depth metrics where the scene has true depth) over the eval
    images, and render ms per image."""
    pipeline.eval()
    start = time.perf_counter()
    metrics = pipeline.get_average_eval_image_metrics()
    count = max(len(pipeline.datamanager.fixed_indices_eval_dataloader), 1)
    ms = 1000.0 * (time.perf_counter() - start) / count
    pipeline.train()
    result = {"psnr": float(metrics["psnr"]), "ssim": float(metrics["ssim"]), "render_ms_per_image": ms}
    if "lpips" in metrics and metrics["lpips"] == metrics["lpips"]:
        result["lpips"] = float(metrics["lpips"])
    for key in ("depth_delta1", "depth_median_rel_error"):  # scenes with true depth (the town)
        if key in metrics:
            result[key] = float(metrics[key])
    return result


def _trained_parameters(model) -> Tuple[int, float]:
    """(parameters, MiB as float32) of the models a run trained: the global model and the started
    blocks, whether or not their weights are in memory (a finished block lives in its file)."""
    if not hasattr(model, "global_model"):
        params = list(model.parameters())
        return sum(p.numel() for p in params), tensor_bytes(params) / MIB
    count = sum(p.numel() for p in model.global_model.parameters())
    count += sum(model.block_parameter_count(k) for k in model.started_block_ids())
    return count, count * 4 / MIB


def _resume_into(config, run_dir: Path) -> None:
    """Make ``config`` resume the run in ``run_dir`` from its newest checkpoint (a variant stopped midway)."""
    config.load_dir = run_dir / config.relative_model_dir
    config.timestamp = run_dir.name


def _partial_path(spec: Dict[str, Any]) -> Path:
    """Where a run with ``eval_at_s`` keeps its curve so far and its run folder (``--resume`` continues it)."""
    return Path(spec["result"]).with_suffix(".partial.json")


def run(spec: Dict[str, Any]) -> Dict[str, Any]:
    """Train and evaluate one variant as ``spec`` says; returns the result written to ``spec["result"]``.

    With ``eval_at_s`` (training seconds on the trainer's clock, a time budget's run), the run is evaluated
    at those times, saves a checkpoint every ``save_every_steps`` steps and keeps its curve in a partial
    file; with ``resume`` set, a run stopped midway continues from its newest checkpoint and curve."""
    config = trainer_config(spec)
    eval_at_s = sorted(float(t) for t in spec.get("eval_at_s") or [])
    partial_path = _partial_path(spec)
    partial = json.loads(partial_path.read_text()) if spec.get("resume") and partial_path.is_file() else None
    if eval_at_s:
        config.steps_per_save = int(spec.get("save_every_steps") or 10**9)
    if partial is not None:
        from scalar_nerfstudio.runs import latest_checkpoint_step

        run_dir = Path(partial["run_dir"])
        if latest_checkpoint_step(run_dir / config.relative_model_dir) is not None:
            _resume_into(config, run_dir)
            print(f"resuming {run_dir} from its newest checkpoint", flush=True)
        else:
            partial = None
    config.set_timestamp()
    config.save_config()
    trainer = setup_trainer(config)
    if eval_at_s:
        return _run_on_the_clock(spec, trainer, eval_at_s, partial)
    fusions = spec.get("fusions") or []
    split = getattr(trainer.pipeline.model, "split", None)
    if split is not None:  # a fusion naming a block this run does not have fails now, not after its training
        for mode in fusions:
            parse_fusion_mode(mode, split.num_blocks)
    save_checkpoint = trainer.save_checkpoint
    requested_saves: List[int] = []
    """Steps nerfstudio asked to save at: none is written inside the timed steps; the last one is
    written after them, so that every variant's run can be loaded (ns-eval, train_vs_heldout.py)."""
    trainer.save_checkpoint = requested_saves.append
    pipeline = trainer.pipeline
    total = _planned_steps(trainer)
    eval_every = int(spec.get("eval_every", 0))
    eval_steps = set(range(eval_every, total + 1, eval_every)) if eval_every > 0 else set()
    time_limit = float(spec.get("time_limit_s", 0.0))
    curve: List[Dict[str, float]] = []
    phase_at = getattr(pipeline, "phase_at", None)
    block_train_s: Dict[str, float] = {}
    """Training seconds of each block's phase (the slowest one is the wall-clock of K workers)."""
    timed_s = 0.0

    def after_step(step: int, result, clock: StepClock) -> None:
        nonlocal timed_s
        block = phase_at(step).block if phase_at is not None else None
        if block is not None:
            block_train_s[str(block)] = block_train_s.get(str(block), 0.0) + clock.busy_s - timed_s
        timed_s = clock.busy_s
        if time_limit > 0:
            print(f"PROGRESS {min(clock.busy_s, time_limit):.0f} {time_limit:.0f}", flush=True)
        else:
            print(f"PROGRESS {clock.steps} {total}", flush=True)
        out_of_time = time_limit > 0 and clock.busy_s >= time_limit
        if clock.steps in eval_steps or out_of_time:
            curve.append({"step": clock.steps, "train_s": clock.busy_s, **_evaluate(pipeline)})
        if out_of_time:
            trainer.stop_training = True

    clock = time_train_iterations(trainer, after_step)
    trainer.train()
    if requested_saves:
        save_checkpoint(requested_saves[-1])
    if spec.get("eval_at_end", True) and (not curve or curve[-1]["step"] != clock.steps):
        curve.append({"step": clock.steps, "train_s": clock.busy_s, **_evaluate(pipeline)})
    finals: Dict[str, Dict[str, float]] = {}
    for index, mode in enumerate(fusions):
        if index == 0:
            finals[mode] = {k: v for k, v in curve[-1].items() if k not in ("step", "train_s")}
            continue
        pipeline.model.set_fusion(mode)
        finals[mode] = _evaluate(pipeline)
    model = pipeline.model
    num_parameters, parameter_mib = _trained_parameters(model)
    rays = pipeline.datamanager.get_train_rays_per_batch()
    result = {
        "name": spec["name"],
        "method": spec["method"],
        "steps": clock.steps,
        "train_s": clock.busy_s,
        "train_rays_per_s": clock.steps * rays / max(clock.busy_s, 1e-9),
        "curve": curve,
        "final": curve[-1] if curve else {},
        "fusions": finals,
        "parameters": num_parameters,
        "parameter_mib": parameter_mib,
        "peak_rss_mib": peak_memory_mib("cpu")["peak_rss_mib"],
        "threads": torch.get_num_threads(),
        "run_dir": str(trainer.base_dir),
    }
    if hasattr(pipeline, "auto_num_blocks"):
        started = model.started_block_ids()
        result["num_blocks"] = len(started)
        result["block_tables"] = {str(k): int(model.blocks[str(k)].field.config.log2_hashmap_size) for k in started}
        result["block_train_s"] = block_train_s
    atomic_write_text(Path(spec["result"]), json.dumps(result, indent=2))
    return result


def _run_on_the_clock(spec: Dict[str, Any], trainer, eval_at_s: List[float], partial) -> Dict[str, Any]:
    """:func:`run` for a time budget's run: evaluated at ``eval_at_s`` training seconds and at its end."""
    from scalar_nerfstudio.seam.trainer import start_step  # imports nerfstudio's trainer

    pipeline = trainer.pipeline
    clock = trainer.training_clock
    first_step = start_step(trainer)
    curve: List[Dict[str, float]] = [p for p in (partial or {}).get("curve", []) if p["step"] <= first_step]
    phase_end_s: Dict[str, float] = {k: v for k, v in (partial or {}).get("phase_end_s", {}).items()}
    """Training seconds at the end of each finished phase (the blocks' times give the wall-clock of K workers)."""
    pending = [t for t in eval_at_s if not any(p.get("at_s") == t for p in curve)]
    partial_path = _partial_path(spec)
    progress_s = float(spec.get("progress_s") or eval_at_s[-1])

    def keep() -> None:
        content = {"run_dir": str(trainer.base_dir), "curve": curve, "phase_end_s": phase_end_s}
        atomic_write_text(partial_path, json.dumps(content, indent=2))

    keep()

    def after_step(step: int, result, step_clock: StepClock) -> None:
        print(f"PROGRESS {min(clock.elapsed_s(), progress_s):.0f} {progress_s:.0f}", flush=True)
        phase = pipeline.phase_at(step)
        if step + 1 == phase.end_step:
            phase_end_s[phase.name] = clock.elapsed_s()
        due = [t for t in pending if clock.elapsed_s() >= t]
        if due and step + 1 < trainer.total_steps:
            with clock.paused():
                curve.append({"step": step + 1, "train_s": clock.elapsed_s(), "at_s": due[-1], **_evaluate(pipeline)})
            for t in due:
                pending.remove(t)
            keep()

    time_train_iterations(trainer, after_step)
    trainer.train()
    with clock.paused():
        curve.append({"step": trainer.total_steps, "train_s": clock.elapsed_s(), "at_s": eval_at_s[-1], **_evaluate(pipeline)})
    keep()
    result = _finish(spec, trainer, curve, clock.elapsed_s(), trainer.total_steps - first_step)
    result["phase_s"] = _phase_seconds(pipeline.phases, phase_end_s)
    atomic_write_text(Path(spec["result"]), json.dumps(result, indent=2))
    return result


def _phase_seconds(phases, phase_end_s: Dict[str, float]) -> Dict[str, float]:
    """Training seconds of each phase, from the training time at the end of each (in order)."""
    seconds: Dict[str, float] = {}
    previous = 0.0
    for phase in phases:
        if phase.name in phase_end_s:
            seconds[phase.name] = phase_end_s[phase.name] - previous
            previous = phase_end_s[phase.name]
    return seconds


def _finish(spec: Dict[str, Any], trainer, curve: List[Dict[str, float]], train_s: float, steps_here: int) -> Dict[str, Any]:
    """The result of a time budget's run: its curve, the other fusions at its end, its blocks' times."""
    pipeline = trainer.pipeline
    model = pipeline.model
    finals: Dict[str, Dict[str, float]] = {}
    for index, mode in enumerate(spec.get("fusions") or []):
        if index == 0:
            finals[mode] = {k: v for k, v in curve[-1].items() if k not in ("step", "train_s", "at_s")}
            continue
        model.set_fusion(mode)
        finals[mode] = _evaluate(pipeline)
    num_parameters, parameter_mib = _trained_parameters(model)
    length = pipeline.length
    phases = {phase.name: phase.num_steps for phase in pipeline.phases}
    result = {
        "name": spec["name"], "method": spec["method"], "steps": curve[-1]["step"], "train_s": train_s,
        "train_rays_per_s": steps_here * pipeline.datamanager.get_train_rays_per_batch() / max(train_s, 1e-9),
        "curve": curve, "final": curve[-1], "fusions": finals, "parameters": num_parameters, "parameter_mib": parameter_mib,
        "peak_rss_mib": peak_memory_mib("cpu")["peak_rss_mib"], "threads": torch.get_num_threads(), "run_dir": str(trainer.base_dir),
        "length": {"global_steps": length.global_steps, "block_steps": length.block_steps, "budget_s": length.budget_s, "phases": phases},
        "num_blocks": len(model.started_block_ids()) if hasattr(model, "started_block_ids") else 0,
    }
    atomic_write_text(Path(spec["result"]), json.dumps(result, indent=2))
    return result


def main() -> None:
    run(json.loads(Path(sys.argv[1]).read_text()))


if __name__ == "__main__":
    main()
