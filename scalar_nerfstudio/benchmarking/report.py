"""The benchmark's report: one row per (variant, fusion) with its Pareto fronts, and the files.

Written to the output folder: results.json (the report: command, machine, config, notes, rows, the
variants' results), results.md (the table, equal wall-clock, the blocks against the better schedule of
each one model) and psnr_vs_time.png, psnr_vs_render_time.png,
psnr_vs_parameters.png. The JSON and Markdown are written atomically.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from scalar_nerfstudio.atomic_io import atomic_write_text
from scalar_nerfstudio.benchmarking.variants import (
    DECAY_SUFFIX,
    ONE_MODEL_SCHEDULES,
    ONE_MODEL_VARIANTS,
    WALL_CLOCK_SUFFIX,
    BenchmarkConfig,
    canonical_variant,
    parallel_block_steps,
)

__all__ = [
    "LABELS", "SCHEDULE_NAMES", "blocks_against_one_model", "describe_machine", "equal_wall_clock", "labels", "markdown",
    "on_pareto_front", "one_model_at", "one_model_baseline", "plots", "psnr_at", "results_table_text", "rewrite_report", "rows",
    "write_report",
]

#: How the report names the one-model schedules of :data:`.variants.ONE_MODEL_SCHEDULES`.
SCHEDULE_NAMES: Dict[str, str] = {"restart": "the one-model default, hold then restart", "decay": "one decay over the run"}

#: Rows of the report at the paper's T = 19: (variant, fusion) -> label (see :func:`labels`).
LABELS: Dict[Tuple[str, str], str] = {
    ("ngp-t", "global"): "NGP_19 (one model, 2^19)",
    ("ngp-t2", "global"): "NGP_21 (one model, 2^21)",
    ("scalar", "global"): "SCALAR-NeRF (blocks + global fusion)",
    ("scalar", "surface"): "blocks + surface fusion (same models)",
    ("scalar", "idw"): "blocks + IDW (same models)",
    ("scalar", "nearest"): "blocks + nearest (same models)",
    ("scalar", "global-only"): "its global model alone",
    ("scalar-init-global", "global"): "SCALAR-NeRF, blocks start as the global model",
    ("scalar-init-global", "surface"): "blocks start as the global model + surface fusion",
    ("scalar-init-global", "idw"): "blocks start as the global model + IDW",
    ("scalar-init-global", "nearest"): "blocks start as the global model + nearest",
    ("scalar-init-global", "global-only"): "its global model alone",
    ("scalar-fitted", "nearest"): "blocks with fitted tables + nearest",
    ("scalar-fitted", "global"): "blocks with fitted tables + global fusion",
    ("scalar-fitted", "surface"): "blocks with fitted tables + surface fusion",
    ("scalar-fitted", "global-only"): "its global model alone",
    ("scalar-wo-sd", "global"): "SCALAR-NeRF w/o SD (independent decoders)",
    ("scalar-wo-sd", "idw"): "Block-NeRF-style (independent blocks + IDW)",
    ("scalar-wo-ft", "global"): "SCALAR-NeRF w/o FT (frozen decoder)",
    ("scalar-s1.0", "global"): "SCALAR-NeRF, s_AABB = 1.0",
    ("scalar-autocap", "global"): "SCALAR-NeRF, automatic block tables",
    ("auto", "nearest"): "the defaults' blocks + nearest (no guard; the default fusion until 2026-11-27)",
    ("auto", "global"): "the defaults' blocks + global fusion (the paper's)",
    ("auto", "nearest-idw"): "the defaults' blocks + nearest-idw (two nearest blocks per ray)",
    ("auto", "nearest-guarded"): "ns-train scalar-nerf defaults (automatic K, nearest-guarded fusion)",
    ("auto", "global-only"): "its global model alone",
    ("auto-fitted", "nearest"): "the fitted blocks + nearest (no guard)",
    ("auto-fitted", "nearest-idw"): "the fitted blocks + nearest-idw",
    ("auto-fitted", "nearest-guarded"): "the defaults with fitted block tables (--pipeline.block-init fitted)",
    ("auto-fitted", "global-only"): "its global model alone",
    ("auto-parallel", "nearest"): "the same blocks + nearest (no guard)",
    ("auto-parallel", "nearest-idw"): "the same blocks + nearest-idw (two nearest blocks per ray)",
    ("auto-parallel", "nearest-guarded"): "the defaults, each block trained as long as NGP_T after the global phase",
    ("auto-parallel", "global-only"): "its global model alone",
    ("auto-parallel-fitted", "nearest"): "the same fitted blocks + nearest (no guard)",
    ("auto-parallel-fitted", "nearest-idw"): "the same fitted blocks + nearest-idw",
    ("auto-parallel-fitted", "nearest-guarded"): "the same with fitted block tables (--pipeline.block-init fitted)",
    ("auto-parallel-fitted", "global-only"): "its global model alone",
    ("nerfacto", "global"): "nerfacto (torch), same wall-clock",
}


def labels(log2_table: int = 19) -> Dict[Tuple[str, str], str]:
    """:data:`LABELS` for tables of 2^``log2_table`` (NGP_T and NGP_{T+2})."""
    out = dict(LABELS)
    out[("ngp-t", "global")] = f"NGP_{log2_table} (one model, 2^{log2_table})"
    out[("ngp-t2", "global")] = f"NGP_{log2_table + 2} (one model, 2^{log2_table + 2})"
    for size, schedules in ONE_MODEL_SCHEDULES.items():
        out[(schedules["decay"], "global")] = out[(size, "global")] + ", one decay over the run"
    for name in ONE_MODEL_VARIANTS:
        out[(name + WALL_CLOCK_SUFFIX, "global")] = out[(name, "global")] + ", trained for the blocks' wall-clock"
    return out


def rows(results: Dict[str, Dict[str, Any]], notes: Optional[Dict[str, str]] = None, log2_table: int = 19) -> List[Dict[str, Any]]:
    """One row per (variant, fusion): label, time, metrics, parameters, memory."""
    labels_ = labels(log2_table)
    if notes and "auto" in notes and "auto" not in results:  # automatic K = 1: the ngp-t run is it
        labels_[("ngp-t", "global")] += " = automatic K and capacity"
    out = []
    for name, result in results.items():
        if name == "global":
            continue
        for fusion, metrics in (result.get("fusions") or {"global": result["final"]}).items():
            fusion_key = "global" if fusion == "global-only" and (name, fusion) not in labels_ else fusion
            out.append({
                "variant": name, "fusion": fusion, "label": labels_.get((name, fusion_key), f"{name} ({fusion})"),
                "steps": result["steps"], "train_s": result["train_s"], "train_rays_per_s": result["train_rays_per_s"],
                "psnr": metrics["psnr"], "ssim": metrics["ssim"], "lpips": metrics.get("lpips"),
                "depth_delta1": metrics.get("depth_delta1"),
                "render_ms_per_image": metrics["render_ms_per_image"], "parameters": result["parameters"],
                "peak_rss_mib": result["peak_rss_mib"], "num_blocks": result.get("num_blocks"),
                "parallel_train_s": result.get("parallel_train_s"),
            })
    for row in out:
        row["pareto_parameters"] = on_pareto_front(row, out, "parameters")
        row["pareto_time"] = on_pareto_front(row, out, "train_s")
    return out


def on_pareto_front(row: Dict[str, Any], all_rows: List[Dict[str, Any]], cost: str) -> bool:
    """No other row has lower-or-equal ``cost`` and higher-or-equal PSNR with one of them strict."""
    return not any(
        other is not row and other[cost] <= row[cost] and other["psnr"] >= row["psnr"]
        and (other[cost] < row[cost] or other["psnr"] > row["psnr"])
        for other in all_rows
    )


def psnr_at(curve: List[Dict[str, float]], seconds: float) -> Optional[Tuple[float, float]]:
    """(PSNR, step) of a training curve at ``seconds`` of training, linearly interpolated between its
    evaluations; None before the first evaluation or after the last."""
    points = sorted(curve, key=lambda p: p["train_s"])
    for before, after in zip(points, points[1:]):
        if before["train_s"] <= seconds <= after["train_s"]:
            span = max(after["train_s"] - before["train_s"], 1e-9)
            share = (seconds - before["train_s"]) / span
            return (before["psnr"] + share * (after["psnr"] - before["psnr"]), before["step"] + share * (after["step"] - before["step"]))
    if points and abs(points[-1]["train_s"] - seconds) < 1e-9:
        return points[-1]["psnr"], points[-1]["step"]
    return None


def equal_wall_clock(results: Dict[str, Dict[str, Any]], table: List[Dict[str, Any]], log2_table: int = 19) -> List[str]:
    """Markdown lines: each block variant's PSNR with its K blocks trained in parallel, against the one-model
    runs (NGP curves) at the same wall-clock."""
    parallel = [r for r in table if r.get("parallel_train_s")]
    if not parallel:
        return []
    names = labels(log2_table)
    lines = ["", "## Equal wall-clock, K blocks on K workers", "",
             "A block variant's time here is its global phase plus its slowest block's (the K blocks trained at once, as "
             "`scalar-nerf-train-blocks` does); each one-model run is read off its PSNR curve at that time, or, when it ended "
             "earlier, the same model trained again from the start for that wall-clock is read at its end. The equal-steps "
             "variants do NGP_T's total work, so on K workers they finish early; `auto-parallel` gives each block the "
             "steps NGP_T trains after the global phase.", "",
             "| model | fusion | wall-clock s | PSNR |", "|---|---|---|---|"]
    times = sorted({round(r["parallel_train_s"], 1) for r in parallel})
    for r in sorted(parallel, key=lambda r: -r["psnr"]):
        lines.append(f"| {r['label']} | {r['fusion']} | {r['parallel_train_s']:.0f} | {r['psnr']:.2f} |")
    for name in ONE_MODEL_VARIANTS:
        if name not in results:
            continue
        for seconds in times:
            cell = one_model_at(results, name, seconds)["cell"]
            lines.append(f"| {names[(name, 'global')]} at the same wall-clock | - | {seconds:.0f} | {cell} |")
    return lines


def one_model_at(results: Dict[str, Dict[str, Any]], name: str, seconds: Optional[float] = None) -> Dict[str, Any]:
    """What the one-model run ``name`` scored at a budget: ``psnr`` (None: no figure there), ``cell`` (the
    figure and how it was read) and ``run`` (the variant whose run it was read from).

    ``seconds`` None: equal total steps, its run's end. Else the wall-clock ``seconds``: its curve read
    there; when it ended earlier, its rerun for the blocks' wall-clock (``<name>-wall-clock``) at its
    end, else its own end (and the cell says so); before its first evaluation, no figure."""
    result = results[name]
    if seconds is None:
        return {"psnr": result["final"]["psnr"], "cell": f"{result['final']['psnr']:.2f} ({result['steps']} steps)", "run": name}
    again = results.get(name + WALL_CLOCK_SUFFIX)  # trained once more for the blocks' wall-clock (--match-wall-clock)
    curve = result["curve"]
    found = psnr_at(curve, seconds)
    last = max(curve, key=lambda p: p["train_s"]) if curve else None
    if found:
        return {"psnr": found[0], "cell": f"{found[0]:.2f} (step {found[1]:.0f})", "run": name}
    if last is not None and seconds <= last["train_s"]:  # before its first evaluation: the rerun, planned for a later time, does not stand for it
        first = min(curve, key=lambda p: p["train_s"])
        return {"psnr": None, "run": name,
                "cell": f"no evaluation at that time; its first, at {first['train_s']:.0f} s (step {first['step']}): {first['psnr']:.2f}"}
    if again is not None:
        return {"psnr": again["final"]["psnr"], "run": name + WALL_CLOCK_SUFFIX,
                "cell": f"**{again['final']['psnr']:.2f}**: trained again for this wall-clock, {again['steps']} steps in {again['train_s']:.0f} s"}
    if last is not None:
        return {"psnr": last["psnr"], "run": name, "cell": f"{last['psnr']:.2f}: it ended earlier, at {last['train_s']:.0f} s (step {last['step']})"}
    return {"psnr": None, "run": name, "cell": "no evaluation at that time"}


def one_model_baseline(results: Dict[str, Dict[str, Any]], size: str, seconds: Optional[float] = None) -> Optional[Dict[str, Any]]:
    """The one-model baseline of table size ``size`` (``ngp-t`` or ``ngp-t2``) at a budget: of its runs with
    each schedule (:data:`.variants.ONE_MODEL_SCHEDULES`) in ``results``, the one that scored the higher
    held-out PSNR there (``seconds`` as in :func:`one_model_at`; on a tie the restart run, the default).
    :func:`one_model_at`'s dict with ``variant`` and ``schedule`` added; None when no run has a figure there."""
    scored = [{**one_model_at(results, variant, seconds), "variant": variant, "schedule": schedule}
              for schedule, variant in ONE_MODEL_SCHEDULES[size].items() if variant in results]
    scored = [s for s in scored if s["psnr"] is not None]
    return max(scored, key=lambda s: s["psnr"]) if scored else None  # (max keeps the first of equals: restart)


def blocks_against_one_model(results: Dict[str, Dict[str, Any]], table: List[Dict[str, Any]], log2_table: int = 19) -> List[str]:
    """Markdown lines: every block variant (its own fusion) minus NGP_T and minus NGP_{T+2}, each the better of
    its schedules (:func:`one_model_baseline`) at the same budget: equal total steps (every block variant
    but ``auto-parallel*``) and equal wall-clock on K workers (every block variant)."""
    own: Dict[str, Dict[str, Any]] = {}
    for row in table:
        if row.get("parallel_train_s"):
            own.setdefault(row["variant"], row)  # a variant's first row is its run's own fusion
    sizes = [size for size, schedules in ONE_MODEL_SCHEDULES.items() if any(v in results for v in schedules.values())]
    if not own or not sizes:
        return []
    short = {"ngp-t": f"NGP_{log2_table}", "ngp-t2": f"NGP_{log2_table + 2}"}
    header = " | ".join(f"{short[size]} (schedule, run read) | blocks - {short[size]}" for size in sizes)
    lines = ["", "## The blocks against the one model", "",
             "Each block variant with its own fusion against each table size's one model, the better of its two schedules "
             f"at that budget: restart, {SCHEDULE_NAMES['restart']} (`ngp-t`, `ngp-t2`), or decay, {SCHEDULE_NAMES['decay']} "
             f"(`ngp-t{DECAY_SUFFIX}`, `ngp-t2{DECAY_SUFFIX}`); both runs are in the table above.", "",
             f"| blocks | fusion | budget | PSNR | {header} |", "|---|---|---|---|" + "---|---|" * len(sizes)]
    for r in sorted(own.values(), key=lambda r: -r["psnr"]):
        budgets = [(f"equal wall-clock, {r['parallel_train_s']:.0f} s", r["parallel_train_s"])]
        if not r["variant"].startswith("auto-parallel"):  # (auto-parallel trains more steps: compared at equal wall-clock only)
            budgets.insert(0, (f"equal total steps, {r['steps']}", None))
        for budget, seconds in budgets:
            cells = []
            for size in sizes:
                best = one_model_baseline(results, size, seconds)
                cells += ([f"{best['psnr']:.2f} ({best['schedule']}, `{best['run']}`)", f"{r['psnr'] - best['psnr']:+.2f}"]
                          if best else ["no figure at that budget", "-"])
            lines.append(f"| {r['label']} | {r['fusion']} | {budget} | {r['psnr']:.2f} | " + " | ".join(cells) + " |")
    return lines


def decoder_width_used(config: BenchmarkConfig) -> int:
    """The decoder width every SCALAR/NGP variant of a run trains with: ``--decoder-width``, else the field's default."""
    from scalar_nerfstudio.fields.scalar_field import ScalarFieldConfig

    return config.decoder_width if config.decoder_width is not None else ScalarFieldConfig.hidden_dim


def markdown(config: BenchmarkConfig, table: List[Dict[str, Any]], *, notes: Dict[str, str], command: str, machine: str,
             results: Optional[Dict[str, Dict[str, Any]]] = None, decoder_width: Optional[int] = None, seed: Optional[int] = None,
             heldout_view: Optional[Dict[str, Any]] = None) -> str:
    """results.md; ``decoder_width``: the width the run's variants trained with (None: a report written
    before the width was recorded, which says so); ``seed``: their ``machine.seed`` (None: a report of
    runs from before the benchmark seeded them); ``heldout_view``: the picture's view and panels
    (:func:`.heldout_view.write_heldout_view`), None: no picture."""
    total = config.global_steps + config.num_blocks * config.block_steps
    parallel_budget = ""
    if any(name.startswith("auto-parallel") for name in (results or {})):
        parallel_budget = f"; `auto-parallel`: G, then each of its blocks {parallel_block_steps(config)} steps"
    lines = [
        f"# Speed against error: {config.data.name if config.data else 'synthetic'} (downscale {config.downscale})",
        "",
        f"Command: `{command}`",
        "",
        f"Machine: {machine}. Budget: {total} steps of {config.rays_per_batch} rays for every SCALAR/NGP variant "
        f"(global phase G = {config.global_steps}, K = {config.num_blocks} blocks x B = {config.block_steps}{parallel_budget}; "
        f"decoder {f'{decoder_width} wide' if decoder_width is not None else 'width not recorded'}); nerfacto: "
        "the wall-clock of `scalar`. Training time excludes evaluation. Eval split: every 8th image. "
        + (f"Seed {seed} (`machine.seed` of every run). " if seed is not None else "Runs not seeded (written before the benchmark seeded them). ") +
        "LPIPS: not computed for nerfacto (its weights need a download); for ours only when the weights are available offline.",
        "",
    ]
    has_depth = any(r.get("depth_delta1") is not None for r in table)  # a scene with true depth (the town)
    depth_header = " depth within 25 % |" if has_depth else ""
    lines += [
        f"| variant | fusion | steps | train s | rays/s | PSNR | SSIM |{depth_header} render ms/img | parameters | peak RSS MiB | Pareto (params / time) |",
        "|---|---|---|---|---|---|---|" + ("---|" if has_depth else "") + "---|---|---|---|",
    ]
    for r in sorted(table, key=lambda r: -r["psnr"]):
        front = f"{'yes' if r['pareto_parameters'] else '-'} / {'yes' if r['pareto_time'] else '-'}"
        depth = (f" {r['depth_delta1']:.1%} |" if r.get("depth_delta1") is not None else " - |") if has_depth else ""
        lines.append(
            f"| {r['label']} | {r['fusion']} | {r['steps']} | {r['train_s']:.0f} | {r['train_rays_per_s']:.0f} | {r['psnr']:.2f} | "
            f"{r['ssim']:.3f} |{depth} {r['render_ms_per_image']:.0f} | {r['parameters'] / 1e6:.1f} M | {r['peak_rss_mib']:.0f} | {front} |"
        )
    if has_depth:
        lines += ["", "Depth within 25 %: the share of the held-out views' pixels of known depth whose rendered depth is "
                  "within a factor 1.25 of the scene's true depth (mean over the views): a model that renders colour "
                  "from haze in the wrong place scores low here, whatever its PSNR."]
    if notes:
        lines += ["", *[f"- {name}: {note}" for name, note in notes.items()]]
    lines += equal_wall_clock(results or {}, table, config.log2_table)
    lines += blocks_against_one_model(results or {}, table, config.log2_table)
    if heldout_view:
        captions = " | ".join(panel["caption"] for panel in heldout_view["panels"])
        lines += ["", f"## Held-out view {heldout_view['view']}", "", captions, "", "![held-out view](heldout_view.png)"]
    lines += ["", "![PSNR vs training time](psnr_vs_time.png)", "", "![PSNR vs render time](psnr_vs_render_time.png)", "",
              "![PSNR vs parameters](psnr_vs_parameters.png)", ""]
    return "\n".join(lines)


def plots(results: Dict[str, Dict[str, Any]], table: List[Dict[str, Any]], output_dir: Path, *, log2_table: int = 19) -> List[Path]:
    """PSNR vs training time (curves), vs render time and vs parameters (points): three PNGs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    figure, axes = plt.subplots(figsize=(8, 5))
    names = labels(log2_table)

    def curve_label(name: str, result: Dict[str, Any]) -> str:  # a curve is rendered with the variant's first fusion
        return names.get((name, next(iter(result.get("fusions") or {"global": None}))), name)

    for name, result in results.items():
        curve = result["curve"]
        if curve:
            axes.plot([p["train_s"] / 60 for p in curve], [p["psnr"] for p in curve], marker="o", markersize=3,
                      label=curve_label(name, result), linestyle="--" if name == "global" else "-")
    base_end = (results.get("global") or {}).get("curve", [])[-1:]
    for name, result in results.items():  # the block variants on K workers: from the global phase's end to their wall-clock
        if result.get("parallel_train_s") and result["curve"] and base_end:
            axes.plot([base_end[0]["train_s"] / 60, result["parallel_train_s"] / 60], [base_end[0]["psnr"], result["curve"][-1]["psnr"]],
                      marker="*", markersize=8, linestyle=":", label=f"{curve_label(name, result)}, K blocks on K workers")
    axes.set_xlabel("training time (min, evaluation excluded; solid: one machine, dotted: K workers)")
    axes.set_ylabel("eval PSNR (dB)")
    axes.grid(alpha=0.3)
    axes.legend(fontsize=6, loc="lower right")
    figure.tight_layout()
    written.append(output_dir / "psnr_vs_time.png")
    figure.savefig(written[-1], dpi=120)
    plt.close(figure)
    for key, xlabel, filename in (
        ("render_ms_per_image", "render time per eval image (ms, log)", "psnr_vs_render_time.png"),
        ("parameters", "parameters (log)", "psnr_vs_parameters.png"),
    ):
        figure, axes = plt.subplots(figsize=(9, 4.5))
        markers = "osD^vP*Xh<>p"
        for index, row in enumerate(sorted(table, key=lambda r: -r["psnr"])):
            axes.scatter(row[key], row["psnr"], s=36, marker=markers[index % len(markers)], label=f"{row['label']} ({row['psnr']:.2f} dB)")
        axes.set_xscale("log")
        axes.set_xlabel(xlabel)
        axes.set_ylabel("eval PSNR (dB)")
        axes.grid(alpha=0.3)
        axes.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
        figure.tight_layout()
        written.append(output_dir / filename)
        figure.savefig(written[-1], dpi=120)
        plt.close(figure)
    return written


def describe_machine() -> str:
    """E.g. ``"16 CPU cores, CUDA"``: the report's machine line."""
    import torch

    return f"{os.cpu_count()} CPU cores" + (", CUDA" if torch.cuda.is_available() else ", no GPU")


def _write(output_dir: Path, config: BenchmarkConfig, report: Dict[str, Any]) -> None:
    """results.json, results.md and the plots of ``report``."""
    atomic_write_text(output_dir / "results.json", json.dumps(report, indent=2))
    atomic_write_text(output_dir / "results.md", markdown(
        config, report["rows"], notes=report["notes"], command=report["command"], machine=report["machine"], results=report["results"],
        decoder_width=report.get("decoder_width"), seed=report["config"].get("seed"), heldout_view=report.get("heldout_view"),
    ))
    plots(report["results"], report["rows"], output_dir, log2_table=config.log2_table)


def write_report(
    config: BenchmarkConfig, results: Dict[str, Dict[str, Any]], *, notes: Dict[str, str], command: str, started: float,
    machine_probe: Optional[Dict[str, float]] = None, heldout_view: Optional[Dict[str, Any]] = None,
) -> Dict[str, Any]:
    """The report of a benchmark run (``started``: ``time.time()`` when its variants started), written
    to ``config.output_dir``; returns it. ``machine_probe``: the machine's speed before and after the
    runs (M points/s, :func:`.machine.hash_grid_speed`), shown on the report's machine line;
    ``heldout_view``: the held-out picture's view and panels (heldout_view.png), None: none."""
    table = rows(results, notes, config.log2_table)
    machine = describe_machine()
    if machine_probe is not None:
        machine += (f"; hash-grid probe {machine_probe['before']:.2f} M points/s before the runs, "
                    f"{machine_probe['after']:.2f} after (absolute times move with it)")
    report = {
        "command": command, "machine": machine, "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(config).items()},
        "notes": notes, "rows": table, "results": results, "wall_clock_s": time.time() - started,
        "decoder_width": decoder_width_used(config), "machine_probe_mpts_per_s": machine_probe, "heldout_view": heldout_view,
    }
    _write(config.output_dir, config, report)
    return report


def rewrite_report(output_dir: Path) -> Dict[str, Any]:
    """results.md and the plots again from results.json (e.g. after a change to the report). Variants
    recorded under a former name (``ngp19``, ``ngp21`` and the names derived from them) are renamed."""
    path = output_dir / "results.json"
    if not path.is_file():
        raise SystemExit(f"scalar-nerf-benchmark: {path} not found (run the benchmark first)")
    report = json.loads(path.read_text())
    for key in ("results", "notes"):
        report[key] = {canonical_variant(name): value for name, value in report[key].items()}
    saved = report["config"]
    config = BenchmarkConfig(**{k: v for k, v in saved.items() if k in BenchmarkConfig.__dataclass_fields__})
    config.data = Path(saved["data"]) if saved.get("data") not in (None, "None") else None
    config.output_dir = output_dir
    report["rows"] = rows(report["results"], report["notes"], config.log2_table)
    _write(output_dir, config, report)
    return report


def results_table_text(output_dir: Path) -> str:
    """results.md of ``output_dir`` without its plots (what the command prints)."""
    return (output_dir / "results.md").read_text().split("\n![")[0]
