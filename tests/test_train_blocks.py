"""``scalar-nerf-train-blocks``: every block of a global run trained in parallel (local pool or Ray),
a failed attempt retried in a fresh folder and kept apart, finished blocks skipped on a re-run, and
the result assembled into a run that ``ns-eval`` fuses."""

from __future__ import annotations

import copy
import hashlib
import json
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np
import psutil
import pytest
import torch
import yaml
from conftest import TINY, ns_eval, ns_train_command, run_dirs, trained_block_tensors
from prerequisites import has_module, need
from quality import FUSION_TOLERANCE_DB, eval_renders, load_pipeline, working_directory

from scalar_nerfstudio.blocks.split import save_blocks_json, split_cameras
from scalar_nerfstudio.distributed import TrainBlocksError, scheduling
from scalar_nerfstudio.distributed.executors import LocalExecutor, local_gpu_slots, thread_env
from scalar_nerfstudio.distributed.run_folders import DONE_MARKER, GlobalRun, prepare_blocks, write_done
from scalar_nerfstudio.distributed.scheduling import (
    Resources,
    block_command,
    default_cpus_per_block,
    default_local_gpus_per_block,
    start_executor,
)
from scalar_nerfstudio.runs import latest_checkpoint_step
from scalar_nerfstudio.scripts import train_blocks
from scalar_nerfstudio.scripts.train_blocks import main

BLOCK_STEPS = 8  # per block in these tests: the time goes into starting the processes, not training


def _state(run: Path):
    step = latest_checkpoint_step(run / "nerfstudio_models")
    return torch.load(run / "nerfstudio_models" / f"step-{step:09d}.ckpt", map_location="cpu", weights_only=True)["pipeline"]


def _done_run(out: Path, block: int) -> Path:
    done = json.loads((out / f"block{block}" / DONE_MARKER).read_text())
    return out / f"block{block}" / done["run"]


# ------------------------------------------------------------------ quick: no training


@pytest.fixture
def fake_global_run(scene: Path, tmp_path: Path) -> Path:
    """A folder that looks like a finished ``scalar-nerf`` global run (config, blocks.json, a checkpoint
    at the last global step) without training one: enough for the command's checks."""
    from scalar_nerfstudio.method_configs import scalar_nerf

    run = tmp_path / "out" / "scene" / "scalar-nerf" / "fake"
    (run / "nerfstudio_models").mkdir(parents=True)
    config = copy.deepcopy(scalar_nerf.config)
    config.data = config.pipeline.datamanager.data = scene
    config.pipeline.num_blocks = 2
    config.pipeline.global_steps, config.pipeline.block_steps = 2000, 1000  # as a run without a recorded length says them
    (run / "config.yml").write_text(yaml.dump(config))
    names = [f"images/frame_{i:05d}.png" for i in range(12)]
    centres = np.stack([np.linspace(-1, 1, 12), np.zeros(12), np.zeros(12)], axis=1)
    save_blocks_json(split_cameras(centres, 2, aabb_scale=(1.2, 1.2, 1.2)), run / "blocks.json", names)
    (run / "nerfstudio_models" / f"step-{config.pipeline.global_steps - 1:09d}.ckpt").touch()
    return run


def _error(capsys, argv: List[str]) -> str:
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    return err


def test_clear_errors(fake_global_run: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    assert "no config.yml" in _error(capsys, [str(tmp_path / "nothing")])
    assert "block 7 does not exist" in _error(capsys, [str(fake_global_run), "--blocks", "0", "7"])
    unfinished = tmp_path / "unfinished"
    (unfinished / "nerfstudio_models").mkdir(parents=True)
    for name in ("config.yml", "blocks.json"):
        (unfinished / name).write_text((fake_global_run / name).read_text())
    (unfinished / "nerfstudio_models" / "step-000000010.ckpt").touch()
    err = _error(capsys, [str(unfinished)])
    assert "global phase" in err and "not finished" in err
    err = _error(capsys, [str(fake_global_run), "--", "--pipeline.block-steps", "3"])
    assert "--block-steps" in err
    assert "must be 1/n" in _error(capsys, [str(fake_global_run), "--gpus-per-block", "0.3"])
    if not torch.cuda.is_available():
        assert "this machine has no GPU" in _error(capsys, [str(fake_global_run), "--gpus-per-block", "0.5"])
    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    assert "pip install 'scalar-nerfstudio[distributed]'" in _error(capsys, [str(fake_global_run), "--executor", "ray"])
    assert not (tmp_path / "out" / "scene" / "scalar-nerf" / "fake-blocks").exists(), "nothing is written on an error"


def test_threads_and_pool_size_do_not_oversubscribe() -> None:
    assert default_cpus_per_block(2, 2) == 1
    assert default_cpus_per_block(16, 4) == 4
    assert default_cpus_per_block(2, 5) == 1
    assert default_cpus_per_block(32, 3, node_cpus=16) == 10
    env = thread_env(3, 0)
    assert env["OMP_NUM_THREADS"] == env["MKL_NUM_THREADS"] == "3" and env["CUDA_VISIBLE_DEVICES"] == ""
    assert "CUDA_VISIBLE_DEVICES" not in thread_env(3, 1)  # Ray assigns the GPU
    assert LocalExecutor(2, 1, 0).slots == 2
    assert LocalExecutor(2, 2, 0).slots == 1
    assert LocalExecutor(8, 3, 0).slots == 2
    run = GlobalRun(Path("/runs/g"), 2, Path("/runs/g/nerfstudio_models/step-000000039.ckpt"), 15)
    command = block_command(run, 1, attempt_dir=Path("/o/block1/attempt-3"), gpus=0, block_steps=None, extra=["--steps-per-save", "4"])
    assert command[:5] == ["scalar-nerf-block", "--global-run", "/runs/g", "--block", "1"]
    assert command[command.index("--pipeline.block-steps") + 1] == "15" and command[command.index("--max-num-iterations") + 1] == "15"
    assert "--machine.device-type" in command and command[-2:] == ["--steps-per-save", "4"]
    command = block_command(run, 1, attempt_dir=Path("/o"), gpus=1, block_steps=6, extra=[])
    assert command[command.index("--pipeline.block-steps") + 1] == "6" and "--machine.device-type" not in command


def test_local_blocks_share_a_gpu_when_asked() -> None:
    """--gpus-per-block 1/n trains n blocks on each GPU at once (one block rarely keeps a GPU busy);
    whole GPUs give each block its own; the pool never exceeds the CPUs."""
    assert local_gpu_slots(1, 2) == ["0", "1"]
    assert local_gpu_slots(2, 5) == ["0,1", "2,3"]
    assert local_gpu_slots(0.25, 1) == ["0"] * 4
    assert local_gpu_slots(0.5, 2) == ["0", "1", "0", "1"]  # spread over the GPUs first
    pool = LocalExecutor(16, 2, 0.125, gpu_count=1)
    assert pool.slots == 8 and pool.devices == ["0"] * 8 and "8 blocks per GPU" in pool.description
    assert LocalExecutor(4, 2, 0.125, gpu_count=1).slots == 2  # 2 CPUs per block on 4 CPUs
    assert LocalExecutor(16, 1, 1, gpu_count=1).slots == 1  # a whole GPU each: one at a time
    assert LocalExecutor(16, 1, 1, gpu_count=1).devices == ["0"]
    for gpus, count, message in ((0.3, 1, "1/n"), (1.5, 2, "whole number"), (2, 1, "has 1 GPU"), (0.5, 0, "no GPU")):
        with pytest.raises(TrainBlocksError, match=message):
            LocalExecutor(16, 1, gpus, gpu_count=count)


def test_by_default_local_blocks_share_the_gpus(monkeypatch) -> None:
    """Without --gpus-per-block, --executor local trains the blocks of a GPU machine at once, up to 8
    on each GPU and 2 GiB of its memory per block (one block alone leaves a GPU mostly idle), and on
    the CPU without a GPU."""
    gib = 1024**3
    assert default_local_gpus_per_block([80 * gib], 8) == 1 / 8
    assert default_local_gpus_per_block([80 * gib], 20) == 1 / 8  # at most 8 share one GPU
    assert default_local_gpus_per_block([80 * gib, 80 * gib], 8) == 1 / 4
    assert default_local_gpus_per_block([8 * gib], 8) == 1 / 4  # 2 GiB per block
    assert default_local_gpus_per_block([80 * gib, 3 * gib], 8) == 1.0  # the smallest GPU decides
    assert default_local_gpus_per_block([80 * gib] * 4, 2) == 1.0
    assert default_local_gpus_per_block([], 8) == 0.0
    assert local_gpu_slots(default_local_gpus_per_block([80 * gib], 3), 1) == ["0"] * 3
    monkeypatch.setattr(scheduling, "local_gpu_memory_bytes", lambda: [80 * gib])
    executor, cpus, gpus = start_executor(Resources(num_cpus=16), 8)
    try:
        assert (cpus, gpus, executor.slots, executor.devices) == (2, 1 / 8, 8, ["0"] * 8)
    finally:
        executor.close()
    executor, cpus, gpus = start_executor(Resources(num_cpus=16, gpus_per_block=1), 8)  # asked: one at a time
    try:
        assert (gpus, executor.slots) == (1, 1)
    finally:
        executor.close()
    monkeypatch.setattr(scheduling, "local_gpu_memory_bytes", lambda: [])
    executor, cpus, gpus = start_executor(Resources(num_cpus=2), 8)
    try:
        assert (cpus, gpus, executor.slots, executor.devices) == (1, 0.0, 2, [None, None])
    finally:
        executor.close()



def test_skip_done_set_aside_leftovers_and_stale(tmp_path: Path, capsys) -> None:
    checkpoint = Path("/runs/g/nerfstudio_models/step-000000039.ckpt")
    done_run = tmp_path / "block0" / "attempt-2" / "scene" / "scalar-nerf-block" / "t-block0"
    done_run.mkdir(parents=True)
    (done_run / "config.yml").touch()
    (tmp_path / "block0" / "failed-attempt-1").mkdir()
    write_done(tmp_path / "block0", done_run, attempt=2, seconds=12.0, global_checkpoint=checkpoint)
    (tmp_path / "block1" / "attempt-1").mkdir(parents=True)  # left by a killed command
    states = prepare_blocks(tmp_path, [0, 1], checkpoint)
    assert states[0].status.startswith("skipped") and states[0].run == done_run
    assert states[1].status == "pending" and states[1].next_attempt == 2
    assert (tmp_path / "block1" / "interrupted-attempt-1").is_dir() and not (tmp_path / "block1" / "attempt-1").exists()
    # the global run trained on: block 0's result is set aside and trained again
    states = prepare_blocks(tmp_path, [0], Path("/runs/g/nerfstudio_models/step-000000099.ckpt"))
    assert states[0].status == "pending" and states[0].next_attempt == 3
    assert (tmp_path / "block0" / "stale-attempt-2").is_dir() and not (tmp_path / "block0" / DONE_MARKER).exists()
    assert "training again" in capsys.readouterr().out


# ------------------------------------------------------------- end to end (tiny runs)


@pytest.fixture(scope="module")
def global_run(scene: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny ``scalar-nerf`` run trained through its global phase only (2 blocks in blocks.json),
    with the scene given as a relative path (``--data courtyard0``, as users type it), started in the
    scene's parent folder: every command on it runs from there (``cwd=global_run_cwd``)."""
    output_dir = tmp_path_factory.mktemp("global_only")
    result = subprocess.run(ns_train_command(Path(scene.name), output_dir, *TINY, "--pipeline.train-blocks", "False"),
                            capture_output=True, text=True, timeout=900, cwd=scene.parent, check=False)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    (run,) = run_dirs(output_dir)
    return run


@pytest.fixture(scope="module")
def global_run_cwd(scene: Path) -> Path:
    """The folder ``global_run`` was trained in (its config names the scene relative to it)."""
    return scene.parent


def _digests(run: Path) -> Dict[str, str]:
    """SHA-256 of every file under ``run``, by relative path."""
    return {str(p.relative_to(run)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(run.rglob("*")) if p.is_file()}


def _block_processes(out: Path, block: int, attempt: int) -> List[psutil.Process]:
    """The ``ns-train scalar-nerf-block`` processes training ``block``'s attempt ``attempt`` under ``out``."""
    folder = str(out / f"block{block}" / f"attempt-{attempt}")
    found = []
    for process in psutil.process_iter(["cmdline"]):
        cmdline = process.info["cmdline"] or []
        if "scalar-nerf-block" in cmdline and folder in cmdline:
            found.append(process)
    return found


def _ray_processes(since: float) -> List[str]:
    left = []
    for process in psutil.process_iter(["cmdline", "create_time"]):
        cmdline = " ".join(process.info["cmdline"] or [])
        if process.info["create_time"] >= since and ("raylet" in cmdline or "gcs_server" in cmdline or cmdline.startswith("ray::")):
            left.append(cmdline[:120])
    return left


def _assert_block_1_retried_and_assembled(out: Path, tmp_path: Path, cwd: Path) -> Tuple[Dict[int, Path], Path]:
    """Block 1's killed first attempt is set aside, partial (no final checkpoint) and never used; its
    second attempt and block 0's first finished; the assembled run holds both, and ``ns-eval`` scores
    its fused render at least as well as the global run alone (within FUSION_TOLERANCE_DB).
    Returns (the run of each block, the assembled run)."""
    failed = out / "block1" / "failed-attempt-1"
    (partial,) = [p.parent for p in failed.glob("*/scalar-nerf-block/*/config.yml")]
    assert latest_checkpoint_step(partial / "nerfstudio_models") != BLOCK_STEPS - 1
    runs = {block: _done_run(out, block) for block in (0, 1)}
    assert "/block0/attempt-1/" in str(runs[0]) and "/block1/attempt-2/" in str(runs[1])
    for run in runs.values():
        assert latest_checkpoint_step(run / "nerfstudio_models") == BLOCK_STEPS - 1
    (assembled,) = run_dirs(out / "assembled")
    sources = json.loads((assembled / "assembled_from.json").read_text())["blocks"]
    assert sources == {str(b): str(r.resolve()) for b, r in runs.items()}
    assert _state(assembled)["_model.blocks_started"].tolist() == [True, True]
    evaluation = ns_eval(assembled, tmp_path / "eval.json", cwd=cwd)
    assert evaluation.returncode == 0, evaluation.stdout[-3000:] + evaluation.stderr[-3000:]
    fused_psnr = json.loads((tmp_path / "eval.json").read_text())["results"]["psnr"]
    global_run = Path(json.loads((assembled / "assembled_from.json").read_text())["global_run"])
    with working_directory(cwd):  # the global run names its scene relative to where it was trained
        global_psnr = eval_renders(load_pipeline(global_run))[0]["psnr"]
    assert fused_psnr >= global_psnr - FUSION_TOLERANCE_DB, f"the assembled blocks {fused_psnr:.2f} dB, their global run alone {global_psnr:.2f} dB"
    return runs, assembled


def _ray_node(attempt_dir: Path) -> str:
    """The Ray node id that an attempt's ``train.log`` names in its first line."""
    header = (attempt_dir / "train.log").read_text().splitlines()[0]
    match = re.search(r"Ray node ([0-9a-f]+),", header)
    assert match, header
    return match.group(1)


@pytest.mark.slow
def test_ray_cluster_of_two_nodes_retries_a_killed_block_on_the_other_node(global_run: Path, global_run_cwd: Path, tmp_path: Path) -> None:
    """A Ray cluster of several nodes on this machine (``ray.cluster_utils.Cluster``), joined with
    ``--address``: the two blocks train at once, the node running block 1's first attempt is lost,
    block 1 is retried on the other, the two results are assembled and fused, and the same command
    run again trains nothing.

    - The head node has no CPUs; two worker nodes of 1 CPU each run one block at a time. The head
      cannot be the node that is lost: it holds the GCS (the cluster's control plane), and no Ray
      cluster survives losing it. With a 1-CPU head, Ray's scheduler, not the test, would choose
      whether block 1 runs on the head, so the head runs no blocks (as on many real clusters).
    - Once block 1's ``ns-train`` process has written its run folder, the test removes its node with
      ``allow_graceful=False``: the node's raylet and agents are SIGKILLed, as when a machine is lost.
      The Ray worker exits with its raylet and the block process with its worker. The command gets
      a ``NodeDiedError`` within seconds, so nothing hangs.
    - Each attempt's ``train.log`` names the Ray node it ran on, since every node here has the same
      hostname. The test checks the node names there: the failed attempt on the lost node, the retry
      on the surviving one.
    """
    need("ray", has_module("ray"), provided_by="the test extra installs it: pip install -e '.[test]'")
    from ray import cluster_utils
    out = tmp_path / "blocks"
    log_path = tmp_path / "command.log"
    started = time.time()
    cluster = cluster_utils.Cluster(initialize_head=True, head_node_args=dict(num_cpus=0, include_dashboard=False))
    process = None
    try:
        workers = [cluster.add_node(num_cpus=1) for _ in range(2)]
        command = ["scalar-nerf-train-blocks", str(global_run), "--executor", "ray", "--address", cluster.address,
                   "--cpus-per-block", "1", "--block-steps", str(BLOCK_STEPS), "--output-dir", str(out),
                   "--", "--steps-per-save", "4"]
        with open(log_path, "w") as log:
            process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, text=True, cwd=global_run_cwd)
            lost = None
            both_at_once = False
            deadline = time.time() + 600
            while process.poll() is None and time.time() < deadline and lost is None:
                victims = _block_processes(out, 1, 1)
                both_at_once = both_at_once or bool(victims and _block_processes(out, 0, 1))
                if victims and list((out / "block1" / "attempt-1").glob("*/scalar-nerf-block/*/config.yml")):
                    node_id = _ray_node(out / "block1" / "attempt-1")
                    (lost,) = [node for node in workers if node.node_id == node_id]
                    cluster.remove_node(lost, allow_graceful=False)
                    gone, alive = psutil.wait_procs(victims, timeout=60)
                    assert not alive, "the block process must die with its node"
                time.sleep(0.05)
            assert lost is not None, "block 1's first attempt was never seen running"
            process.wait(timeout=600)
        # the same command again skips both blocks (no Ray task, no training) and reuses the assembled run
        rerun = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=global_run_cwd, check=False)
    finally:
        if process is not None and process.poll() is None:
            process.kill()
            process.wait()
        cluster.shutdown()
    seconds = time.time() - started
    output = log_path.read_text()
    assert process.returncode == 0, output[-5000:]
    assert "Ray cluster at" in output and "3 node(s), 2 CPUs" in output, output[:2000]
    assert both_at_once, "the two blocks should train at the same time, one on each node"
    assert re.search(r"block 1: attempt 1 failed( \(Ray node \w+\))?: (NodeDiedError|WorkerCrashedError)", output), output[-5000:]
    assert "kept apart" in output

    (survivor,) = [node for node in workers if node is not lost]
    failed = out / "block1" / "failed-attempt-1"
    assert _ray_node(failed) == lost.node_id
    assert _ray_node(out / "block1" / "attempt-2") == survivor.node_id, "the retry runs on the surviving node"
    assert _ray_node(out / "block0" / "attempt-1") == survivor.node_id, "block 0 ran beside block 1, on the other node"
    runs, assembled = _assert_block_1_retried_and_assembled(out, tmp_path, global_run_cwd)
    for block, run in runs.items():
        assert torch.equal(trained_block_tensors(assembled, block)["field.encoder.table"], trained_block_tensors(run, block)["field.encoder.table"])
    assert rerun.returncode == 0, rerun.stdout[-3000:] + rerun.stderr[-3000:]
    assert rerun.stdout.count("skipped (done before)") == 2 and "already assembled" in rerun.stdout
    assert ": attempt" not in rerun.stdout and "Ray cluster" not in rerun.stdout, "nothing is trained, Ray is not started"
    assert run_dirs(out / "assembled") == [assembled]

    time.sleep(2)
    assert not _ray_processes(started), "every node of the cluster must be shut down"
    print(f"ray cluster of 2 worker nodes: 2 blocks of {BLOCK_STEPS} steps, node lost, block 1 retried, in {seconds:.0f} s")


@pytest.mark.slow
def test_local_executor_reports_failures_then_trains_and_fuses(global_run: Path, global_run_cwd: Path, tmp_path: Path) -> None:
    """Without Ray: a block whose every attempt fails makes the command exit non-zero naming it;
    the same command, fixed, then trains it with the threads asked for and fuses it. The global run
    it starts from is never written to."""
    before = _digests(global_run)
    out = tmp_path / "blocks"
    base = ["scalar-nerf-train-blocks", str(global_run), "--blocks", "0", "--num-cpus", "2", "--cpus-per-block", "2",
            "--block-steps", str(BLOCK_STEPS), "--output-dir", str(out), "--max-retries", "1"]
    broken = subprocess.run([*base, "--", "--no-such-option", "1"], capture_output=True, text=True, timeout=600, cwd=global_run_cwd, check=False)
    assert broken.returncode == 1
    assert "block(s) 0 failed after 2 attempt(s)" in broken.stderr
    assert sorted(p.name for p in (out / "block0").iterdir()) == ["failed-attempt-1", "failed-attempt-2"]
    assert not run_dirs(out / "assembled")

    result = subprocess.run(base, capture_output=True, text=True, timeout=600, cwd=global_run_cwd, check=False)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    run = _done_run(out, 0)
    assert "/block0/attempt-3/" in str(run)
    assert "OMP_NUM_THREADS=2" in (out / "block0" / "attempt-3" / "train.log").read_text().splitlines()[1]
    (assembled,) = run_dirs(out / "assembled")
    assert _state(assembled)["_model.blocks_started"].tolist() == [True, False]
    assert f"ns-eval --load-config {assembled / 'config.yml'}" in result.stdout
    assert train_blocks.PROG in result.stdout
    assert _digests(global_run) == before, "training blocks must not write into the global run"


def test_a_gpu_run_that_trains_its_blocks_in_turn_points_to_train_blocks() -> None:
    """On a GPU, ns-train's log says that scalar-nerf-train-blocks trains the blocks at once."""
    from scalar_nerfstudio.pipeline_text import sequential_blocks_hint

    hint = sequential_blocks_hint(8, "cuda")
    assert hint is not None and "8 blocks train one after another" in hint and "scalar-nerf-train-blocks" in hint
    assert sequential_blocks_hint(8, "cpu") is None  # on the CPU the cores are already shared out
    assert sequential_blocks_hint(1, "cuda") is None and sequential_blocks_hint(0, "cuda") is None
