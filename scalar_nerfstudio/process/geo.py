"""Geometry of a capture's frame: GPS to a local metric frame, similarity fits, the up direction.

numpy only. Conventions: positions are [N, 3] float64; a similarity ``(scale, rotation, translation)``
maps ``x`` to ``scale * rotation @ x + translation``; camera-to-world poses are [N, 4, 4] with
OpenCV camera axes (x right, y down, z forward) unless a name says OpenGL.
"""

from __future__ import annotations

from typing import NamedTuple, Tuple

import numpy as np

# WGS84 ellipsoid (what EXIF GPS positions refer to).
_WGS84_A = 6378137.0
_WGS84_F = 1.0 / 298.257223563
_WGS84_E2 = _WGS84_F * (2.0 - _WGS84_F)


class Similarity(NamedTuple):
    """``x -> scale * rotation @ x + translation``."""

    scale: float
    rotation: np.ndarray
    """[3, 3] proper rotation."""
    translation: np.ndarray
    """[3]."""

    def apply(self, points: np.ndarray) -> np.ndarray:
        """[N, 3] points -> [N, 3] transformed points."""
        return self.scale * np.asarray(points, dtype=np.float64) @ self.rotation.T + self.translation

    def matrix(self) -> np.ndarray:
        """[4, 4] homogeneous matrix of the similarity."""
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rotation
        out[:3, 3] = self.translation
        return out

    def apply_to_poses(self, camera_to_world: np.ndarray) -> np.ndarray:
        """[N, 4, 4] camera-to-world poses -> the same cameras in the new frame (rotation part stays
        orthonormal: the scale moves the centres only)."""
        poses = np.array(camera_to_world, dtype=np.float64)
        poses[:, :3, :3] = self.rotation @ poses[:, :3, :3]
        poses[:, :3, 3] = self.apply(poses[:, :3, 3])
        return poses

    def inverse(self) -> "Similarity":
        """The similarity that undoes this one."""
        rotation = self.rotation.T
        return Similarity(1.0 / self.scale, rotation, -(rotation @ self.translation) / self.scale)


def identity() -> Similarity:
    """The identity similarity."""
    return Similarity(1.0, np.eye(3), np.zeros(3))


def wgs84_to_ecef(lat_lon_alt: np.ndarray) -> np.ndarray:
    """[N, 3] latitude, longitude (degrees) and ellipsoidal height (m) -> [N, 3] Earth-centred,
    Earth-fixed coordinates (m)."""
    lla = np.asarray(lat_lon_alt, dtype=np.float64).reshape(-1, 3)
    lat, lon, alt = np.radians(lla[:, 0]), np.radians(lla[:, 1]), lla[:, 2]
    n = _WGS84_A / np.sqrt(1.0 - _WGS84_E2 * np.sin(lat) ** 2)
    return np.stack(
        [
            (n + alt) * np.cos(lat) * np.cos(lon),
            (n + alt) * np.cos(lat) * np.sin(lon),
            (n * (1.0 - _WGS84_E2) + alt) * np.sin(lat),
        ],
        axis=1,
    )


def enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """[3, 3] rotation from ECEF axes to the local east-north-up axes at (lat, lon) in degrees."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    return np.array(
        [
            [-np.sin(lon), np.cos(lon), 0.0],
            [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)],
            [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)],
        ]
    )


def wgs84_to_enu(lat_lon_alt: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """[N, 3] GPS positions -> [N, 3] east, north, up in metres from ``origin`` ([3] lat, lon, alt)."""
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    ecef = wgs84_to_ecef(lat_lon_alt) - wgs84_to_ecef(origin[None])[0]
    return ecef @ enu_rotation(origin[0], origin[1]).T


def ecef_to_wgs84(ecef: np.ndarray) -> np.ndarray:
    """[N, 3] Earth-centred, Earth-fixed (m) -> [N, 3] latitude, longitude (degrees), height (m)
    (fixed-point iteration on the latitude; sub-millimetre near the Earth's surface)."""
    xyz = np.asarray(ecef, dtype=np.float64).reshape(-1, 3)
    lon = np.arctan2(xyz[:, 1], xyz[:, 0])
    p = np.hypot(xyz[:, 0], xyz[:, 1])
    lat = np.arctan2(xyz[:, 2], p * (1.0 - _WGS84_E2))
    for _ in range(10):
        n = _WGS84_A / np.sqrt(1.0 - _WGS84_E2 * np.sin(lat) ** 2)
        alt = p / np.cos(lat) - n
        lat = np.arctan2(xyz[:, 2], p * (1.0 - _WGS84_E2 * n / (n + alt)))
    n = _WGS84_A / np.sqrt(1.0 - _WGS84_E2 * np.sin(lat) ** 2)
    alt = p / np.cos(lat) - n
    return np.stack([np.degrees(lat), np.degrees(lon), alt], axis=1)


def enu_to_wgs84(enu: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """[N, 3] east, north, up (m) from ``origin`` ([3] lat, lon, alt) -> [N, 3] GPS positions."""
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    ecef = np.asarray(enu, dtype=np.float64).reshape(-1, 3) @ enu_rotation(origin[0], origin[1]) + wgs84_to_ecef(origin[None])[0]
    return ecef_to_wgs84(ecef)


def mean_origin(lat_lon_alt: np.ndarray) -> np.ndarray:
    """[3] the mean GPS position (lat, lon, alt), the origin of a capture's local frame (fine for
    captures of a few km; the mean of longitudes is not taken across the antimeridian)."""
    return np.asarray(lat_lon_alt, dtype=np.float64).reshape(-1, 3).mean(axis=0)


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = True) -> Similarity:
    """Least-squares similarity that maps [N, D] ``source`` onto [N, D] ``target`` (Umeyama 1991;
    D = 3, or 2 for a fit in the horizontal plane: then the rotation is [2, 2]).

    Raises:
        ValueError: for fewer than 3 points or points that do not span a plane (collinear or
            coincident: the rotation about their line is then undetermined).
    """
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    if src.ndim != 2 or src.shape != dst.shape or src.shape[1] not in (2, 3) or len(src) < 3:
        raise ValueError(f"a similarity needs at least 3 point pairs of 2 or 3 coordinates, got {src.shape} and {dst.shape}")
    dim = src.shape[1]
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mu_src, dst - mu_dst
    for name, points in (("source", src_c), ("target", dst_c)):
        spread = np.linalg.svd(points, compute_uv=False)
        if not (spread[0] > 0 and spread[1] > 1e-6 * spread[0]):
            raise ValueError(f"the {name} points are collinear or coincident (singular values {spread.round(6).tolist()})")
    covariance = dst_c.T @ src_c / len(src)
    u, d, vt = np.linalg.svd(covariance)
    sign = np.eye(dim)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[-1, -1] = -1.0
    rotation = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / (src_c**2).sum(axis=1).mean()) if with_scale else 1.0
    translation = mu_dst - scale * rotation @ mu_src
    return Similarity(scale, rotation, translation)


def robust_umeyama(source: np.ndarray, target: np.ndarray, *, rounds: int = 3, factor: float = 3.0) -> Tuple[Similarity, np.ndarray]:
    """:func:`umeyama`, then refit without pairs whose residual exceeds ``factor`` x the median
    residual (GPS fixes that jumped), ``rounds`` times.

    Returns:
        The similarity and the [N] bool mask of the pairs the last fit used.
    """
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    keep = np.ones(len(src), dtype=bool)
    sim = umeyama(src, dst)
    for _ in range(rounds):
        residual = np.linalg.norm(sim.apply(src) - dst, axis=1)
        new_keep = residual <= factor * max(float(np.median(residual)), 1e-9)
        if new_keep.sum() < 3 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
        sim = umeyama(src[keep], dst[keep])
    return sim, keep


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[3, 3] the smallest rotation taking direction ``a`` [3] to direction ``b`` [3]."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    if c < -1.0 + 1e-12:  # opposite: half a turn about any axis perpendicular to a
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


#: The image rows fix "up" when the cameras' x axes span a plane: the smallest eigenvalue of their
#: scatter is below this fraction of the middle one.
LEVEL_RATIO = 0.1


def camera_up(camera_to_world_cv: np.ndarray) -> Tuple[np.ndarray, str]:
    """[3] the up direction the cameras suggest, and how it was found.

    ``level``: photos are taken with level image rows (no roll), by hand or from a drone, so up is
    the direction most nearly perpendicular to every camera's x axis (the smallest eigenvector of
    their scatter; it needs x axes of several headings). Its sign makes the cameras' image-up (-y)
    point up and their viewing directions (+z) point down, on the whole. ``mean up``: with x axes of
    about one heading (a straight drive), the cameras' mean image-up direction.

    Args:
        camera_to_world_cv: [N, 4, 4] poses with OpenCV camera axes.
    """
    poses = np.asarray(camera_to_world_cv, dtype=np.float64)
    x_axes, image_up, view = poses[:, :3, 0], -poses[:, :3, 1], poses[:, :3, 2]
    values, vectors = np.linalg.eigh(x_axes.T @ x_axes / len(poses))
    if values[0] < LEVEL_RATIO * values[1]:
        up = vectors[:, 0]
        if (image_up @ up).sum() - (view @ up).sum() < 0:
            up = -up
        return up, "level"
    up = image_up.mean(axis=0)
    return (up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-9 else np.array([0.0, 0.0, 1.0])), "mean up"


def up_alignment(camera_to_world_cv: np.ndarray) -> Tuple[Similarity, str]:
    """The rigid transform (scale 1) that moves the cameras' centroid to the origin and turns
    :func:`camera_up` to +z (the frame of a capture without GPS), and how up was found.

    Args:
        camera_to_world_cv: [N, 4, 4] poses with OpenCV camera axes.
    """
    poses = np.asarray(camera_to_world_cv, dtype=np.float64)
    up, how = camera_up(poses)
    rotation = rotation_between(up, np.array([0.0, 0.0, 1.0]))
    centre = poses[:, :3, 3].mean(axis=0)
    return Similarity(1.0, rotation, -(rotation @ centre)), how


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[N] angles in degrees between [N, 3, 3] rotations ``a`` and ``b``."""
    relative = np.einsum("nji,njk->nik", np.asarray(a), np.asarray(b))
    cos = (np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
