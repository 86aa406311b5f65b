"""How long a run trains: its steps from the capture, or from a wall-clock budget and the measured pace.

A run trains ``G`` steps of the global model, then ``B`` steps for each of its blocks. Unless the
user gives them (``--pipeline.global-steps``, ``--pipeline.block-steps``), they are planned here:

* **from the capture** (the default): every training pixel should be drawn about ``rays_per_pixel``
  times by the global phase, and every pixel of a block's images about ``block_rays_per_pixel``
  times by that block's phase, so that a capture of 10 photos and one of 10,000 are not given the
  same steps: ``G = ceil(rays_per_pixel * P / R)`` for ``P`` training pixels and ``R`` rays per
  step, within ``[min_global_steps, max_steps]``; ``B`` likewise from the mean pixels of a block's
  images, within ``[min_block_steps, max_steps]``;
* **from a time budget** (``--pipeline.time-budget 1h``): the capture's plan scaled so that the
  run's critical path (``G``, then the blocks in ``ceil(n / workers)`` waves of ``B``) fits the
  budget at the pace the run measures in its first steps. The plan is provisional until then; the
  blocks' steps are planned once more when the global phase ends, from the time that is left, and on
  one machine again in each block, at the pace of the blocks so far (blocks differ in cost).

Pure Python: no torch or nerfstudio import, so it is tested on its own.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from typing import Any, Dict, Literal, Optional, Sequence, Tuple

__all__ = [
    "LengthError", "LengthSettings", "LengthSource", "TrainingLength", "blocks_from_remaining_time", "format_duration",
    "length_from_budget", "length_from_capture", "length_from_json", "length_to_json", "parse_duration", "plan_length",
]

LengthSource = Literal["given", "capture", "budget"]

_UNITS = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}
_DURATION = re.compile(r"(\d+(?:\.\d*)?|\.\d+)\s*([smhd])", re.IGNORECASE)


class LengthError(ValueError):
    """A training length that cannot be planned (a malformed budget, a budget beside given steps)."""


def parse_duration(text: str) -> float:
    """Seconds of a duration written like ``90s``, ``45m``, ``2h``, ``1h30m``, ``1.5h`` or ``3600`` (seconds).

    Raises:
        LengthError: ``text`` is not such a duration, or it is not positive.
    """
    cleaned = str(text).strip().lower().replace(" ", "")
    seconds: Optional[float] = None
    if re.fullmatch(r"\d+(?:\.\d*)?|\.\d+", cleaned):
        seconds = float(cleaned)
    elif cleaned and _DURATION.sub("", cleaned) == "":
        seconds = sum(float(value) * _UNITS[unit] for value, unit in _DURATION.findall(cleaned))
    if seconds is None or not math.isfinite(seconds):
        raise LengthError(f"{text!r} is not a duration: write it like 90s, 45m, 2h or 1h30m")
    if seconds <= 0:
        raise LengthError(f"{text!r}: a time budget must be longer than 0 s")
    return seconds


def format_duration(seconds: float) -> str:
    """``seconds`` for a log line: ``45 s``, ``12 min 05 s``, ``3 h 20 min``."""
    seconds = max(float(seconds), 0.0)
    if not math.isfinite(seconds):
        return "unknown"
    if seconds < 60:
        return f"{seconds:.0f} s"
    minutes, rest = divmod(int(round(seconds)), 60)
    if minutes < 60:
        return f"{minutes} min {rest:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"


@dataclass(frozen=True)
class LengthSettings:
    """The options a training length is planned from (the pipeline config's)."""

    global_steps: Optional[int] = None
    """Given steps of the global phase; None: planned."""
    block_steps: Optional[int] = None
    """Given steps of each block's phase; None: planned."""
    time_budget_s: Optional[float] = None
    """Wall-clock budget of the whole run (seconds); None: the capture's plan."""
    rays_per_batch: int = 4096
    """Training rays per step."""
    rays_per_pixel: float = 0.5
    """Times the global phase draws each training pixel, on average."""
    block_rays_per_pixel: float = 1.0
    """Times a block's phase draws each pixel of the block's images, on average."""
    min_global_steps: int = 2000
    min_block_steps: int = 1000
    max_steps: int = 200_000
    """Most steps of one phase (the paper's run length)."""
    block_workers: int = 1
    """Blocks that train at once (on other processes or machines): a budget's blocks run in waves of this many."""


@dataclass(frozen=True)
class TrainingLength:
    """How long a run trains, and where that came from.

    Attributes:
        global_steps: steps of the global phase (``G``).
        block_steps: steps of each block's phase (``B``).
        source: ``given`` (both set by the user), ``capture`` (planned from the pixels), ``budget``.
        budget_s: the wall-clock budget, for a budget's plan.
        pace_steps_per_s: the training pace the plan was made for (measured), for a budget's plan.
        measured: False while a budget's plan waits for the pace of the run's first steps.
        blocks_measured: False while a budget's block steps wait for the end of the global phase.
        finished_block_steps: steps of the first blocks, as they trained, when a budget on one machine planned
            the blocks after them again at the pace those blocks measured (``()``: every block trains
            ``block_steps``).
    """

    global_steps: int
    block_steps: int
    source: LengthSource
    budget_s: Optional[float] = None
    pace_steps_per_s: Optional[float] = None
    measured: bool = True
    blocks_measured: bool = True
    finished_block_steps: Tuple[int, ...] = ()

    @property
    def final(self) -> bool:
        """Nothing of the plan is left to measure."""
        return self.measured and self.blocks_measured

    def steps_of_block(self, index: int) -> int:
        """Steps of the ``index``-th block phase (in training order)."""
        return self.finished_block_steps[index] if index < len(self.finished_block_steps) else self.block_steps

    def total_steps(self, num_blocks_trained: int) -> int:
        """Steps of the whole run on one machine."""
        return self.global_steps + sum(self.steps_of_block(i) for i in range(num_blocks_trained))


def _steps(rays_per_pixel: float, pixels: float, rays_per_batch: int, low: int, high: int) -> int:
    wanted = math.ceil(max(rays_per_pixel, 0.0) * max(pixels, 0.0) / max(rays_per_batch, 1))
    return int(min(max(wanted, low), high))


def length_from_capture(settings: LengthSettings, train_pixels: int, block_pixels: Sequence[int]) -> TrainingLength:
    """The capture's plan: given steps kept, the others from the pixels (see the module's text).

    Args:
        settings: the options.
        train_pixels: pixels of all training images.
        block_pixels: pixels of each block's training images (empty for a run of one model).
    """
    high = max(settings.max_steps, 1)
    global_steps = settings.global_steps
    if global_steps is None:
        global_steps = _steps(settings.rays_per_pixel, train_pixels, settings.rays_per_batch, min(settings.min_global_steps, high), high)
    block_steps = settings.block_steps
    if block_steps is None:
        mean_block = sum(block_pixels) / len(block_pixels) if block_pixels else 0.0
        block_steps = _steps(settings.block_rays_per_pixel, mean_block, settings.rays_per_batch, min(settings.min_block_steps, high), high)
    given = settings.global_steps is not None and settings.block_steps is not None
    return TrainingLength(int(global_steps), int(block_steps), "given" if given else "capture")


def _waves(num_blocks_trained: int, workers: int) -> int:
    return math.ceil(num_blocks_trained / max(workers, 1)) if num_blocks_trained > 0 else 0


def length_from_budget(
    capture: TrainingLength, settings: LengthSettings, *, num_blocks_trained: int, pace_steps_per_s: Optional[float],
    steps_done: int = 0,
) -> TrainingLength:
    """A budget's plan: ``capture``'s steps scaled to fit ``settings.time_budget_s`` at ``pace_steps_per_s``.

    ``capture``'s ratio of global to block steps is kept (a plan of this function may be passed again).
    ``steps_done``: the run has trained this many steps, so its first phase keeps at least those plus one.
    A step count the user gave stays as given and the budget fills the rest. ``pace_steps_per_s``
    None: not measured yet, the capture's plan stands for now (``measured`` False). The blocks' steps
    are provisional (``blocks_measured`` False) until :func:`blocks_from_remaining_time`.

    Raises:
        LengthError: both step counts are given as well as a budget, or no budget is set.
    """
    budget = settings.time_budget_s
    if budget is None:
        raise LengthError("length_from_budget needs a time budget")
    if settings.global_steps is not None and settings.block_steps is not None:
        raise LengthError("--pipeline.time-budget plans the steps: give it, or --pipeline.global-steps and "
                          "--pipeline.block-steps, not all three")
    waves = _waves(num_blocks_trained, settings.block_workers)
    blocks_pending = waves > 0 and settings.global_steps != 0  # a run of blocks only plans them with its first steps
    if pace_steps_per_s is None or not (math.isfinite(pace_steps_per_s) and pace_steps_per_s > 0):
        return replace(capture, source="budget", budget_s=budget, pace_steps_per_s=None, measured=False, blocks_measured=not blocks_pending)
    steps = budget * pace_steps_per_s  # steps on the critical path
    high = max(settings.max_steps, 1)
    if settings.global_steps is not None:
        global_steps = settings.global_steps
        block_steps = (steps - global_steps) / waves if waves else capture.block_steps
    elif settings.block_steps is not None:
        block_steps = settings.block_steps
        global_steps = steps - waves * block_steps
    else:
        scale = steps / (capture.global_steps + waves * capture.block_steps)
        global_steps, block_steps = scale * capture.global_steps, scale * capture.block_steps
    if settings.global_steps == 0:  # a run of blocks only: its first block has trained steps_done
        block_steps = max(block_steps, steps_done + 1)
    else:
        global_steps = max(global_steps, steps_done + 1) if settings.global_steps is None else global_steps
    return TrainingLength(
        global_steps=int(min(max(math.floor(global_steps), 1), high)), block_steps=int(min(max(math.floor(block_steps), 1), high)),
        source="budget", budget_s=budget, pace_steps_per_s=float(pace_steps_per_s), measured=True, blocks_measured=not blocks_pending,
    )


def blocks_from_remaining_time(
    length: TrainingLength, settings: LengthSettings, *, num_blocks_trained: int, remaining_s: float, pace_steps_per_s: float,
    later_blocks_pace_steps_per_s: Optional[float] = None, current_block_steps_done: int = 0, finished_block_steps: Sequence[int] = (),
) -> TrainingLength:
    """A budget's plan once its global phase has ended: the blocks' steps from the time left.

    Each of the ``ceil(n / workers)`` waves gets an equal share of ``remaining_s`` at
    ``pace_steps_per_s`` (at least 1 step: a run that has spent its budget still trains each block
    briefly, and says so in its log); ``later_blocks_pace_steps_per_s`` (default: the same) the pace of
    the waves after the first, when it differs (the current block's own pace against all blocks' so far).
    ``current_block_steps_done``: the block that trains now has trained
    this many of its steps (planned again at the blocks' own pace: a block's steps cost more than the
    global model's) and keeps at least those plus one. ``finished_block_steps``: on one machine
    (``block_workers`` 1), the steps of the blocks that have trained to their end, which keep them; the
    time left is shared by the blocks after them. Given block steps stay as given.

    Raises:
        LengthError: finished blocks are given for blocks that train in parallel waves, or more of them
            than there are blocks.
    """
    if settings.block_steps is not None:
        return replace(length, blocks_measured=True)
    finished = tuple(int(steps) for steps in finished_block_steps)
    if finished and (settings.block_workers > 1 or len(finished) >= num_blocks_trained):
        raise LengthError(f"{len(finished)} finished blocks of {num_blocks_trained} on {settings.block_workers} workers: "
                          "only blocks trained one after another on one machine are planned again block by block")
    waves = max(_waves(num_blocks_trained - len(finished), settings.block_workers), 1)
    pace, later = max(pace_steps_per_s, 0.0), later_blocks_pace_steps_per_s
    if pace <= 0:
        steps = 0.0
    elif later is None or not (math.isfinite(later) and later > 0):
        steps = (max(remaining_s, 0.0) * pace + current_block_steps_done) / waves
    else:  # B - done steps at ``pace``, then (waves - 1) x B at ``later``, in the time left
        steps = (max(remaining_s, 0.0) + current_block_steps_done / pace) / (1.0 / pace + (waves - 1) / later)
    block_steps = int(min(max(math.floor(steps), current_block_steps_done + 1, 1), max(settings.max_steps, 1)))
    return replace(length, block_steps=block_steps, blocks_measured=True, finished_block_steps=finished)


def plan_length(
    settings: LengthSettings, *, train_pixels: int, block_pixels: Sequence[int], pace_steps_per_s: Optional[float] = None,
) -> TrainingLength:
    """The run's length: the capture's plan, or with a budget that plan scaled to the budget."""
    capture = length_from_capture(settings, train_pixels, block_pixels)
    if settings.time_budget_s is None:
        return capture
    return length_from_budget(capture, settings, num_blocks_trained=len(block_pixels), pace_steps_per_s=pace_steps_per_s)


def length_to_json(length: TrainingLength) -> Dict[str, Any]:
    """``length`` as the JSON object saved in a run's blocks.json."""
    return {
        "global_steps": length.global_steps, "block_steps": length.block_steps, "source": length.source,
        "budget_s": length.budget_s, "pace_steps_per_s": length.pace_steps_per_s,
        "measured": length.measured, "blocks_measured": length.blocks_measured,
        "finished_block_steps": list(length.finished_block_steps),
    }


def length_from_json(content: Dict[str, Any]) -> TrainingLength:
    """The length :func:`length_to_json` wrote.

    Raises:
        LengthError: a field is missing or of the wrong kind.
    """
    try:
        source = str(content["source"])
        if source not in ("given", "capture", "budget"):
            raise ValueError(f"unknown source {source!r}")
        budget, pace = content.get("budget_s"), content.get("pace_steps_per_s")
        length = TrainingLength(
            global_steps=int(content["global_steps"]), block_steps=int(content["block_steps"]), source=source,  # type: ignore[arg-type]
            budget_s=None if budget is None else float(budget), pace_steps_per_s=None if pace is None else float(pace),
            measured=bool(content.get("measured", True)), blocks_measured=bool(content.get("blocks_measured", True)),
            finished_block_steps=tuple(int(steps) for steps in content.get("finished_block_steps", ())),
        )
    except (KeyError, TypeError, ValueError) as error:
        raise LengthError(f"malformed training length {content!r}: {error}") from None
    if length.global_steps < 0 or length.block_steps < 0 or any(steps < 0 for steps in length.finished_block_steps):
        raise LengthError(f"malformed training length {content!r}: negative steps")
    return length
