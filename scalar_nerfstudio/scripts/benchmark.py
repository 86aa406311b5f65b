"""``scalar-nerf-benchmark``: speed against error of every variant on one scene, in one run.

    scalar-nerf-benchmark --data ../shared/data/castle-P30 --downscale 4 --output-dir docs/benchmark/castle-P30
    scalar-nerf-benchmark --quick --output-dir /tmp/bench     # synthetic scene, a minute: checks the harness

Variants (same scene, same machine, same run; each trains in its own process):

* ``ngp19`` / ``ngp21``: one model (the paper's NGP_19 / NGP_21), ``G + K B`` steps, table 2^19 / 2^21.
* ``global``: the SCALAR-NeRF global phase (``G`` steps, table 2^19). The block variants below all
  start from this one trained global model (its time is counted in theirs), as in the paper.
* ``scalar``: K blocks of ``B`` steps each, fine-tuned decoders, s_AABB = 1.2, tables 2^19; evaluated
  with ``global`` fusion (SCALAR-NeRF), ``idw`` and ``nearest`` (the same models, other fusions).
* ``scalar-wo-sd``: independent decoders (the paper's "w/o SD"); evaluated with ``global`` fusion and
  with ``idw``, which is Block-NeRF's recipe (independent blocks + inverse distance weighting).
* ``scalar-wo-ft``: frozen copies of the global decoder ("w/o FT").
* ``scalar-s1.0``: s_AABB = 1.0 (no overlap beyond KMeans' cells).
* ``scalar-autocap``: K blocks with per-block table size and resolution chosen automatically.
* ``auto``: everything automatic (K and capacity; K = 1 means one model of ``G + K B`` steps).
* ``nerfacto``: nerfstudio's nerfacto, torch implementation, for the wall-clock SCALAR-NeRF took.
  Its LPIPS needs downloaded AlexNet weights, so it is not computed for nerfacto.

Equal budgets: every SCALAR/NGP variant trains ``G + K B`` steps of the same ray batch; nerfacto
trains for the same wall-clock as ``scalar``. Training time excludes evaluation. PSNR / SSIM (and
LPIPS when its weights are available offline) are measured on the eval split (every 8th image)
every ``eval_every`` steps. Written to ``--output-dir``: results.json, results.md, and
psnr_vs_time.png, psnr_vs_render_time.png, psnr_vs_parameters.png.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import tyro

VARIANTS: Tuple[str, ...] = (
    "ngp19", "ngp21", "scalar", "scalar-wo-sd", "scalar-wo-ft", "scalar-s1.0", "scalar-autocap", "auto", "nerfacto",
)
#: Rows of the report: (variant, fusion) -> label.
LABELS: Dict[Tuple[str, str], str] = {
    ("ngp19", "global"): "NGP_19 (one model, 2^19)",
    ("ngp21", "global"): "NGP_21 (one model, 2^21)",
    ("scalar", "global"): "SCALAR-NeRF (blocks + global fusion)",
    ("scalar", "idw"): "blocks + IDW (same models)",
    ("scalar", "nearest"): "blocks + nearest (same models)",
    ("scalar-wo-sd", "global"): "SCALAR-NeRF w/o SD (independent decoders)",
    ("scalar-wo-sd", "idw"): "Block-NeRF-style (independent blocks + IDW)",
    ("scalar-wo-ft", "global"): "SCALAR-NeRF w/o FT (frozen decoder)",
    ("scalar-s1.0", "global"): "SCALAR-NeRF, s_AABB = 1.0",
    ("scalar-autocap", "global"): "SCALAR-NeRF, automatic block tables",
    ("auto", "global"): "automatic K and capacity",
    ("nerfacto", "global"): "nerfacto (torch), same wall-clock",
}


@dataclass
class BenchmarkConfig:
    """Speed against error of every variant on one scene."""

    data: Optional[Path] = None
    """Scene folder (nerfstudio format). Required unless --quick (which makes a synthetic scene)."""
    downscale: int = 4
    """Image downscale factor (nerfstudio's --downscale-factor; images_4/ at 4)."""
    output_dir: Path = Path("outputs/benchmark")
    """Where results.json/.md and the plots go (runs under output_dir/runs)."""
    global_steps: int = 400
    """G: steps of the global phase."""
    block_steps: int = 100
    """B: steps of each block."""
    num_blocks: int = 4
    """K of the fixed-K variants."""
    rays_per_batch: int = 2048
    """Training rays per step (every variant)."""
    eval_every: int = 200
    """Evaluate every this many steps (plus at the end of each variant)."""
    variants: Tuple[str, ...] = VARIANTS
    """Which variants to run (the block variants add the global phase they start from)."""
    quick: bool = False
    """Synthetic 24-image scene, tiny models, a few steps: checks the harness end to end in about a minute."""
    verbose: bool = False
    """Show the variants' training output."""
    from_results: bool = False
    """Train nothing: rewrite results.md and the plots from output_dir/results.json."""


@dataclass
class Variant:
    name: str
    method: str
    overrides: Dict[str, Any]
    fusions: List[str] = field(default_factory=lambda: ["global"])
    base: Optional[str] = None
    """Variant whose trained global model this one starts from (its time and curve are prepended)."""
    time_limit_s: float = 0.0


def _tables(config: BenchmarkConfig) -> Tuple[int, int, Dict[str, Any]]:
    """(log2 T of NGP_19, of NGP_21, field/sampling overrides shared by all our variants)."""
    if config.quick:
        return 14, 16, {
            "pipeline.model.field.max_resolution": 256, "pipeline.model.num_samples_per_ray": 32,
            "pipeline.model.occupancy_warmup_steps": 8,
        }
    return 19, 21, {}


def auto_k(config: BenchmarkConfig, log2_t: int) -> int:
    """The automatic K scalar-nerf would choose on this scene (same rule as the pipeline)."""
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig

    from scalar_nerfstudio.pipeline import ScalarPipelineConfig, parsed_layout_scale

    parsed = NerfstudioDataParserConfig(
        data=config.data, downscale_factor=config.downscale, eval_mode="interval", eval_interval=8
    ).setup().get_dataparser_outputs("train")
    pipeline = ScalarPipelineConfig()
    pipeline.model.field.log2_hashmap_size = log2_t
    return pipeline.automatic_num_blocks(parsed_layout_scale(parsed), len(parsed.image_filenames))


def plan(config: BenchmarkConfig) -> Tuple[List[Variant], Dict[str, str]]:
    """The variants to run, in order, and notes (e.g. a variant that is the same as another)."""
    g, b, k = config.global_steps, config.block_steps, config.num_blocks
    total = g + k * b
    log2_19, log2_21, shared = _tables(config)
    common = {**shared, "pipeline.datamanager.train_num_rays_per_batch": config.rays_per_batch, "pipeline.model.field.log2_hashmap_size": log2_19}
    fixed_tables = {"pipeline.block_log2_hashmap_size": log2_19, "pipeline.block_max_resolution": 256 if config.quick else 2048}
    single = {**common, "pipeline.num_blocks": 1, "pipeline.train_blocks": False, "pipeline.global_steps": total}
    blocks = {**common, "pipeline.num_blocks": k, "pipeline.global_steps": 0, "pipeline.block_steps": b}
    notes: Dict[str, str] = {}
    wanted = list(config.variants)
    unknown = [v for v in wanted if v not in VARIANTS]
    if unknown:
        raise SystemExit(f"scalar-nerf-benchmark: unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
    out: List[Variant] = []
    if any(v.startswith("scalar") or v == "nerfacto" for v in wanted) or "auto" in wanted:
        out.append(Variant("global", "scalar-nerf", {**common, "pipeline.num_blocks": k, "pipeline.train_blocks": False, "pipeline.global_steps": g}))
    for name in wanted:
        if name == "ngp19":
            out.append(Variant(name, "scalar-nerf", single))
        elif name == "ngp21":
            out.append(Variant(name, "scalar-nerf", {**single, "pipeline.model.field.log2_hashmap_size": log2_21}))
        elif name == "scalar":
            out.append(Variant(name, "scalar-nerf", {**blocks, **fixed_tables}, ["global", "idw", "nearest"], base="global"))
        elif name == "scalar-wo-sd":
            out.append(Variant(name, "scalar-nerf", {**blocks, **fixed_tables, "pipeline.decoder_mode": "independent"}, ["global", "idw"], base="global"))
        elif name == "scalar-wo-ft":
            out.append(Variant(name, "scalar-nerf", {**blocks, **fixed_tables, "pipeline.decoder_mode": "frozen"}, base="global"))
        elif name == "scalar-s1.0":
            out.append(Variant(name, "scalar-nerf", {**blocks, **fixed_tables, "pipeline.aabb_scale": [1.0, 1.0, 1.0]}, base="global"))
        elif name == "scalar-autocap":
            out.append(Variant(name, "scalar-nerf", blocks, base="global"))
        elif name == "auto":
            chosen = auto_k(config, log2_19)
            if chosen == 1:
                notes[name] = f"automatic K = 1 on this scene: one 2^{log2_19} model of {total} steps, the same configuration as ngp19"
                if "ngp19" not in wanted:
                    out.append(Variant("ngp19", "scalar-nerf", single))
            else:
                notes[name] = f"automatic K = {chosen}, {k * b // chosen} steps per block, automatic block tables"
                out.append(Variant(name, "scalar-nerf", {**blocks, "pipeline.num_blocks": None, "pipeline.block_steps": k * b // chosen}, base="global"))
        elif name == "nerfacto":
            overrides: Dict[str, Any] = {"pipeline.datamanager.train_num_rays_per_batch": config.rays_per_batch}
            if config.quick:
                overrides.update({"pipeline.datamanager.train_num_rays_per_batch": 256, "pipeline.model.eval_num_rays_per_chunk": 4096})
            out.append(Variant(name, "nerfacto", overrides))
    return out, notes


def _spec(config: BenchmarkConfig, variant: Variant, runs: Path, results: Dict[str, Dict[str, Any]]) -> Dict[str, Any]:
    overrides = dict(variant.overrides)
    if variant.base is not None:
        overrides["pipeline.global_checkpoint"] = results[variant.base]["checkpoint"]
    eval_every = config.eval_every
    if variant.method == "nerfacto":  # time-limited: evaluated at the end only (its renders take ~1 min)
        eval_every = 0
        overrides["max_num_iterations"] = 10**6
    return {
        "name": variant.name, "method": variant.method, "data": str(config.data), "downscale": config.downscale,
        "overrides": overrides, "eval_every": eval_every, "time_limit_s": variant.time_limit_s, "fusions": variant.fusions,
        "output_dir": str(runs / variant.name), "result": str(runs / f"{variant.name}.json"),
        "keep_checkpoint": variant.name == "global",
    }


def run_variant(config: BenchmarkConfig, variant: Variant, runs: Path, results: Dict[str, Dict[str, Any]], progress, task) -> Dict[str, Any]:
    """Train one variant in a subprocess (progress bar from its PROGRESS lines); its result dict."""
    spec = _spec(config, variant, runs, results)
    spec_path = runs / f"{variant.name}.spec.json"
    spec_path.write_text(json.dumps(spec, indent=2))
    log_path = runs / f"{variant.name}.log"
    command = [sys.executable, "-m", "scalar_nerfstudio.scripts._benchmark_runner", str(spec_path)]
    with log_path.open("w", buffering=1) as log:  # line-buffered: the log can be followed while it runs
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        assert process.stdout is not None
        for line in process.stdout:
            log.write(line)
            if line.startswith("PROGRESS "):
                done, total = (float(x) for x in line.split()[1:3])
                progress.update(task, completed=done, total=max(total, 1.0))
            elif config.verbose:
                progress.console.print(line.rstrip())
        code = process.wait()
    if code != 0:
        tail = "".join(log_path.read_text().splitlines(keepends=True)[-30:])
        raise SystemExit(f"scalar-nerf-benchmark: variant {variant.name} failed (exit {code}); log {log_path}:\n{tail}")
    result = json.loads(Path(spec["result"]).read_text())
    if variant.name == "global":
        checkpoints = sorted((Path(result["run_dir"]) / "nerfstudio_models").glob("step-*.ckpt"))
        result["checkpoint"] = str(checkpoints[-1])
    if variant.base is not None:  # the global phase it started from is part of its cost
        base = results[variant.base]
        offset_s, offset_steps = base["train_s"], base["steps"]
        result["curve"] = base["curve"] + [{**p, "train_s": p["train_s"] + offset_s, "step": p["step"] + offset_steps} for p in result["curve"]]
        rays = result["train_rays_per_s"] * result["train_s"] + base["train_rays_per_s"] * offset_s
        result["train_s"] += offset_s
        result["steps"] += offset_steps
        result["train_rays_per_s"] = rays / max(result["train_s"], 1e-9)
    return result


def rows(results: Dict[str, Dict[str, Any]], notes: Optional[Dict[str, str]] = None) -> List[Dict[str, Any]]:
    """One row per (variant, fusion): label, time, metrics, parameters, memory."""
    labels = dict(LABELS)
    if notes and "auto" in notes and "auto" not in results:  # automatic K = 1: the ngp19 run is it
        labels[("ngp19", "global")] += " = automatic K and capacity"
    out = []
    for name, result in results.items():
        if name == "global":
            continue
        for fusion, metrics in (result.get("fusions") or {"global": result["final"]}).items():
            fusion_key = "global" if fusion in ("global", "global-only") else fusion
            out.append({
                "variant": name, "fusion": fusion, "label": labels.get((name, fusion_key), f"{name} ({fusion})"),
                "steps": result["steps"], "train_s": result["train_s"], "train_rays_per_s": result["train_rays_per_s"],
                "psnr": metrics["psnr"], "ssim": metrics["ssim"], "lpips": metrics.get("lpips"),
                "render_ms_per_image": metrics["render_ms_per_image"], "parameters": result["parameters"],
                "peak_rss_mib": result["peak_rss_mib"], "num_blocks": result.get("num_blocks"),
            })
    for row in out:
        row["pareto_parameters"] = _on_front(row, out, "parameters")
        row["pareto_time"] = _on_front(row, out, "train_s")
    return out


def _on_front(row: Dict[str, Any], all_rows: List[Dict[str, Any]], cost: str) -> bool:
    """No other row has lower-or-equal ``cost`` and higher-or-equal PSNR with one of them strict."""
    return not any(
        other is not row and other[cost] <= row[cost] and other["psnr"] >= row["psnr"]
        and (other[cost] < row[cost] or other["psnr"] > row["psnr"])
        for other in all_rows
    )


def markdown(config: BenchmarkConfig, table: List[Dict[str, Any]], notes: Dict[str, str], command: str, machine: str) -> str:
    total = config.global_steps + config.num_blocks * config.block_steps
    lines = [
        f"# Speed against error: {config.data.name if config.data else 'synthetic'} (downscale {config.downscale})",
        "",
        f"Command: `{command}`",
        "",
        f"Machine: {machine}. Budget: {total} steps of {config.rays_per_batch} rays for every SCALAR/NGP variant "
        f"(global phase G = {config.global_steps}, K = {config.num_blocks} blocks x B = {config.block_steps}); nerfacto: "
        "the wall-clock of `scalar`. Training time excludes evaluation. Eval split: every 8th image. "
        "LPIPS: not computed for nerfacto (its weights need a download); for ours only when the weights are available offline.",
        "",
        "| variant | fusion | steps | train s | rays/s | PSNR | SSIM | render ms/img | parameters | peak RSS MiB | Pareto (params / time) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(table, key=lambda r: -r["psnr"]):
        front = f"{'yes' if r['pareto_parameters'] else '-'} / {'yes' if r['pareto_time'] else '-'}"
        lines.append(
            f"| {r['label']} | {r['fusion']} | {r['steps']} | {r['train_s']:.0f} | {r['train_rays_per_s']:.0f} | {r['psnr']:.2f} | "
            f"{r['ssim']:.3f} | {r['render_ms_per_image']:.0f} | {r['parameters'] / 1e6:.1f} M | {r['peak_rss_mib']:.0f} | {front} |"
        )
    if notes:
        lines += ["", *[f"- {name}: {note}" for name, note in notes.items()]]
    lines += ["", "![PSNR vs training time](psnr_vs_time.png)", "", "![PSNR vs render time](psnr_vs_render_time.png)", "",
              "![PSNR vs parameters](psnr_vs_parameters.png)", ""]
    return "\n".join(lines)


def plots(results: Dict[str, Dict[str, Any]], table: List[Dict[str, Any]], output_dir: Path) -> List[Path]:
    """PSNR vs training time (curves), vs render time and vs parameters (points): three PNGs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    figure, axes = plt.subplots(figsize=(7, 4.5))
    for name, result in results.items():
        curve = result["curve"]
        if curve:
            axes.plot([p["train_s"] / 60 for p in curve], [p["psnr"] for p in curve], marker="o", markersize=3,
                      label=LABELS.get((name, "global"), name), linestyle="--" if name == "global" else "-")
    axes.set_xlabel("training time (min, evaluation excluded)")
    axes.set_ylabel("eval PSNR (dB)")
    axes.grid(alpha=0.3)
    axes.legend(fontsize=7)
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


def _quick_scene(output_dir: Path) -> Path:
    from scalar_nerfstudio.data.synthetic_scene import write_scene

    scene = output_dir / "scene"
    if not (scene / "transforms.json").is_file():
        write_scene(scene, num_images=24, width=96, height=72)
    return scene


def main(config: BenchmarkConfig) -> Dict[str, Any]:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    command = "scalar-nerf-benchmark " + " ".join(sys.argv[1:])
    output_dir = config.output_dir
    if config.from_results:
        return rewrite_report(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    if config.quick:
        config.data = config.data or _quick_scene(output_dir)
        config.downscale, config.global_steps, config.block_steps, config.num_blocks = 1, 20, 6, 2
        config.rays_per_batch, config.eval_every = 512, 10
    if config.data is None or not Path(config.data).is_dir():
        raise SystemExit(f"scalar-nerf-benchmark: --data {config.data} is not a scene folder (or use --quick)")
    variants, notes = plan(config)
    runs = output_dir / "runs"
    runs.mkdir(exist_ok=True)
    results: Dict[str, Dict[str, Any]] = {}
    started = time.time()
    with Progress(TextColumn("{task.description:<16}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()) as progress:
        tasks = {v.name: progress.add_task(v.name, total=1.0, start=False) for v in variants}
        for variant in variants:
            progress.start_task(tasks[variant.name])
            if variant.name == "nerfacto":
                variant.time_limit_s = results["scalar"]["train_s"] if "scalar" in results else results["global"]["train_s"] * 2
            results[variant.name] = run_variant(config, variant, runs, results, progress, tasks[variant.name])
            progress.update(tasks[variant.name], completed=progress.tasks[tasks[variant.name]].total)
    table = rows(results, notes)
    machine = f"{os.cpu_count()} CPU cores" + (", CUDA" if _cuda() else ", no GPU")
    report = {
        "command": command, "machine": machine, "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(config).items()},
        "notes": notes, "rows": table, "results": results, "wall_clock_s": time.time() - started,
    }
    (output_dir / "results.json").write_text(json.dumps(report, indent=2))
    (output_dir / "results.md").write_text(markdown(config, table, notes, command, machine))
    plots(results, table, output_dir)
    print((output_dir / "results.md").read_text().split("\n![")[0])
    print(f"written: {output_dir / 'results.md'}, results.json and 3 PNG plots ({(time.time() - started) / 60:.1f} min)")
    return report


def rewrite_report(output_dir: Path) -> Dict[str, Any]:
    """results.md and the plots again from results.json (e.g. after a change to the report)."""
    path = output_dir / "results.json"
    if not path.is_file():
        raise SystemExit(f"scalar-nerf-benchmark: {path} not found (run the benchmark first)")
    report = json.loads(path.read_text())
    saved = report["config"]
    config = BenchmarkConfig(**{k: v for k, v in saved.items() if k in BenchmarkConfig.__dataclass_fields__})
    config.data = Path(saved["data"]) if saved.get("data") not in (None, "None") else None
    config.output_dir = output_dir
    report["rows"] = rows(report["results"], report["notes"])
    path.write_text(json.dumps(report, indent=2))
    (output_dir / "results.md").write_text(markdown(config, report["rows"], report["notes"], report["command"], report["machine"]))
    plots(report["results"], report["rows"], output_dir)
    print((output_dir / "results.md").read_text().split("\n![")[0])
    return report


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def entrypoint() -> None:
    """Console entry point."""
    main(tyro.cli(BenchmarkConfig))


if __name__ == "__main__":
    entrypoint()
