"""When a nerfstudio model adds the ``normals`` output, its RGBA image, and the chunked loop of its camera
renders (:class:`NormalsOutput`, a mixin of :class:`~scalar_nerfstudio.models.scalar_model.ScalarModel`
and :class:`~scalar_nerfstudio.models.scene_model.ScalarSceneModel`; :func:`render_in_chunks`)."""

from __future__ import annotations

from collections import defaultdict
from contextlib import contextmanager
from typing import Callable, Dict, Iterator, List, Literal, Tuple, get_args

import torch
from nerfstudio.cameras.rays import RayBundle
from torch import Tensor

from scalar_nerfstudio.device_sizes import render_rays_per_chunk
from scalar_nerfstudio.model_components.rendering import EVAL_BACKGROUND

RenderNormals = Literal["rays", "always", "never"]
RENDER_NORMALS: Tuple[str, ...] = get_args(RenderNormals)


def check_render_normals(mode: str) -> RenderNormals:
    """``mode`` if it is one of :data:`RENDER_NORMALS`, else a ValueError naming them."""
    if mode not in RENDER_NORMALS:
        raise ValueError(f"render_normals {mode!r}: expected one of {', '.join(RENDER_NORMALS)}")
    return mode  # type: ignore[return-value]


def render_in_chunks(
    forward: Callable[..., Dict[str, Tensor]], camera_ray_bundle: RayBundle, *, rays_per_chunk: int, device: torch.device
) -> Dict[str, Tensor]:
    """nerfstudio's camera render loop: ``forward`` on ``rays_per_chunk`` rays at a time of an
    ``[H, W]`` camera ray bundle (moved to ``device``), each tensor output put back on the bundle's
    device as ``[H, W, C]``."""
    if rays_per_chunk < 1:
        raise ValueError(f"eval_num_rays_per_chunk {rays_per_chunk}: must be >= 1")
    input_device = camera_ray_bundle.directions.device
    height, width = camera_ray_bundle.origins.shape[:2]
    num_rays = len(camera_ray_bundle)
    chunks: Dict[str, List[Tensor]] = defaultdict(list)
    for start in range(0, num_rays, rays_per_chunk):
        rays = camera_ray_bundle.get_row_major_sliced_ray_bundle(start, start + rays_per_chunk).to(device)
        for name, output in forward(ray_bundle=rays).items():
            if isinstance(output, Tensor):
                chunks[name].append(output.to(input_device))
    return {name: torch.cat(parts).view(height, width, -1) for name, parts in chunks.items()}


class NormalsOutput:
    """When a nerfstudio :class:`Model` adds the ``normals`` output; its RGBA image (mixin).

    ``render_normals`` (initialised from the config, settable at run time, or for a block of code
    with :meth:`rendering_normals`) is "rays", "always" or "never" (see
    :attr:`ScalarModelConfig.render_normals`). Camera images are told apart from ray batches by
    :meth:`get_outputs_for_camera_ray_bundle`, through which every camera render of nerfstudio
    (eval, ns-render, the viewer, the TSDF export) passes.
    """

    training: bool
    _render_normals: RenderNormals
    _camera_renders: int

    def _init_normals_output(self, mode: str) -> None:
        self._render_normals = check_render_normals(mode)
        self._camera_renders = 0

    @property
    def render_normals(self) -> RenderNormals:
        """"rays", "always" or "never": when rendering outside training adds ``normals``."""
        return self._render_normals

    @render_normals.setter
    def render_normals(self, mode: RenderNormals) -> None:
        self._render_normals = check_render_normals(mode)

    @contextmanager
    def rendering_normals(self, mode: RenderNormals = "always") -> Iterator[None]:
        """Use ``mode`` for :attr:`render_normals` inside the ``with`` block."""
        previous = self._render_normals
        self.render_normals = mode
        try:
            yield
        finally:
            self._render_normals = previous

    def normals_wanted(self) -> bool:
        """Whether the render running now adds ``normals`` (never in training)."""
        if self.training or self._render_normals == "never":
            return False
        return self._render_normals == "always" or self._camera_renders == 0

    @torch.no_grad()
    def get_outputs_for_camera_ray_bundle(self, camera_ray_bundle: RayBundle) -> Dict[str, Tensor]:
        """nerfstudio's chunked camera render, marked as a camera image (see :meth:`normals_wanted`),
        in chunks of ``eval_num_rays_per_chunk`` rays (None: by the device, :func:`render_rays_per_chunk`)."""
        self._camera_renders += 1
        try:
            chunk = render_rays_per_chunk(self.config.eval_num_rays_per_chunk, self.device)  # type: ignore[attr-defined]
            return render_in_chunks(self.forward, camera_ray_bundle, rays_per_chunk=chunk, device=self.device)  # type: ignore[attr-defined]
        finally:
            self._camera_renders -= 1

    def get_rgba_image(self, outputs: Dict[str, Tensor], output_name: str = "rgb") -> Tensor:
        """[..., 4]: the colour without the background and the accumulation as alpha.

        Outside training the background is :data:`EVAL_BACKGROUND` grey, so ``rgb = c + (1 - a) grey``
        and the foreground colour is ``c / a``. nerfstudio's exporters keep the points / pixels of
        alpha > 0.5 (``ns-export pointcloud``) and texture meshes with this colour.
        """
        accumulation_name = output_name.replace("rgb", "accumulation")
        if output_name not in outputs or accumulation_name not in outputs:
            raise KeyError(f"get_rgba_image needs outputs {output_name!r} and {accumulation_name!r}; got {sorted(outputs)}")
        rgb = outputs[output_name]
        accumulation = outputs[accumulation_name]
        if accumulation.dim() < rgb.dim():
            accumulation = accumulation.unsqueeze(-1)
        foreground = (rgb - (1.0 - accumulation) * EVAL_BACKGROUND) / accumulation.clamp_min(1e-6)
        foreground = torch.where(accumulation > 1e-6, foreground, torch.full_like(foreground, EVAL_BACKGROUND))
        return torch.cat((torch.nan_to_num(foreground, nan=EVAL_BACKGROUND).clamp(0.0, 1.0), accumulation.clamp(0.0, 1.0)), dim=-1)
