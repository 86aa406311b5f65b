"""A large procedural town written in nerfstudio format: the project's own scene that is too big for
one hash table.

The town is a grid of streets lined with box buildings, enclosed by a ring of buildings so that every
street ends at a facade (:mod:`.layout`). Cameras capture it from a vehicle's rig on the streets, on
foot, or from a drone flying over it (:mod:`.cameras`). Everything is ray-cast with numpy
(:mod:`.raycast`, :mod:`.render`); textures are pure functions of the hit point, so every view agrees,
and the lighting is fixed (:mod:`.materials`). :func:`write_town` writes the scene folder, images,
depth images (16-bit PNGs, or ``.npy`` for a high flight) and scene.json (:mod:`.scene_folder`). Only
numpy and PIL are needed (a progress bar uses rich or tqdm when installed).

Modules, each importing only those above it: :mod:`.config`, :mod:`.layout`, :mod:`.raycast`,
:mod:`.materials`, :mod:`.render`, :mod:`.cameras`, :mod:`.scene_folder`. This package's namespace
is their public API.
"""

from scalar_nerfstudio.scenes.town.cameras import town_camera_poses, town_intrinsics
from scalar_nerfstudio.scenes.town.config import DEPTH_PNG_MAX_M, DEPTH_PNG_UNIT_M, TownConfig, blocks_for_extent
from scalar_nerfstudio.scenes.town.layout import (
    Town,
    build_town,
    points_inside_buildings,
    points_on_streets,
    town_boxes,
)
from scalar_nerfstudio.scenes.town.raycast import GROUND, SKY, TownHits, intersect_town
from scalar_nerfstudio.scenes.town.render import render_town_image, render_town_rays
from scalar_nerfstudio.scenes.town.scene_folder import depth_suffix, iter_frames, load_town, read_depth, write_town

__all__ = [
    "DEPTH_PNG_MAX_M",
    "DEPTH_PNG_UNIT_M",
    "GROUND",
    "SKY",
    "Town",
    "TownConfig",
    "TownHits",
    "blocks_for_extent",
    "build_town",
    "depth_suffix",
    "intersect_town",
    "iter_frames",
    "load_town",
    "points_inside_buildings",
    "points_on_streets",
    "read_depth",
    "render_town_image",
    "render_town_rays",
    "town_boxes",
    "town_camera_poses",
    "town_intrinsics",
    "write_town",
]
