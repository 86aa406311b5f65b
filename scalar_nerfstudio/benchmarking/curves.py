"""Speed against error to the plateau: ``scalar-nerf-benchmark --budgets 15m 1h ...``.

For every wall-clock budget, each variant trains once, from the start, as ``ns-train scalar-nerf
--pipeline.time-budget B`` would (its steps planned to fit the budget at its measured pace, its
learning-rate schedule spanning them), and is evaluated on the held-out views at 25, 50 and 75 % of
its training time and at its end. The variants (``--variants``; by default ``ngp-t``, ``ngp-t2``, ``auto`` and
``auto-parallel``):

* ``ngp-t``: one model with the blocks' table 2^T (the paper's NGP_T), ``ngp-t2``: a 4x table;
  ``ngp-t-decay`` / ``ngp-t2-decay``: the same with one decay over the run instead of the one-model restart;
* ``auto``: ``ns-train scalar-nerf``'s defaults (automatic K, blocks after the global phase, on one machine);
* ``auto-parallel``: the same on K workers (``--pipeline.block-workers K``): the budget is the wall-clock of
  the global phase plus one block, every block getting the time after the global phase (trained here one
  after another, each timed; the report reads the global phase plus the slowest block).

A budget's end points of one variant make its curve: PSNR and SSIM against training time on a log axis.
Each run keeps its curve so far and checkpoints as it trains, so ``--resume`` continues a run that was
interrupted where it stopped (a 4-hour curve need not run in one go) and reuses finished ones. Written to
``--output-dir``: results.json, results.md, psnr_vs_time.png, ssim_vs_time.png and, per budget, crops of one
held-out view at full resolution (``crops-<budget>.png``).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from scalar_nerfstudio.atomic_io import atomic_write_bytes, atomic_write_text
from scalar_nerfstudio.benchmarking.schedule import finished_run, run_runner, same_run
from scalar_nerfstudio.benchmarking.variants import (
    ONE_MODEL_VARIANTS,
    BenchmarkConfig,
    auto_k,
    curve_variants,
    one_model_schedule,
    ray_choice_overrides,
)
from scalar_nerfstudio.blocks.length import format_duration, parse_duration

__all__ = ["automatic_k_of", "budget_specs", "curve_table", "run_curves", "setting_line"]

#: The minutes the time axis is labelled at (those within the plotted range).
NICE_MINUTES: Tuple[float, ...] = (0.25, 0.5, 1, 2, 3, 5, 10, 15, 30, 60, 120, 240, 480)

#: Training steps between a budget run's checkpoints (what ``--resume`` continues from).
SAVE_EVERY_STEPS = 1000


def _label(budget: str) -> str:
    return budget.strip().lower().replace(" ", "")


def budget_specs(config: BenchmarkConfig, runs: Path) -> List[Dict[str, Any]]:
    """One runner SPEC per (budget, variant), in order: every variant of the shortest budget first."""
    budgets = sorted(config.budgets or (), key=parse_duration)
    wanted = curve_variants(config)
    log2_t = config.log2_table
    common: Dict[str, Any] = {
        "machine.seed": config.seed, "pipeline.datamanager.train_num_rays_per_batch": config.rays_per_batch,
        "pipeline.model.field.log2_hashmap_size": log2_t, "pipeline.global_steps": None, "pipeline.block_steps": None,
    }
    if config.decoder_width is not None:
        common["pipeline.model.field.hidden_dim"] = config.decoder_width
    common.update(ray_choice_overrides(config))
    from scalar_nerfstudio.models.scene_model import ScalarSceneModelConfig

    k = auto_k(config, log2_t) if any(v.startswith("auto") for v in wanted) else 1
    specs = []
    for budget in budgets:
        seconds = parse_duration(budget)
        for variant in wanted:
            overrides = {**common, "pipeline.time_budget": _label(budget)}
            fusions: List[str] = []
            eval_at = [share * seconds for share in sorted(config.budget_eval_shares)] + [seconds]
            progress = seconds
            if variant in ONE_MODEL_VARIANTS:
                size, schedule = one_model_schedule(variant)
                overrides.update({"pipeline.num_blocks": 1, "pipeline.train_blocks": False})
                if size == "ngp-t2":
                    overrides["pipeline.model.field.log2_hashmap_size"] = log2_t + 2
                if schedule == "decay":
                    overrides["pipeline.one_model_restart"] = 0.0
            else:
                fusions = [ScalarSceneModelConfig.fusion, "global-only"]
                if variant == "auto-parallel":
                    overrides["pipeline.block_workers"] = k
                    eval_at = [10.0 * seconds * max(k, 1)]  # at its end only: its blocks stand for K workers
                    progress = seconds * max(k, 1)
            name = f"{variant}@{_label(budget)}"
            specs.append({
                "name": name, "variant": variant, "budget": _label(budget), "budget_s": seconds, "num_blocks_auto": k,
                "method": "scalar-nerf", "data": str(config.data), "downscale": config.downscale, "overrides": overrides,
                "eval_at_s": eval_at, "progress_s": progress, "save_every_steps": SAVE_EVERY_STEPS, "fusions": fusions,
                "output_dir": str(runs / name), "result": str(runs / f"{name}.json"),
            })
    return specs


def _train(spec: Dict[str, Any], runs: Path, resume: bool, progress, task) -> Dict[str, Any]:
    """Train one budget run in its own process (or read it back / continue it with ``resume``)."""
    spec_path = runs / f"{spec['name']}.spec.json"
    if resume:
        done = finished_run(spec, spec_path)
        if done is not None:
            progress.console.print(f"{spec['name']}: reusing its finished run ({spec['result']})")
            return {**done, "reused": True}
    same_spec = spec_path.is_file() and same_run(json.loads(spec_path.read_text()), spec)
    runner_spec = {**spec, "resume": bool(resume and same_spec)}
    spec_path.write_text(json.dumps(spec, indent=2))
    runner_path = runs / f"{spec['name']}.runner.json"
    runner_path.write_text(json.dumps(runner_spec, indent=2))
    run_runner(runner_path, runs / f"{spec['name']}.log", what=spec["name"], progress=progress, task=task, append=True)
    result = json.loads(Path(spec["result"]).read_text())
    os.utime(spec["result"])  # newer than its spec: --resume reads it back
    return result


def wall_clock_s(spec: Dict[str, Any], result: Dict[str, Any]) -> float:
    """The run's wall-clock: its training time, or for ``auto-parallel`` its global phase plus its slowest block."""
    if spec["variant"] != "auto-parallel":
        return float(result["train_s"])
    phases = result.get("phase_s") or {}
    blocks = [s for name, s in phases.items() if name != "global"]
    return float(phases.get("global", 0.0)) + (max(blocks) if blocks else 0.0)


def best_drop_db(result: Dict[str, Any]) -> float:
    """How far the run's end lies below its own best evaluation (dB; 0 when its end is its best)."""
    psnrs = [p["psnr"] for p in result.get("curve", [])]
    return max(psnrs) - psnrs[-1] if psnrs else 0.0


def curve_table(specs: List[Dict[str, Any]], results: Dict[str, Dict[str, Any]]) -> str:
    """results.md's table: one row per variant, one column per budget (PSNR / SSIM, wall-clock, steps)."""
    budgets = list(dict.fromkeys(s["budget"] for s in specs))
    variants = list(dict.fromkeys(s["variant"] for s in specs))
    lines = ["| variant | " + " | ".join(budgets) + " |", "|---|" + "---|" * len(budgets)]
    for variant in variants:
        cells = []
        for budget in budgets:
            spec = next((s for s in specs if s["variant"] == variant and s["budget"] == budget), None)
            result = results.get(spec["name"]) if spec else None
            if spec is None or result is None:
                cells.append("not run")
                continue
            final = result["final"]
            length = result.get("length", {})
            blocks = [n for name, n in (length.get("phases") or {}).items() if name != "global"]
            each = (f"{len(blocks)} x {blocks[0]}" if len(set(blocks)) == 1 else " + ".join(map(str, blocks))) if blocks else \
                f"{result.get('num_blocks', 0)} x {length.get('block_steps')}"
            steps = f"{length.get('global_steps')} + {each}" if result.get("num_blocks") else f"{result['steps']}"
            drop = best_drop_db(result)
            cells.append(f"{final['psnr']:.2f} / {final['ssim']:.3f} ({format_duration(wall_clock_s(spec, result))}, {steps} steps"
                         + (f"; {drop:.2f} dB below its best" if drop > 0.005 else "") + ")")
        lines.append(f"| {variant} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _plots(specs: List[Dict[str, Any]], results: Dict[str, Dict[str, Any]], output_dir: Path) -> List[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FixedLocator, FuncFormatter, NullFormatter

    written = []
    for metric in ("psnr", "ssim"):
        figure, axis = plt.subplots(figsize=(7, 4.5))
        minutes_seen: List[float] = []
        for variant in dict.fromkeys(s["variant"] for s in specs):
            points = sorted((wall_clock_s(s, results[s["name"]]), results[s["name"]]["final"][metric])
                            for s in specs if s["variant"] == variant and s["name"] in results)
            if not points:
                continue
            (line,) = axis.plot([p[0] / 60 for p in points], [p[1] for p in points], marker="o", label=variant)
            minutes_seen += [p[0] / 60 for p in points]
            for s in specs:  # each run's own evaluations on the way, faint, in its variant's colour
                if s["variant"] == variant and s["name"] in results and variant != "auto-parallel":
                    curve = results[s["name"]]["curve"]
                    axis.plot([p["train_s"] / 60 for p in curve], [p[metric] for p in curve], color=line.get_color(),
                              alpha=0.35, linewidth=0.9, marker=".", markersize=3)
                    minutes_seen += [p["train_s"] / 60 for p in curve]
        axis.set_xscale("log")
        if minutes_seen:  # ticks at round minutes over the range shown, none between them
            low, high = min(minutes_seen), max(minutes_seen)
            ticks = [t for t in NICE_MINUTES if low / 1.5 <= t <= high * 1.5] or [round(high, 1)]
            axis.xaxis.set_major_locator(FixedLocator(ticks))
        axis.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        axis.xaxis.set_minor_formatter(NullFormatter())
        axis.set_xlabel("training wall-clock (min, log scale)")
        axis.set_ylabel(f"held-out {metric.upper()}")
        axis.grid(True, which="both", alpha=0.3)
        axis.legend()
        name = f"{metric}_vs_time.png"
        figure.tight_layout()
        figure.savefig(output_dir / name, dpi=120)
        plt.close(figure)
        written.append(name)
    return written


def _crops(specs: List[Dict[str, Any]], results: Dict[str, Dict[str, Any]], output_dir: Path, view: int, size: int = 256) -> List[str]:
    """Per budget: a full-resolution crop of held-out view ``view`` (its centre) from the truth and every run."""
    import numpy as np

    from scalar_nerfstudio.benchmarking.heldout_view import figure_png, render_view

    written = []
    for budget in dict.fromkeys(s["budget"] for s in specs):
        images, captions = [], []
        for spec in (s for s in specs if s["budget"] == budget and s["name"] in results):
            rendered = render_view(Path(results[spec["name"]]["run_dir"]), view)
            height, width = rendered["rgb"].shape[:2]
            top, left = max((height - size) // 2, 0), max((width - size) // 2, 0)
            if not images:
                images.append(np.asarray(rendered["truth"][top:top + size, left:left + size]))
                captions.append(f"truth, held-out view {view} (crop at full resolution)")
            images.append(np.asarray(rendered["rgb"][top:top + size, left:left + size]))
            captions.append(f"{spec['variant']}, {budget}: {rendered['psnr']:.2f} dB")
        if images:
            name = f"crops-{budget}.png"
            atomic_write_bytes(output_dir / name, figure_png(images, captions))
            written.append(name)
    return written


def automatic_k_of(specs: List[Dict[str, Any]]) -> Optional[int]:
    """The automatic K the budget runs ``specs`` were planned with, or None when none of them is a block
    variant (:func:`budget_specs` then records 1 without asking the capture)."""
    return specs[0]["num_blocks_auto"] if any(s["variant"].startswith("auto") for s in specs) else None


def setting_line(config: BenchmarkConfig, machine: str, automatic_k: Optional[int]) -> str:
    """The report's line on the machine and the runs' settings; ``automatic_k`` None: no block variant ran
    (the automatic K was not asked for, and is not stated)."""
    k = f"automatic K = {automatic_k}" if automatic_k is not None else "no block variant"
    return (f"Machine: {machine}. Tables 2^{config.log2_table} (ngp-t2: 2^{config.log2_table + 2}), {k}, seed {config.seed}, "
            f"{config.rays_per_batch} rays per step{', drawn by error' if config.ray_choice == 'error' else ''}.")


def run_curves(config: BenchmarkConfig, command: str, machine: str) -> Dict[str, Any]:
    """Train (or read back, or continue) every budget run, then write the report; returns results.json's content."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    output_dir = config.output_dir
    runs = output_dir / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    specs = budget_specs(config, runs)
    results: Dict[str, Dict[str, Any]] = {}
    started = time.time()
    with Progress(TextColumn("{task.description:<22}"), BarColumn(), TextColumn("{task.completed:.0f}/{task.total:.0f} s"),
                  TimeElapsedColumn()) as progress:
        tasks = {s["name"]: progress.add_task(s["name"], total=s["progress_s"], start=False) for s in specs}
        for spec in specs:
            progress.start_task(tasks[spec["name"]])
            results[spec["name"]] = _train(spec, runs, config.resume, progress, tasks[spec["name"]])
            progress.update(tasks[spec["name"]], completed=progress.tasks[tasks[spec["name"]]].total)
    files = _plots(specs, results, output_dir)
    files += _crops(specs, results, output_dir, config.heldout_view)
    k = automatic_k_of(specs)
    report = {"command": command, "machine": machine, "budgets": list(dict.fromkeys(s["budget"] for s in specs)),
              "automatic_k": k, "seed": config.seed, "log2_table": config.log2_table, "files": files,
              "runs": {s["name"]: {"spec": s, "wall_clock_s": wall_clock_s(s, results[s["name"]]),
                                   "best_drop_db": best_drop_db(results[s["name"]]), **results[s["name"]]} for s in specs},
              "minutes": (time.time() - started) / 60}
    atomic_write_text(output_dir / "results.json", json.dumps(report, indent=2))
    markdown = [f"# Speed against error: {config.data}", "", f"`{command}`", "", setting_line(config, machine, k), "",
                "Held-out PSNR / SSIM at the end of each budget's run (its wall-clock; auto-parallel: global phase + slowest block "
                "of K workers; steps as planned for the budget):", "", curve_table(specs, results), "",
                *[f"![{f}]({f})" for f in files]]
    atomic_write_text(output_dir / "results.md", "\n".join(markdown) + "\n")
    print(curve_table(specs, results))
    return report
