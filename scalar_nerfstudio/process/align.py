"""The capture's frame: where process-data puts the reconstruction.

With EXIF GPS in every registered photo, the reconstruction is fitted (a similarity: scale, rotation,
translation; GPS fixes that jumped are dropped) to the photos' GPS positions in a local
east-north-up frame centred at their mean position: units are metres and +z is up. Consumer GPS
altitude often drifts by tens of metres over a flight while the horizontal position holds to a few
metres; when the 3-D fit would tilt the cameras' own level (:func:`geo.camera_up`) by more than
:data:`MAX_GPS_TILT_DEG`, up comes from the cameras instead and GPS gives the horizontal position,
heading and scale (a fit in the horizontal plane) and the mean height.

Without GPS the reconstruction stays in COLMAP's scale (arbitrary units), moved so the cameras'
centroid is the origin and turned so the cameras' up (:func:`geo.camera_up`) is +z.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Sequence

import numpy as np

from scalar_nerfstudio.process import geo

#: Largest tilt (degrees) between the cameras' level and a 3-D GPS fit's up that the fit may keep.
MAX_GPS_TILT_DEG = 10.0
_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class CaptureFrame:
    """The similarity from COLMAP's frame to the capture's frame, and what that frame is."""

    scene_from_colmap: geo.Similarity
    kind: str
    """``enu``: metres, east-north-up about ``gps_origin`` (up from the GPS fit); ``enu-level``: the
    same with up from the cameras' level; ``up``: COLMAP's units, +z the cameras' up."""
    gps_origin: Optional[np.ndarray] = None
    """[3] lat, lon (degrees), altitude (m) of the ENU origin (``enu`` kinds only)."""
    gps_rms_m: Optional[float] = None
    """RMS distance between the fitted camera centres and their GPS positions (horizontal only for
    ``enu-level``), metres."""
    gps_used: int = 0
    """Photos whose GPS positions the fit used."""
    note: str = ""
    """How up was found, and why GPS was not (fully) used."""

    def _gps_origin(self) -> np.ndarray:
        """[3] ``gps_origin``, which the ``enu`` kinds have."""
        if self.gps_origin is None:
            raise ValueError(f"a {self.kind!r} capture frame needs its gps_origin")
        return self.gps_origin

    def describe(self) -> str:
        if self.kind in ("enu", "enu-level"):
            lat, lon, alt = self._gps_origin()
            where = "horizontal " if self.kind == "enu-level" else ""
            text = (
                f"metres, east-north-up about the photos' mean GPS position ({lat:.7f}, {lon:.7f}, {alt:.1f} m); "
                f"camera centres lie {self.gps_rms_m:.2f} m RMS ({where}distance) from their GPS positions ({self.gps_used} photos)"
            )
        else:
            text = "COLMAP's units (no GPS scale), origin at the cameras' centroid, +z up"
        return f"{text}; {self.note}" if self.note else text

    def to_json(self) -> dict:
        out = {"kind": self.kind, "scene_from_colmap": self.scene_from_colmap.matrix().tolist(), "units": "m" if self.kind != "up" else "colmap"}
        if self.kind != "up":
            out.update(gps_origin_lat_lon_alt=[float(v) for v in self._gps_origin()], gps_rms_m=self.gps_rms_m, gps_used=self.gps_used)
        if self.note:
            out["note"] = self.note
        return out


def _up_note(how: str) -> str:
    return "up from the cameras' level image rows" if how == "level" else "up along the cameras' mean image-up direction"


def _level_fit(centres: np.ndarray, enu: np.ndarray, up: np.ndarray) -> tuple:
    """Similarity with rotation = (yaw about z) @ (``up`` -> +z): a robust 2-D fit of the levelled
    centres' horizontal positions to the GPS ones, and the median height offset. Returns
    (similarity, keep mask, horizontal RMS in m, vertical RMS in m)."""
    level = geo.rotation_between(up, _Z)
    levelled = centres @ level.T
    flat, keep = geo.robust_umeyama(levelled[:, :2], enu[:, :2])
    rotation = np.eye(3)
    rotation[:2, :2] = flat.rotation
    heights = flat.scale * levelled[:, 2]
    offset = float(np.median(enu[keep, 2] - heights[keep]))
    sim = geo.Similarity(flat.scale, rotation @ level, np.array([*flat.translation, offset]))
    residual = sim.apply(centres) - enu
    horizontal = float(np.sqrt(np.mean(np.sum(residual[keep, :2] ** 2, axis=1))))
    vertical = float(np.sqrt(np.mean(residual[keep, 2] ** 2)))
    return sim, keep, horizontal, vertical


def capture_frame(names: Sequence[str], camera_to_world_cv: np.ndarray, gps: Dict[str, np.ndarray], *,
                  gps_origin_from: Optional[Sequence[np.ndarray]] = None) -> CaptureFrame:
    """Choose the capture's frame for a reconstruction.

    Args:
        names: [N] registered photos.
        camera_to_world_cv: [N, 4, 4] their poses in COLMAP's frame (OpenCV axes).
        gps: photo name -> [3] lat, lon, alt for the photos that have GPS.
        gps_origin_from: the GPS positions whose mean is the ENU origin (default: the registered photos').
    """
    poses = np.asarray(camera_to_world_cv, dtype=np.float64)
    centres = poses[:, :3, 3]
    up, how = geo.camera_up(poses)
    notes = []
    if gps and all(name in gps for name in names):
        positions = np.stack([gps[name] for name in names])
        origin = geo.mean_origin(np.stack(list(gps_origin_from)) if gps_origin_from is not None else positions)
        enu = geo.wgs84_to_enu(positions, origin)
        try:
            sim, keep = geo.robust_umeyama(centres, enu)
        except ValueError as error:
            notes.append(f"GPS not used: {error}")
        else:
            tilt = float(np.degrees(np.arccos(np.clip((sim.rotation @ up) @ _Z, -1.0, 1.0))))
            if tilt <= MAX_GPS_TILT_DEG or how != "level":
                rms = float(np.sqrt(np.mean(np.sum((sim.apply(centres[keep]) - enu[keep]) ** 2, axis=1))))
                note = f"up from the GPS fit ({tilt:.1f} deg from the cameras' level)" if how == "level" else "up from the GPS fit"
                return CaptureFrame(sim, "enu", gps_origin=origin, gps_rms_m=rms, gps_used=int(keep.sum()), note=note)
            try:
                sim, keep, horizontal, vertical = _level_fit(centres, enu, up)
            except ValueError as error:
                notes.append(f"GPS not used: {error}")
            else:
                note = (
                    f"GPS altitudes disagree with the cameras' level (a 3-D fit tilts it {tilt:.0f} deg; heights differ "
                    f"{vertical:.1f} m RMS): up from the cameras' level image rows, horizontal position, heading and scale from GPS"
                )
                return CaptureFrame(sim, "enu-level", gps_origin=origin, gps_rms_m=horizontal, gps_used=int(keep.sum()), note=note)
    elif gps:
        missing = [name for name in names if name not in gps]
        notes.append(f"GPS not used: {len(missing)} registered photo(s) have none, e.g. {missing[0]}")
    sim, how = geo.up_alignment(poses)
    return CaptureFrame(sim, "up", note="; ".join([_up_note(how), *notes]))
