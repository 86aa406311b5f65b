"""What the pipeline prints: the run's plan for the training log, the hint to train blocks at once on
a GPU, and a line of eval metrics (text only: no torch, no nerfstudio)."""

from __future__ import annotations

from typing import Dict, Optional, Sequence

from scalar_nerfstudio.blocks.length import TrainingLength, format_duration
from scalar_nerfstudio.blocks.plan import BlockPlan
from scalar_nerfstudio.blocks.split import format_split_table
from scalar_nerfstudio.engine.contract import Phase

__all__ = ["format_eval_metrics", "format_length", "format_plan_report", "sequential_blocks_hint"]

#: What the plan report says of a block's start, per ``--pipeline.block-init``.
_BLOCK_START = {"global": " (starts as a copy of the global model)", "fitted": " (its table fitted to the global model first)"}


def format_plan_report(plan: BlockPlan, phases: Sequence[Phase], *, log2_hashmap_size: int, block_init: str, device_type: str) -> str:
    """The split, the automatic K, the block capacities and the phases, for the training log.

    Args:
        plan: the run's block plan.
        phases: the run's training phases, in order.
        log2_hashmap_size: log2 table rows of the global model (T of the automatic K).
        block_init: how a block's model starts (``--pipeline.block-init``).
        device_type: ``cuda`` or ``cpu`` (a GPU run of several blocks gets :func:`sequential_blocks_hint`).
    """
    lines = [format_split_table(plan.split, plan.image_names)]
    pixels = plan.layout.layout_pixels
    if plan.auto_num_blocks is not None:
        lines.append(
            f"automatic K = {plan.auto_num_blocks}: the camera layout is {pixels:.0f} training pixels across at the "
            f"viewing distance (R^2 / T = {pixels ** 2 / 2 ** log2_hashmap_size:.2f} for T = 2^{log2_hashmap_size})"
            + ("; one model suffices, no block is trained" if plan.single_model else "")
        )
    start = _BLOCK_START.get(block_init, "")
    for index, capacity in plan.capacities.items():
        lines.append(f"block {index}: table 2^{capacity.log2_hashmap_size}, finest resolution {capacity.max_resolution}{start}")
    lines.append("phases: " + ", ".join(f"{p.name}: steps {p.start_step}-{p.end_step - 1}" for p in phases if p.num_steps > 0))
    if plan.length is not None:
        lines.append(format_length(plan.length, phases))
    hint = sequential_blocks_hint(sum(p.block is not None and p.num_steps > 0 for p in phases), device_type)
    if hint is not None:
        lines.append(hint)
    return "\n".join(lines)


def format_length(length: TrainingLength, phases: Sequence[Phase]) -> str:
    """One line: the run's steps and where they came from (given, the capture, a time budget)."""
    blocks = [p for p in phases if p.block is not None and p.num_steps > 0]
    steps = phases[-1].end_step if phases else 0
    parts = [f"global {length.global_steps} steps"] if any(p.block is None for p in phases) else []
    if blocks:
        counts = sorted({p.num_steps for p in blocks})
        each = f"x {counts[0]}" if len(counts) == 1 else f"of {counts[0]}-{counts[-1]}"
        parts.append(f"{len(blocks)} block{'s' if len(blocks) != 1 else ''} {each} steps")
    shape = " + ".join(parts) + f" = {steps} steps"
    if length.source == "given":
        return f"training length: {shape} (as given)"
    if length.source == "capture":
        return f"training length: {shape}, planned from the capture's pixels (--pipeline.rays-per-pixel, --pipeline.block-rays-per-pixel)"
    budget = format_duration(length.budget_s or 0.0)
    if not length.measured:
        return f"training length: {shape} for now; planned for a budget of {budget} once the pace of the first steps is measured"
    pending = "; the blocks' steps are planned again from the time left when the global phase ends" if not length.blocks_measured else ""
    return f"training length: {shape}, planned for a budget of {budget} at {length.pace_steps_per_s:.2f} steps/s{pending}"


def sequential_blocks_hint(num_blocks_trained: int, device_type: str) -> Optional[str]:
    """The training log's hint, on a GPU, that this process trains its blocks one after another while
    ``scalar-nerf-train-blocks`` trains them at once (one block leaves a GPU mostly idle); None
    when it does not apply (the CPU, or at most one block)."""
    if device_type != "cuda" or num_blocks_trained < 2:
        return None
    return (
        f"the {num_blocks_trained} blocks train one after another in this process; on a GPU they train faster at once: "
        "--pipeline.train-blocks False, then scalar-nerf-train-blocks RUN (8 blocks on one H200: 4.2x faster)"
    )


def format_eval_metrics(metrics: Dict[str, float], fusion: str) -> str:
    """One line: the fusion, PSNR / SSIM / LPIPS (with std when present), the depth metrics (scenes with
    true depth) and time per image."""
    parts = []
    for key, label, digits in (("psnr", "PSNR", 2), ("ssim", "SSIM", 3), ("lpips", "LPIPS", 3)):
        if key in metrics:
            std = f" ± {metrics[key + '_std']:.{digits}f}" if f"{key}_std" in metrics else ""
            parts.append(f"{label} {metrics[key]:.{digits}f}{std}")
    if "lpips" not in metrics:
        parts.append("LPIPS skipped")
    if "depth_delta1" in metrics:  # a scene with true depth (the town)
        parts.append(f"depth within 25 % {metrics['depth_delta1']:.1%}, median depth error {metrics['depth_median_rel_error']:.1%}")
    timing = f", {1.0 / metrics['fps']:.2f} s/image" if metrics.get("fps") else ""
    return f"eval ({fusion} fusion): " + ", ".join(parts) + timing
