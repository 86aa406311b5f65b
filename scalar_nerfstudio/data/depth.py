"""A scene's depth images (``depth_file_path`` in transforms.json): each pixel's distance along its
ray, and how far the scene they show extends.

Evaluation scores rendered depth against :func:`ray_depth_image`; the pipeline bounds a new run's
scene by :func:`scene_radius_logged` (rays end where they leave that sphere, see
``model_components/sampling.sphere_interval``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, NamedTuple, Optional, Sequence

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.utils.data_utils import get_depth_image_from_path
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

#: Images read to bound the scene (evenly spaced over the training images).
BOUND_IMAGES = 64
#: Share of the known-depth surface points the bound's radius holds before its margin.
BOUND_QUANTILE = 0.999
#: The bound's radius over that of the farthest surface points: what lies beyond them (sky, the
#: town's far facades seen from few views) sits within this margin.
BOUND_MARGIN = 2.0
#: Surface points taken per image (evenly strided), so memory stays bounded on large images.
BOUND_POINTS_PER_IMAGE = 16384


class RayDepthImage(NamedTuple):
    """One image's depth as distances along its rays, with the rays (all [H, W, ...], float32)."""

    ray_depth: Tensor
    """[H, W] distance from the camera centre along each pixel's ray; 0 where unknown."""
    origins: Tensor
    """[H, W, 3] ray origins (the dataparser's frame)."""
    directions: Tensor
    """[H, W, 3] unit ray directions."""


def depth_scale(outputs: DataparserOutputs) -> float:
    """Model units per unit stored in the depth images: ``depth_unit_scale_factor`` (metres per
    unit, nerfstudio's default 1e-3) times the dataparser's scale."""
    return float(outputs.metadata.get("depth_unit_scale_factor", 1e-3)) * float(outputs.dataparser_scale)


def missing_depth_files(metadata: Dict[str, Any]) -> Optional[List[Path]]:
    """The depth files that a dataparser's (or dataset's) ``metadata`` names and that are not there;
    None when it names none (the scene has no ``depth_file_path``)."""
    filenames = metadata.get("depth_filenames")
    if filenames is None:
        return None
    return [Path(path) for path in filenames if not Path(path).is_file()]


def ray_depth_image(cameras: Cameras, image_idx: int, *, path: Path, scale: float) -> RayDepthImage:
    """Image ``image_idx``'s depth file at ``path`` as distance along each pixel's ray.

    The depth images hold z-depth (along the optical axis, nerfstudio's convention) in units that
    ``scale`` turns into model units; each pixel's ray length per unit of z-depth
    (``directions_norm``) comes from the camera, so distortion is accounted for. The image is read
    by nerfstudio's reader (16/32-bit images, ``.npy``) at the camera's size, resized by nearest so
    unknown pixels (0: sky, or farther than the format holds) stay unknown.

    Raises:
        ValueError: naming ``path`` when it cannot be read.
    """
    camera = cameras[image_idx]
    height, width = int(camera.height), int(camera.width)
    try:
        z_depth = get_depth_image_from_path(Path(path), height, width, scale)[..., 0].float()  # [H, W]
    except Exception as error:  # cv2 gives None for a file it cannot read, and fails on that
        raise ValueError(f"{path}: cannot read this depth image ({type(error).__name__}: {error})") from error
    rays = cameras[image_idx : image_idx + 1].generate_rays(camera_indices=0, keep_shape=True)
    norms = rays.metadata["directions_norm"].reshape(z_depth.shape).float()  # [H, W]
    ray_depth = torch.where(z_depth > 0, z_depth * norms, torch.zeros_like(z_depth))
    return RayDepthImage(ray_depth, rays.origins.reshape(height, width, 3).float(), rays.directions.reshape(height, width, 3).float())


def surface_radii(image: RayDepthImage, max_points: int = BOUND_POINTS_PER_IMAGE) -> Tensor:
    """[M] distances from the frame's origin of the image's known-depth surface points (at most
    ``max_points``, evenly strided)."""
    known = torch.nonzero(image.ray_depth.reshape(-1) > 0).squeeze(-1)
    known = known[:: max(1, -(-known.numel() // max_points))]
    points = image.origins.reshape(-1, 3)[known] + image.directions.reshape(-1, 3)[known] * image.ray_depth.reshape(-1, 1)[known]
    radii = points.norm(dim=-1)
    return radii[torch.isfinite(radii)]


def scene_radius_from_depth(
    outputs: DataparserOutputs,
    *,
    max_images: int = BOUND_IMAGES,
    quantile: float = BOUND_QUANTILE,
    margin: float = BOUND_MARGIN,
) -> Optional[float]:
    """The radius, around the dataparser frame's origin, of the sphere that holds the scene its
    depth images show: ``margin`` times the ``quantile`` of the known surface points' distances
    from the origin, over up to ``max_images`` evenly spaced images. None when the scene has no
    depth images, one of them is missing, or no pixel's depth is known.

    Raises:
        ValueError: naming a depth file that is there but cannot be read.
    """
    missing = missing_depth_files(outputs.metadata)
    if missing is None or missing:
        return None
    filenames: Sequence[str] = outputs.metadata["depth_filenames"]
    count = len(filenames)
    if count == 0:
        return None
    picked = sorted({round(i * (count - 1) / max(max_images - 1, 1)) for i in range(min(max_images, count))})
    scale = depth_scale(outputs)
    radii = torch.cat([surface_radii(ray_depth_image(outputs.cameras, i, path=Path(filenames[i]), scale=scale)) for i in picked])
    if radii.numel() == 0:
        return None
    return float(margin * torch.quantile(radii.double(), quantile))


def scene_radius_logged(outputs: DataparserOutputs) -> Optional[float]:
    """:func:`scene_radius_from_depth`, with one log line saying the radius, or why there is none
    (depth files missing, or no pixel of known depth); silent for a scene without depth images."""
    missing = missing_depth_files(outputs.metadata)
    if missing is None:
        return None
    if missing:
        CONSOLE.print(f"[yellow]scene not bounded by depth: {len(missing)} of its depth files are missing (first: {missing[0]})")
        return None
    radius = scene_radius_from_depth(outputs)
    if radius is None:
        CONSOLE.print("[yellow]scene not bounded by depth: no pixel of its depth images has a known depth")
    else:
        CONSOLE.print(f"scene bounded by its depth images: rays end {radius:.3g} units from the centre "
                      "(--pipeline.model.scene-radius; --pipeline.scene-radius-from-depth False: unbounded)")
    return radius
