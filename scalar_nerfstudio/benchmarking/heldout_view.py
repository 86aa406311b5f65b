"""One held-out view side by side, at the end of ``scalar-nerf-benchmark``: heldout_view.png.

Panels: the ground truth | the one-model baseline of table 2^T (the better of its schedules at the
blocks' budget, :func:`.report.one_model_baseline`) | the blocks (``auto-parallel`` when it ran, else
``auto``, else the first block variant that ran) | the blocks' ``block_colour`` output (which block
gave each pixel; grey: the global model). A caption over each panel names the run and its PSNR on
this view.

Each run is loaded from its folder (config.yml and newest checkpoint, nerfstudio's ``eval_setup``, as
``scalar-nerf-eval-fusion`` and benchmarks/train_vs_heldout.py load a run), in this process, one at a
time, and renders the view as the runner's evaluation did: its own fusion, the PSNR of the model's
image metrics.
"""

from __future__ import annotations

import io
import textwrap
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

from scalar_nerfstudio.atomic_io import atomic_write_bytes
from scalar_nerfstudio.benchmarking.report import one_model_baseline
from scalar_nerfstudio.benchmarking.variants import BenchmarkConfig

__all__ = ["FILE_NAME", "render_view", "shown_runs", "write_heldout_view"]

#: The picture's file in the benchmark's output folder.
FILE_NAME = "heldout_view.png"
#: The block variants the picture shows, by preference (else the first block variant that ran).
BLOCKS_SHOWN = ("auto-parallel", "auto")
#: Characters per caption line in the picture.
CAPTION_WIDTH = 42


def shown_runs(results: Dict[str, Dict[str, Any]]) -> Tuple[Optional[Dict[str, Any]], Optional[str]]:
    """(the one-model baseline of table 2^T to show, :func:`.report.one_model_baseline`'s dict, its
    ``run`` the run to render; the block variant to show): each None when none ran. The baseline is
    picked at the shown blocks' budget: equal wall-clock for ``auto-parallel``, else equal total steps."""
    blocks = next((name for name in BLOCKS_SHOWN if name in results), None)
    if blocks is None:
        blocks = next((name for name, result in results.items() if result.get("parallel_train_s")), None)
    seconds = results[blocks]["parallel_train_s"] if blocks is not None and blocks.startswith("auto-parallel") else None
    return one_model_baseline(results, "ngp-t", seconds), blocks


def render_view(run_dir: Path, view: int) -> Dict[str, Any]:
    """Held-out view ``view`` rendered by the run in ``run_dir``: ``truth``, ``rgb``, ``block_colour``
    ([H, W, 3] float arrays in [0, 1]) and ``psnr`` (dB), ``fusion`` (the run's), ``views`` (held-out
    views of the scene). A run without config.yml, or a view out of range, is refused by name."""
    import torch
    from nerfstudio.data.utils.dataloaders import FixedIndicesEvalDataloader
    from nerfstudio.utils.eval_utils import eval_setup

    config_path = Path(run_dir) / "config.yml"
    if not config_path.is_file():
        raise SystemExit(f"scalar-nerf-benchmark: no {config_path} to render the held-out view from")
    _, pipeline, _, _ = eval_setup(config_path, test_mode="test")
    eval_dataset = pipeline.datamanager.eval_dataset
    loader = getattr(pipeline.datamanager, "fixed_indices_eval_dataloader", None)
    if eval_dataset is None or not isinstance(loader, FixedIndicesEvalDataloader):
        raise SystemExit(f"scalar-nerf-benchmark: {run_dir}: its datamanager has no held-out views to render")
    views = len(eval_dataset)
    if not 0 <= view < views:
        raise SystemExit(f"scalar-nerf-benchmark: --heldout-view {view}: the scene has {views} held-out views (0 to {views - 1})")
    model = pipeline.model
    model.eval()
    with torch.no_grad():
        camera, batch = loader.get_camera(view)
        outputs = model.get_outputs_for_camera(camera=camera)
        metrics, images = model.get_image_metrics_and_images(outputs, batch)
    rgb = outputs["rgb"].clamp(0, 1).float().cpu()  # [H, W, 3]
    truth = images["img"][:, : rgb.shape[1]].float().cpu()  # [H, W, 3]: the target the metrics compared with
    colour = outputs.get("block_colour", torch.zeros_like(rgb)).float().cpu()  # [H, W, 3]
    return {"truth": truth.numpy(), "rgb": rgb.numpy(), "block_colour": colour.numpy(), "psnr": float(metrics["psnr"]),
            "fusion": str(getattr(model, "fusion_mode", "global")), "views": views}


def figure_png(images: List[Any], captions: List[str]) -> bytes:
    """The panels side by side, each with its caption above: PNG bytes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    height, width = images[0].shape[:2]
    panel_in = 4.0
    lines = max(len(textwrap.wrap(caption, CAPTION_WIDTH)) for caption in captions)
    figure, axes = plt.subplots(1, len(images), figsize=(panel_in * len(images), panel_in * height / width + 0.2 + 0.16 * lines))
    for axis, image, caption in zip(axes, images, captions):
        axis.imshow(image)
        axis.set_title(textwrap.fill(caption, CAPTION_WIDTH), fontsize=8)
        axis.axis("off")
    figure.tight_layout()
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=120)
    plt.close(figure)
    return buffer.getvalue()


def write_heldout_view(config: BenchmarkConfig, results: Dict[str, Dict[str, Any]]) -> Optional[Dict[str, Any]]:
    """Render the picture (:data:`FILE_NAME` in ``config.output_dir``) of held-out view ``config.heldout_view``;
    its view and panels (caption, variant, run, PSNR) for the report, or None when neither a one-model
    run nor a block variant ran."""
    baseline, blocks = shown_runs(results)
    if baseline is None and blocks is None:
        return None
    panels: List[Dict[str, Any]] = []
    images: List[Any] = []
    truth = None
    if baseline is not None:
        run = results[baseline["run"]]
        rendered = render_view(Path(run["run_dir"]), config.heldout_view)
        truth = rendered["truth"]
        caption = (f"one model {baseline['run']} (2^{config.log2_table}, {baseline['schedule']} schedule, {run['steps']} steps): "
                   f"{rendered['psnr']:.2f} dB")
        panels.append({"caption": caption, "variant": baseline["run"], "psnr": rendered["psnr"]})
        images.append(rendered["rgb"])
    if blocks is not None:
        run = results[blocks]
        rendered = render_view(Path(run["run_dir"]), config.heldout_view)
        truth = rendered["truth"] if truth is None else truth
        k = f"K = {run['num_blocks']}, " if run.get("num_blocks") else ""
        caption = f"blocks {blocks} ({k}{rendered['fusion']} fusion, {run['steps']} steps): {rendered['psnr']:.2f} dB"
        panels.append({"caption": caption, "variant": blocks, "psnr": rendered["psnr"]})
        panels.append({"caption": f"block colours of {blocks} (grey: the global model)", "variant": blocks, "psnr": None})
        images += [rendered["rgb"], rendered["block_colour"]]
    panels.insert(0, {"caption": f"ground truth, held-out view {config.heldout_view}", "variant": None, "psnr": None})
    images.insert(0, truth)
    atomic_write_bytes(config.output_dir / FILE_NAME, figure_png(images, [p["caption"] for p in panels]))
    return {"view": config.heldout_view, "file": FILE_NAME, "panels": panels}
