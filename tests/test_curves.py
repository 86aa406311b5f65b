"""``scalar-nerf-benchmark --budgets``: its plan of runs and its report, read from made-up results (no training;
tests/test_benchmark.py runs the harness end to end)."""

from __future__ import annotations

from pathlib import Path

import pytest

from scalar_nerfstudio.benchmarking.curves import (
    automatic_k_of,
    best_drop_db,
    budget_specs,
    curve_table,
    setting_line,
    wall_clock_s,
)
from scalar_nerfstudio.benchmarking.variants import BenchmarkConfig, check_options


def test_every_budget_trains_every_variant_from_the_start_as_a_user_would(scene: Path, tmp_path: Path) -> None:
    config = BenchmarkConfig(data=scene, downscale=1, log2_table=12, budgets=("1h", "15m"), seed=3, output_dir=tmp_path)
    specs = budget_specs(config, tmp_path / "runs")
    assert [s["name"] for s in specs] == [f"{v}@{b}" for b in ("15m", "1h") for v in ("ngp-t", "ngp-t2", "auto", "auto-parallel")]
    by_name = {s["name"]: s for s in specs}
    for spec in specs:
        overrides = spec["overrides"]
        assert overrides["pipeline.time_budget"] == spec["budget"] and overrides["machine.seed"] == 3
        assert overrides["pipeline.global_steps"] is None and overrides["pipeline.block_steps"] is None  # planned by the budget
    assert by_name["ngp-t@15m"]["overrides"]["pipeline.model.field.log2_hashmap_size"] == 12
    assert by_name["ngp-t2@15m"]["overrides"]["pipeline.model.field.log2_hashmap_size"] == 14
    assert by_name["ngp-t@15m"]["overrides"]["pipeline.num_blocks"] == 1
    assert "pipeline.num_blocks" not in by_name["auto@15m"]["overrides"]  # automatic K, as ns-train decides
    k = by_name["auto@15m"]["num_blocks_auto"]
    assert by_name["auto-parallel@15m"]["overrides"]["pipeline.block_workers"] == k
    assert by_name["ngp-t@1h"]["eval_at_s"] == [900.0, 1800.0, 2700.0, 3600.0]
    assert by_name["auto@15m"]["fusions"][0] == "nearest-guarded"


def test_the_variants_asked_are_the_runs_trained_and_a_variant_no_budget_trains_is_refused(scene: Path, tmp_path: Path) -> None:
    """``--variants`` with ``--budgets`` trains exactly the variants asked (the one models' ``-decay`` schedule
    among them, former names accepted); one that a budget does not train is refused before anything is written,
    never replaced by the default four."""
    config = BenchmarkConfig(data=scene, downscale=1, log2_table=12, budgets=("1h",), variants=("ngp-t-decay", "ngp21"),
                             output_dir=tmp_path / "out")
    check_options(config)
    specs = budget_specs(config, tmp_path / "runs")
    assert [s["name"] for s in specs] == ["ngp-t-decay@1h", "ngp-t2@1h"]
    decay, table = (s["overrides"] for s in specs)
    assert decay["pipeline.one_model_restart"] == 0.0 and decay["pipeline.model.field.log2_hashmap_size"] == 12
    assert "pipeline.one_model_restart" not in table and table["pipeline.model.field.log2_hashmap_size"] == 14
    for variants in (("ngp-t", "scalar"), ("nerfacto",)):
        with pytest.raises(SystemExit, match=f"--variants {variants[-1]}: not trained by --budgets"):
            check_options(BenchmarkConfig(data=scene, budgets=("15m",), variants=variants, output_dir=tmp_path / "out"))
    assert not (tmp_path / "out").exists()


def test_a_budget_that_is_no_duration_is_refused() -> None:
    with pytest.raises(SystemExit, match="--budgets soon"):
        check_options(BenchmarkConfig(budgets=("15m", "soon")))
    with pytest.raises(SystemExit, match="at least one budget"):
        check_options(BenchmarkConfig(budgets=()))


def _result(psnrs, train_s=100.0, phase_s=None, **extra):
    curve = [{"step": 10 * (i + 1), "train_s": train_s * (i + 1) / len(psnrs), "psnr": p, "ssim": 0.5} for i, p in enumerate(psnrs)]
    return {"curve": curve, "final": curve[-1], "train_s": train_s, "steps": curve[-1]["step"], "phase_s": phase_s or {}, **extra}


def test_the_k_workers_wall_clock_is_the_global_phase_and_the_slowest_block() -> None:
    parallel = {"variant": "auto-parallel"}
    result = _result([20.0], train_s=500.0, phase_s={"global": 100.0, "block 0": 90.0, "block 1": 110.0, "block 2": 95.0})
    assert wall_clock_s(parallel, result) == pytest.approx(210.0)
    assert wall_clock_s({"variant": "auto"}, result) == pytest.approx(500.0)


def test_the_report_says_when_a_run_ends_below_its_own_best() -> None:
    assert best_drop_db(_result([20.0, 21.0, 21.5])) == 0.0
    worse = _result([20.0, 21.8, 21.5])
    assert best_drop_db(worse) == pytest.approx(0.3)
    specs = [{"name": "ngp-t@1m", "variant": "ngp-t", "budget": "1m"}, {"name": "ngp-t@2m", "variant": "ngp-t", "budget": "2m"}]
    table = curve_table(specs, {"ngp-t@1m": worse})
    assert "21.50 / 0.500" in table and "0.30 dB below its best" in table and "not run" in table


def test_the_report_states_the_automatic_k_only_when_a_block_variant_ran(scene: Path, tmp_path: Path) -> None:
    """A report of one-model runs only must not claim an automatic K (it once said K = 1 on a K = 5 capture)."""
    one_model = BenchmarkConfig(data=scene, downscale=1, log2_table=12, budgets=("15m",), variants=("ngp-t", "ngp-t2"), output_dir=tmp_path)
    assert automatic_k_of(budget_specs(one_model, tmp_path / "runs")) is None
    with_blocks = BenchmarkConfig(data=scene, downscale=1, log2_table=12, budgets=("15m",), variants=("ngp-t", "auto"), output_dir=tmp_path)
    specs = budget_specs(with_blocks, tmp_path / "runs")
    assert automatic_k_of(specs) == specs[1]["num_blocks_auto"] >= 1
    config = BenchmarkConfig(data=tmp_path, log2_table=17)
    assert "automatic K = 5," in setting_line(config, "2 cores", 5)
    line = setting_line(config, "2 cores", None)
    assert "automatic K" not in line and "no block variant" in line and "2^17 (ngp-t2: 2^19)" in line


def test_a_finished_one_model_run_is_reused_whichever_variants_are_asked_beside_it(scene: Path, tmp_path: Path) -> None:
    """NGP_T run alone records automatic K 1 (none asked); asked again beside the blocks (K from the capture), its
    finished run is the same run and ``--resume`` reads it back; a block variant's K still makes its spec."""
    from scalar_nerfstudio.benchmarking.schedule import same_run

    alone = budget_specs(BenchmarkConfig(data=scene, downscale=1, log2_table=12, budgets=("15m",), variants=("ngp-t",),
                                         output_dir=tmp_path), tmp_path / "runs")[0]
    beside = {s["name"]: s for s in budget_specs(BenchmarkConfig(data=scene, downscale=1, log2_table=12, budgets=("15m",),
                                                                 variants=("ngp-t", "auto"), output_dir=tmp_path), tmp_path / "runs")}
    assert beside["auto@15m"]["num_blocks_auto"] != alone["num_blocks_auto"]  # the scene's automatic K is not 1
    assert same_run(alone, beside["ngp-t@15m"]) and same_run(beside["ngp-t@15m"], alone)
    assert not same_run({**alone, "overrides": {**alone["overrides"], "machine.seed": 7}}, beside["ngp-t@15m"])
    auto = beside["auto@15m"]
    assert not same_run({**auto, "num_blocks_auto": auto["num_blocks_auto"] + 1}, auto)
