"""``scalar-nerf-benchmark``: speed against error of every variant on one scene, in one run.

    scalar-nerf-benchmark --data ../shared/data/castle-P30 --downscale 4 --output-dir docs/benchmark/castle-P30
    scalar-nerf-benchmark --quick --output-dir /tmp/bench     # synthetic scene, a minute: checks the harness

The variants (one model with the blocks' table, ``ngp-t``, and with a 4x table, ``ngp-t2``: the
paper's NGP_T / NGP_{T+2}, each with the one-model default schedule and with one decay over the run,
``-decay``; SCALAR-NeRF and its ablations with several fusions, automatic K and
capacity; nerfacto) are listed in :mod:`scalar_nerfstudio.benchmarking.variants`;
each trains in its own process, on the same scene and machine, in the same run.

Equal budgets: every SCALAR/NGP variant trains ``G + K B`` steps of the same ray batch; nerfacto
trains for the same wall-clock as ``scalar``. Training time excludes evaluation. PSNR / SSIM (and
LPIPS when its weights are available offline) are measured on the eval split (every 8th image)
every ``eval_every`` steps. Written to ``--output-dir``: results.json, results.md, and
psnr_vs_time.png, psnr_vs_render_time.png, psnr_vs_parameters.png, and heldout_view.png (one
held-out view: truth, one model, blocks, block colours; :mod:`scalar_nerfstudio.benchmarking.heldout_view`).
The blocks are compared with the better schedule of each one model. The machine line of the report
carries the machine's speed before and after the runs (:mod:`scalar_nerfstudio.benchmarking.machine`).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any, Dict

import tyro

from scalar_nerfstudio.benchmarking.heldout_view import write_heldout_view
from scalar_nerfstudio.benchmarking.machine import hash_grid_speed
from scalar_nerfstudio.benchmarking.report import results_table_text, rewrite_report, write_report
from scalar_nerfstudio.benchmarking.schedule import prepare, run_variants
from scalar_nerfstudio.benchmarking.variants import BenchmarkConfig, check_options, plan

__all__ = ["BenchmarkConfig", "entrypoint", "main", "plan"]


def main(config: BenchmarkConfig) -> Dict[str, Any]:
    command = "scalar-nerf-benchmark " + " ".join(sys.argv[1:])
    output_dir = config.output_dir
    if config.from_results:
        report = rewrite_report(output_dir)
        print(results_table_text(output_dir))
        return report
    if config.budgets is not None:
        from scalar_nerfstudio.benchmarking.curves import run_curves
        from scalar_nerfstudio.benchmarking.machine import describe_cpu

        check_options(config)
        if config.data is None or not Path(config.data).is_dir():
            raise SystemExit(f"scalar-nerf-benchmark: --data {config.data} is not a scene folder")
        return run_curves(config, command, describe_cpu())
    variants, notes = prepare(config)
    # the machine's speed around the runs (--quick: a small probe, only to exercise the harness)
    probe_size = {"num_points": 1 << 14, "log2_hashmap_size": 14, "repeats": 2} if config.quick else {}
    machine_probe = {"before": hash_grid_speed(**probe_size)}
    started = time.time()
    results = run_variants(config, variants, notes)
    machine_probe["after"] = hash_grid_speed(**probe_size)
    report = write_report(config, results, notes=notes, command=command, started=started,
                          machine_probe=machine_probe)  # first without the picture: a failed render loses no table
    view = write_heldout_view(config, results)
    if view is not None:
        report = write_report(config, results, notes=notes, command=command, started=started, machine_probe=machine_probe,
                              heldout_view=view)
    print(results_table_text(output_dir))
    picture = f" and {view['file']}" if view is not None else ""
    print(f"written: {output_dir / 'results.md'}, results.json, 3 PNG plots{picture} ({(time.time() - started) / 60:.1f} min)")
    return report


def entrypoint() -> None:
    """Console entry point."""
    main(tyro.cli(BenchmarkConfig))


if __name__ == "__main__":
    entrypoint()
