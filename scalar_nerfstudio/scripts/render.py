"""``scalar-nerf-render``: nerfstudio's ``ns-render`` with ``--fusion``.

Same subcommands (camera-path, interpolate, spiral, dataset) and options as ``ns-render``, plus
``--fusion {nearest-guarded,nearest,nearest-idw,global,surface,idw,global-only,block:K}``. Without ``--fusion`` (and with plain
``ns-render``) a scalar-nerf run renders with the fusion it was configured with (default nearest-guarded).

    scalar-nerf-render dataset --load-config RUN/config.yml --fusion idw --output-path renders/
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Optional, Union

import tyro
from nerfstudio.scripts import render as ns_render
from typing_extensions import Annotated

from scalar_nerfstudio.fusion import FusionModeError, parse_fusion_mode
from scalar_nerfstudio.runs import RunError, check_trained_run
from scalar_nerfstudio.seam.render_command import after_each_load

PROG = "scalar-nerf-render"


@contextlib.contextmanager
def fusion_applied(fusion: Optional[str]) -> Iterator[None]:
    """While active, runs loaded by ``ns-render``'s commands render with ``fusion``."""
    if fusion is None:
        yield
        return

    def set_fusion(config: Any, pipeline: Any) -> None:
        model = pipeline.model
        if not hasattr(model, "set_fusion"):
            raise SystemExit(f"--fusion: {config.method_name} runs have no fusion (only scalar-nerf runs do)")
        try:
            model.set_fusion(fusion)
        except FusionModeError as error:
            raise SystemExit(f"--fusion: {error}") from None

    with after_each_load(set_fusion):
        yield


def check_arguments(load_config: Path, fusion: Optional[str]) -> None:
    """Refuse an unknown fusion, a run that cannot be loaded, and ``--fusion`` on a run of another
    method, in one line before anything is loaded or written (SystemExit, exit status 1)."""
    if fusion is not None:
        try:
            parse_fusion_mode(fusion)
        except FusionModeError as error:
            raise SystemExit(f"{PROG}: --fusion: {error}") from None
    try:
        check_trained_run(load_config, scalar_only=fusion is not None)
    except RunError as error:
        raise SystemExit(f"{PROG}: {error}") from None


@dataclass
class _FusionOption:
    """Adds ``--fusion`` to one of ns-render's commands (put first among the bases)."""

    fusion: Optional[str] = None
    """nearest, nearest-guarded, nearest-idw, global, surface, idw, global-only or block:K (default: the run's configured fusion)."""

    def main(self) -> None:
        check_arguments(self.load_config, self.fusion)  # type: ignore[attr-defined]
        with fusion_applied(self.fusion):
            super().main()  # type: ignore[misc]


@dataclass
class FusionRenderCameraPath(_FusionOption, ns_render.RenderCameraPath):
    """Render a camera path (as ``ns-render camera-path``) with a chosen fusion."""


@dataclass
class FusionRenderInterpolated(_FusionOption, ns_render.RenderInterpolated):
    """Render a trajectory interpolated between training or eval cameras, with a chosen fusion."""


@dataclass
class FusionSpiralRender(_FusionOption, ns_render.SpiralRender):
    """Render a spiral trajectory, with a chosen fusion."""


@dataclass
class FusionDatasetRender(_FusionOption, ns_render.DatasetRender):
    """Render the dataset's images (train/val/test split), with a chosen fusion."""


Commands = tyro.conf.FlagConversionOff[
    Union[
        Annotated[FusionRenderCameraPath, tyro.conf.subcommand(name="camera-path")],
        Annotated[FusionRenderInterpolated, tyro.conf.subcommand(name="interpolate")],
        Annotated[FusionSpiralRender, tyro.conf.subcommand(name="spiral")],
        Annotated[FusionDatasetRender, tyro.conf.subcommand(name="dataset")],
    ]
]


def entrypoint() -> None:
    """Console script ``scalar-nerf-render``."""
    tyro.extras.set_accent_color("bright_yellow")
    tyro.cli(Commands).main()


if __name__ == "__main__":
    entrypoint()
