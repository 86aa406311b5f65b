"""Rendering the town: shaded colour and depth of rays, and whole frames (with optional supersampling).

Lighting is fixed (Lambertian surfaces under a sun that does not move, plus ambient light); rays that
hit nothing see the sky gradient at infinity.
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple

import numpy as np

from scalar_nerfstudio.scenes.town.config import TownConfig
from scalar_nerfstudio.scenes.town.layout import Town
from scalar_nerfstudio.scenes.town.materials import SUN, facade_colour, ground_colour, roof_colour, sky_colour
from scalar_nerfstudio.scenes.town.raycast import CHUNK_RAYS, GROUND, SKY, TownHits, intersect_town

__all__ = ["render_town_image", "render_town_rays"]


#: The smallest |cos| between a ray and the surface it hits that widens its footprint (grazing rays: 5x at most).
GRAZING_COS = 0.2


def _shade(town: Town, origins: np.ndarray, directions: np.ndarray, hits: TownHits, sample_angle: float) -> np.ndarray:
    """Colour of each ray's hit: albedo x (ambient + sun) for surfaces, the sky gradient otherwise ([P, 3]).
    ``sample_angle``: radians one colour sample spans (0: the point itself), for the textures' footprints."""
    rgb = sky_colour(directions)
    hit = hits.surface != SKY
    depth = np.where(hit, hits.depth, 0.0)  # [P]
    points = origins + directions * depth[:, None]
    incidence = np.maximum(np.abs(np.sum(hits.normal * directions, axis=1)), GRAZING_COS)
    footprint = depth * float(sample_angle) / incidence  # [P] metres of surface a sample covers
    ground = np.flatnonzero(hits.surface == GROUND)
    albedo = np.zeros_like(rgb)
    if len(ground):
        albedo[ground] = ground_colour(town, points[ground, 0], points[ground, 1], footprint=footprint[ground])
    roofs = np.flatnonzero((hits.surface >= 0) & (hits.axis == 2))
    if len(roofs):
        albedo[roofs] = roof_colour(town, hits.surface[roofs], x=points[roofs, 0], y=points[roofs, 1], footprint=footprint[roofs])
    walls = np.flatnonzero((hits.surface >= 0) & (hits.axis != 2))
    if len(walls):
        b = hits.surface[walls]
        ax = hits.axis[walls]
        p = points[walls]
        along = 1 - ax  # facade normal along x -> u runs along y, and vice versa
        rows = np.arange(len(walls))
        u = p[rows, along] - town.lo[b, along]
        width = town.hi[b, along] - town.lo[b, along]
        face = ax * 2 + (hits.normal[walls, ax] > 0)
        albedo[walls] = facade_colour(town, b, face, u=u, v=p[:, 2], width=width, footprint=footprint[walls])
    light = 0.5 + 0.55 * np.clip(hits.normal @ SUN, 0.0, 1.0)
    surface_rgb = albedo * light[:, None]
    rgb[hit] = surface_rgb[hit]
    return np.clip(rgb, 0.0, 1.0)


def render_town_rays(origins: np.ndarray, directions: np.ndarray, town: Town, *, sample_angle: float = 0.0) -> Tuple[np.ndarray, np.ndarray]:
    """Ray-cast the town.

    Args:
        origins: [N, 3] ray origins (metres), outside the buildings.
        directions: [N, 3] ray directions (need not be normalised).
        town: from :func:`build_town` or :func:`load_town`.
        sample_angle: radians each ray's colour sample spans: the textures average their detail over the
            surface it covers (``"filtered"`` textures; materials.py). 0: the colour at the hit point.

    Returns:
        rgb: [N, 3] colour in [0, 1]; depth: [N] distance to the first hit along the normalised
        direction (inf for the sky).
    """
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if origins.shape != directions.shape:
        raise ValueError(f"render_town_rays: origins {origins.shape} and directions {directions.shape} differ in shape")
    rgb = np.empty_like(origins)
    depth = np.empty(len(origins))
    # Chunks of a few thousand rays keep every temporary small (cache-friendly, no page faults).
    chunk = CHUNK_RAYS
    for start in range(0, len(origins), chunk):
        o, d = origins[start : start + chunk], directions[start : start + chunk]
        hits = intersect_town(o, d, town, chunk_rays=chunk)
        unit = d / np.linalg.norm(d, axis=1, keepdims=True)
        rgb[start : start + chunk] = _shade(town, o, unit, hits, sample_angle)
        depth[start : start + chunk] = hits.depth
    return rgb, depth


def _pixel_directions(config: TownConfig, offsets: Sequence[Tuple[float, float]]) -> np.ndarray:
    """[S, H * W, 3] camera-space ray directions (OpenGL: -z forward) through the pixel at
    sub-pixel ``offsets`` (0.5, 0.5 = centre), not normalised (z = -1)."""
    focal = config.focal_px
    cx, cy = config.width / 2.0, config.height / 2.0
    out = []
    for du, dv in offsets:
        u, v = np.meshgrid(np.arange(config.width) + du, np.arange(config.height) + dv)
        out.append(np.stack([(u - cx) / focal, -(v - cy) / focal, -np.ones_like(u)], axis=-1).reshape(-1, 3))
    return np.stack(out)


def render_town_image(town: Town, camera_to_world: np.ndarray, supersample: Optional[int] = None) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one frame of ``town.config``'s size from a [4, 4] (or [3, 4]) OpenGL camera-to-world.

    Args:
        supersample: colour samples per pixel along each axis (default ``town.config.supersample``).

    Returns:
        rgb: [H, W, 3] float colour in [0, 1]; ray_depth: [H, W] distance from the camera centre
        to the pixel centre's hit (inf: sky); z_depth: [H, W] the same along the optical axis
        (what the depth PNGs hold, in millimetres).
    """
    config = town.config
    ss = config.supersample if supersample is None else int(supersample)
    if ss < 1:
        raise ValueError(f"render_town_image: supersample must be >= 1, got {ss}")
    c2w = np.asarray(camera_to_world, dtype=np.float64)[:3, :4]
    centre = _pixel_directions(config, [(0.5, 0.5)])[0]  # [H*W, 3]
    cos = 1.0 / np.linalg.norm(centre, axis=1)
    directions = centre @ c2w[:3, :3].T
    origins = np.broadcast_to(c2w[:3, 3], directions.shape)
    # A sample spans 1 / (focal x ss) radians at the image centre (a little less towards the edges).
    sample_angle = 1.0 / (config.focal_px * ss) if config.textures == "filtered" else 0.0
    if ss == 1:
        rgb, depth = render_town_rays(origins, directions, town, sample_angle=sample_angle)
    else:
        depth = intersect_town(origins, directions, town).depth
        offsets = [((a + 0.5) / ss, (b + 0.5) / ss) for b in range(ss) for a in range(ss)]
        rgb = np.zeros_like(directions)
        for sub in _pixel_directions(config, offsets):
            rgb += render_town_rays(origins, sub @ c2w[:3, :3].T, town, sample_angle=sample_angle)[0]
        rgb /= len(offsets)
    shape = (config.height, config.width)
    return rgb.reshape(*shape, 3), depth.reshape(shape), (depth * cos).reshape(shape)
