"""The capture's frame: where process-data puts the reconstruction.

With EXIF GPS in every registered photo, the reconstruction is fitted (a similarity: scale, rotation,
translation; GPS fixes that jumped are dropped) to the photos' GPS positions in a local
east-north-up frame centred at their mean position: units are metres and +z is up. Without GPS it
stays in COLMAP's frame and scale (arbitrary units), moved so the cameras' centroid is the origin
and turned so the cameras' mean up direction is +z.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Sequence

import numpy as np

from scalar_nerfstudio.process import geo


@dataclass(frozen=True)
class CaptureFrame:
    """The similarity from COLMAP's frame to the capture's frame, and what that frame is."""

    scene_from_colmap: geo.Similarity
    kind: str
    """``enu``: metres, east-north-up about ``gps_origin``; ``up``: COLMAP's units, +z the cameras' mean up."""
    gps_origin: Optional[np.ndarray] = None
    """[3] lat, lon (degrees), altitude (m) of the ENU origin (``enu`` only)."""
    gps_rms_m: Optional[float] = None
    """RMS distance between the fitted camera centres and their GPS positions, metres (``enu`` only)."""
    gps_used: int = 0
    """Photos whose GPS positions the fit used (``enu`` only)."""
    note: str = ""
    """Why GPS was not used, when photos had some."""

    def describe(self) -> str:
        if self.kind == "enu":
            lat, lon, alt = self.gps_origin
            return (
                f"metres, east-north-up about the photos' mean GPS position ({lat:.7f}, {lon:.7f}, {alt:.1f} m); "
                f"camera centres lie {self.gps_rms_m:.2f} m RMS from their GPS positions ({self.gps_used} photos)"
            )
        text = "COLMAP's units (no GPS scale), origin at the cameras' centroid, +z along the cameras' mean up direction"
        return f"{text} ({self.note})" if self.note else text

    def to_json(self) -> dict:
        out = {"kind": self.kind, "scene_from_colmap": self.scene_from_colmap.matrix().tolist(), "units": "m" if self.kind == "enu" else "colmap"}
        if self.kind == "enu":
            out.update(gps_origin_lat_lon_alt=[float(v) for v in self.gps_origin], gps_rms_m=self.gps_rms_m, gps_used=self.gps_used)
        if self.note:
            out["note"] = self.note
        return out


def capture_frame(names: Sequence[str], camera_to_world_cv: np.ndarray, gps: Dict[str, np.ndarray], gps_origin_from: Optional[Sequence[np.ndarray]] = None) -> CaptureFrame:
    """Choose the capture's frame for a reconstruction.

    Args:
        names: [N] registered photos.
        camera_to_world_cv: [N, 4, 4] their poses in COLMAP's frame (OpenCV axes).
        gps: photo name -> [3] lat, lon, alt for the photos that have GPS.
        gps_origin_from: the GPS positions whose mean is the ENU origin (default: the registered photos').
    """
    centres = np.asarray(camera_to_world_cv, dtype=np.float64)[:, :3, 3]
    note = ""
    if gps and all(name in gps for name in names):
        positions = np.stack([gps[name] for name in names])
        origin = geo.mean_origin(np.stack(list(gps_origin_from)) if gps_origin_from is not None else positions)
        enu = geo.wgs84_to_enu(positions, origin)
        try:
            sim, keep = geo.robust_umeyama(centres, enu)
        except ValueError as error:
            note = f"GPS not used: {error}"
        else:
            rms = float(np.sqrt(np.mean(np.sum((sim.apply(centres[keep]) - enu[keep]) ** 2, axis=1))))
            return CaptureFrame(sim, "enu", gps_origin=origin, gps_rms_m=rms, gps_used=int(keep.sum()))
    elif gps:
        missing = [name for name in names if name not in gps]
        note = f"GPS not used: {len(missing)} registered photo(s) have none, e.g. {missing[0]}"
    return CaptureFrame(geo.up_alignment(camera_to_world_cv), "up", note=note)
