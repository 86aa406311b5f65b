"""``scalar-nerf-benchmark``: equal wall-clock runs, the better schedule of each one model, and resuming a benchmark."""

from __future__ import annotations

import json
from pathlib import Path
from unittest import mock

import pytest

from scalar_nerfstudio.benchmarking.schedule import variant_spec
from scalar_nerfstudio.scripts.benchmark import BenchmarkConfig, plan


def test_resume_reads_a_run_recorded_under_a_former_name(tmp_path: Path) -> None:
    """``--resume`` reuses a finished run an earlier benchmark recorded as ``runs/ngp19.spec.json`` (its
    spec otherwise the same) as ``ngp-t``; a changed spec is trained again."""
    import dataclasses

    from scalar_nerfstudio.benchmarking import schedule

    runs = tmp_path / "bench" / "runs"
    runs.mkdir(parents=True)
    config = BenchmarkConfig(data=tmp_path, output_dir=tmp_path / "bench", log2_table=10, variants=("ngp-t",), resume=True)
    variant = plan(config)[0][0]
    assert variant.name == "ngp-t"
    former = dataclasses.replace(variant, name="ngp19")
    (runs / "ngp19.spec.json").write_text(json.dumps(variant_spec(config, former, runs=runs, results={})))
    checkpoints = tmp_path / "run" / "nerfstudio_models"
    checkpoints.mkdir(parents=True)
    (checkpoints / "step-000001599.ckpt").write_bytes(b"")
    (runs / "ngp19.json").write_text(json.dumps({"name": "ngp19", "steps": 1600, "train_s": 119.0, "run_dir": str(tmp_path / "run")}))

    def run(config) -> dict:
        with mock.patch.object(schedule.subprocess, "Popen", side_effect=RuntimeError("trains")):
            try:
                return schedule.run_variant(config, variant, runs=runs, results={}, progress=mock.MagicMock(), task=0)
            except RuntimeError:
                return {}

    result = run(config)
    assert result["reused"] and result["name"] == "ngp-t" and result["steps"] == 1600
    config.seed = 1
    assert run(config) == {}


def test_equal_wall_clock_reads_the_one_model_curve_at_the_parallel_time() -> None:
    from scalar_nerfstudio.benchmarking.report import equal_wall_clock, psnr_at

    curve = [{"step": 100, "train_s": 10.0, "psnr": 18.0}, {"step": 200, "train_s": 20.0, "psnr": 20.0}]
    assert psnr_at(curve, 15.0) == (19.0, 150.0)
    assert psnr_at(curve, 20.0) == (20.0, 200.0)
    assert psnr_at(curve, 5.0) is None and psnr_at(curve, 25.0) is None
    table = [{"label": "SCALAR", "fusion": "global", "psnr": 21.0, "parallel_train_s": 15.0}, {"label": "NGP", "fusion": "global", "psnr": 20.0}]
    lines = "\n".join(equal_wall_clock({"ngp-t": {"curve": curve}}, table, log2_table=14))
    assert "| SCALAR | global | 15 | 21.00 |" in lines and "NGP_14 (one model, 2^14) at the same wall-clock | - | 15 | 19.00 (step 150) |" in lines


def test_equal_wall_clock_says_when_a_one_model_run_ended_before_that_time() -> None:
    """A block variant whose K workers finish after the one-model run's last evaluation is not compared
    with a value read off past the curve's end: the cell says when the run ended and what it scored."""
    from scalar_nerfstudio.benchmarking.report import equal_wall_clock

    curve = [{"step": 100, "train_s": 10.0, "psnr": 18.0}, {"step": 200, "train_s": 20.0, "psnr": 20.0}]
    table = [{"label": "SCALAR", "fusion": "nearest", "psnr": 21.0, "parallel_train_s": 22.0}]
    lines = "\n".join(equal_wall_clock({"ngp-t": {"curve": curve}}, table, log2_table=12))
    assert "| NGP_12 (one model, 2^12) at the same wall-clock | - | 22 | 20.00: it ended earlier, at 20 s (step 200) |" in lines


def test_the_wall_clock_rerun_stands_only_for_a_time_its_first_run_ended_before() -> None:
    """The rerun is planned for the blocks' (longest) wall-clock: an equal-steps block variant that ends
    on K workers before the one model's first evaluation is not compared with that longer rerun (the
    aerial 4 x 4 town's report did, at 254 s, with a run of 378 s): its cell says there is no
    evaluation at that time and what the first one, later, scored."""
    from scalar_nerfstudio.benchmarking.report import equal_wall_clock

    results = {
        "ngp-t": {"curve": [{"step": 1600, "train_s": 348.0, "psnr": 17.55}]},
        "ngp-t-wall-clock": {"steps": 2113, "train_s": 378.0, "final": {"psnr": 17.88}},
    }
    table = [{"label": "parallel", "fusion": "nearest-guarded", "psnr": 19.07, "parallel_train_s": 417.0},
             {"label": "equal steps", "fusion": "nearest-guarded", "psnr": 17.73, "parallel_train_s": 254.0}]
    lines = "\n".join(equal_wall_clock(results, table, log2_table=10))
    assert "| NGP_10 (one model, 2^10) at the same wall-clock | - | 417 | **17.88**: trained again for this wall-clock, 2113 steps in 378 s |" in lines
    assert "| NGP_10 (one model, 2^10) at the same wall-clock | - | 254 | no evaluation at that time; its first, at 348 s (step 1600): 17.55 |" in lines


def test_a_one_model_run_that_ended_before_the_blocks_is_trained_again_for_their_wall_clock(tmp_path: Path) -> None:
    """NGP_T ended at 119 s, the blocks on K workers at 140 s: NGP_T trains again, from the start, for
    the steps its pace fits in 140 s (its learning rate decays over them), evaluated at its end; a run
    that ended within 3 % of that time, or --no-match-wall-clock, trains nothing more."""
    from scalar_nerfstudio.benchmarking.variants import wall_clock_variants

    config = BenchmarkConfig(data=tmp_path, global_steps=900, block_steps=175, num_blocks=4, log2_table=10, variants=("ngp-t", "ngp-t2"))
    variants = plan(config)[0]
    results = {
        "ngp-t": {"steps": 1600, "train_s": 119.0}, "ngp-t2": {"steps": 1600, "train_s": 149.0},
        "global": {"steps": 900, "train_s": 63.0}, "auto-parallel": {"steps": 7700, "train_s": 658.0, "parallel_train_s": 140.0},
    }
    (again, note), = wall_clock_variants(config, variants, results)
    first = {v.name: v for v in variants}["ngp-t"]
    assert again.name == "ngp-t-wall-clock" and again.method == first.method and again.eval_every == 0
    assert again.overrides == {**first.overrides, "pipeline.global_steps": 1883}  # ceil(140 s x 1600 / 119 s)
    assert "1883 steps" in note and "119 s" in note and "140 s" in note
    results["ngp-t"]["train_s"] = 136.0  # within 3 % of 140 s: read at its end
    assert wall_clock_variants(config, variants, results) == []
    results["ngp-t"]["train_s"] = 119.0
    config.match_wall_clock = False
    assert wall_clock_variants(config, variants, results) == []
    config.match_wall_clock = True
    del results["auto-parallel"]["parallel_train_s"]  # no block variant on K workers: nothing to match
    assert wall_clock_variants(config, variants, results) == []


def test_the_one_models_train_with_each_schedule_and_their_decay_runs_are_rerun_for_the_wall_clock(tmp_path: Path) -> None:
    """``ngp-t-decay`` / ``ngp-t2-decay``: the same one models as ``ngp-t`` / ``ngp-t2`` with one decay over the
    run (``one_model_restart`` 0), in the default variant list; a decay run that ended before the blocks'
    wall-clock is trained again for it as ``ngp-t`` is (``ngp-t-decay-wall-clock``), and labelled."""
    from scalar_nerfstudio.benchmarking.report import labels
    from scalar_nerfstudio.benchmarking.variants import (
        VARIANTS,
        one_model_schedule,
        wall_clock_retry,
        wall_clock_variants,
    )

    assert {"ngp-t", "ngp-t2", "ngp-t-decay", "ngp-t2-decay"} <= set(VARIANTS) == set(BenchmarkConfig().variants)
    assert one_model_schedule("ngp-t2-decay") == ("ngp-t2", "decay") and one_model_schedule("ngp-t") == ("ngp-t", "restart")
    with pytest.raises(KeyError, match="scalar"):
        one_model_schedule("scalar")
    config = BenchmarkConfig(data=tmp_path, global_steps=900, block_steps=175, num_blocks=4, log2_table=10,
                             variants=("ngp-t", "ngp-t-decay", "ngp-t2", "ngp-t2-decay"))
    variants = plan(config)[0]
    by_name = {v.name: v for v in variants}
    assert list(by_name) == ["ngp-t", "ngp-t-decay", "ngp-t2", "ngp-t2-decay"]
    for restart, decay in (("ngp-t", "ngp-t-decay"), ("ngp-t2", "ngp-t2-decay")):
        assert by_name[decay].overrides == {**by_name[restart].overrides, "pipeline.one_model_restart": 0.0}
        assert "pipeline.one_model_restart" not in by_name[restart].overrides  # the pipeline's default schedule
    assert by_name["ngp-t2-decay"].overrides["pipeline.model.field.log2_hashmap_size"] == 12
    assert by_name["ngp-t-decay"].overrides["pipeline.global_steps"] == 1600
    results = {"ngp-t": {"steps": 1600, "train_s": 119.0}, "ngp-t-decay": {"steps": 1600, "train_s": 120.0},
               "ngp-t2": {"steps": 1600, "train_s": 139.0}, "ngp-t2-decay": {"steps": 1600, "train_s": 137.0},
               "auto-parallel": {"parallel_train_s": 140.0}}
    planned = {again.name: again for again, _ in wall_clock_variants(config, variants, results)}
    assert list(planned) == ["ngp-t-wall-clock", "ngp-t-decay-wall-clock"]  # the 2^12 runs ended within 3 %
    assert planned["ngp-t-decay-wall-clock"].overrides == {**by_name["ngp-t-decay"].overrides, "pipeline.global_steps": 1867}
    second = wall_clock_retry(config, [(planned["ngp-t-decay-wall-clock"], {"steps": 1867, "train_s": 120.0})], 140.0)
    assert second.name == "ngp-t-decay-wall-clock-2" and second.overrides["pipeline.one_model_restart"] == 0.0
    names = labels(10)
    assert names[("ngp-t-decay", "global")] == "NGP_10 (one model, 2^10), one decay over the run"
    assert names[("ngp-t2-decay-wall-clock", "global")] == "NGP_12 (one model, 2^12), one decay over the run, trained for the blocks' wall-clock"


def test_the_blocks_are_compared_with_the_better_schedule_of_each_one_model() -> None:
    """At each budget the one-model baseline of a table size is the better of its restart and decay runs
    (the restart run on a tie; the one that ran when only one did); at equal wall-clock each is read as
    the equal wall-clock table reads it. The report's "blocks - NGP" rows use it and name its schedule
    and run; both runs stay in the full table."""
    from scalar_nerfstudio.benchmarking.report import blocks_against_one_model, one_model_baseline, rows

    def run(steps: int, train_s: float, psnr: float, **extra) -> dict:
        return {"steps": steps, "train_s": train_s, "train_rays_per_s": 1.0, "parameters": 1, "peak_rss_mib": 1.0, "fusions": None,
                "curve": [{"step": steps // 2, "train_s": train_s / 2, "psnr": psnr - 1.0}, {"step": steps, "train_s": train_s, "psnr": psnr}],
                "final": {"psnr": psnr, "ssim": 0.5, "render_ms_per_image": 1.0}, **extra}

    results = {
        "ngp-t": run(1600, 100.0, 17.60), "ngp-t-decay": run(1600, 100.0, 17.90),
        "ngp-t-wall-clock": run(1900, 120.0, 17.70), "ngp-t-decay-wall-clock": run(1900, 120.0, 18.00),
        "ngp-t2": run(1600, 130.0, 18.80), "ngp-t2-decay": run(1600, 130.0, 18.50),
    }
    best = one_model_baseline(results, "ngp-t")
    assert (best["variant"], best["schedule"], best["psnr"], best["run"]) == ("ngp-t-decay", "decay", 17.90, "ngp-t-decay")
    assert one_model_baseline(results, "ngp-t2")["variant"] == "ngp-t2"
    at_wall_clock = one_model_baseline(results, "ngp-t", 120.0)  # both ended at 100 s: their reruns' ends
    assert (at_wall_clock["variant"], at_wall_clock["run"], at_wall_clock["psnr"]) == ("ngp-t-decay", "ngp-t-decay-wall-clock", 18.00)
    at_75 = one_model_baseline(results, "ngp-t2", 97.5)  # read off the curves: 18.30 against 18.00
    assert at_75["variant"] == "ngp-t2" and at_75["psnr"] == pytest.approx(18.30)
    assert one_model_baseline(results, "ngp-t2", 10.0) is None  # before either's first evaluation
    tie = {"ngp-t": run(1600, 100.0, 17.5), "ngp-t-decay": run(1600, 100.0, 17.5)}
    assert one_model_baseline(tie, "ngp-t")["schedule"] == "restart"
    assert one_model_baseline({"ngp-t-decay": run(1600, 100.0, 17.5)}, "ngp-t")["variant"] == "ngp-t-decay"
    assert one_model_baseline({"scalar": run(1600, 100.0, 19.0)}, "ngp-t") is None

    blocks = run(1600, 200.0, 19.00, parallel_train_s=120.0, fusions={"nearest-guarded": {"psnr": 19.0, "ssim": 0.5, "render_ms_per_image": 1.0},
                                                                       "global-only": {"psnr": 17.0, "ssim": 0.5, "render_ms_per_image": 1.0}})
    results["auto"] = blocks
    table = rows(results, log2_table=10)
    assert {"ngp-t", "ngp-t-decay", "ngp-t2", "ngp-t2-decay"} <= {r["variant"] for r in table}
    lines = "\n".join(blocks_against_one_model(results, table, log2_table=10))
    assert "| blocks | fusion | budget | PSNR | NGP_10 (schedule, run read) | blocks - NGP_10 | NGP_12 (schedule, run read) | blocks - NGP_12 |" in lines
    assert "| equal total steps, 1600 | 19.00 | 17.90 (decay, `ngp-t-decay`) | +1.10 | 18.80 (restart, `ngp-t2`) | +0.20 |" in lines
    assert "| equal wall-clock, 120 s | 19.00 | 18.00 (decay, `ngp-t-decay-wall-clock`) | +1.00 |" in lines
    assert "global-only" not in lines  # each block variant with its own fusion
    results["auto-parallel"] = {**blocks, "steps": 7700}
    lines = blocks_against_one_model(results, rows(results, log2_table=10), log2_table=10)
    assert sum("equal total steps" in line for line in lines) == 1  # auto-parallel: at equal wall-clock only
    assert blocks_against_one_model({"auto": blocks}, rows({"auto": blocks})) == []  # no one model ran


def test_the_benchmark_trains_the_wall_clock_run_after_the_others_and_reports_it(tmp_path: Path) -> None:
    """The schedule runs the extra one-model run once every planned variant has run, records its note,
    and the equal wall-clock table reads that run's end (not the first run's) at the blocks' time."""
    from scalar_nerfstudio.benchmarking import schedule
    from scalar_nerfstudio.benchmarking.report import equal_wall_clock, rows

    config = BenchmarkConfig(data=tmp_path, output_dir=tmp_path / "bench", log2_table=10, variants=("ngp-t",))
    (tmp_path / "bench" / "runs").mkdir(parents=True)
    variants = plan(config)[0]
    parallel = {"steps": 7700, "train_s": 658.0, "parallel_train_s": 140.0, "curve": [], "final": {"psnr": 19.14}}

    def fake_run(config, variant, *, runs, results, progress, task):
        if variant.name == "ngp-t":
            results["auto-parallel"] = parallel  # as if a block variant had run before it
            return {"steps": 1600, "train_s": 119.0, "curve": [{"step": 1600, "train_s": 119.0, "psnr": 17.65}], "final": {"psnr": 17.65}}
        assert variant.name == "ngp-t-wall-clock" and variant.overrides["pipeline.global_steps"] == 1883
        return {"steps": 1883, "train_s": 141.0, "curve": [{"step": 1883, "train_s": 141.0, "psnr": 18.11}], "final": {"psnr": 18.11}}

    notes: dict = {}
    with mock.patch.object(schedule, "run_variant", side_effect=fake_run) as run:
        results = schedule.run_variants(config, variants, notes)
    assert [c.args[1].name for c in run.call_args_list] == ["ngp-t", "ngp-t-wall-clock"]
    assert "1883 steps" in notes["ngp-t-wall-clock"]
    table = [{"label": "blocks", "fusion": "nearest-guarded", "psnr": 19.14, "parallel_train_s": 140.0}]
    lines = "\n".join(equal_wall_clock(results, table, log2_table=10))
    assert "| NGP_10 (one model, 2^10) at the same wall-clock | - | 140 | **18.11**: trained again for this wall-clock, 1883 steps in 141 s |" in lines
    results["ngp-t-wall-clock"].update({"fusions": None, "train_rays_per_s": 1.0, "parameters": 1, "peak_rss_mib": 1.0})
    results["ngp-t-wall-clock"]["final"].update({"ssim": 0.4, "render_ms_per_image": 1.0})
    labelled = {r["variant"]: r["label"] for r in rows({"ngp-t-wall-clock": results["ngp-t-wall-clock"]}, log2_table=10)}
    assert labelled == {"ngp-t-wall-clock": "NGP_10 (one model, 2^10), trained for the blocks' wall-clock"}


def test_a_wall_clock_run_that_ends_away_from_the_blocks_is_planned_again_from_its_own_pace(tmp_path: Path) -> None:
    """The first rerun, planned from NGP_T's first pace, ends at 128 s of the blocks' 140 s (it ran
    faster): a second run is planned from its own pace, ends at 139 s, and is the one read; the note
    lists both. A run within 3 % is read at once; --wall-clock-tries 1 keeps the first rerun."""
    from scalar_nerfstudio.benchmarking import schedule

    config = BenchmarkConfig(data=tmp_path, output_dir=tmp_path / "bench", log2_table=10, variants=("ngp-t",))
    (tmp_path / "bench" / "runs").mkdir(parents=True)
    variants = plan(config)[0]
    parallel = {"steps": 7700, "train_s": 658.0, "parallel_train_s": 140.0, "curve": [], "final": {"psnr": 19.14}}
    ends = {"ngp-t-wall-clock": (1883, 128.0, 18.00), "ngp-t-wall-clock-2": (2060, 139.0, 18.10)}

    def fake_run(config, variant, *, runs, results, progress, task):
        if variant.name == "ngp-t":
            results["auto-parallel"] = parallel
            return {"name": "ngp-t", "steps": 1600, "train_s": 119.0, "curve": [], "final": {"psnr": 17.65}}
        steps, seconds, psnr = ends[variant.name]
        assert variant.overrides["pipeline.global_steps"] == steps  # 1883 = ceil(140 x 1600 / 119); 2060 = ceil(140 x 1883 / 128)
        return {"name": variant.name, "steps": steps, "train_s": seconds, "curve": [], "final": {"psnr": psnr}}

    notes: dict = {}
    with mock.patch.object(schedule, "run_variant", side_effect=fake_run) as run:
        results = schedule.run_variants(config, variants, notes)
    assert [c.args[1].name for c in run.call_args_list] == ["ngp-t", "ngp-t-wall-clock", "ngp-t-wall-clock-2"]
    assert results["ngp-t-wall-clock"]["steps"] == 2060 and results["ngp-t-wall-clock"]["final"]["psnr"] == 18.10
    assert "ngp-t-wall-clock-2" not in results
    note = notes["ngp-t-wall-clock"]
    assert "1883 steps in 128 s, 18.00 dB" in note and "2060 steps in 139 s, 18.10 dB" in note and "read: ngp-t-wall-clock-2" in note

    ends["ngp-t-wall-clock"] = (1883, 137.0, 18.05)  # within 3 % of 140 s: no second run
    with mock.patch.object(schedule, "run_variant", side_effect=fake_run) as run:
        results = schedule.run_variants(config, plan(config)[0], {})
    assert [c.args[1].name for c in run.call_args_list] == ["ngp-t", "ngp-t-wall-clock"]

    ends["ngp-t-wall-clock"] = (1883, 128.0, 18.00)
    config.wall_clock_tries = 1
    with mock.patch.object(schedule, "run_variant", side_effect=fake_run) as run:
        results = schedule.run_variants(config, plan(config)[0], {})
    assert [c.args[1].name for c in run.call_args_list] == ["ngp-t", "ngp-t-wall-clock"]
    assert results["ngp-t-wall-clock"]["steps"] == 1883


def test_the_wall_clock_runs_stop_at_the_tries_allowed_and_read_the_nearest() -> None:
    """Three runs that all miss by more than 3 % (the machine's pace kept changing): no fourth, and
    the one that ended nearest the blocks' wall-clock is read, whether it ended before or after it."""
    from scalar_nerfstudio.benchmarking.variants import Variant, nearest_to_wall_clock, wall_clock_retry

    config = BenchmarkConfig(wall_clock_tries=3)
    first = Variant("ngp-t-wall-clock", "scalar-nerf", {"pipeline.global_steps": 1915}, eval_every=0)
    tried = [(first, {"steps": 1915, "train_s": 378.0, "final": {"psnr": 17.74}})]
    second = wall_clock_retry(config, tried, 417.0)
    assert second.name == "ngp-t-wall-clock-2" and second.overrides["pipeline.global_steps"] == 2113  # ceil(417 x 1915 / 378)
    assert second.eval_every == 0 and second.method == "scalar-nerf"
    tried.append((second, {"steps": 2113, "train_s": 436.0, "final": {"psnr": 17.90}}))
    third = wall_clock_retry(config, tried, 417.0)
    assert third.name == "ngp-t-wall-clock-3" and third.overrides["pipeline.global_steps"] == 2021  # ceil(417 x 2113 / 436)
    tried.append((third, {"steps": 2021, "train_s": 400.0, "final": {"psnr": 17.85}}))
    assert wall_clock_retry(config, tried, 417.0) is None  # three runs: the most allowed
    chosen, note = nearest_to_wall_clock(tried, 417.0)
    assert chosen["steps"] == 2021  # 17 s before it, against 19 s after and 39 s before
    assert note.startswith("3 run(s) for the blocks' 417 s") and note.endswith("read: ngp-t-wall-clock-3")
    tried[1][1]["train_s"] = 400.0  # as near as the third run, with more steps: read
    assert nearest_to_wall_clock(tried, 417.0)[0]["steps"] == 2113
    # a pace that plans a step count already tried ends the tries: ceil(417 x 2113 / 460.24) = 1915
    again = [(first, {"steps": 1915, "train_s": 378.0, "final": {}}), (second, {"steps": 2113, "train_s": 460.24, "final": {}})]
    assert wall_clock_retry(config, again, 417.0) is None
    again[1][1]["train_s"] = 455.0  # ceil(417 x 2113 / 455) = 1937: a new count, tried
    assert wall_clock_retry(config, again, 417.0).overrides["pipeline.global_steps"] == 1937


def test_resume_reuses_a_finished_run_of_the_same_spec_and_trains_a_changed_one(tmp_path: Path) -> None:
    """``--resume``: a variant whose spec, result and checkpoint are in runs/ is read, not trained, and
    says so. It trains again when its spec changed (another seed), when the result is older than the
    spec (a run stopped midway, after an earlier spec's run had finished), when its checkpoint is gone,
    and without --resume."""
    import os

    from scalar_nerfstudio.benchmarking import schedule

    runs = tmp_path / "bench" / "runs"
    runs.mkdir(parents=True)
    config = BenchmarkConfig(data=tmp_path, output_dir=tmp_path / "bench", log2_table=10, variants=("ngp-t",), resume=True)
    variant = plan(config)[0][0]
    spec_path, result_path = runs / "ngp-t.spec.json", runs / "ngp-t.json"
    checkpoints = tmp_path / "run" / "nerfstudio_models"
    checkpoints.mkdir(parents=True)
    (checkpoints / "step-000001599.ckpt").write_bytes(b"")
    finished = {"name": "ngp-t", "steps": 1600, "train_s": 119.0, "final": {"psnr": 17.65}, "run_dir": str(tmp_path / "run")}
    stopped = RuntimeError("stopped")  # the subprocess that would train it

    def run(config) -> dict:
        with mock.patch.object(schedule.subprocess, "Popen", side_effect=stopped) as popen:
            try:
                return schedule.run_variant(config, variant, runs=runs, results={}, progress=mock.MagicMock(), task=0)
            except RuntimeError:
                assert popen.call_count == 1
                return {}

    assert run(config) == {}  # nothing there: it trains (and writes its spec first)
    result_path.write_text(json.dumps(finished))  # ... and finishes
    result = run(config)
    assert result["final"]["psnr"] == 17.65 and result["reused"]

    config.seed = 1  # another spec: trained
    assert run(config) == {}
    assert json.loads(spec_path.read_text())["overrides"]["machine.seed"] == 1
    assert run(config) == {}  # the seed-42 result is older than the seed-1 spec: never read as its result
    config.seed = 42
    run(config)  # the seed-42 spec written again, and its run stopped: the result is still older
    assert run(config) == {}
    os.utime(result_path)  # the result written after the spec: finished
    assert run(config)["reused"]
    (checkpoints / "step-000001599.ckpt").unlink()  # its checkpoint gone: trained again
    assert run(config) == {}
    (checkpoints / "step-000001599.ckpt").write_bytes(b"")
    os.utime(result_path)
    config.resume = False  # without --resume a finished run of the same spec trains again
    assert run(config) == {}


def test_resume_reads_a_block_variant_with_its_global_phase_once_and_notes_every_reused_run(tmp_path: Path) -> None:
    """A resumed benchmark of NGP_T and the blocks: the global phase, NGP_T and the blocks are read back
    (the blocks' global phase counted once, their spec naming the global checkpoint found again), then
    the wall-clock runs: the first reused, only the second trained (more --wall-clock-tries than the
    first benchmark had); the report's notes name every reused run."""
    from scalar_nerfstudio.benchmarking import schedule

    output = tmp_path / "bench"
    runs = output / "runs"
    runs.mkdir(parents=True)
    config = BenchmarkConfig(data=tmp_path, output_dir=output, log2_table=10, global_steps=900, block_steps=175, num_blocks=4,
                             parallel_block_steps=850, eval_every=1600, variants=("ngp-t", "auto-parallel"), resume=True)
    with mock.patch("scalar_nerfstudio.benchmarking.variants.auto_k", return_value=8):
        variants = plan(config)[0]
    assert [v.name for v in variants] == ["global", "ngp-t", "auto-parallel"]

    def finished(name: str, steps: int, train_s: float, psnr: float, **extra) -> dict:
        run_dir = tmp_path / "run" / name
        (run_dir / "nerfstudio_models").mkdir(parents=True, exist_ok=True)
        (run_dir / "nerfstudio_models" / f"step-{steps - 1:09d}.ckpt").write_bytes(b"")
        return {"name": name, "steps": steps, "train_s": train_s, "train_rays_per_s": 1000.0, "run_dir": str(run_dir),
                "curve": [{"step": steps, "train_s": train_s, "psnr": psnr}], "final": {"psnr": psnr}, **extra}

    def save(variant, result: dict, results: dict) -> None:
        (runs / f"{variant.name}.spec.json").write_text(json.dumps(variant_spec(config, variant, runs=runs, results=results)))
        (runs / f"{variant.name}.json").write_text(json.dumps(result))

    earlier: dict = {}
    by_name = {v.name: v for v in variants}
    save(by_name["global"], finished("global", 900, 200.0, 17.1), earlier)
    earlier["global"] = {**finished("global", 900, 200.0, 17.1), "checkpoint": str(tmp_path / "run" / "global" / "nerfstudio_models" / "step-000000899.ckpt")}
    save(by_name["ngp-t"], finished("ngp-t", 1600, 350.0, 17.5), earlier)
    save(by_name["auto-parallel"], finished("auto-parallel", 6800, 1600.0, 19.0, num_blocks=8, block_train_s={"0": 200.0, "1": 210.0}), earlier)
    first_rerun = schedule.wall_clock_variants(config, variants, {**earlier, "ngp-t": finished("ngp-t", 1600, 350.0, 17.5),
                                                                   "auto-parallel": {"parallel_train_s": 410.0}})[0][0]
    assert first_rerun.overrides["pipeline.global_steps"] == 1875  # ceil(410 x 1600 / 350)
    save(first_rerun, finished("ngp-t-wall-clock", 1875, 380.0, 17.7), earlier)  # 7 % short of 410 s

    def fake_train(config, variant, *, runs, results, progress, task):
        assert variant.name == "ngp-t-wall-clock-2", f"{variant.name} should have been reused"
        assert variant.overrides["pipeline.global_steps"] == 2024  # ceil(410 x 1875 / 380)
        return finished("ngp-t-wall-clock-2", 2024, 408.0, 17.8)

    notes: dict = {}
    real_run_variant = schedule.run_variant
    trained = []

    def run_or_reuse(config, variant, *, runs, results, progress, task):
        result = (real_run_variant(config, variant, runs=runs, results=results, progress=progress, task=task)
                  if variant.name != "ngp-t-wall-clock-2" else None)
        if result is None:
            trained.append(variant.name)
            return fake_train(config, variant, runs=runs, results=results, progress=progress, task=task)
        return result

    with mock.patch.object(schedule, "run_variant", side_effect=run_or_reuse), \
            mock.patch.object(schedule.subprocess, "Popen", side_effect=AssertionError("nothing but the second rerun trains")):
        results = schedule.run_variants(config, variants, notes)
    assert trained == ["ngp-t-wall-clock-2"]
    blocks = results["auto-parallel"]
    assert blocks["steps"] == 900 + 6800 and blocks["parallel_train_s"] == 200.0 + 210.0  # the global phase counted once
    assert results["global"]["checkpoint"].endswith("step-000000899.ckpt")
    assert results["ngp-t-wall-clock"]["steps"] == 2024
    for name in ("global", "ngp-t", "auto-parallel"):
        assert "reused (--resume)" in notes[name], name
    assert "ngp-t-wall-clock: reused (--resume)" in notes["ngp-t-wall-clock"] and "read: ngp-t-wall-clock-2" in notes["ngp-t-wall-clock"]


def test_parallel_budget_gives_every_block_the_steps_one_model_trains_after_the_global_phase(tmp_path: Path) -> None:
    """``auto-parallel``: ns-train's defaults (automatic K, default fusion first) from the shared global
    phase, each block trained K x B steps (or --parallel-block-steps), evaluated at its end only; with
    automatic K = 1 it is the one-model run, planned once."""
    from scalar_nerfstudio.models.scene_model import ScalarSceneModelConfig

    config = BenchmarkConfig(data=tmp_path, global_steps=600, block_steps=250, num_blocks=4, variants=("auto", "auto-parallel"))
    with mock.patch("scalar_nerfstudio.benchmarking.variants.auto_k", return_value=8):
        variants, notes = plan(config)
    by_name = {v.name: v for v in variants}
    parallel, auto = by_name["auto-parallel"], by_name["auto"]
    assert parallel.base == "global" and parallel.eval_every == 0 and auto.eval_every is None
    assert parallel.fusions[0] == ScalarSceneModelConfig.fusion
    assert {"nearest-idw", "nearest-guarded", "global-only"} <= set(parallel.fusions)  # the same blocks, fused otherwise
    assert parallel.overrides == {**auto.overrides, "pipeline.block_steps": 1000}  # K B = 4 x 250, not K B / 8
    assert auto.overrides["pipeline.block_steps"] == 125
    assert "8 workers" in notes["auto-parallel"] and "8000 block steps" in notes["auto-parallel"]
    config.variants = ("auto", "auto-parallel", "auto-parallel-fitted")
    with mock.patch("scalar_nerfstudio.benchmarking.variants.auto_k", return_value=8):
        fitted = {v.name: v for v in plan(config)[0]}["auto-parallel-fitted"]
    assert fitted.overrides == {**parallel.overrides, "pipeline.block_init": "fitted"} and fitted.eval_every == 0
    config.parallel_block_steps = 900
    with mock.patch("scalar_nerfstudio.benchmarking.variants.auto_k", return_value=8):
        assert {v.name: v for v in plan(config)[0]}["auto-parallel"].overrides["pipeline.block_steps"] == 900
    with mock.patch("scalar_nerfstudio.benchmarking.variants.auto_k", return_value=1):
        assert [v.name for v in plan(config)[0]] == ["global", "ngp-t"]
    config.parallel_block_steps = 0
    with pytest.raises(SystemExit, match="--parallel-block-steps 0"):
        plan(config)


def test_a_block_variant_counts_its_global_phase_and_its_slowest_block() -> None:
    """The global phase's time, steps and curve are prepended; with K workers the wall-clock is the
    global phase plus the slowest block (blocks differ in images and table), not the blocks' mean."""
    from scalar_nerfstudio.benchmarking.schedule import with_base_phase

    base = {"train_s": 100.0, "steps": 600, "train_rays_per_s": 2000.0, "curve": [{"step": 600, "train_s": 100.0, "psnr": 17.0}]}
    blocks = {"train_s": 300.0, "steps": 3000, "train_rays_per_s": 1000.0, "num_blocks": 3,
              "block_train_s": {"0": 80.0, "1": 120.0, "2": 100.0}, "curve": [{"step": 3000, "train_s": 300.0, "psnr": 19.0}]}
    result = with_base_phase(blocks, base)
    assert result["parallel_train_s"] == 220.0 and result["train_s"] == 400.0 and result["steps"] == 3600
    assert result["curve"] == [base["curve"][0], {"step": 3600, "train_s": 400.0, "psnr": 19.0}]
    assert result["train_rays_per_s"] == pytest.approx((1000.0 * 300 + 2000.0 * 100) / 400)
    assert blocks["train_s"] == 300.0  # the runner's result is left as it was
    without_phase_times = {k: v for k, v in blocks.items() if k != "block_train_s"}
    assert with_base_phase(without_phase_times, base)["parallel_train_s"] == 200.0
