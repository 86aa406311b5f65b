"""A 64-block run as a user runs it, with tiny steps: it plans, trains, checkpoints, is killed and
resumes, keeps every finished block in its own file (checkpoints stay one block's size), trains one
block again in its own run, assembles, and renders with ns-eval at least as well as its global model.
(Slow: about 2 minutes.)"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from conftest import free_port, ns_eval, ns_train_command, run_dirs, sigkill_after_checkpoint, trained_block_tensors
from quality import FUSION_TOLERANCE_DB, eval_renders, load_pipeline

from scalar_nerfstudio.runs import block_model_path, block_models_dir, latest_checkpoint_step
from scalar_nerfstudio.scenes.town import TownConfig, write_town

NUM_BLOCKS, GLOBAL_STEPS, BLOCK_STEPS = 64, 30, 2
TOTAL_STEPS = GLOBAL_STEPS + NUM_BLOCKS * BLOCK_STEPS
SMALL = [
    "--pipeline.model.field.log2-hashmap-size", "13",
    "--pipeline.block-log2-hashmap-size", "13",  # every block the same size, whatever K is
    "--pipeline.model.field.max-resolution", "128",
    "--pipeline.model.num-samples-per-ray", "24",
    "--pipeline.model.occupancy-resolution", "32",
    "--pipeline.model.occupancy-warmup-steps", "8",
    "--pipeline.model.render-occupancy-resolution", "32",  # each model's render grid is built when it ends: 65 times here
    "--pipeline.datamanager.train-num-rays-per-batch", "256",
    "--pipeline.num-blocks", str(NUM_BLOCKS),
    "--pipeline.global-steps", str(GLOBAL_STEPS),
    "--pipeline.block-steps", str(BLOCK_STEPS),
    "--steps-per-save", "1000",
    "--steps-per-eval-image", "100000", "--steps-per-eval-batch", "100000", "--steps-per-eval-all-images", "100000",
]
DATA = ["nerfstudio-data", "--eval-mode", "interval", "--eval-interval", "8"]


@pytest.fixture(scope="module")
def town(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A town walked by 320 cameras of 40 x 30 pixels (280 training images: enough for 64 blocks)."""
    folder = tmp_path_factory.mktemp("town64")
    write_town(folder, TownConfig(num_images=320, width=40, height=30, blocks_x=4, blocks_y=3, seed=1), progress=False)
    return folder


def _checkpoint(run: Path) -> Path:
    step = latest_checkpoint_step(run / "nerfstudio_models")
    assert step is not None
    return run / "nerfstudio_models" / f"step-{step:09d}.ckpt"


@pytest.mark.slow
def test_64_blocks_train_resume_assemble_and_render_with_bounded_checkpoints(town: Path, tmp_path: Path) -> None:
    output = tmp_path / "out"
    command = ns_train_command(town, output, *SMALL, *DATA)
    killed_at = sigkill_after_checkpoint(subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL),
                                         output, min_step=GLOBAL_STEPS + 20 * BLOCK_STEPS)
    assert killed_at is not None and GLOBAL_STEPS <= killed_at < TOTAL_STEPS - 1, killed_at
    (run,) = run_dirs(output)
    for path in (run / "nerfstudio_models").iterdir():  # whatever survived the kill is complete and loadable
        assert path.name.startswith("step-") and path.suffix == ".ckpt", path.name
        assert torch.load(path, map_location="cpu", weights_only=False)["step"] == int(path.name[5:14])
    resume = ns_train_command(town, output, *SMALL, "--load-dir", str(run / "nerfstudio_models"), *DATA)
    resumed = subprocess.run(resume, capture_output=True, text=True, timeout=1200, check=False)
    assert resumed.returncode == 0, resumed.stdout[-3000:] + resumed.stderr[-3000:]
    assert run_dirs(output) == [run], "the resumed run trains in the same folder"
    log = " ".join(resumed.stdout.split())
    assert "phase block 0: loading" not in log and f"phase block {NUM_BLOCKS - 1}: loading" in log, "it resumes, not restarts"

    # every block finished; each but the last in its own file; the checkpoint holds one block
    state = torch.load(_checkpoint(run), map_location="cpu", weights_only=True)["pipeline"]
    assert latest_checkpoint_step(run / "nerfstudio_models") == TOTAL_STEPS - 1
    assert state["_model.blocks_started"].tolist() == [True] * NUM_BLOCKS
    files = sorted(p.name for p in block_models_dir(run).iterdir())
    assert files == [block_model_path(Path("."), k).name for k in range(NUM_BLOCKS - 1)]
    block_bytes = {k: sum(v.numel() * v.element_size() for v in trained_block_tensors(run, k).values()) for k in (0, NUM_BLOCKS - 1)}
    in_checkpoint = sum(v.numel() * v.element_size() for k, v in state.items() if k.startswith("_model.blocks."))
    assert in_checkpoint == block_bytes[NUM_BLOCKS - 1], "the checkpoint holds the last block only, not 64"
    global_bytes = sum(v.numel() * v.element_size() for k, v in state.items() if k.startswith("_model.global_model."))
    # global model + the last block + that block's Adam moments (2x): the same at K = 4 or 64
    assert _checkpoint(run).stat().st_size < global_bytes + 3 * block_bytes[NUM_BLOCKS - 1] + 2**20

    # one block trained again in a run of its own, assembled with the 63 others
    block_command = [sys.executable, "-m", "nerfstudio.scripts.train", "scalar-nerf-block", "--global-run", str(run), "--block", "5",
                     "--output-dir", str(tmp_path / "block5"), "--viewer.websocket-port", str(free_port()),
                     "--viewer.quit-on-train-completion", "True", "--logging.local-writer.enable", "False", "--pipeline.block-steps", "4"]
    block_run = subprocess.run(block_command, capture_output=True, text=True, timeout=600, check=False)
    assert block_run.returncode == 0, block_run.stdout[-3000:] + block_run.stderr[-3000:]
    (block5,) = run_dirs(tmp_path / "block5", method="scalar-nerf-block")
    assemble = subprocess.run(["scalar-nerf-assemble", "--global-run", str(run), "--block-runs", str(block5),
                               "--output-dir", str(tmp_path / "assembled")], capture_output=True, text=True, timeout=600, check=False)
    assert assemble.returncode == 0, assemble.stdout[-3000:] + assemble.stderr[-3000:]
    (assembled,) = run_dirs(tmp_path / "assembled")
    assert torch.equal(trained_block_tensors(assembled, 5)["field.encoder.table"], trained_block_tensors(block5, 5)["field.encoder.table"])
    assert torch.equal(trained_block_tensors(assembled, 9)["field.encoder.table"], trained_block_tensors(run, 9)["field.encoder.table"])
    assembled_state = torch.load(_checkpoint(assembled), map_location="cpu", weights_only=True)["pipeline"]
    assert all(v.numel() == 0 for k, v in assembled_state.items() if k.startswith("_model.blocks.")), "assembled blocks live in files"

    # the assembled run renders every held-out view, fused from blocks loaded on demand, at least as
    # well as its global model alone
    evaluation = ns_eval(assembled, tmp_path / "assembled.json")
    assert evaluation.returncode == 0, evaluation.stdout[-3000:] + evaluation.stderr[-3000:]
    results = json.loads((tmp_path / "assembled.json").read_text())["results"]
    global_only = eval_renders(load_pipeline(assembled), "global-only")[0]["psnr"]
    assert results["psnr"] >= global_only - FUSION_TOLERANCE_DB, (results["psnr"], global_only)
    # the town has true depth: ns-eval scores the fused depth against it too
    assert 0.0 <= results["depth_delta1"] <= 1.0 and results["depth_median_rel_error"] >= 0.0, results
