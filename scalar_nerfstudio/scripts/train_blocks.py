"""``scalar-nerf-train-blocks``: train every block of a trained global run in parallel, then fuse them.

Once the global model exists the blocks are independent (paper Sec. 3.3). This command runs one
``ns-train scalar-nerf-block --global-run RUN --block K`` process per block, several at once:

- ``--executor local``: a pool of subprocesses on this machine (no Ray needed);
- ``--executor ray``: one Ray task per block with its CPU/GPU request, on a local Ray cluster
  started for the command, or on an existing (multi-machine) cluster given by ``--address``.

Every attempt trains into a fresh folder ``OUT/block{K}/attempt-{n}``. Only an attempt that exited
with 0 *and* wrote its final checkpoint is recorded as the block's result (``OUT/block{K}/DONE.json``);
a failed one is renamed ``failed-attempt-{n}`` and never used. Retries are this command's own loop
(Ray's task retries are off), so that every retry gets a fresh folder. A re-run skips blocks that
have a result. When every block has one, the blocks are assembled with the global model into a new
``scalar-nerf`` run that ``ns-eval`` / ``ns-render`` / ``ns-viewer`` fuse.

This module's top level imports only the standard library and tyro, so a Ray worker that runs an attempt
does not import torch or nerfstudio itself (its ``ns-train`` subprocess does).
"""

from __future__ import annotations

import importlib
import json
import os
import re
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Dict, List, Literal, Optional, Tuple

import tyro

from scalar_nerfstudio.atomic_io import atomic_write_text
from scalar_nerfstudio.runs import latest_checkpoint_step, load_run_config

PROG = "scalar-nerf-train-blocks"
DONE_MARKER = "DONE.json"
LOCK_FILE = ".train-blocks.lock"
ATTEMPT_PATTERN = re.compile(r"^(?:failed-|interrupted-|stale-)?attempt-(\d+)$")
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")
INSTALL_RAY = "pip install 'scalar-nerfstudio[distributed]'"


class TrainBlocksError(RuntimeError):
    """A problem with the command's input, reported as one line."""


# ----------------------------------------------------------------------------- the CLI


@dataclass
class TrainBlocksArgs:
    """Train the blocks of a trained scalar-nerf global run in parallel, then assemble a fused run.

    Arguments after -- are passed to every `ns-train scalar-nerf-block` process, e.g.
    `scalar-nerf-train-blocks RUN --executor ray -- --steps-per-save 100`.
    """

    global_run: Annotated[tyro.conf.Positional[Path], tyro.conf.arg(metavar="RUN")]
    """The scalar-nerf run whose global phase is trained (its folder or config.yml)."""
    blocks: Optional[Tuple[int, ...]] = None
    """Blocks to train (default: every block in the run's blocks.json)."""
    executor: Literal["local", "ray"] = "local"
    """local: subprocesses on this machine; ray: one Ray task per block (local cluster, or --address)."""
    address: Optional[str] = None
    """Ray cluster to use, e.g. HEAD_IP:6379 or auto (default: start a local Ray cluster for this command)."""
    num_cpus: Optional[int] = None
    """CPUs of the local pool / local Ray cluster (default: this machine's cores). Ignored with --address."""
    cpus_per_block: Optional[int] = None
    """CPU cores (and threads) per block (default: the CPUs shared evenly among the blocks, at least 1)."""
    gpus_per_block: Optional[float] = None
    """GPUs per block (default: 1 when GPUs are present, else 0: train on the CPU). Ray accepts fractions."""
    max_retries: int = 2
    """Attempts after the first for a block that fails (each in a fresh folder)."""
    output_dir: Optional[Path] = None
    """Where attempts and the assembled run go (default: RUN-blocks beside the global run)."""
    block_steps: Optional[int] = None
    """Steps per block (default: the global run's --pipeline.block-steps)."""
    assemble: bool = True
    """Assemble the fused run once every block has a result."""


@dataclass
class GlobalRun:
    """What the command needs to know about a checked global run."""

    run_dir: Path
    num_blocks: int
    global_checkpoint: Path
    block_steps: int


def check_global_run(run: Path, blocks: Optional[Tuple[int, ...]]) -> Tuple[GlobalRun, List[int]]:
    """Check ``run`` as ``ns-train scalar-nerf-block`` does; returns it and the blocks to train."""
    import copy

    from scalar_nerfstudio.blocks.split import load_blocks_json
    from scalar_nerfstudio.method_configs import scalar_nerf_block

    config = copy.deepcopy(scalar_nerf_block.config)
    config.global_run = Path(run)
    config.block = 0
    try:
        config._adopt_global_run()
    except SystemExit as error:
        message = str(error.code).replace("scalar-nerf-block: ", "", 1).replace("--global-run ", "", 1)
        raise TrainBlocksError(message) from None
    blocks_json = Path(config.pipeline.blocks_json)
    num_blocks = load_blocks_json(blocks_json)[0].num_blocks
    chosen = list(range(num_blocks)) if blocks is None else list(dict.fromkeys(blocks))
    bad = [b for b in chosen if not 0 <= b < num_blocks]
    if bad:
        raise TrainBlocksError(f"block {bad[0]} does not exist; {blocks_json} has blocks 0..{num_blocks - 1}")
    if not chosen:
        raise TrainBlocksError("--blocks: no block given")
    # _adopt_global_run took the run's block steps, decoder mode and ray batch (all left at defaults here).
    return GlobalRun(blocks_json.parent, num_blocks, Path(config.pipeline.global_checkpoint), config.pipeline.block_steps), chosen


def default_cpus_per_block(total_cpus: int, num_blocks: int, node_cpus: Optional[int] = None) -> int:
    """The CPUs shared evenly among the blocks (at most one node's), at least 1."""
    share = max(1, total_cpus // max(num_blocks, 1))
    return max(1, min(share, node_cpus or share))


def thread_env(cpus: int, gpus: float, set_devices: Optional[str] = None) -> Dict[str, str]:
    """Environment of one block process: ``cpus`` threads for OpenMP/MKL/BLAS (torch follows OMP)."""
    env = {name: str(cpus) for name in THREAD_VARIABLES}
    if gpus <= 0:
        env["CUDA_VISIBLE_DEVICES"] = ""  # train on the CPU even on a GPU node
    elif set_devices is not None:
        env["CUDA_VISIBLE_DEVICES"] = set_devices
    return env


def block_command(global_run: GlobalRun, block: int, attempt_dir: Path, gpus: float, block_steps: Optional[int], extra: List[str]) -> List[str]:
    """``ns-train`` arguments (after ``python -m nerfstudio.scripts.train``) of one block attempt."""
    steps = block_steps if block_steps is not None else global_run.block_steps
    args = [
        "scalar-nerf-block",
        "--global-run", str(global_run.run_dir),
        "--block", str(block),
        "--output-dir", str(attempt_dir),
        "--pipeline.block-steps", str(steps),
        "--max-num-iterations", str(steps),  # the final step, which finished_run checks for
        "--vis", "tensorboard",  # no viewer: parallel blocks would fight over its port
    ]
    if gpus <= 0:
        args += ["--machine.device-type", "cpu"]
    return args + list(extra)


# ------------------------------------------------------------ one attempt (runs anywhere)


@dataclass
class AttemptJob:
    block: int
    attempt: int
    folder: str
    """The attempt folder (absolute; on a filesystem the worker shares)."""
    args: List[str]
    env: Dict[str, str]


@dataclass
class AttemptResult:
    returncode: Optional[int]
    """The ns-train process's exit status (negative: killed by that signal); None if it never ended."""
    seconds: float
    error: str = ""
    host: str = ""


def _die_with_parent() -> None:  # pragma: no cover - runs in the forked child
    """In the block process: be killed when the process that started it dies (Linux)."""
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except Exception:
        pass


def run_attempt(job: AttemptJob) -> AttemptResult:
    """Run one block attempt: ``ns-train scalar-nerf-block ...`` with its log in the attempt folder.

    This is the body of a Ray task, so it uses the interpreter and environment of the worker it runs
    on; the block process is killed if the worker dies.
    """
    import socket

    folder = Path(job.folder)
    command = [sys.executable, "-m", "nerfstudio.scripts.train", *job.args]
    start = time.time()
    with open(folder / "train.log", "w") as log:
        overrides = " ".join(f"{k}={shlex.quote(v)}" for k, v in sorted(job.env.items()))
        log.write(f"# host {socket.gethostname()}, attempt {job.attempt} of block {job.block}\n# {overrides} {shlex.join(command)}\n")
        log.flush()
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, cwd=folder,
                                   env={**os.environ, **job.env}, preexec_fn=_die_with_parent)
        returncode = process.wait()
    return AttemptResult(returncode, time.time() - start, host=socket.gethostname())


# ----------------------------------------------------------------------------- executors


class LocalExecutor:
    """A pool of block subprocesses on this machine, ``num_cpus // cpus`` (and GPUs) at a time."""

    def __init__(self, num_cpus: int, cpus: int, gpus: float) -> None:
        import queue
        from concurrent.futures import ThreadPoolExecutor

        if gpus != int(gpus):
            raise TrainBlocksError("--executor local: --gpus-per-block must be a whole number (fractions need --executor ray)")
        slots = max(1, num_cpus // cpus)
        gpu_ids: List[int] = []
        if gpus > 0:
            import torch

            count = torch.cuda.device_count()
            if count < gpus:
                raise TrainBlocksError(f"--gpus-per-block {gpus:g}: this machine has {count} GPU(s)")
            slots = min(slots, count // int(gpus))
            gpu_ids = list(range(count))
        self.slots = slots
        self._free: "queue.Queue[Optional[str]]" = queue.Queue()
        for slot in range(slots):
            ids = gpu_ids[slot * int(gpus):(slot + 1) * int(gpus)]
            self._free.put(",".join(map(str, ids)) if ids else None)
        self._pool = ThreadPoolExecutor(max_workers=slots)
        self.description = f"local pool of {slots} at a time"

    def _run(self, job: AttemptJob) -> AttemptResult:
        devices = self._free.get()
        try:
            if devices is not None:
                job.env["CUDA_VISIBLE_DEVICES"] = devices
            return run_attempt(job)
        finally:
            self._free.put(devices)

    def submit(self, job: AttemptJob):
        return self._pool.submit(self._run, job)

    def wait(self, handles) -> List[Tuple[object, AttemptResult]]:
        from concurrent.futures import FIRST_COMPLETED, wait

        done, _ = wait(handles, return_when=FIRST_COMPLETED)
        results = []
        for handle in done:
            try:
                results.append((handle, handle.result()))
            except Exception as error:  # the attempt could not even start
                results.append((handle, AttemptResult(None, 0.0, error=f"{type(error).__name__}: {error}")))
        return results

    def close(self) -> None:
        self._pool.shutdown(wait=True)


class RayExecutor:
    """One Ray task per block attempt, each asking for ``cpus`` CPUs and ``gpus`` GPUs."""

    def __init__(self, address: Optional[str], num_cpus: Optional[int]) -> None:
        try:
            import ray
        except ImportError:
            raise TrainBlocksError(f"--executor ray needs Ray, which is not installed: {INSTALL_RAY}") from None
        import logging

        self._ray = ray
        try:
            if address is None:
                ray.init(address="local", num_cpus=num_cpus, include_dashboard=False, object_store_memory=128 << 20,
                         log_to_driver=False, logging_level=logging.WARNING)
            else:
                ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
        except Exception as error:
            where = "start a local Ray cluster" if address is None else f"connect to the Ray cluster at {address}"
            raise TrainBlocksError(f"could not {where}: {str(error).splitlines()[0] if str(error) else type(error).__name__}") from None
        resources = ray.cluster_resources()
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        self.total_cpus = int(resources.get("CPU", 0))
        self.total_gpus = float(resources.get("GPU", 0))
        self.node_cpus = max((int(n["Resources"].get("CPU", 0)) for n in nodes), default=self.total_cpus)
        kind = "local Ray cluster" if address is None else f"Ray cluster at {address}"
        self.description = f"{kind}: {len(nodes)} node(s), {self.total_cpus} CPUs, {self.total_gpus:g} GPUs"
        # Retries are this command's loop (a fresh folder per attempt), so Ray must not re-run a task.
        self._task = ray.remote(max_retries=0, retry_exceptions=False)(run_attempt)
        self.cpus, self.gpus = 1, 0.0
        self._started: Dict[object, float] = {}

    def configure(self, cpus: int, gpus: float) -> None:
        if cpus > self.node_cpus:
            raise TrainBlocksError(f"--cpus-per-block {cpus}: no node of the Ray cluster has that many CPUs (largest: {self.node_cpus})")
        if gpus > 0 and self.total_gpus < gpus:
            raise TrainBlocksError(f"--gpus-per-block {gpus:g}: the Ray cluster has {self.total_gpus:g} GPU(s)")
        self.cpus, self.gpus = cpus, gpus

    def submit(self, job: AttemptJob):
        ref = self._task.options(num_cpus=self.cpus, num_gpus=self.gpus, name=f"block{job.block}-attempt{job.attempt}").remote(job)
        self._started[ref] = time.time()
        return ref

    def wait(self, handles) -> List[Tuple[object, AttemptResult]]:
        ready, _ = self._ray.wait(list(handles), num_returns=1)
        results = []
        for ref in ready:
            started = self._started.pop(ref, time.time())
            try:
                results.append((ref, self._ray.get(ref)))
            except self._ray.exceptions.RayError as error:  # the worker died (killed, out of memory, node lost)
                message = next((line.strip() for line in str(error).splitlines() if line.strip()), type(error).__name__)
                results.append((ref, AttemptResult(None, time.time() - started, error=f"{type(error).__name__}: {message}")))
        return results

    def close(self) -> None:
        self._ray.shutdown()


# ------------------------------------------------------------------- folders and results


def find_block_run(attempt_dir: Path) -> Optional[Path]:
    """The ``scalar-nerf-block`` run folder an attempt wrote (``attempt/EXP/scalar-nerf-block/TS``)."""
    runs = sorted(p.parent for p in attempt_dir.glob("*/scalar-nerf-block/*/config.yml"))
    return runs[-1] if runs else None


def finished_run(attempt_dir: Path) -> Tuple[Optional[Path], str]:
    """(the attempt's run folder, "") when it holds its final checkpoint, else (None, why not)."""
    run = find_block_run(attempt_dir)
    if run is None:
        return None, "no run folder was written"
    config = load_run_config(run)
    final = (config.max_num_iterations if config.max_num_iterations > 0 else config.pipeline.block_steps) - 1
    step = latest_checkpoint_step(run / config.relative_model_dir)
    if step != final:
        return None, f"its newest checkpoint is step {step}, not the final step {final}"
    return run, ""


@dataclass
class BlockState:
    block: int
    folder: Path
    status: str = "pending"
    attempts: int = 0
    seconds: float = 0.0
    run: Optional[Path] = None
    failures: List[str] = field(default_factory=list)
    next_attempt: int = 1


def _attempt_numbers(block_dir: Path) -> List[int]:
    return [int(m.group(1)) for m in map(ATTEMPT_PATTERN.match, os.listdir(block_dir)) if m] if block_dir.is_dir() else []


def _set_aside(attempt_dir: Path, prefix: str) -> Path:
    target = attempt_dir.with_name(f"{prefix}-{attempt_dir.name}")
    os.replace(attempt_dir, target)
    return target


def read_done(block_dir: Path, global_checkpoint: Path) -> Tuple[Optional[dict], str]:
    """The block's recorded result, if it is still valid for the global run's checkpoint."""
    marker = block_dir / DONE_MARKER
    if not marker.is_file():
        return None, ""
    done = json.loads(marker.read_text())
    run = block_dir / done["run"]
    if not (run / "config.yml").is_file():
        marker.unlink()
        return None, f"its result {run} is gone"
    if done.get("global_checkpoint") != str(global_checkpoint):
        marker.unlink()
        attempt_dir = block_dir / Path(done["run"]).parts[0]
        if attempt_dir.is_dir():
            _set_aside(attempt_dir, "stale")
        return None, f"it was trained from {done.get('global_checkpoint')}, the global run's newest checkpoint is now {global_checkpoint}"
    return done, ""


def write_done(block_dir: Path, run: Path, attempt: int, seconds: float, global_checkpoint: Path) -> None:
    """Record ``run`` as the block's result, atomically (:func:`atomic_write_text`)."""
    payload = {"run": str(run.relative_to(block_dir)), "attempt": attempt, "seconds": round(seconds, 1),
               "global_checkpoint": str(global_checkpoint)}
    atomic_write_text(block_dir / DONE_MARKER, json.dumps(payload, indent=2) + "\n")


def prepare_blocks(out: Path, blocks: List[int], global_checkpoint: Path) -> Dict[int, BlockState]:
    """State of each block: skipped (has a valid result) or pending; set aside leftovers of a killed run."""
    states = {}
    for block in blocks:
        block_dir = out / f"block{block}"
        state = BlockState(block, block_dir)
        done, why = read_done(block_dir, global_checkpoint)
        if why:
            print(f"block {block}: training again: {why}")
        if done is not None:
            state.status, state.run = "skipped (done before)", block_dir / done["run"]
            state.seconds = float(done.get("seconds", 0.0))
        elif block_dir.is_dir():
            for leftover in sorted(block_dir.glob("attempt-*")):
                print(f"block {block}: {leftover.name} was left unfinished by an earlier run; set aside as interrupted-{leftover.name}")
                _set_aside(leftover, "interrupted")
        state.next_attempt = max(_attempt_numbers(block_dir), default=0) + 1
        states[block] = state
    return states


# --------------------------------------------------------------------------------- main


def _lock(out: Path):
    """Hold a lock on the output folder so that two commands never train into it at once."""
    import fcntl

    handle = open(out / LOCK_FILE, "w")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.close()
        raise TrainBlocksError(f"another {PROG} is using {out}; wait for it to end") from None
    return handle


def _format_table(states: Dict[int, BlockState]) -> str:
    rows = [("block", "status", "attempts", "seconds", "folder")]
    for state in states.values():
        folder = state.run if state.run is not None else state.folder
        rows.append((str(state.block), state.status, str(state.attempts), f"{state.seconds:.1f}", str(folder)))
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(row[:4], widths)) + "  " + row[4] for row in rows)


def _existing_assembly(assembled_root: Path, global_dir: Path, runs: Dict[int, Path]) -> Optional[Path]:
    wanted = {"global_run": str(global_dir), "blocks": {str(k): str(v) for k, v in sorted(runs.items())}}
    for record in sorted(assembled_root.glob("*/scalar-nerf/*/assembled_from.json"), reverse=True):
        if json.loads(record.read_text()) == wanted and latest_checkpoint_step(record.parent / "nerfstudio_models") is not None:
            return record.parent
    return None


def train_blocks(args: TrainBlocksArgs, extra: List[str]) -> int:
    """The command; returns its exit status."""
    if args.max_retries < 0:
        raise TrainBlocksError("--max-retries must be >= 0")
    if args.cpus_per_block is not None and args.cpus_per_block < 1:
        raise TrainBlocksError("--cpus-per-block must be >= 1")
    if args.gpus_per_block is not None and args.gpus_per_block < 0:
        raise TrainBlocksError("--gpus-per-block must be >= 0")
    for flag in ("--pipeline.block-steps", "--max-num-iterations"):
        if any(arg == flag or arg.startswith(flag + "=") for arg in extra):
            raise TrainBlocksError(f"set the steps per block with --block-steps, not {flag} after --")
    if args.executor == "local" and args.address is not None:
        raise TrainBlocksError("--address is for --executor ray")
    if args.executor == "ray":
        try:
            importlib.import_module("ray")  # checked before the (slower) check of the run
        except ImportError:
            raise TrainBlocksError(f"--executor ray needs Ray, which is not installed: {INSTALL_RAY}") from None
    global_run, blocks = check_global_run(args.global_run, args.blocks)
    global_dir = global_run.run_dir.resolve()
    out = (args.output_dir if args.output_dir is not None else global_dir.with_name(f"{global_dir.name}-blocks")).resolve()
    out.mkdir(parents=True, exist_ok=True)
    lock = _lock(out)
    try:
        return _train_and_assemble(args, extra, global_run, global_dir, blocks, out)
    finally:
        lock.close()


def _train_and_assemble(args: TrainBlocksArgs, extra: List[str], global_run: GlobalRun, global_dir: Path, blocks: List[int], out: Path) -> int:
    global_run.run_dir = global_dir
    states = prepare_blocks(out, blocks, global_run.global_checkpoint)
    todo = [b for b, s in states.items() if s.status == "pending"]
    if todo:
        _train(args, extra, global_run, states, todo)
    print(_format_table(states))
    failed = [s for s in states.values() if s.status == "failed"]
    if failed:
        for state in failed:
            print(f"block {state.block}: " + "; ".join(state.failures))
        names = ", ".join(str(s.block) for s in failed)
        print(f"{PROG}: block(s) {names} failed after {args.max_retries + 1} attempt(s); finished blocks are kept, "
              f"run the same command again to retry only the failed ones", file=sys.stderr)
        return 1
    if not args.assemble:
        return 0
    runs = {}
    for block_dir in sorted(out.glob("block*")):
        match = re.fullmatch(r"block(\d+)", block_dir.name)
        done, _ = read_done(block_dir, global_run.global_checkpoint) if match else (None, "")
        if done is not None:
            runs[int(match.group(1))] = (block_dir / done["run"]).resolve()
    assembled_root = out / "assembled"
    fused = _existing_assembly(assembled_root, global_dir, runs)
    if fused is not None:
        print(f"already assembled (blocks {', '.join(map(str, sorted(runs)))}): {fused}")
    else:
        from scalar_nerfstudio.scripts.assemble import AssembleError, assemble

        try:
            fused = assemble(global_dir, [runs[k] for k in sorted(runs)], assembled_root)
        except AssembleError as error:
            raise TrainBlocksError(f"assemble: {error}") from None
        print(f"assembled run (global model + blocks {', '.join(map(str, sorted(runs)))}): {fused}")
    config = fused / "config.yml"
    print(f"config: {config}\n  ns-eval --load-config {config} --output-path eval.json\n  ns-viewer --load-config {config}")
    return 0


def _train(args: TrainBlocksArgs, extra: List[str], global_run: GlobalRun, states: Dict[int, BlockState], todo: List[int]) -> None:
    local_cpus = args.num_cpus or len(os.sched_getaffinity(0))
    if args.executor == "ray":
        executor = RayExecutor(args.address, local_cpus if args.address is None else None)
        total_cpus, node_cpus, has_gpus = executor.total_cpus, executor.node_cpus, executor.total_gpus > 0
    else:
        import torch

        total_cpus, node_cpus, has_gpus = local_cpus, local_cpus, torch.cuda.is_available()
        executor = None
    try:
        cpus = args.cpus_per_block or default_cpus_per_block(total_cpus, len(todo), node_cpus)
        gpus = args.gpus_per_block if args.gpus_per_block is not None else (1.0 if has_gpus else 0.0)
        if executor is None:
            if cpus > local_cpus:
                raise TrainBlocksError(f"--cpus-per-block {cpus}: this machine has {local_cpus} CPUs")
            executor = LocalExecutor(local_cpus, cpus, gpus)
        else:
            executor.configure(cpus, gpus)
        print(f"{PROG}: {len(todo)} block(s) of {global_run.run_dir} on the {executor.description}; "
              f"{cpus} CPU(s) and {gpus:g} GPU(s) per block, up to {args.max_retries} retries")
        inflight: Dict[object, Tuple[BlockState, Path]] = {}

        def submit(state: BlockState) -> None:
            attempt = state.next_attempt
            state.next_attempt += 1
            state.attempts += 1
            state.status = "running"
            attempt_dir = state.folder / f"attempt-{attempt}"
            attempt_dir.mkdir(parents=True)
            job = AttemptJob(state.block, attempt, str(attempt_dir),
                             block_command(global_run, state.block, attempt_dir, gpus, args.block_steps, extra),
                             thread_env(cpus, gpus))
            inflight[executor.submit(job)] = (state, attempt_dir)
            print(f"block {state.block}: attempt {state.attempts} of {args.max_retries + 1} in {attempt_dir}", flush=True)

        for block in todo:
            submit(states[block])
        while inflight:
            for handle, result in executor.wait(list(inflight)):
                state, attempt_dir = inflight.pop(handle)
                state.seconds += result.seconds
                run, why = (None, result.error or f"ns-train exited with {result.returncode}")
                if result.returncode == 0:
                    run, why = finished_run(attempt_dir)
                if run is not None:
                    attempt = int(ATTEMPT_PATTERN.match(attempt_dir.name).group(1))
                    write_done(state.folder, run, attempt, result.seconds, global_run.global_checkpoint)
                    state.status, state.run = "done", run
                    print(f"block {state.block}: done in {result.seconds:.1f} s ({run})", flush=True)
                    continue
                why = why.rstrip(".")
                failed_dir = _set_aside(attempt_dir, "failed")
                state.failures.append(f"attempt {state.attempts}: {why} (log: {failed_dir / 'train.log'})")
                print(f"block {state.block}: attempt {state.attempts} failed: {why}; kept apart in {failed_dir}", flush=True)
                if state.attempts <= args.max_retries:
                    submit(state)
                else:
                    state.status = "failed"
    finally:
        if executor is not None:
            executor.close()


def split_passthrough(argv: List[str]) -> Tuple[List[str], List[str]]:
    """(this command's arguments, the ns-train arguments after ``--``)."""
    if "--" in argv:
        at = argv.index("--")
        return argv[:at], argv[at + 1:]
    return argv, []


def main(argv: Optional[List[str]] = None) -> int:
    own, extra = split_passthrough(list(sys.argv[1:] if argv is None else argv))
    args = tyro.cli(TrainBlocksArgs, args=own, prog=PROG)
    try:
        return train_blocks(args, extra)
    except TrainBlocksError as error:
        print(f"{PROG}: {error}", file=sys.stderr)
        return 2


def entrypoint() -> None:
    """Console script ``scalar-nerf-train-blocks``."""
    sys.exit(main())


if __name__ == "__main__":
    # Run through the package's module, so that Ray workers import run_attempt from it by name.
    from scalar_nerfstudio.scripts.train_blocks import entrypoint as _entrypoint

    _entrypoint()
