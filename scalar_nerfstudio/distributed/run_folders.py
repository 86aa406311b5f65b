"""The folders of ``scalar-nerf-train-blocks``: the global run it starts from, and its output folder.

Layout of the output folder ``OUT`` (by default ``RUN-blocks`` beside the global run)::

    OUT/.train-blocks.lock           held while a command uses OUT
    OUT/block{K}/attempt-{n}/        an attempt in progress: train.log and the ns-train run folder
    OUT/block{K}/failed-attempt-{n}/ an attempt that failed (also interrupted-, stale-): never used
    OUT/block{K}/DONE.json           the block's result: the run of the attempt that finished
    OUT/assembled/...                the assembled scalar-nerf run(s)

Only an attempt that exited with 0 *and* wrote its final checkpoint is recorded as the block's result.
What a run folder holds (config.yml, checkpoints, blocks.json) is read through ``scalar_nerfstudio.runs``.
"""

from __future__ import annotations

import copy
import json
import os
import re
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Dict, Iterator, List, Optional, Tuple

from scalar_nerfstudio.atomic_io import atomic_write_text
from scalar_nerfstudio.distributed import TrainBlocksError
from scalar_nerfstudio.runs import (
    ASSEMBLED_FROM_NAME,
    CONFIG_NAME,
    RunError,
    blocks_json_path,
    latest_checkpoint_step,
    load_run_config,
    run_config_path,
)

if TYPE_CHECKING:
    from scalar_nerfstudio.engine.block_trainer import ScalarBlockTrainerConfig

DONE_MARKER = "DONE.json"
LOCK_FILE = ".train-blocks.lock"
ATTEMPT_PATTERN = re.compile(r"^(?:failed-|interrupted-|stale-)?attempt-(\d+)$")
BLOCK_FOLDER_PATTERN = re.compile(r"block(\d+)")
#: Written by ``scalar-nerf-assemble`` into the run it makes: the global run and the block runs it took.


# ------------------------------------------------------------------------------ the global run


@dataclass
class GlobalRun:
    """What the command needs to know about a checked global run."""

    run_dir: Path
    num_blocks: int
    global_checkpoint: Path
    block_steps: Optional[int]


def check_global_run(run: Path, blocks: Optional[Tuple[int, ...]], *, block_method: "ScalarBlockTrainerConfig") -> Tuple[GlobalRun, List[int]]:
    """Check ``run`` as ``ns-train scalar-nerf-block`` does; returns it and the blocks to train.

    ``block_method`` is the ``scalar-nerf-block`` method's config (copied here, never changed).
    """
    from scalar_nerfstudio.blocks.split import load_blocks_json

    config = copy.deepcopy(block_method)
    config.global_run = Path(run)
    config.block = 0
    try:
        config.adopt_global_run()
    except RunError as error:
        raise TrainBlocksError(str(error)) from None
    pipeline = config.scalar_pipeline
    assert pipeline.blocks_json is not None and pipeline.global_checkpoint is not None  # both set by adopt_global_run
    blocks_json = Path(pipeline.blocks_json)
    num_blocks = load_blocks_json(blocks_json)[0].num_blocks
    chosen = list(range(num_blocks)) if blocks is None else list(dict.fromkeys(blocks))
    bad = [b for b in chosen if not 0 <= b < num_blocks]
    if bad:
        raise TrainBlocksError(f"block {bad[0]} does not exist; {blocks_json} has blocks 0..{num_blocks - 1}")
    if not chosen:
        raise TrainBlocksError("--blocks: no block given")
    # adopt_global_run took the run's block steps, decoder mode and ray batch (all left at defaults here).
    return GlobalRun(blocks_json.parent, num_blocks, Path(pipeline.global_checkpoint), pipeline.block_steps), chosen


def default_output_dir(global_dir: Path) -> Path:
    """``RUN-blocks`` beside the global run."""
    return global_dir.with_name(f"{global_dir.name}-blocks")


# ---------------------------------------------------------------------------- attempt folders


def find_block_run(attempt_dir: Path) -> Optional[Path]:
    """The ``scalar-nerf-block`` run folder an attempt wrote (``attempt/EXP/scalar-nerf-block/TS``)."""
    runs = sorted(p.parent for p in attempt_dir.glob(f"*/scalar-nerf-block/*/{CONFIG_NAME}"))
    return runs[-1] if runs else None


def _planned_steps(run: Path, config: Any) -> int:
    """The steps a ``scalar-nerf-block`` run trains: ``--max-num-iterations`` when given, else its block's
    steps as its blocks.json planned them (a run from before plans recorded them: its config.yml's)."""
    from scalar_nerfstudio.blocks.plan import load_plan  # numpy and scikit-learn
    from scalar_nerfstudio.blocks.split import BlockSplitError

    if config.max_num_iterations > 0:
        return int(config.max_num_iterations)
    try:
        length = load_plan(blocks_json_path(run)).length
    except BlockSplitError:
        length = None
    return int(length.block_steps if length is not None else config.pipeline.block_steps)


def finished_run(attempt_dir: Path) -> Tuple[Optional[Path], str]:
    """(the attempt's run folder, "") when it holds its final checkpoint, else (None, why not)."""
    run = find_block_run(attempt_dir)
    if run is None:
        return None, "no run folder was written"
    config = load_run_config(run)
    final = _planned_steps(run, config) - 1
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


def attempt_number(attempt_dir: Path) -> int:
    """``n`` of an ``attempt-n`` folder (or a set-aside one)."""
    match = ATTEMPT_PATTERN.match(attempt_dir.name)
    if match is None:
        raise ValueError(f"{attempt_dir} is not an attempt folder (attempt-N)")
    return int(match.group(1))


def _attempt_numbers(block_dir: Path) -> List[int]:
    return [int(m.group(1)) for m in map(ATTEMPT_PATTERN.match, os.listdir(block_dir)) if m] if block_dir.is_dir() else []


def set_aside(attempt_dir: Path, prefix: str) -> Path:
    """Rename ``attempt-n`` to ``{prefix}-attempt-n`` (never used again); returns the new path."""
    target = attempt_dir.with_name(f"{prefix}-{attempt_dir.name}")
    os.replace(attempt_dir, target)
    return target


def new_attempt(state: BlockState) -> Path:
    """Create the block's next attempt folder (a fresh one for every attempt) and count the attempt."""
    attempt_dir = state.folder / f"attempt-{state.next_attempt}"
    attempt_dir.mkdir(parents=True)
    state.next_attempt += 1
    state.attempts += 1
    return attempt_dir


# ------------------------------------------------------------------------------------ results


def read_done(block_dir: Path, global_checkpoint: Path) -> Tuple[Optional[dict], str]:
    """The block's recorded result, if it is still valid for the global run's checkpoint."""
    marker = block_dir / DONE_MARKER
    if not marker.is_file():
        return None, ""
    done = json.loads(marker.read_text())
    run = block_dir / done["run"]
    if not run_config_path(run).is_file():
        marker.unlink()
        return None, f"its result {run} is gone"
    if done.get("global_checkpoint") != str(global_checkpoint):
        marker.unlink()
        attempt_dir = block_dir / Path(done["run"]).parts[0]
        if attempt_dir.is_dir():
            set_aside(attempt_dir, "stale")
        return None, f"it was trained from {done.get('global_checkpoint')}, the global run's newest checkpoint is now {global_checkpoint}"
    return done, ""


def write_done(block_dir: Path, run: Path, *, attempt: int, seconds: float, global_checkpoint: Path) -> None:
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
                set_aside(leftover, "interrupted")
        state.next_attempt = max(_attempt_numbers(block_dir), default=0) + 1
        states[block] = state
    return states


def done_runs(out: Path, global_checkpoint: Path) -> Dict[int, Path]:
    """{block: its recorded run (absolute)} for every block folder of ``out`` with a valid result."""
    runs = {}
    for block_dir in sorted(out.glob("block*")):
        match = BLOCK_FOLDER_PATTERN.fullmatch(block_dir.name)
        done, _ = read_done(block_dir, global_checkpoint) if match else (None, "")
        if match is not None and done is not None:
            runs[int(match.group(1))] = (block_dir / done["run"]).resolve()
    return runs


def existing_assembly(assembled_root: Path, global_dir: Path, runs: Dict[int, Path]) -> Optional[Path]:
    """An assembled run under ``assembled_root`` made from exactly this global run and these block runs."""
    wanted = {"global_run": str(global_dir), "blocks": {str(k): str(v) for k, v in sorted(runs.items())}}
    for record in sorted(assembled_root.glob(f"*/scalar-nerf/*/{ASSEMBLED_FROM_NAME}"), reverse=True):
        if json.loads(record.read_text()) != wanted:
            continue
        try:
            checkpoint_dir = record.parent / load_run_config(record.parent).relative_model_dir
        except RunError:
            continue
        if latest_checkpoint_step(checkpoint_dir) is not None:
            return record.parent
    return None


# --------------------------------------------------------------------------------------- lock


@contextmanager
def locked_output(out: Path, holder: str) -> Iterator[None]:
    """Hold a lock on the output folder so that two commands never train into it at once."""
    import fcntl

    handle = open(out / LOCK_FILE, "w")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.close()
        raise TrainBlocksError(f"another {holder} is using {out}; wait for it to end") from None
    try:
        yield
    finally:
        handle.close()
