"""Ray colliders: where each ray starts and ends (nerfstudio's near/far planes, kept inside a sphere)."""

from __future__ import annotations

import math
from typing import Optional

import torch
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.model_components.scene_colliders import NearFarCollider

from scalar_nerfstudio.model_components.sampling import sphere_interval


class BoundedNearFarCollider(NearFarCollider):
    """nerfstudio's NearFarCollider, and, with a ``scene_radius``, rays kept inside the sphere of that
    radius around the origin: a ray starts no earlier than where it enters the sphere and ends
    where it leaves it (or at the far plane, if that comes first); a ray that misses it is empty
    (near = far) and renders as the background."""

    def __init__(self, near_plane: float, far_plane: float, *, reset_near_plane: bool, scene_radius: Optional[float] = None) -> None:
        super().__init__(near_plane=near_plane, far_plane=far_plane, reset_near_plane=reset_near_plane)
        if scene_radius is not None and not (math.isfinite(scene_radius) and scene_radius > 0):
            raise ValueError(f"scene radius {scene_radius}: must be a finite number > 0 (None: unbounded)")
        self.scene_radius = scene_radius

    def set_nears_and_fars(self, ray_bundle: RayBundle) -> RayBundle:
        ray_bundle = super().set_nears_and_fars(ray_bundle)
        if self.scene_radius is None or ray_bundle.nears is None or ray_bundle.fars is None:
            return ray_bundle
        shape = ray_bundle.nears.shape
        t_entry, t_exit = sphere_interval(ray_bundle.origins.reshape(-1, 3), ray_bundle.directions.reshape(-1, 3), self.scene_radius)
        nears = torch.maximum(ray_bundle.nears.reshape(-1, 1), t_entry.to(ray_bundle.nears.dtype))
        fars = torch.maximum(torch.minimum(ray_bundle.fars.reshape(-1, 1), t_exit.to(ray_bundle.fars.dtype)), nears)
        ray_bundle.nears = nears.reshape(shape)
        ray_bundle.fars = fars.reshape(shape)
        return ray_bundle
