"""Running the benchmark's variants: the scene, then each planned variant in its own subprocess, in order.

Each variant is trained by ``python -m scalar_nerfstudio.benchmarking.runner SPEC.json`` (see
:mod:`.runner`); its output goes to ``runs/<variant>.log``, its ``PROGRESS`` lines drive a progress
bar, and its result JSON is read back. A block variant's result includes the global phase it started
from (time, steps and curve).
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from scalar_nerfstudio.benchmarking.variants import (
    BenchmarkConfig,
    Variant,
    blocks_wall_clock_s,
    check_options,
    former_variant_name,
    nearest_to_wall_clock,
    plan,
    use_quick_budgets,
    wall_clock_retry,
    wall_clock_variants,
)

__all__ = [
    "RUNNER_MODULE", "finished_run", "finished_run_of_former_name", "prepare", "run_runner", "run_variant", "run_variants", "variant_spec",
    "with_base_phase",
]

#: The worker module each variant runs in (``python -m RUNNER_MODULE SPEC.json``).
RUNNER_MODULE = "scalar_nerfstudio.benchmarking.runner"
#: The report's note on a run read back by ``--resume``.
REUSED_NOTE = "reused (--resume): an earlier run of the same spec, timed on the machine as it was then"


def _quick_scene(output_dir: Path) -> Path:
    from scalar_nerfstudio.scenes.courtyard import write_scene

    scene = output_dir / "scene"
    if not (scene / "transforms.json").is_file():
        write_scene(scene, num_images=24, width=96, height=72)
    return scene


def prepare(config: BenchmarkConfig) -> Tuple[List[Variant], Dict[str, str]]:
    """Make ``config.output_dir`` (and ``runs/`` in it), the synthetic scene and budgets of ``--quick``,
    check the scene folder; the planned variants and notes (see :func:`.variants.plan`). Bad options and
    a missing scene folder are refused before anything is written."""
    check_options(config)
    makes_its_own_scene = config.quick and config.data is None
    if not makes_its_own_scene and (config.data is None or not Path(config.data).is_dir()):
        raise SystemExit(f"scalar-nerf-benchmark: --data {config.data} is not a scene folder (or use --quick)")
    output_dir = config.output_dir
    output_dir.mkdir(parents=True, exist_ok=True)
    if config.quick:
        config.data = config.data or _quick_scene(output_dir)
        use_quick_budgets(config)
    variants, notes = plan(config)
    (output_dir / "runs").mkdir(exist_ok=True)
    return variants, notes


def variant_spec(config: BenchmarkConfig, variant: Variant, *, runs: Path, results: Dict[str, Dict[str, Any]]) -> Dict[str, Any]:
    """The SPEC the runner trains ``variant`` from (``results``: the variants run so far)."""
    overrides = {"machine.seed": config.seed, **variant.overrides}
    if variant.base is not None:
        overrides["pipeline.global_checkpoint"] = results[variant.base]["checkpoint"]
    eval_every = config.eval_every if variant.eval_every is None else variant.eval_every
    if variant.method == "nerfacto":  # time-limited: evaluated at the end only (its renders take ~1 min)
        eval_every = 0
        overrides["max_num_iterations"] = 10**6
    return {
        "name": variant.name, "method": variant.method, "data": str(config.data), "downscale": config.downscale,
        "overrides": overrides, "eval_every": eval_every, "time_limit_s": variant.time_limit_s, "fusions": variant.fusions,
        "output_dir": str(runs / variant.name), "result": str(runs / f"{variant.name}.json"),
    }


def run_variant(
    config: BenchmarkConfig, variant: Variant, *, runs: Path, results: Dict[str, Dict[str, Any]], progress, task,
) -> Dict[str, Any]:
    """Train one variant in a subprocess (progress bar from its PROGRESS lines); its result dict. With
    ``config.resume``, a finished run of the same spec in ``runs`` is read instead (:func:`finished_run`),
    also one recorded under the variant's former name (:func:`finished_run_of_former_name`)."""
    spec = variant_spec(config, variant, runs=runs, results=results)
    spec_path = runs / f"{variant.name}.spec.json"
    result = ((finished_run(spec, spec_path) or finished_run_of_former_name(config, variant, runs=runs, results=results))
              if config.resume else None)
    if result is not None:
        progress.console.print(f"{variant.name}: reusing its finished run ({spec['result']})")
        return _completed(variant, {**result, "reused": True}, results)
    spec_path.write_text(json.dumps(spec, indent=2))
    run_runner(spec_path, runs / f"{variant.name}.log", what=f"variant {variant.name}", progress=progress, task=task,
               verbose=config.verbose)
    return _completed(variant, json.loads(Path(spec["result"]).read_text()), results)


def run_runner(spec_path: Path, log_path: Path, *, what: str, progress, task, verbose: bool = False, append: bool = False) -> None:
    """Run ``python -m RUNNER_MODULE spec_path``, its output to ``log_path`` (``append``: after what is there),
    its ``PROGRESS`` lines driving ``task``; a failure ends the benchmark with ``what``, its exit code and its log's tail."""
    command = [sys.executable, "-m", RUNNER_MODULE, str(spec_path)]
    with log_path.open("a" if append else "w", buffering=1) as log:  # line-buffered: the log can be followed while it runs
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                   env={**os.environ, "PYTHONUNBUFFERED": "1"})
        assert process.stdout is not None
        for line in process.stdout:
            log.write(line)
            if line.startswith("PROGRESS "):
                done, total = (float(x) for x in line.split()[1:3])
                progress.update(task, completed=done, total=max(total, 1.0))
            elif verbose:
                progress.console.print(line.rstrip())
        code = process.wait()
    if code != 0:
        tail = "".join(log_path.read_text().splitlines(keepends=True)[-30:])
        raise SystemExit(f"scalar-nerf-benchmark: {what} failed (exit {code}); log {log_path}:\n{tail}")


def same_run(recorded: Dict[str, Any], spec: Dict[str, Any]) -> bool:
    """Whether the spec ``recorded`` for a run describes the run ``spec`` does: equal as JSON, except that a
    one-model variant (``ngp-*``) does not use the capture's automatic K, which a budget spec records as 1
    when no block variant is asked beside it and as the capture's K otherwise; asking another variant with
    it must not make its finished run another run."""
    ignored = ("num_blocks_auto",) if str(spec.get("variant", "")).startswith("ngp") else ()

    def identity(value: Dict[str, Any]) -> Dict[str, Any]:
        return {k: v for k, v in json.loads(json.dumps(value)).items() if k not in ignored}

    return identity(recorded) == identity(spec)


def finished_run(spec: Dict[str, Any], spec_path: Path) -> Optional[Dict[str, Any]]:
    """The result of the run ``spec_path`` describes, or None. It is that run's when the spec there is
    ``spec`` (compared as JSON, so paths as written: a scene or output folder given another way is
    another spec), the result file was written after that spec (a run stopped midway leaves the
    result of an earlier spec older than its own), it names the variant, and its run folder, with its
    checkpoint, is still there."""
    result_path = Path(spec["result"])
    if not (spec_path.is_file() and result_path.is_file()):
        return None
    if not same_run(json.loads(spec_path.read_text()), spec):
        return None
    if result_path.stat().st_mtime < spec_path.stat().st_mtime:
        return None
    result = json.loads(result_path.read_text())
    if result.get("name") != spec["name"] or _checkpoint_of(result) is None:
        return None
    return result


def finished_run_of_former_name(config: BenchmarkConfig, variant: Variant, *, runs: Path,
                                results: Dict[str, Dict[str, Any]]) -> Optional[Dict[str, Any]]:
    """The result of a finished run of ``variant`` that an earlier benchmark recorded in ``runs`` under the
    variant's former name (``ngp19.spec.json`` for ``ngp-t``; :func:`.variants.former_variant_name`), with
    the spec that name gives otherwise the same; renamed to ``variant.name``. None when there is none."""
    former = former_variant_name(variant.name)
    if former is None:
        return None
    as_before = dataclasses.replace(variant, name=former)
    result = finished_run(variant_spec(config, as_before, runs=runs, results=results), runs / f"{former}.spec.json")
    return None if result is None else {**result, "name": variant.name}


def _checkpoint_of(result: Dict[str, Any]) -> Optional[Path]:
    """The newest checkpoint in the run folder a runner's ``result`` names, or None."""
    from scalar_nerfstudio.runs import MODEL_DIR_NAME, newest_checkpoint

    return newest_checkpoint(Path(result.get("run_dir", "")) / MODEL_DIR_NAME)


def _completed(variant: Variant, result: Dict[str, Any], results: Dict[str, Dict[str, Any]]) -> Dict[str, Any]:
    """A runner's ``result`` as the benchmark keeps it: the global phase's checkpoint found, a block
    variant's global phase counted in (:func:`with_base_phase`)."""
    if variant.name == "global":
        checkpoint = _checkpoint_of(result)
        if checkpoint is None:
            raise SystemExit(f"scalar-nerf-benchmark: the global phase's run {result.get('run_dir')} has no checkpoint to start the blocks from")
        result["checkpoint"] = str(checkpoint)
    if variant.base is not None:  # the global phase it started from is part of its cost
        result = with_base_phase(result, results[variant.base])
    return result


def with_base_phase(result: Dict[str, Any], base: Dict[str, Any]) -> Dict[str, Any]:
    """A block variant's ``result`` with the global phase ``base`` it started from counted in: its curve
    prepended (later points shifted by its time and steps), time, steps and rays/s added, and
    ``parallel_train_s``, the wall-clock with K workers training the K blocks at once
    (``scalar-nerf-train-blocks``): the global phase, then the slowest block (from the runner's
    ``block_train_s``; without it, the blocks' mean)."""
    result = dict(result)
    offset_s, offset_steps = base["train_s"], base["steps"]
    result["curve"] = base["curve"] + [{**p, "train_s": p["train_s"] + offset_s, "step": p["step"] + offset_steps} for p in result["curve"]]
    rays = result["train_rays_per_s"] * result["train_s"] + base["train_rays_per_s"] * offset_s
    block_times = list((result.get("block_train_s") or {}).values())
    one_block = max(block_times) if block_times else result["train_s"] / max(int(result.get("num_blocks") or 1), 1)
    result["parallel_train_s"] = offset_s + one_block
    result["train_s"] += offset_s
    result["steps"] += offset_steps
    result["train_rays_per_s"] = rays / max(result["train_s"], 1e-9)
    return result


def run_variants(config: BenchmarkConfig, variants: List[Variant], notes: Optional[Dict[str, str]] = None) -> Dict[str, Dict[str, Any]]:
    """Every variant in order under ``config.output_dir/runs``, with a progress bar each; their results
    by name. nerfacto gets the wall-clock of ``scalar`` (else twice the global phase's). Then the one-model
    runs that ended before the blocks' wall-clock on K workers train again for it
    (:func:`.variants.wall_clock_variants`), up to ``config.wall_clock_tries`` times while a run ends away
    from it (:func:`.variants.wall_clock_retry`); the run nearest it is kept under ``<name>-wall-clock``,
    and their notes are added to ``notes``."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    runs = config.output_dir / "runs"
    results: Dict[str, Dict[str, Any]] = {}
    with Progress(TextColumn("{task.description:<16}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()) as progress:

        def train(variant: Variant, task) -> Dict[str, Any]:
            progress.start_task(task)
            result = run_variant(config, variant, runs=runs, results=results, progress=progress, task=task)
            progress.update(task, completed=progress.tasks[task].total)
            return result

        tasks = {v.name: progress.add_task(v.name, total=1.0, start=False) for v in variants}
        for variant in variants:
            if variant.name == "nerfacto":
                variant.time_limit_s = results["scalar"]["train_s"] if "scalar" in results else results["global"]["train_s"] * 2
            results[variant.name] = train(variant, tasks[variant.name])
            if results[variant.name].get("reused") and notes is not None:
                notes[variant.name] = "; ".join(filter(None, [notes.get(variant.name), REUSED_NOTE]))
        seconds = blocks_wall_clock_s(results)
        for variant, note in wall_clock_variants(config, variants, results):
            tried: List[Tuple[Variant, Dict[str, Any]]] = []
            again: Optional[Variant] = variant
            while again is not None:
                tried.append((again, train(again, progress.add_task(again.name, total=1.0, start=False))))
                again = wall_clock_retry(config, tried, seconds)
            results[variant.name], runs_note = nearest_to_wall_clock(tried, seconds)
            reused = [v.name for v, r in tried if r.get("reused")]
            if notes is not None:
                notes[variant.name] = f"{note}. {runs_note}" + (f"; {', '.join(reused)}: {REUSED_NOTE}" if reused else "")
    return results
