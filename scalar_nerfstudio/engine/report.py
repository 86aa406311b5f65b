"""What a run's models hold: parameters, table sizes, memory (printed and saved as model_report.json)."""

from __future__ import annotations

import json
import resource
import sys
from pathlib import Path
from typing import Any, Dict, Iterable, List, Optional

import torch
from torch import nn

from scalar_nerfstudio.atomic_io import atomic_write_text

MIB = float(1 << 20)


def tensor_bytes(tensors: Iterable[torch.Tensor]) -> int:
    """Bytes held by ``tensors``."""
    return sum(t.numel() * t.element_size() for t in tensors)


def optimizer_state_bytes(optimizers: Iterable[torch.optim.Optimizer], params: Iterable[nn.Parameter]) -> int:
    """Bytes of optimiser state (Adam moments ...) kept for ``params``."""
    wanted = {id(p) for p in params}
    total = 0
    for optimizer in optimizers:
        for param, state in optimizer.state.items():
            if id(param) in wanted:
                total += tensor_bytes(v for v in state.values() if isinstance(v, torch.Tensor) and v.dim() > 0)
    return total


def peak_memory_mib(device: torch.device | str) -> Dict[str, float]:
    """Peak resident memory of this process (MiB), and peak CUDA allocation when on a GPU."""
    rss_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    peak = {"peak_rss_mib": rss_kib / (1024.0 if sys.platform != "darwin" else MIB)}
    if torch.device(device).type == "cuda" and torch.cuda.is_available():
        peak["peak_cuda_mib"] = torch.cuda.max_memory_allocated(device) / MIB
    return peak


def model_entry(name: str, model: Any, *, optimizers: Iterable[torch.optim.Optimizer], trained: bool,
                parameter_count: Optional[Dict[str, int]] = None) -> Dict[str, Any]:
    """One row of the report for a :class:`ScalarModel` (global or block).

    ``parameter_count`` ({"all": n, "encoder": n}) gives the sizes of a model whose weights are not in
    memory (a finished block kept in its file): its memory and occupancy then read 0 and None."""
    params = list(model.parameters())
    encoder = model.field.encoder
    in_memory = parameter_count is None
    return {
        "model": name,
        "trained": trained,
        "in_memory": in_memory,
        "parameters": sum(p.numel() for p in params) if in_memory else parameter_count["all"],
        "parameter_mib": tensor_bytes(params) / MIB,
        "optimizer_state_mib": optimizer_state_bytes(optimizers, params) / MIB,
        "log2_hashmap_size": int(model.field.config.log2_hashmap_size),
        "max_resolution": int(model.field.config.max_resolution),
        "encoder_parameters": sum(p.numel() for p in encoder.parameters()) if in_memory else parameter_count["encoder"],
        "occupied_fraction": float(model.occupancy.occupied_fraction()) if in_memory else None,
    }


def scene_model_report(scene_model: Any, optimizers: Iterable[torch.optim.Optimizer], device: torch.device | str) -> Dict[str, Any]:
    """Report of a :class:`ScalarSceneModel`: one entry per model, totals and peak memory (a block kept
    in its file counts its parameters, with 0 MiB in memory)."""
    optimizers = list(optimizers)
    started = set(scene_model.started_block_ids())
    models = [model_entry("global", scene_model.global_model, optimizers=optimizers, trained=True)]
    for index in scene_model.block_ids:
        count = None if scene_model.block_is_resident(index) else {
            "all": scene_model.block_parameter_count(index), "encoder": scene_model.block_parameter_count(index, "encoder")}
        models.append(model_entry(f"block {index}", scene_model.blocks[str(index)], optimizers=optimizers, trained=index in started,
                                  parameter_count=count))
    return {
        "models": models,
        "total_parameters": sum(m["parameters"] for m in models),
        "total_parameter_mib": sum(m["parameter_mib"] for m in models),
        "total_optimizer_state_mib": sum(m["optimizer_state_mib"] for m in models),
        **peak_memory_mib(device),
    }


def format_report(report: Dict[str, Any]) -> str:
    """The report as a plain-text table."""
    lines: List[str] = [
        f"{'model':<10} {'log2 T':>6} {'max res':>7} {'params':>12} {'MiB':>8} {'Adam MiB':>9} {'occupied':>8}",
    ]
    for m in report["models"]:
        occupied = "on disk" if m.get("occupied_fraction") is None else f"{m['occupied_fraction']:.1%}"
        lines.append(
            f"{m['model']:<10} {m['log2_hashmap_size']:>6} {m['max_resolution']:>7} {m['parameters']:>12,} "
            f"{m['parameter_mib']:>8.1f} {m['optimizer_state_mib']:>9.1f} {occupied:>8}"
        )
    lines.append(
        f"{'total':<10} {'':>6} {'':>7} {report['total_parameters']:>12,} {report['total_parameter_mib']:>8.1f} "
        f"{report['total_optimizer_state_mib']:>9.1f}"
    )
    peak = f"peak memory: {report['peak_rss_mib']:.0f} MiB resident"
    if "peak_cuda_mib" in report:
        peak += f", {report['peak_cuda_mib']:.0f} MiB CUDA"
    lines.append(peak)
    return "\n".join(lines)


def write_report(report: Dict[str, Any], path: Path, extra: Optional[Dict[str, Any]] = None) -> None:
    """Save the report (and ``extra`` keys) as JSON."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps({**report, **(extra or {})}, indent=2) + "\n")

