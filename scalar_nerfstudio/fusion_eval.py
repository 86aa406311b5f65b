"""Every fusion mode of a trained scalar-nerf pipeline on its eval images: the paper's Tab. 3.

:func:`evaluate_fusion_modes` renders every eval image once per fusion mode and averages the
image metrics (PSNR, SSIM, LPIPS when its weights are on disk) and the render time in ms per image;
it also measures what skipping blocks outside the view frustum does (``global`` fusion with and
without skipping, and how much the images differ). :func:`markdown_table` formats the result.
``scalar-nerf-eval-fusion`` (scripts/eval_fusion.py) is the command line around these.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Callable, Dict, List, Optional, Sequence, Tuple

import torch

from scalar_nerfstudio.metrics import psnr

if TYPE_CHECKING:
    from scalar_nerfstudio.pipeline import ScalarPipeline

__all__ = ["evaluate_fusion_modes", "markdown_table"]


def _render_all(pipeline: "ScalarPipeline", mode: str, skip: bool) -> Tuple[Dict[str, float], List[torch.Tensor]]:
    """Mean metrics and ms/image of ``mode`` over the eval images; returns the rendered images too."""
    model = pipeline.model
    model.set_fusion(mode)
    sums: Dict[str, float] = {}
    images, times, blocks_rendered, globals_rendered = [], [], [], []
    for camera, batch in pipeline.datamanager.fixed_indices_eval_dataloader:
        start = time.perf_counter()
        outputs = model.get_outputs_for_camera(camera=camera, skip_invisible_blocks=skip)
        times.append(time.perf_counter() - start)
        blocks_rendered.append(len(model.rendered_models - {"global"}))
        globals_rendered.append("global" in model.rendered_models)
        metrics, _ = model.get_image_metrics_and_images(outputs, batch)
        for key, value in metrics.items():
            sums[key] = sums.get(key, 0.0) + float(value)
        images.append(outputs["rgb"].clamp(0, 1).cpu())
    count = max(len(images), 1)
    result = {key: value / count for key, value in sums.items()}
    result["ms_per_image"] = 1000.0 * sum(times) / count
    result["num_images"] = len(images)
    result["blocks_rendered_per_image"] = sum(blocks_rendered) / count
    result["global_model_rendered"] = all(globals_rendered)
    return result, images


def evaluate_fusion_modes(
    pipeline: "ScalarPipeline",
    modes: Sequence[str],
    measure_skipping: bool = True,
    on_mode: Optional[Callable[[str, Dict[str, float]], None]] = None,
) -> Dict[str, Dict[str, float]]:
    """The table: ``{mode: {"psnr", "ssim", ["lpips"], "ms_per_image", ...}}`` for every mode in
    ``modes`` (rendered with frustum skipping), plus, when ``measure_skipping`` and ``"global"`` is
    among the modes, ``"global-without-skipping"`` and a ``"skipping"`` summary. ``on_mode(mode, row)``
    is called as soon as each mode's row is done (e.g. to print progress). Puts ``pipeline`` in eval mode."""
    pipeline.eval()
    table: Dict[str, Dict[str, float]] = {}
    rendered: Dict[str, List[torch.Tensor]] = {}
    with torch.no_grad():
        for mode in modes:
            table[mode], rendered[mode] = _render_all(pipeline, mode, skip=True)
            if on_mode is not None:
                on_mode(mode, table[mode])
        if measure_skipping and "global" in rendered:
            unskipped, images = _render_all(pipeline, "global", skip=False)
            differences = [float((a - b).abs().max()) for a, b in zip(rendered["global"], images)]
            agreement = [float(psnr(a, b)) for a, b in zip(rendered["global"], images)]
            table["global-without-skipping"] = unskipped
            table["skipping"] = {
                "ms_per_image_with": table["global"]["ms_per_image"],
                "ms_per_image_without": unskipped["ms_per_image"],
                "time_saved_fraction": 1.0 - table["global"]["ms_per_image"] / max(unskipped["ms_per_image"], 1e-9),
                "max_abs_pixel_difference": max(differences, default=0.0),
                "min_psnr_between_renders": min(agreement, default=float("inf")),
                "identical_images": sum(d == 0.0 for d in differences),
                "num_images": len(differences),
            }
    return table


def markdown_table(table: Dict[str, Dict[str, float]]) -> str:
    """The per-mode rows as a Markdown table (and a line on skipping)."""
    has_lpips = any("lpips" in row for row in table.values())
    header = "| fusion | PSNR | SSIM |" + (" LPIPS |" if has_lpips else "") + " ms / image | models rendered / image |"
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for mode, row in table.items():
        if mode == "skipping":
            continue
        cells = [mode, f"{row['psnr']:.2f}", f"{row['ssim']:.3f}"]
        if has_lpips:
            cells.append(f"{row['lpips']:.3f}" if "lpips" in row else "-")
        models = f"{row['blocks_rendered_per_image']:.2f} blocks" + (" + global" if row.get("global_model_rendered") else "")
        cells += [f"{row['ms_per_image']:.0f}", models]
        lines.append("| " + " | ".join(cells) + " |")
    if "skipping" in table:
        s = table["skipping"]
        lines.append("")
        lines.append(
            f"Frustum skipping (global fusion): {s['ms_per_image_with']:.0f} ms/image with, {s['ms_per_image_without']:.0f} without "
            f"({100 * s['time_saved_fraction']:.0f} % saved); {s['identical_images']} of {s['num_images']} images identical, "
            f"largest pixel difference {s['max_abs_pixel_difference']:.3f}."
        )
    if not has_lpips:
        lines.append("")
        lines.append("LPIPS skipped: torchvision's AlexNet weights are not on disk (nothing is downloaded).")
    return "\n".join(lines) + "\n"
