"""Every fusion mode of a trained scalar-nerf pipeline on its eval images: the paper's Tab. 3.

:func:`evaluate_fusion_modes` renders every eval image once per fusion mode and averages the
image metrics (PSNR, SSIM, LPIPS when its weights are on disk) and the render time in ms per image.
It also measures what choosing blocks per ray does (``--pipeline.model.blocks-per-ray``): each of
``global``, ``idw`` and ``surface`` is rendered again with every block on every ray, and the table
gives both render times and the largest pixel difference. :func:`markdown_table` formats the result.
``scalar-nerf-eval-fusion`` (scripts/eval_fusion.py) is the command line around these.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Callable, Dict, List, Optional, Sequence, Tuple

import torch

from scalar_nerfstudio.metrics import psnr

if TYPE_CHECKING:
    from nerfstudio.cameras.cameras import Cameras

    from scalar_nerfstudio.pipeline import ScalarPipeline

__all__ = ["SELECTING_MODES", "evaluate_fusion_modes", "markdown_table", "render_eval_images"]

#: The modes whose blocks are chosen per ray by ``blocks_per_ray``.
SELECTING_MODES = ("global", "surface", "idw")
#: Suffix of the table rows rendered with every block on every ray.
EVERY_BLOCK = "@every-block"


def _eval_images(pipeline: "ScalarPipeline", max_images: Optional[int]) -> List[Tuple["Cameras", Dict[str, torch.Tensor]]]:
    """The (camera, batch) pairs evaluated: every eval image, or ``max_images`` of them evenly spread."""
    from nerfstudio.data.utils.dataloaders import FixedIndicesEvalDataloader

    loader = getattr(pipeline.datamanager, "fixed_indices_eval_dataloader", None)
    if not isinstance(loader, FixedIndicesEvalDataloader):
        raise TypeError(f"{type(pipeline.datamanager).__name__} has no fixed_indices_eval_dataloader of eval images")
    pairs = list(loader)
    if max_images is None or max_images >= len(pairs):
        return pairs
    step = len(pairs) / max_images
    return [pairs[int(i * step)] for i in range(max_images)]


def render_eval_images(pipeline: "ScalarPipeline", mode: str, *, blocks_per_ray: Optional[int] = None,
                       max_images: Optional[int] = None) -> Tuple[Dict[str, float], List[torch.Tensor]]:
    """Mean metrics and ms/image of ``mode`` over the eval images (with ``blocks_per_ray`` if given),
    and the rendered images ``[H, W, 3]`` in [0, 1] in the eval dataloader's order. Leaves the model
    set to ``mode``; call it under ``torch.no_grad()`` with the pipeline in eval mode."""
    model = pipeline.model
    model.set_fusion(mode)
    configured = model.config.blocks_per_ray
    if blocks_per_ray is not None:
        model.config.blocks_per_ray = blocks_per_ray
    sums: Dict[str, float] = {}
    images, times, blocks_rendered, globals_rendered, block_rays, global_pixels = [], [], [], [], [], []
    try:
        for camera, batch in _eval_images(pipeline, max_images):
            start = time.perf_counter()
            outputs = model.get_outputs_for_camera(camera=camera)
            times.append(time.perf_counter() - start)
            blocks_rendered.append(len(model.rendered_models - {"global"}))
            globals_rendered.append("global" in model.rendered_models)
            block_rays.append(sum(model.rays_rendered_by_block.values()) / max(outputs["rgb"][..., 0].numel(), 1))
            global_pixels.append(float((outputs["block_winner"] < 0).float().mean()) if "block_winner" in outputs else 1.0)
            metrics, _ = model.get_image_metrics_and_images(outputs, batch)
            for key, value in metrics.items():
                sums[key] = sums.get(key, 0.0) + float(value)
            images.append(outputs["rgb"].clamp(0, 1).cpu())
    finally:
        model.config.blocks_per_ray = configured
    count = max(len(images), 1)
    result = {key: value / count for key, value in sums.items()}
    result["ms_per_image"] = 1000.0 * sum(times) / count
    result["num_images"] = len(images)
    result["blocks_rendered_per_image"] = sum(blocks_rendered) / count
    result["block_renders_per_ray"] = sum(block_rays) / count
    result["global_model_rendered"] = all(globals_rendered)
    result["global_pixel_share"] = sum(global_pixels) / count
    return result, images


def evaluate_fusion_modes(
    pipeline: "ScalarPipeline",
    modes: Sequence[str],
    *,
    measure_selection: bool = True,
    on_mode: Optional[Callable[[str, Dict[str, float]], None]] = None,
    max_images: Optional[int] = None,
) -> Dict[str, Dict[str, float]]:
    """The table: ``{mode: {"psnr", "ssim", ["lpips"], "ms_per_image", ...}}`` for every mode in
    ``modes``, plus, when ``measure_selection``, for each of :data:`SELECTING_MODES` among them, a row
    ``"<mode>@every-block"`` (every block rendered on every ray) and ``"selection:<mode>"`` comparing
    the two (times, largest pixel difference, lowest PSNR between the renders). ``on_mode(mode, row)``
    is called as soon as each row is done (e.g. to print progress). ``max_images``: only that many eval
    images, evenly spread. Puts ``pipeline`` in eval mode."""
    pipeline.eval()
    table: Dict[str, Dict[str, float]] = {}
    rendered: Dict[str, List[torch.Tensor]] = {}
    with torch.no_grad():
        for mode in modes:
            table[mode], rendered[mode] = render_eval_images(pipeline, mode, max_images=max_images)
            if on_mode is not None:
                on_mode(mode, table[mode])
        if not measure_selection:
            return table
        for mode in [m for m in SELECTING_MODES if m in rendered]:
            every, images = render_eval_images(pipeline, mode, blocks_per_ray=0, max_images=max_images)
            table[mode + EVERY_BLOCK] = every
            if on_mode is not None:
                on_mode(mode + EVERY_BLOCK, every)
            differences = [float((a - b).abs().max()) for a, b in zip(rendered[mode], images)]
            agreement = [float(psnr(a, b)) for a, b in zip(rendered[mode], images)]
            table["selection:" + mode] = {
                "blocks_per_ray": pipeline.model.config.blocks_per_ray,
                "ms_per_image_selected": table[mode]["ms_per_image"],
                "ms_per_image_every_block": every["ms_per_image"],
                "max_abs_pixel_difference": max(differences, default=0.0),
                "min_psnr_between_renders": min(agreement, default=float("inf")),
                "identical_images": sum(d == 0.0 for d in differences),
                "num_images": len(differences),
            }
    return table


def markdown_table(table: Dict[str, Dict[str, float]]) -> str:
    """The per-mode rows as a Markdown table (and a line per mode on block selection)."""
    has_lpips = any("lpips" in row for row in table.values())
    has_depth = any("depth_delta1" in row for row in table.values())  # a scene with true depth (the town)
    header = ("| fusion | PSNR | SSIM |" + (" LPIPS |" if has_lpips else "")
              + (" depth within 25 % | median depth error |" if has_depth else "")
              + " ms / image | models rendered / image | block renders / ray | pixels from the global model |")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    single = table.get("global-only", {}).get("ms_per_image")
    for mode, row in table.items():
        if mode.startswith("selection:"):
            continue
        cells = [mode, f"{row['psnr']:.2f}", f"{row['ssim']:.3f}"]
        if has_lpips:
            cells.append(f"{row['lpips']:.3f}" if "lpips" in row else "-")
        if has_depth:
            cells += [f"{row['depth_delta1']:.1%}", f"{row['depth_median_rel_error']:.1%}"] if "depth_delta1" in row else ["-", "-"]
        models = f"{row['blocks_rendered_per_image']:.2f} blocks" + (" + global" if row.get("global_model_rendered") else "")
        time_cell = f"{row['ms_per_image']:.0f}" + (f" ({row['ms_per_image'] / single:.2f}x)" if single else "")
        cells += [time_cell, models, f"{row.get('block_renders_per_ray', 0.0):.2f}",
                  f"{row['global_pixel_share']:.2%}" if "global_pixel_share" in row else "-"]
        lines.append("| " + " | ".join(cells) + " |")
    if single:
        lines += ["", "Times in brackets: relative to `global-only` (one model)."]
    for key, s in table.items():
        if not key.startswith("selection:"):
            continue
        lines.append("")
        lines.append(
            f"Blocks per ray ({key.split(':', 1)[1]}, {s['blocks_per_ray']} per ray): {s['ms_per_image_selected']:.0f} ms/image, "
            f"{s['ms_per_image_every_block']:.0f} with every block on every ray; {s['identical_images']} of {s['num_images']} images "
            f"identical, largest pixel difference {s['max_abs_pixel_difference']:.4f}, lowest PSNR between them "
            f"{s['min_psnr_between_renders']:.1f} dB."
        )
    if has_depth:
        lines += ["", "Depth against the scene's true depth, over its pixels of known depth (mean over the images): the share "
                  "within a factor 1.25 of the truth, and the median of |depth - truth| / truth."]
    if not has_lpips:
        lines.append("")
        lines.append("LPIPS skipped: torchvision's AlexNet weights are not on disk (nothing is downloaded).")
    return "\n".join(lines) + "\n"
