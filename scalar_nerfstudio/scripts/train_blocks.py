"""``scalar-nerf-train-blocks``: train every block of a trained global run in parallel, then fuse them.

Once the global model exists the blocks are independent (paper Sec. 3.3). This command runs one
``ns-train scalar-nerf-block --global-run RUN --block K`` process per block, several at once:

- ``--executor local``: a pool of subprocesses on this machine (no Ray needed);
- ``--executor ray``: one Ray task per block with its CPU/GPU request, on a local Ray cluster
  started for the command, or on an existing (multi-machine) cluster given by ``--address``.

Every attempt trains into a fresh folder ``OUT/block{K}/attempt-{n}``. Only an attempt that exited
with 0 *and* wrote its final checkpoint is recorded as the block's result (``OUT/block{K}/DONE.json``);
a failed one is renamed ``failed-attempt-{n}`` and never used. A re-run skips blocks that have a
result. When every block has one, the blocks are assembled with the global model into a new
``scalar-nerf`` run that ``ns-eval`` / ``ns-render`` / ``ns-viewer`` fuse.

This module is the command line only: the executors, the folders and the scheduling loop are in
``scalar_nerfstudio/distributed/``.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Dict, List, Literal, Optional, Tuple

import tyro

from scalar_nerfstudio.distributed import COMMAND, TrainBlocksError
from scalar_nerfstudio.distributed.executors import local_gpu_count, local_gpu_slots, require_ray
from scalar_nerfstudio.distributed.run_folders import (
    BlockState,
    check_global_run,
    default_output_dir,
    done_runs,
    existing_assembly,
    locked_output,
    prepare_blocks,
)
from scalar_nerfstudio.distributed.scheduling import Resources, train_pending
from scalar_nerfstudio.runs import run_config_path

PROG = COMMAND


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
    """GPUs per block; a share 1/n (0.5, 0.25, ...) trains n blocks on each GPU at once. Default: 0 without
    a GPU; with GPUs, local spreads the blocks over them (up to 8 per GPU, 2 GiB each), Ray gives each 1."""
    max_retries: int = 2
    """Attempts after the first for a block that fails (each in a fresh folder)."""
    output_dir: Optional[Path] = None
    """Where attempts and the assembled run go (default: RUN-blocks beside the global run)."""
    block_steps: Optional[int] = None
    """Steps per block (default: the global run's --pipeline.block-steps)."""
    assemble: bool = True
    """Assemble the fused run once every block has a result."""

    def resources(self) -> Resources:
        return Resources(self.executor, self.address, self.num_cpus, self.cpus_per_block, self.gpus_per_block)


def check_args(args: TrainBlocksArgs, extra: List[str]) -> None:
    """The checks that need no run folder (before the slower check of the run)."""
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
    if args.executor == "local" and args.gpus_per_block:
        local_gpu_slots(args.gpus_per_block, local_gpu_count())  # a share that is not 1/n, or GPUs this machine lacks
    if args.executor == "ray":
        require_ray()


def train_blocks(args: TrainBlocksArgs, extra: List[str]) -> int:
    """The command; returns its exit status."""
    check_args(args, extra)
    from scalar_nerfstudio.engine.block_trainer import ScalarBlockTrainerConfig
    from scalar_nerfstudio.method_configs import (
        scalar_nerf_block,  # the whole method: imported once the options are read
    )

    block_method = scalar_nerf_block.config
    if not isinstance(block_method, ScalarBlockTrainerConfig):
        raise TypeError(f"scalar-nerf-block's config is {type(block_method).__name__}, not a ScalarBlockTrainerConfig")
    global_run, blocks = check_global_run(args.global_run, args.blocks, block_method=block_method)
    global_dir = global_run.run_dir = global_run.run_dir.resolve()
    out = (args.output_dir if args.output_dir is not None else default_output_dir(global_dir)).resolve()
    out.mkdir(parents=True, exist_ok=True)
    with locked_output(out, PROG):
        states = prepare_blocks(out, blocks, global_run.global_checkpoint)
        todo = [b for b, s in states.items() if s.status == "pending"]
        if todo:
            train_pending(args.resources(), global_run, states=states, todo=todo, max_retries=args.max_retries,
                          block_steps=args.block_steps, extra=extra)
        print(format_table(states))
        failed = [s for s in states.values() if s.status == "failed"]
        if failed:
            for state in failed:
                print(f"block {state.block}: " + "; ".join(state.failures))
            names = ", ".join(str(s.block) for s in failed)
            print(f"{PROG}: block(s) {names} failed after {args.max_retries + 1} attempt(s); finished blocks are kept, "
                  f"run the same command again to retry only the failed ones", file=sys.stderr)
            return 1
        if args.assemble:
            assemble_blocks(global_dir, done_runs(out, global_run.global_checkpoint), out / "assembled")
    return 0


def assemble_blocks(global_dir: Path, runs: Dict[int, Path], assembled_root: Path) -> Path:
    """The assembled run of the global model and ``runs`` (made once: an identical one is reused)."""
    names = ", ".join(map(str, sorted(runs)))
    fused = existing_assembly(assembled_root, global_dir, runs)
    if fused is not None:
        print(f"already assembled (blocks {names}): {fused}")
    else:
        from scalar_nerfstudio.assembly import AssembleError, assemble  # torch and the model: only when assembling

        try:
            fused = assemble(global_dir, [runs[k] for k in sorted(runs)], assembled_root)
        except AssembleError as error:
            raise TrainBlocksError(f"assemble: {error}") from None
        print(f"assembled run (global model + blocks {names}): {fused}")
    config = run_config_path(fused)
    print(f"config: {config}\n  ns-eval --load-config {config} --output-path eval.json\n  ns-viewer --load-config {config}")
    return fused


def format_table(states: Dict[int, BlockState]) -> str:
    rows = [("block", "status", "attempts", "seconds", "folder")]
    for state in states.values():
        folder = state.run if state.run is not None else state.folder
        rows.append((str(state.block), state.status, str(state.attempts), f"{state.seconds:.1f}", str(folder)))
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(row[:4], widths)) + "  " + row[4] for row in rows)


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
        return 1


def entrypoint() -> None:
    """Console script ``scalar-nerf-train-blocks``."""
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
