"""Running block attempts: a pool of subprocesses on this machine, or one Ray task per attempt.

An attempt is one ``ns-train scalar-nerf-block ...`` process with its log in its attempt folder
(:func:`run_attempt`). Both executors have the same three methods: ``submit(job)`` returns a handle,
``wait(handles)`` returns ``(handle, AttemptResult)`` for at least one finished attempt, ``close()``.

This module's top level imports only the standard library, so a Ray worker that runs an attempt does
not import torch or nerfstudio itself (its ``ns-train`` subprocess does).
"""

from __future__ import annotations

import importlib
import os
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from scalar_nerfstudio.distributed import TrainBlocksError

THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")
INSTALL_RAY = "pip install 'scalar-nerfstudio[distributed]'"
LOG_NAME = "train.log"


@dataclass
class AttemptJob:
    block: int
    attempt: int
    folder: str
    """The attempt folder (absolute; on a filesystem the worker shares)."""
    args: List[str]
    env: Dict[str, str]
    cwd: str = ""
    """The directory the block process starts in: the one ``scalar-nerf-train-blocks`` was started in,
    so that the relative paths in the global run's config (``--data scene/``) mean what they meant
    there. Where it is not a directory (another host), the attempt folder."""


@dataclass
class AttemptResult:
    returncode: Optional[int]
    """The ns-train process's exit status (negative: killed by that signal); None if it never ended."""
    seconds: float
    error: str = ""
    host: str = ""
    node: str = ""
    """The Ray node id of the worker that ran it (hex); "" outside Ray."""


def thread_env(cpus: int, gpus: float, set_devices: Optional[str] = None) -> Dict[str, str]:
    """Environment of one block process: ``cpus`` threads for OpenMP/MKL/BLAS (torch follows OMP)."""
    env = {name: str(cpus) for name in THREAD_VARIABLES}
    if gpus <= 0:
        env["CUDA_VISIBLE_DEVICES"] = ""  # train on the CPU even on a GPU node
    elif set_devices is not None:
        env["CUDA_VISIBLE_DEVICES"] = set_devices
    return env


def _die_with_parent() -> None:  # pragma: no cover - runs in the forked child
    """In the block process: be killed when the process that started it dies (Linux)."""
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except Exception:
        pass


def ray_node_id() -> str:
    """The id (hex) of the Ray node this process runs on when it is a Ray worker, else "".

    Several Ray nodes can share one host (and its hostname), so the node id says where an attempt ran.
    """
    ray = sys.modules.get("ray")  # never imported here: outside a Ray worker, Ray is not used
    if ray is None or not ray.is_initialized():
        return ""
    try:
        return str(ray.get_runtime_context().get_node_id())
    except Exception:
        return ""


def run_attempt(job: AttemptJob) -> AttemptResult:
    """Run one block attempt: ``ns-train scalar-nerf-block ...`` with its log in the attempt folder.

    This is the body of a Ray task, so it uses the interpreter and environment of the worker it runs
    on; the block process is killed if the worker dies.
    """
    import socket

    folder = Path(job.folder)
    command = [sys.executable, "-m", "nerfstudio.scripts.train", *job.args]
    start = time.time()
    host, node = socket.gethostname(), ray_node_id()
    with open(folder / LOG_NAME, "w") as log:
        overrides = " ".join(f"{k}={shlex.quote(v)}" for k, v in sorted(job.env.items()))
        where = f"host {host}, Ray node {node}" if node else f"host {host}"
        log.write(f"# {where}, attempt {job.attempt} of block {job.block}\n# {overrides} {shlex.join(command)}\n")
        log.flush()
        cwd = job.cwd if job.cwd and os.path.isdir(job.cwd) else folder
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, cwd=cwd,
                                   env={**os.environ, **job.env}, preexec_fn=_die_with_parent)  # noqa: PLW1509 (prctl only, before exec)
        returncode = process.wait()
    return AttemptResult(returncode, time.time() - start, host=host, node=node)


def require_ray() -> None:
    """Raise :class:`TrainBlocksError` (how to install it) when Ray cannot be imported."""
    try:
        importlib.import_module("ray")
    except ImportError:
        raise TrainBlocksError(f"--executor ray needs Ray, which is not installed: {INSTALL_RAY}") from None


def local_gpu_count() -> int:
    """How many CUDA GPUs this machine has (imports torch: only the command's own process asks)."""
    import torch

    return torch.cuda.device_count() if torch.cuda.is_available() else 0


def local_gpu_memory_bytes() -> List[int]:
    """Each CUDA GPU's total memory in bytes, from its device properties."""
    import torch

    return [int(torch.cuda.get_device_properties(i).total_memory) for i in range(local_gpu_count())]


def local_gpu_slots(gpus: float, gpu_count: int) -> List[str]:
    """The ``CUDA_VISIBLE_DEVICES`` of each block slot on a machine with ``gpu_count`` GPUs when each
    block gets ``gpus`` of them: whole GPUs (``gpus`` >= 1, a whole number) or a share of one
    (``gpus`` = 1/n: n blocks train on each GPU at once, as Ray's fractional GPUs do).

    One block process rarely keeps a GPU busy (its steps wait on kernel launches), so sharing lets
    the blocks of a one-GPU machine train at once instead of one after another.
    """
    if gpus <= 0:
        return []
    if gpus >= 1:
        if gpus != int(gpus):
            raise TrainBlocksError(f"--gpus-per-block {gpus:g}: give a whole number of GPUs, or a share 1/n of one (0.5, 0.25, ...)")
        if gpu_count < gpus:
            raise TrainBlocksError(f"--gpus-per-block {gpus:g}: this machine has {gpu_count} GPU(s)")
        per_block = int(gpus)
        return [",".join(str(i) for i in range(s * per_block, (s + 1) * per_block)) for s in range(gpu_count // per_block)]
    blocks_per_gpu = round(1.0 / gpus)
    if abs(blocks_per_gpu * gpus - 1.0) > 1e-6:
        raise TrainBlocksError(f"--gpus-per-block {gpus:g}: a share of a GPU must be 1/n (0.5, 0.25, 0.125, ...) with --executor local")
    if gpu_count < 1:
        raise TrainBlocksError(f"--gpus-per-block {gpus:g}: this machine has no GPU")
    return [str(i) for _ in range(blocks_per_gpu) for i in range(gpu_count)]


class LocalExecutor:
    """A pool of block subprocesses on this machine: ``num_cpus // cpus`` at a time, and no more than
    the GPUs allow (``gpus`` per block, a share 1/n of one lets n blocks train on each GPU at once)."""

    def __init__(self, num_cpus: int, cpus: int, gpus: float, *, gpu_count: Optional[int] = None) -> None:
        import queue
        from concurrent.futures import ThreadPoolExecutor

        slots = max(1, num_cpus // cpus)
        devices: List[str] = []
        if gpus > 0:
            if gpu_count is None:
                gpu_count = local_gpu_count()
            devices = local_gpu_slots(gpus, gpu_count)
            slots = min(slots, len(devices))
        self.slots = slots
        self.devices: List[Optional[str]] = list(devices[:slots]) if devices else [None] * slots
        """Each slot's ``CUDA_VISIBLE_DEVICES`` (None: left as it is, CPU blocks)."""
        self._free: "queue.Queue[Optional[str]]" = queue.Queue()
        for device in self.devices:
            self._free.put(device)
        self._pool = ThreadPoolExecutor(max_workers=slots)
        shared = f", {round(1 / gpus)} blocks per GPU" if 0 < gpus < 1 else ""
        self.description = f"local pool of {slots} at a time{shared}"

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
        require_ray()
        import logging

        import ray
        import ray.exceptions  # imported by ray itself; named here so that the type checker knows self._ray.exceptions

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
        # Retries are the scheduler's loop (a fresh folder per attempt), so Ray must not re-run a task.
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
