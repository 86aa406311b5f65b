"""``scalar-nerf-benchmark --quick``: the speed-against-error harness end to end (not its numbers)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from prerequisites import REPO
from quality import eval_renders, load_pipeline

from scalar_nerfstudio.benchmarking.report import on_pareto_front
from scalar_nerfstudio.benchmarking.schedule import variant_spec
from scalar_nerfstudio.scripts.benchmark import BenchmarkConfig, plan

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_quick_benchmark_end_to_end(tmp_path: Path) -> None:
    """Global phase, one model, blocks with three fusions, and nerfacto (offline, no LPIPS) on the
    synthetic scene: table, JSON, curves, the three plots and the held-out view."""
    output = tmp_path / "bench"
    result = subprocess.run(
        ["scalar-nerf-benchmark", "--quick", "--output-dir", str(output), "--variants", "ngp-t", "scalar", "nerfacto",
         "--no-match-wall-clock"],  # (the one-model run trained again for the blocks' wall-clock: tested below)
        capture_output=True, text=True, timeout=900, check=False
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    report = json.loads((output / "results.json").read_text())
    labels = {row["label"] for row in report["rows"]}
    assert labels == {
        "NGP_14 (one model, 2^14)", "SCALAR-NeRF (blocks + global fusion)", "blocks + surface fusion (same models)",
        "blocks + IDW (same models)", "blocks + nearest (same models)", "its global model alone", "nerfacto (torch), same wall-clock",
    }
    results = report["results"]
    scalar, ngp, global_phase = results["scalar"], results["ngp-t"], results["global"]
    # Equal step budgets; the block variant includes the global phase it started from, in time and curve.
    assert scalar["steps"] == ngp["steps"] == 32 and global_phase["steps"] == 20
    assert scalar["curve"][: len(global_phase["curve"])] == global_phase["curve"]
    assert scalar["train_s"] > global_phase["train_s"]
    for name in ("scalar", "ngp-t"):
        steps = [p["step"] for p in results[name]["curve"]]
        times = [p["train_s"] for p in results[name]["curve"]]
        assert steps == [10, 20, 30, 32], f"{name}: evaluated every 10 steps and at the end"
        assert times == sorted(times)
    assert scalar["num_blocks"] == 2 and scalar["parameters"] > ngp["parameters"]
    # nerfacto ran for the wall-clock the block variant took, and has no LPIPS (needs a download).
    nerfacto = results["nerfacto"]
    assert nerfacto["train_s"] >= scalar["train_s"] and "lpips" not in nerfacto["final"]
    for row in report["rows"]:
        assert row["render_ms_per_image"] > 0 and row["peak_rss_mib"] > 100 and row["train_rays_per_s"] > 0
    table = (output / "results.md").read_text()
    assert "| SCALAR-NeRF (blocks + global fusion) | global | 32 |" in table
    # the machine's speed around the runs, so that absolute times can be read against it
    probe = report["machine_probe_mpts_per_s"]
    assert probe["before"] > 0 and probe["after"] > 0 and "hash-grid probe" in report["machine"] and "hash-grid probe" in table
    # equal wall-clock with K workers: the global phase plus the slower of the 2 blocks, timed phase by phase
    block_s = scalar["block_train_s"]
    assert set(block_s) == {"0", "1"} and all(t > 0 for t in block_s.values())
    assert sum(block_s.values()) == pytest.approx(scalar["train_s"] - global_phase["train_s"], rel=1e-6)
    assert scalar["parallel_train_s"] == pytest.approx(global_phase["train_s"] + max(block_s.values()))
    assert scalar["parallel_train_s"] < scalar["train_s"] and "## Equal wall-clock, K blocks on K workers" in table
    for name in ("psnr_vs_time.png", "psnr_vs_render_time.png", "psnr_vs_parameters.png", "heldout_view.png"):
        data = (output / name).read_bytes()
        assert data.startswith(PNG_SIGNATURE) and len(data) > 5000, name
    # the blocks against the one model's better schedule (only ngp-t ran: it), and one held-out view side by side:
    # truth | ngp-t | scalar (neither auto nor auto-parallel ran) | its block colours, each run's PSNR on that view
    assert "## The blocks against the one model" in table and "(restart, `ngp-t`)" in table
    panels = report["heldout_view"]["panels"]
    assert [p["variant"] for p in panels] == [None, "ngp-t", "scalar", "scalar"]
    assert "![held-out view](heldout_view.png)" in table
    # The figures are the runs' own evaluations: every run keeps its final checkpoint (written after its
    # timed steps), and loaded again from its folder it scores on the held-out views what its curve ends at,
    # and on the held-out view what its panel says.
    view = report["heldout_view"]["view"]
    for name, panel in (("ngp-t", panels[1]), ("scalar", panels[2])):
        pipeline = load_pipeline(Path(results[name]["run_dir"]))
        metrics, images = eval_renders(pipeline)
        assert abs(metrics["psnr"] - results[name]["final"]["psnr"]) < 0.05, (name, metrics["psnr"], results[name]["final"])
        truth = pipeline.datamanager.eval_dataset[view]["image"][..., :3].numpy()
        view_psnr = -10.0 * float(np.log10(np.mean((images[view] - truth) ** 2)))
        assert abs(view_psnr - panel["psnr"]) < 0.05, (name, view_psnr, panel)
    # The same command with --resume trains nothing: every run is read back and reported the same.
    again = subprocess.run(
        ["scalar-nerf-benchmark", "--quick", "--output-dir", str(output), "--variants", "ngp-t", "scalar", "nerfacto",
         "--no-match-wall-clock", "--resume"],
        capture_output=True, text=True, timeout=300, check=False
    )
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert again.stdout.count("reusing its finished run") == 4  # global, ngp-t, scalar, nerfacto
    reread = json.loads((output / "results.json").read_text())["results"]
    for name in ("global", "ngp-t", "scalar", "nerfacto"):
        assert reread[name]["final"] == results[name]["final"] and reread[name]["train_s"] == results[name]["train_s"], name


def test_plan_and_budgets(tmp_path: Path) -> None:
    """Every block variant starts from the one global phase; budgets are equal; unknown names fail."""
    config = BenchmarkConfig(data=tmp_path, global_steps=400, block_steps=100, num_blocks=4,
                             variants=("ngp-t", "ngp-t2", "scalar", "scalar-wo-sd", "scalar-wo-ft", "scalar-s1.0"))
    variants, _ = plan(config)
    by_name = {v.name: v for v in variants}
    assert list(by_name)[0] == "global" and by_name["global"].overrides["pipeline.global_steps"] == 400
    assert by_name["ngp-t"].overrides["pipeline.global_steps"] == 800 == 400 + 4 * 100
    assert by_name["ngp-t2"].overrides["pipeline.model.field.log2_hashmap_size"] == 21
    for name in ("scalar", "scalar-wo-sd", "scalar-wo-ft", "scalar-s1.0"):
        assert by_name[name].base == "global" and by_name[name].overrides["pipeline.global_steps"] == 0
        assert by_name[name].overrides["pipeline.block_log2_hashmap_size"] == 19
    assert by_name["scalar-wo-sd"].overrides["pipeline.decoder_mode"] == "independent"
    assert by_name["scalar-wo-ft"].overrides["pipeline.decoder_mode"] == "frozen"
    assert by_name["scalar-s1.0"].overrides["pipeline.aabb_scale"] == [1.0, 1.0, 1.0]
    with pytest.raises(SystemExit, match="unknown variant"):
        plan(BenchmarkConfig(data=tmp_path, variants=("ngp18",)))


def test_the_former_variant_names_are_accepted_and_mapped_to_the_new_ones(tmp_path: Path) -> None:
    """``ngp19`` / ``ngp21`` (and the names derived from them) still work, as ``ngp-t`` / ``ngp-t2``: given to
    the config or on the command line, in a check, and in the names of the wall-clock reruns."""
    import tyro

    from scalar_nerfstudio.benchmarking.variants import canonical_variant, check_options, former_variant_name

    config = BenchmarkConfig(data=tmp_path, variants=("ngp19", "ngp21", "scalar"))
    assert config.variants == ("ngp-t", "ngp-t2", "scalar")
    by_name = {v.name: v for v in plan(config)[0]}
    assert list(by_name) == ["global", "ngp-t", "ngp-t2", "scalar"]
    assert by_name["ngp-t2"].overrides["pipeline.model.field.log2_hashmap_size"] == 21
    parsed = tyro.cli(BenchmarkConfig, args=["--data", str(tmp_path), "--variants", "ngp19", "ngp21"])
    assert parsed.variants == ("ngp-t", "ngp-t2")
    config.variants = ("ngp21",)  # set after construction: checked and planned under its new name
    check_options(config)
    assert [v.name for v in plan(config)[0]] == ["ngp-t2"]
    assert canonical_variant("ngp19-wall-clock-2") == "ngp-t-wall-clock-2" and canonical_variant("ngp21-wall-clock") == "ngp-t2-wall-clock"
    assert canonical_variant("scalar") == "scalar" and canonical_variant("ngp18") == "ngp18"
    assert former_variant_name("ngp-t2-wall-clock") == "ngp21-wall-clock" and former_variant_name("ngp-t") == "ngp19"
    assert former_variant_name("scalar") is None


def test_a_report_of_runs_under_the_former_names_is_rewritten_with_the_new_ones(tmp_path: Path) -> None:
    """``--from-results`` on a results.json whose variants have the former names labels their rows as before."""
    from dataclasses import asdict

    from scalar_nerfstudio.benchmarking.report import rewrite_report

    def result(steps: int, train_s: float, psnr: float) -> dict:
        return {"steps": steps, "train_s": train_s, "train_rays_per_s": 1000.0, "parameters": 10, "peak_rss_mib": 1.0,
                "curve": [{"step": steps, "train_s": train_s, "psnr": psnr}],
                "final": {"psnr": psnr, "ssim": 0.5, "render_ms_per_image": 1.0}}

    config = {k: str(v) if isinstance(v, Path) else v for k, v in asdict(BenchmarkConfig(data=tmp_path, log2_table=10)).items()}
    config["variants"] = ["ngp19", "ngp21"]
    report = {"command": "scalar-nerf-benchmark", "machine": "2 CPU cores", "config": config, "rows": [],
              "notes": {"ngp19-wall-clock": "trained again"},
              "results": {"ngp19": result(1600, 119.0, 17.5), "ngp21": result(1600, 149.0, 17.9), "ngp19-wall-clock": result(1900, 140.0, 17.7)}}
    (tmp_path / "results.json").write_text(json.dumps(report))
    rewritten = rewrite_report(tmp_path)
    assert list(rewritten["results"]) == ["ngp-t", "ngp-t2", "ngp-t-wall-clock"] and list(rewritten["notes"]) == ["ngp-t-wall-clock"]
    assert {r["variant"]: r["label"] for r in rewritten["rows"]} == {
        "ngp-t": "NGP_10 (one model, 2^10)", "ngp-t2": "NGP_12 (one model, 2^12)",
        "ngp-t-wall-clock": "NGP_10 (one model, 2^10), trained for the blocks' wall-clock"}


def test_fusions_option_sets_the_modes_every_block_variant_is_evaluated_with(tmp_path: Path) -> None:
    """``--fusions`` replaces each block variant's list of fusions (its first is the run's); the one-model
    runs and the global phase keep rendering one model; a mode that does not exist is refused by name."""
    config = BenchmarkConfig(data=tmp_path, variants=("ngp-t", "scalar", "scalar-wo-sd"), fusions=("nearest-guarded", "global-only"))
    by_name = {v.name: v for v in plan(config)[0]}
    assert by_name["scalar"].fusions == by_name["scalar-wo-sd"].fusions == ["nearest-guarded", "global-only"]
    assert by_name["ngp-t"].fusions == by_name["global"].fusions == ["global"]
    spec = variant_spec(config, by_name["scalar"], runs=tmp_path, results={"global": {"checkpoint": "g.ckpt"}})
    assert spec["fusions"] == ["nearest-guarded", "global-only"]
    default = {v.name: v for v in plan(BenchmarkConfig(data=tmp_path, variants=("scalar",)))[0]}
    assert default["scalar"].fusions == ["global", "surface", "idw", "nearest", "global-only"]
    assert [v.fusions for v in plan(BenchmarkConfig(data=tmp_path, variants=("scalar",), fusions=("block:1",)))[0]][1] == ["block:1"]
    for fusions, message in ((("nearest", "best"), "--fusions best: unknown fusion mode"), ((), "at least one fusion mode")):
        with pytest.raises(SystemExit, match=message):
            plan(BenchmarkConfig(data=tmp_path, variants=("scalar",), fusions=fusions))


def test_pareto_front() -> None:
    rows = [
        {"psnr": 20.0, "parameters": 10, "train_s": 5},
        {"psnr": 21.0, "parameters": 20, "train_s": 5},
        {"psnr": 19.0, "parameters": 30, "train_s": 9},
    ]
    assert [on_pareto_front(r, rows, "parameters") for r in rows] == [True, True, False]
    assert [on_pareto_front(r, rows, "train_s") for r in rows] == [False, True, False]


def test_timing_helpers_time_steps_and_calls() -> None:
    """The one timing helper every benchmark uses (engine/timing.py): steps of a trainer, and calls."""
    from scalar_nerfstudio.engine.timing import median_seconds, time_train_iterations

    class Trainer:
        stop_training = False

        def train_iteration(self, step: int) -> int:
            time.sleep(0.01)
            return 2 * step

    trainer, seen = Trainer(), []

    def after_step(step: int, result: int, clock) -> None:
        time.sleep(0.02)  # outside the timed span: counted in wall_s only
        seen.append((step, result, clock.steps))
        trainer.stop_training = clock.steps >= 3

    clock = time_train_iterations(trainer, after_step)
    assert [trainer.train_iteration(step) for step in range(3)] == [0, 2, 4]
    assert seen == [(0, 0, 1), (1, 2, 2), (2, 4, 3)] and trainer.stop_training
    assert clock.steps == 3 and 0.03 <= clock.busy_s < clock.wall_s
    calls = []
    assert median_seconds(lambda: calls.append(time.sleep(0.001)), repeats=3, warmup=2) >= 0.001
    assert len(calls) == 5


def test_table_size_option_sets_every_table(tmp_path: Path) -> None:
    config = BenchmarkConfig(data=tmp_path, log2_table=14, variants=("ngp-t", "ngp-t2", "scalar"))
    by_name = {v.name: v for v in plan(config)[0]}
    assert by_name["ngp-t"].overrides["pipeline.model.field.log2_hashmap_size"] == 14
    assert by_name["ngp-t2"].overrides["pipeline.model.field.log2_hashmap_size"] == 16
    assert by_name["scalar"].overrides["pipeline.block_log2_hashmap_size"] == 14
    assert "global-only" in by_name["scalar"].fusions and "surface" in by_name["scalar"].fusions
    assert all("pipeline.model.field.hidden_dim" not in v.overrides for v in by_name.values())  # the field's default


def test_decoder_width_option_reaches_every_variant_of_ours_and_the_report(tmp_path: Path) -> None:
    """``--decoder-width 128`` (the paper's decoder, what the 2026-11-23 town pages used) is set on the
    global phase, NGP_T, NGP_{T+2} and the block variants, not on nerfacto; the report states it."""
    from scalar_nerfstudio.benchmarking.report import decoder_width_used, markdown

    config = BenchmarkConfig(data=tmp_path, decoder_width=128, variants=("ngp-t", "ngp-t2", "scalar", "nerfacto"))
    by_name = {v.name: v for v in plan(config)[0]}
    assert {name for name, v in by_name.items() if v.overrides.get("pipeline.model.field.hidden_dim") == 128} == {
        "global", "ngp-t", "ngp-t2", "scalar"}
    assert "pipeline.model.field.hidden_dim" not in by_name["nerfacto"].overrides
    assert decoder_width_used(config) == 128 and decoder_width_used(BenchmarkConfig(data=tmp_path)) == 64
    assert "decoder 128 wide" in markdown(config, [], notes={}, command="cmd", machine="2 CPU cores", results={}, decoder_width=128)
    assert "decoder width not recorded" in markdown(config, [], notes={}, command="cmd", machine="2 CPU cores", results={})


def test_the_report_shows_depth_where_the_scene_has_it(tmp_path: Path) -> None:
    """On a scene with true depth (the town) results.md gets a depth column from the runs' figures;
    elsewhere (castle-P30, fox) the table is as before."""
    from scalar_nerfstudio.benchmarking.report import markdown, rows

    def result(psnr: float, depth=None) -> dict:
        final = {"psnr": psnr, "ssim": 0.5, "render_ms_per_image": 10.0}
        if depth is not None:
            final["depth_delta1"] = depth
        return {"final": final, "steps": 100, "train_s": 1.0, "train_rays_per_s": 1.0, "parameters": 1, "peak_rss_mib": 1.0}

    config = BenchmarkConfig(data=tmp_path, variants=("ngp-t", "ngp-t2"))
    with_depth = markdown(config, rows({"ngp-t": result(18.0, 0.318), "ngp-t2": result(19.1, 0.456)}), notes={}, command="cmd",
                          machine="2 CPU cores")
    assert "depth within 25 % |" in with_depth
    assert "| 19.10 | 0.500 | 45.6% |" in with_depth and "| 18.00 | 0.500 | 31.8% |" in with_depth
    without = markdown(config, rows({"ngp-t": result(18.0), "ngp-t2": result(19.1)}), notes={}, command="cmd", machine="2 CPU cores")
    assert "depth within" not in without and "| 19.10 | 0.500 | 10 |" in without


def test_a_run_renders_with_the_first_fusion_it_reports(tmp_path: Path) -> None:
    """The first fusion of a variant labels its curve, so the run must render with it, whatever the
    model's default (the paper's variant reports ``global`` while the default is ``nearest``); the
    ``auto`` variant is ns-train's defaults, so it reports the default fusion first."""
    from scalar_nerfstudio.benchmarking.runner import trainer_config
    from scalar_nerfstudio.models.scene_model import ScalarSceneModelConfig

    spec = {"method": "scalar-nerf", "data": str(tmp_path), "downscale": 1, "output_dir": str(tmp_path / "out"), "overrides": {}}
    assert trainer_config({**spec, "fusions": ["global", "nearest"]}).pipeline.model.fusion == "global"
    assert trainer_config({**spec, "fusions": ["idw"]}).pipeline.model.fusion == "idw"
    assert trainer_config(spec).pipeline.model.fusion == ScalarSceneModelConfig.fusion
    config = BenchmarkConfig(data=tmp_path, variants=("scalar", "auto", "scalar-fitted", "auto-fitted"))
    with mock.patch("scalar_nerfstudio.benchmarking.variants.auto_k", return_value=3):
        by_name = {v.name: v for v in plan(config)[0]}
    assert by_name["scalar"].fusions[0] == "global"
    assert by_name["auto"].fusions[0] == ScalarSceneModelConfig.fusion and by_name["auto"].overrides["pipeline.num_blocks"] is None
    assert "pipeline.block_init" not in by_name["auto"].overrides  # the defaults' own
    fitted = by_name["auto-fitted"]
    assert fitted.overrides == {**by_name["auto"].overrides, "pipeline.block_init": "fitted"} and fitted.base == "global"
    assert by_name["scalar-fitted"].overrides["pipeline.block_init"] == "fitted" and by_name["scalar-fitted"].fusions[0] == "nearest"
    config = BenchmarkConfig(data=tmp_path, variants=("auto", "auto-fitted"))
    with mock.patch("scalar_nerfstudio.benchmarking.variants.auto_k", return_value=1):  # both are one model then: ngp-t, once
        assert [v.name for v in plan(config)[0]] == ["global", "ngp-t"]


def test_the_heldout_view_shows_truth_one_model_blocks_and_block_colours(full_run: Path, tmp_path: Path) -> None:
    """heldout_view.png from trained runs' folders (here one 2-block run stands for both): ground truth,
    the one model, the blocks and their block colours, captioned with each run's PSNR on that view, which
    is the run's own eval PSNR of that image; a view the scene does not have is refused by its option."""
    import numpy as np

    from scalar_nerfstudio.benchmarking.heldout_view import render_view, shown_runs, write_heldout_view
    from scalar_nerfstudio.blocks.palette import BLOCK_PALETTE

    rendered = render_view(full_run, 1)
    assert rendered["truth"].shape == rendered["rgb"].shape == rendered["block_colour"].shape == (72, 96, 3)
    assert rendered["views"] == 3
    _, own_renders = eval_renders(load_pipeline(full_run))  # the run's own render of held-out view 1, as ns-eval makes it
    assert np.abs(rendered["rgb"] - own_renders[1]).max() < 1e-4
    assert rendered["psnr"] == pytest.approx(-10.0 * np.log10(np.mean((own_renders[1] - rendered["truth"]) ** 2)), abs=0.01)
    colours = rendered["block_colour"].reshape(-1, 3)
    assert any(np.isclose(colours, c, atol=1e-3).all(axis=1).any() for c in BLOCK_PALETTE[:2])  # pixels given by a block
    with pytest.raises(SystemExit, match="--heldout-view 3: the scene has 3 held-out views"):
        render_view(full_run, 3)

    def result(psnr: float, **extra) -> dict:
        return {"run_dir": str(full_run), "steps": 70, "train_s": 10.0, "final": {"psnr": psnr},
                "curve": [{"step": 70, "train_s": 10.0, "psnr": psnr}], **extra}

    results = {"ngp-t": result(17.0), "ngp-t-decay": result(17.2), "scalar": result(18.0, parallel_train_s=8.0),
               "auto": result(18.5, parallel_train_s=9.0)}
    baseline, blocks = shown_runs(results)
    assert baseline["variant"] == "ngp-t-decay" and blocks == "auto"
    assert shown_runs({k: v for k, v in results.items() if k != "auto"})[1] == "scalar"  # neither auto nor auto-parallel ran
    config = BenchmarkConfig(data=tmp_path, output_dir=tmp_path, log2_table=14, heldout_view=1)
    view = write_heldout_view(config, results)
    data = (tmp_path / "heldout_view.png").read_bytes()
    assert data.startswith(PNG_SIGNATURE) and len(data) > 5000
    captions = [p["caption"] for p in view["panels"]]
    assert view["view"] == 1 and len(captions) == 4 and captions[0] == "ground truth, held-out view 1"
    assert captions[1].startswith("one model ngp-t-decay (2^14, decay schedule, 70 steps): ") and captions[1].endswith(" dB")
    assert captions[2].startswith("blocks auto (nearest-guarded fusion, 70 steps): ") and captions[3].startswith("block colours of auto")
    assert view["panels"][1]["psnr"] == view["panels"][2]["psnr"] == pytest.approx(rendered["psnr"])
    assert write_heldout_view(config, {"nerfacto": result(15.0)}) is None


def test_a_spec_override_reaches_an_optimizer_setting(tmp_path: Path) -> None:
    """Overrides walk dataclass attributes and dict keys (the optimizers), and a wrong name is refused
    with the name in the message instead of being set on nothing."""
    from scalar_nerfstudio.benchmarking.runner import trainer_config

    spec = {"method": "scalar-nerf", "data": str(tmp_path), "downscale": 1, "output_dir": str(tmp_path / "out"),
            "overrides": {"optimizers.block_decoder.optimizer.lr": 1e-3}}
    config = trainer_config(spec)
    assert config.optimizers["block_decoder"]["optimizer"].lr == 1e-3
    assert config.optimizers["decoder"]["optimizer"].lr == 1e-3 and config.optimizers["encoder"]["optimizer"].lr == 1e-2
    with pytest.raises(KeyError, match="block_decodr"):
        trainer_config({**spec, "overrides": {"optimizers.block_decodr.optimizer.lr": 1e-3}})
    with pytest.raises(AttributeError, match="lrr"):
        trainer_config({**spec, "overrides": {"optimizers.block_decoder.optimizer.lrr": 1e-3}})


def test_bad_benchmark_options_are_refused_before_anything_is_written(tmp_path: Path) -> None:
    """An unknown variant, a parallel budget of no steps or a missing scene folder end in a one-line
    error naming the option, and no output folder is made."""
    from scalar_nerfstudio.benchmarking.schedule import prepare

    output = tmp_path / "bench"
    scene = tmp_path / "scene"
    scene.mkdir()
    for config, message in (
        (BenchmarkConfig(data=scene, output_dir=output, variants=("ngp18",)), "unknown variant"),
        (BenchmarkConfig(data=scene, output_dir=output, parallel_block_steps=-3), "--parallel-block-steps -3"),
        (BenchmarkConfig(data=scene, output_dir=output, decoder_width=0), "--decoder-width 0"),
        (BenchmarkConfig(data=scene, output_dir=output, fusions=("guided",)), "--fusions guided"),
        (BenchmarkConfig(data=scene, output_dir=output, wall_clock_tries=0), "--wall-clock-tries 0"),
        (BenchmarkConfig(data=scene, output_dir=output, heldout_view=-1), "--heldout-view -1"),
        (BenchmarkConfig(data=tmp_path / "missing", output_dir=output), "is not a scene folder"),
        (BenchmarkConfig(output_dir=output), "is not a scene folder"),
    ):
        with pytest.raises(SystemExit, match=message):
            prepare(config)
        assert not output.exists()


def test_the_machine_probe_measures_the_hash_grid_and_restores_the_thread_count() -> None:
    """The training benchmark prints the machine's speed before and after its runs (its absolute figures
    move with it): a positive, finite rate, measured without leaving torch's thread count changed."""
    import math

    import torch

    from scalar_nerfstudio.benchmarking.machine import hash_grid_speed

    threads = torch.get_num_threads()
    rate = hash_grid_speed(num_points=4096, log2_hashmap_size=12, threads=1, warmup=0, repeats=2)
    assert math.isfinite(rate) and rate > 0
    assert torch.get_num_threads() == threads
    with pytest.raises(ValueError, match="num_points >= 1"):
        hash_grid_speed(num_points=0)


def test_training_benchmark_settings_read_booleans_numbers_and_strings() -> None:
    """``bench_training.py --scalar-set``: ``False`` and ``false`` are the boolean (``False`` used to
    stay the string 'False', which a config reads as true), numbers are numbers, other text stays text,
    and a setting without ``=`` is refused."""
    import importlib.util

    path = Path(__file__).resolve().parent.parent / "benchmarks" / "bench_training.py"
    spec = importlib.util.spec_from_file_location("bench_training", path)
    assert spec is not None and spec.loader is not None
    bench_training = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench_training)
    settings = bench_training.parse_settings(
        ["a.flag=False", "b.flag=false", "c.flag=True", "d.size=128", "e.rate=2e-3", "f.name=auto", "g.pair=(1, 2)"]
    )
    assert settings == {
        "a.flag": False, "b.flag": False, "c.flag": True, "d.size": 128, "e.rate": 2e-3, "f.name": "auto", "g.pair": (1, 2)
    }
    with pytest.raises(SystemExit, match="NAME=VALUE"):
        bench_training.parse_settings(["pipeline.model.field.fused_decoder"])


@pytest.mark.slow
def test_train_vs_heldout_scores_held_out_views_as_ns_eval_does(full_run: Path, tmp_path: Path) -> None:
    """benchmarks/train_vs_heldout.py on a trained run: its held-out PSNR is nerfstudio's (what ns-eval
    computes, here in-process), every held-out view and every 4th training view are rendered."""
    ns_eval_psnr = eval_renders(load_pipeline(full_run))[0]["psnr"]
    result = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "train_vs_heldout.py"), "--load-config", str(full_run / "config.yml"),
         "--every", "4", "--json", str(tmp_path / "rows.json")],
        capture_output=True, text=True, timeout=600, check=False
    )
    assert result.returncode == 0, result.stderr[-2000:]
    (row,) = json.loads((tmp_path / "rows.json").read_text()).values()
    assert row["held_out_views"] == 3 and row["train_views"] == 6  # 24 images, every 8th held out: 21 train, 3 held out
    assert abs(row["held_out_psnr"] - ns_eval_psnr) < 0.05, (row, ns_eval_psnr)
    assert abs(row["gap_db"] - (row["train_psnr"] - row["held_out_psnr"])) < 1e-9


@pytest.mark.slow  # trains
def test_the_same_spec_trains_the_same_model_and_another_seed_another(scene: Path, tmp_path: Path) -> None:
    """A benchmark run is seeded as ns-train seeds its runs (``machine.seed``): the same spec gives the
    same held-out PSNR to the last bit, another seed another one. (Unseeded, two runs of one spec
    differed by 0.7 dB.) A spec whose fusions name a block the run lacks stops before training."""
    from scalar_nerfstudio.benchmarking.runner import run

    overrides = {
        "pipeline.model.field.log2_hashmap_size": 14, "pipeline.model.field.max_resolution": 256,
        "pipeline.model.num_samples_per_ray": 32, "pipeline.model.occupancy_warmup_steps": 8,
        "pipeline.datamanager.train_num_rays_per_batch": 512,
        "pipeline.num_blocks": 1, "pipeline.train_blocks": False, "pipeline.global_steps": 30,
    }

    def held_out_psnr(name: str, seed: int) -> float:
        spec = {"name": name, "method": "scalar-nerf", "data": str(scene), "downscale": 1, "eval_every": 0,
                "overrides": {**overrides, "machine.seed": seed}, "fusions": ["global"],
                "output_dir": str(tmp_path / name), "result": str(tmp_path / f"{name}.json")}
        return run(spec)["final"]["psnr"]

    first, again, other = held_out_psnr("first", 42), held_out_psnr("again", 42), held_out_psnr("other", 7)
    assert first == again and other != first, (first, again, other)
    # a fusion naming a block the run does not have is refused before its training, not after it
    from scalar_nerfstudio.fusion import FusionModeError

    spec = {"name": "bad", "method": "scalar-nerf", "data": str(scene), "downscale": 1, "eval_every": 0, "overrides": overrides,
            "fusions": ["global", "block:1"], "output_dir": str(tmp_path / "bad"), "result": str(tmp_path / "bad.json")}
    with pytest.raises(FusionModeError, match="block index out of range, there are 1 blocks"):
        run(spec)
    assert not (tmp_path / "bad.json").exists() and not list((tmp_path / "bad").rglob("*.ckpt"))
    config = BenchmarkConfig(data=tmp_path, variants=("ngp-t", "auto"), seed=7)
    with mock.patch("scalar_nerfstudio.benchmarking.variants.auto_k", return_value=3):
        specs = [variant_spec(config, v, runs=tmp_path, results={"global": {"checkpoint": "g.ckpt"}}) for v in plan(config)[0]]
    assert [spec["overrides"]["machine.seed"] for spec in specs] == [7, 7, 7]  # global, ngp-t, auto


def test_train_vs_heldout_refuses_bad_options(tmp_path: Path) -> None:
    script = str(REPO / "benchmarks" / "train_vs_heldout.py")
    result = subprocess.run([sys.executable, script, "--load-config", str(tmp_path / "none.yml")], capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode != 0 and "no such config.yml" in result.stderr
    (tmp_path / "config.yml").write_text("{}")
    result = subprocess.run([sys.executable, script, "--load-config", str(tmp_path / "config.yml"), "--every", "0"],
                            capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode != 0 and "--every 0: must be >= 1" in result.stderr


def test_the_method_never_imports_the_lab() -> None:
    """No module of the method (anything under scalar_nerfstudio/ but scripts/, benchmarking/ and scenes/)
    imports the benchmark harness or the scene generators, not even inside a function."""
    import ast

    package = REPO / "scalar_nerfstudio"
    lab = ("scalar_nerfstudio.benchmarking", "scalar_nerfstudio.scenes")
    offenders = []
    for path in sorted(package.rglob("*.py")):
        if path.relative_to(package).parts[0] in ("scripts", "benchmarking", "scenes"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            offenders += [f"{path.relative_to(REPO)}: {name}" for name in names if name.startswith(lab)]
    assert not offenders, offenders
