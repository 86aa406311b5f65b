"""Scheduling the block attempts: CPUs and GPUs per block, each attempt's command, retries.

Every attempt trains into a fresh folder (``run_folders.new_attempt``). A failed attempt is set aside
and, while the block has retries left, the block is submitted again; retries are this loop's own
(Ray's task retries are off), so that every retry gets a fresh folder.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Union

from scalar_nerfstudio.distributed import COMMAND, TrainBlocksError
from scalar_nerfstudio.distributed.executors import (
    LOG_NAME,
    AttemptJob,
    LocalExecutor,
    RayExecutor,
    local_gpu_memory_bytes,
    thread_env,
)
from scalar_nerfstudio.distributed.run_folders import (
    BlockState,
    GlobalRun,
    attempt_number,
    finished_run,
    new_attempt,
    set_aside,
    write_done,
)

Executor = Union[LocalExecutor, RayExecutor]


MAX_BLOCKS_PER_GPU = 8
"""The most blocks ``--executor local`` trains on one GPU at once by default."""
GPU_BYTES_PER_SHARED_BLOCK = 2 * 1024**3
"""GPU memory counted per block when blocks share a GPU by default (bytes): more than a block of the
3 x 3 town (4096 rays per step) used with 8 sharing one GPU."""


def default_local_gpus_per_block(gpu_memory_bytes: List[int], num_blocks: int) -> float:
    """GPUs per block when ``--gpus-per-block`` is not given and ``--executor local`` runs on GPUs
    of ``gpu_memory_bytes`` (each one's total): the blocks spread over them, up to
    :data:`MAX_BLOCKS_PER_GPU` sharing one and no more than the smallest GPU holds at
    :data:`GPU_BYTES_PER_SHARED_BLOCK` each (a share 1/n); 0 (the CPU) without a GPU.

    One block process keeps a GPU far from busy, so blocks sharing one finish well before the same
    blocks trained one after another.
    """
    if not gpu_memory_bytes:
        return 0.0
    fits = max(1, min(gpu_memory_bytes) // GPU_BYTES_PER_SHARED_BLOCK)
    per_gpu = min(MAX_BLOCKS_PER_GPU, fits, max(1, -(-num_blocks // len(gpu_memory_bytes))))
    return 1.0 / per_gpu


def default_cpus_per_block(total_cpus: int, num_blocks: int, node_cpus: Optional[int] = None) -> int:
    """The CPUs shared evenly among the blocks (at most one node's), at least 1."""
    share = max(1, total_cpus // max(num_blocks, 1))
    return max(1, min(share, node_cpus or share))


def block_command(global_run: GlobalRun, block: int, *, attempt_dir: Path, gpus: float, block_steps: Optional[int],
                  extra: List[str]) -> List[str]:
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


@dataclass
class Resources:
    """What to run the attempts on, as the command was asked (None: decide)."""

    executor: str = "local"
    """local or ray."""
    address: Optional[str] = None
    num_cpus: Optional[int] = None
    cpus_per_block: Optional[int] = None
    gpus_per_block: Optional[float] = None


def start_executor(resources: Resources, num_blocks: int) -> Tuple[Executor, int, float]:
    """The executor for ``num_blocks`` blocks, and the CPUs and GPUs each block gets."""
    local_cpus = resources.num_cpus or len(os.sched_getaffinity(0))
    executor: Optional[Executor] = None
    try:
        if resources.executor == "ray":
            executor = RayExecutor(resources.address, local_cpus if resources.address is None else None)
            cpus = resources.cpus_per_block or default_cpus_per_block(executor.total_cpus, num_blocks, executor.node_cpus)
            gpus = resources.gpus_per_block if resources.gpus_per_block is not None else (1.0 if executor.total_gpus > 0 else 0.0)
            executor.configure(cpus, gpus)
        else:
            gpu_memory = local_gpu_memory_bytes()
            cpus = resources.cpus_per_block or default_cpus_per_block(local_cpus, num_blocks, local_cpus)
            gpus = resources.gpus_per_block if resources.gpus_per_block is not None else default_local_gpus_per_block(gpu_memory, num_blocks)
            if cpus > local_cpus:
                raise TrainBlocksError(f"--cpus-per-block {cpus}: this machine has {local_cpus} CPUs")
            executor = LocalExecutor(local_cpus, cpus, gpus, gpu_count=len(gpu_memory))
    except BaseException:
        if executor is not None:
            executor.close()
        raise
    return executor, cpus, gpus


def train_pending(resources: Resources, global_run: GlobalRun, *, states: Dict[int, BlockState], todo: List[int],
                  max_retries: int, block_steps: Optional[int], extra: List[str]) -> None:
    """Train the blocks ``todo`` (each with up to ``max_retries`` retries); ``states`` says how each ended."""
    executor, cpus, gpus = start_executor(resources, len(todo))
    try:
        print(f"{COMMAND}: {len(todo)} block(s) of {global_run.run_dir} on the {executor.description}; "
              f"{cpus} CPU(s) and {gpus:g} GPU(s) per block, up to {max_retries} retries")
        inflight: Dict[object, Tuple[BlockState, Path]] = {}

        def submit(state: BlockState) -> None:
            attempt_dir = new_attempt(state)
            state.status = "running"
            job = AttemptJob(state.block, attempt_number(attempt_dir), str(attempt_dir),
                             block_command(global_run, state.block, attempt_dir=attempt_dir, gpus=gpus, block_steps=block_steps,
                                           extra=extra),
                             thread_env(cpus, gpus), cwd=os.getcwd())
            inflight[executor.submit(job)] = (state, attempt_dir)
            print(f"block {state.block}: attempt {state.attempts} of {max_retries + 1} in {attempt_dir}", flush=True)

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
                    write_done(state.folder, run, attempt=attempt_number(attempt_dir), seconds=result.seconds,
                               global_checkpoint=global_run.global_checkpoint)
                    state.status, state.run = "done", run
                    where = f" on Ray node {result.node[:12]}" if result.node else ""
                    print(f"block {state.block}: done in {result.seconds:.1f} s{where} ({run})", flush=True)
                    continue
                why = why.rstrip(".")
                failed_dir = set_aside(attempt_dir, "failed")
                state.failures.append(f"attempt {state.attempts}: {why} (log: {failed_dir / LOG_NAME})")
                where = f" (Ray node {result.node[:12]})" if result.node else ""
                print(f"block {state.block}: attempt {state.attempts} failed{where}: {why}; kept apart in {failed_dir}", flush=True)
                if state.attempts <= max_retries:
                    submit(state)
                else:
                    state.status = "failed"
    finally:
        executor.close()
