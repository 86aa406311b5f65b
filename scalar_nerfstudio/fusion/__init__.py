"""Final image blending of block renders (SCALAR-NeRF Sec. 3.4).

Pure tensor functions (torch only, any device).  Shapes use ``K`` blocks, ``N`` pixels
(rays) and ``C`` channels.  Colours are linear RGB in [0, 1]; depths are in the world
units of the renders; positions (camera origins, block centres) must be in one and the
same coordinate frame (e.g. both in the dataparser's transformed frame).

Every mode is a set of per-pixel block weights (:func:`fusion_weights`, one-hot for the winner
modes) applied by :func:`fuse_weighted`. ``global``, ``idw`` and ``surface`` can be restricted per
pixel to a few blocks chosen by :func:`select_blocks` (those whose region holds the global model's
surface point): a block outside a pixel's selection is not rendered there (its values are NaN, which
every rule treats as "not available").

Modes (see :func:`parse_fusion_mode`):

* ``"global"``  -- per pixel, the block colour closest (L2) to the coarse global model's
  colour (the paper's global guidance).  Depth and accumulation follow the colour's winner.
* ``"idw"``     -- inverse distance weighting ``w_k ~ d_k^-gamma`` between the camera origin
  and the block centres (Block-NeRF style).
* ``"nearest"`` -- the block whose centre is nearest to the camera origin.
* ``"nearest-guarded"`` -- ``nearest``, except where that block is transparent and the global model
  opaque (:func:`guard_transparent`): the global model's values there. Guards against a block that
  did not learn what the global model shows (a block that never trained renders the background).
* ``"nearest-idw"`` -- the ``blocks_per_ray`` blocks whose centres are nearest to the camera origin,
  weighted by inverse distance ``d_k^-gamma`` (:func:`nearest_idw_weights`): ``nearest`` blended
  with its neighbours where a camera stands between blocks.
* ``"surface"`` -- the block whose region holds the surface the global model's depth points to:
  per pixel, the point ``o + t d`` at the global depth ``t`` is scored against every block's region
  (:func:`region_scores`, <= 1 inside it), the ``blocks_per_ray`` best are kept and weighted by
  inverse score (one block per ray: that block's colour).
* ``"global-only"`` -- the global model's outputs, no blocks.
* ``"block:<k>"`` -- block ``k`` only (debugging).

Modules, each importing only those above it: ``modes`` (names, parsing), ``numerics`` (shared checks
and float32-safe distances), ``selection`` (which blocks a ray may use), ``blend`` (applying weights),
``rules`` (the weights of each mode), ``outputs`` (fusing whole output dicts).
"""

from scalar_nerfstudio.fusion.blend import fuse_weighted, select_winner, weights_winner
from scalar_nerfstudio.fusion.modes import (
    FUSION_MODES,
    FusionMode,
    FusionModeError,
    ParsedFusionMode,
    parse_fusion_mode,
)
from scalar_nerfstudio.fusion.outputs import FUSED_KEYS, fuse_outputs
from scalar_nerfstudio.fusion.rules import (
    fuse_global_guided,
    fusion_weights,
    guard_transparent,
    idw_weights,
    nearest_idw_weights,
    score_weights,
    transparent_pixels,
)
from scalar_nerfstudio.fusion.selection import (
    nearest_block,
    nearest_blocks,
    region_scores,
    select_blocks,
    surface_points,
)

__all__ = [
    "FUSED_KEYS",
    "FUSION_MODES",
    "FusionMode",
    "FusionModeError",
    "ParsedFusionMode",
    "fuse_global_guided",
    "fuse_outputs",
    "fuse_weighted",
    "fusion_weights",
    "guard_transparent",
    "idw_weights",
    "nearest_block",
    "nearest_blocks",
    "nearest_idw_weights",
    "parse_fusion_mode",
    "region_scores",
    "score_weights",
    "select_blocks",
    "select_winner",
    "surface_points",
    "transparent_pixels",
    "weights_winner",
]
