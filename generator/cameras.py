"""Camera poses and pinhole projection in the dataset's convention (numpy only).

Poses are OpenGL camera-to-world 4 x 4 matrices, as in Blender and NeRF ``transforms_*.json``: the
camera looks down its local -Z with +Y up and +X right. Pixel coordinates are x right, y down, with the
centre of pixel (i, j) at (i + 0.5, j + 0.5); the principal point is the image centre; pixels are square
and ``camera_angle_x`` is the full horizontal field of view (Blender's sensor fit 'HORIZONTAL').
"""
from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np

__all__ = ["look_at", "train_cameras", "test_cameras", "intrinsics", "focal_length", "project",
           "camera_directions", "transforms_dict"]

_GOLDEN_FRACTION = (3.0 - math.sqrt(5.0)) / 2.0  # golden angle / 360 degrees
_PLASTIC = 1.324717957244746                         # R2 low-discrepancy sequence constant


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world matrix of a camera at ``eye`` looking at ``target`` with ``up`` roughly up.

    When the view direction is parallel to ``up`` (a camera straight overhead) the camera's up falls
    back to world +Y so that the pose stays defined.
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(3)
    target = np.asarray(target, dtype=np.float64).reshape(3)
    forward = target - eye
    dist = np.linalg.norm(forward)
    if dist < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    forward /= dist
    right = np.cross(forward, np.asarray(up, dtype=np.float64).reshape(3))
    if np.linalg.norm(right) < 1e-9:
        right = np.cross(forward, np.array([0.0, 1.0, 0.0]))
        if np.linalg.norm(right) < 1e-9:
            right = np.cross(forward, np.array([1.0, 0.0, 0.0]))
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0] = right
    c2w[:3, 1] = cam_up
    c2w[:3, 2] = -forward
    c2w[:3, 3] = eye
    return c2w


def _check_ring(n: int, radius: float, elevation_deg: Sequence[float]) -> tuple[float, float]:
    if int(n) != n or n < 0:
        raise ValueError(f"number of cameras must be a non-negative integer, got {n!r}")
    if not radius > 0:
        raise ValueError(f"camera radius must be positive, got {radius!r}")
    lo, hi = (float(x) for x in elevation_deg)
    if not (-90.0 <= lo <= hi <= 90.0):
        raise ValueError(f"elevation range must satisfy -90 <= lo <= hi <= 90, got ({lo}, {hi})")
    return lo, hi


def _poses(az: np.ndarray, height_frac: np.ndarray, radius: float, target, lo: float, hi: float) -> list[np.ndarray]:
    """Cameras at azimuths ``az`` (radians) and elevations uniform in area (sin elevation) over [lo, hi]."""
    s_lo, s_hi = math.sin(math.radians(lo)), math.sin(math.radians(hi))
    elev = np.arcsin(s_lo + (s_hi - s_lo) * height_frac)
    target = np.asarray(target, dtype=np.float64).reshape(3)
    out = []
    for a, e in zip(az, elev):
        eye = target + radius * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        out.append(look_at(eye, target))
    return out


def train_cameras(n: int, radius: float, target=(0.0, 0.0, 0.0), elevation_deg=(15.0, 60.0),
                  seed: int = 0) -> list[np.ndarray]:
    """``n`` cameras on a sphere about ``target``: golden-angle steps in azimuth, low-discrepancy elevation.

    Consecutive cameras (consecutive timesteps of a dynamic scene) are far apart, and any run of
    timesteps covers all azimuths and elevations, so no part of the motion is seen from one side only.
    Elevations are uniform in area over [lo, hi]. The seed sets the starting azimuth and elevation phase.
    """
    lo, hi = _check_ring(n, radius, elevation_deg)
    rng = np.random.default_rng([int(seed), 0x7261696E])
    a0, h0 = rng.random(2)
    i = np.arange(n)
    az = 2.0 * math.pi * np.mod(a0 + i * _GOLDEN_FRACTION, 1.0)
    h = np.mod(h0 + i / _PLASTIC**2, 1.0)
    return _poses(az, h, radius, target, lo, hi)


def camera_directions(c2ws: Iterable[np.ndarray], target=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Unit vectors from ``target`` to each camera centre, (N, 3)."""
    target = np.asarray(target, dtype=np.float64).reshape(3)
    pts = np.array([np.asarray(c, dtype=np.float64)[:3, 3] - target for c in c2ws]).reshape(-1, 3)
    return pts / np.maximum(np.linalg.norm(pts, axis=1, keepdims=True), 1e-12)


def test_cameras(n: int, radius: float, target=(0.0, 0.0, 0.0), elevation_deg=(15.0, 60.0), seed: int = 0,
                 avoid: Iterable[np.ndarray] | None = None, min_separation_deg: float = 2.0) -> list[np.ndarray]:
    """``n`` novel cameras (evaluation views), from a random stream independent of the training one.

    Candidates are drawn deterministically for the seed; a candidate closer than ``min_separation_deg``
    (angle seen from ``target``) to any pose in ``avoid`` (e.g. the training cameras) is skipped, so a
    test view never coincides with a training view.
    """
    lo, hi = _check_ring(n, radius, elevation_deg)
    if n == 0:
        return []
    rng = np.random.default_rng([int(seed), 0x74657374])
    avoid_dirs = camera_directions(list(avoid), target) if avoid is not None else np.zeros((0, 3))
    cos_min = math.cos(math.radians(min_separation_deg))
    chosen: list[np.ndarray] = []
    taken = avoid_dirs  # directions no new camera may come close to
    for _ in range(64):  # rounds of n candidates, stratified in azimuth; the first usually suffices
        k = np.arange(n)
        az = 2.0 * math.pi * np.mod(rng.random() + (k + 0.5 * rng.random(n)) / n, 1.0)
        h = np.mod(k * _GOLDEN_FRACTION + rng.random() + 0.25 * rng.random(n), 1.0)
        for pose in _poses(az, h, radius, target, lo, hi):
            d = camera_directions([pose], target)
            if np.all(taken @ d[0] < cos_min):
                chosen.append(pose)
                taken = np.concatenate([taken, d])
                if len(chosen) == n:
                    return chosen
    raise ValueError(f"could not place {n} test cameras {min_separation_deg} degrees away from "
                     f"{len(avoid_dirs)} training cameras; lower min_separation_deg or widen the elevation range")


def focal_length(camera_angle_x: float, width: int) -> float:
    """Focal length in pixels for a full horizontal field of view ``camera_angle_x`` (radians)."""
    if not 0.0 < camera_angle_x < math.pi:
        raise ValueError(f"camera_angle_x must be in (0, pi) radians, got {camera_angle_x!r}")
    return 0.5 * width / math.tan(0.5 * camera_angle_x)


def intrinsics(camera_angle_x: float, width: int, height: int) -> np.ndarray:
    """3 x 3 K for y-down pixel coordinates: square pixels, principal point at the image centre."""
    f = focal_length(camera_angle_x, width)
    return np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]])


def project(points_world, c2w, camera_angle_x: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (N, 3): returns pixel coordinates (N, 2) (x right, y down) and depth (N,).

    Depth is the distance along the viewing axis (positive in front of the camera); points behind the
    camera get a negative depth and meaningless pixel coordinates.
    """
    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    c2w = np.asarray(c2w, dtype=np.float64)
    rot, t = c2w[:3, :3], c2w[:3, 3]
    cam = (p - t) @ rot  # = R^T (p - t) for each row
    depth = -cam[:, 2]
    safe = np.where(np.abs(depth) > 1e-12, depth, 1e-12)
    K = intrinsics(camera_angle_x, width, height)
    x = K[0, 2] + K[0, 0] * cam[:, 0] / safe
    y = K[1, 2] - K[1, 1] * cam[:, 1] / safe
    return np.stack([x, y], axis=1), depth


def transforms_dict(camera_angle_x: float, frames) -> dict:
    """The ``transforms_{split}.json`` document: camera_angle_x and frames (file_path, time, c2w)."""
    out = []
    for file_path, c2w, time in frames:
        m = np.asarray(c2w, dtype=np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError(f"frame {file_path}: transform_matrix must be a finite 4 x 4 matrix")
        if not 0.0 <= float(time) <= 1.0:
            raise ValueError(f"frame {file_path}: time {time} is outside [0, 1]")
        out.append({"file_path": str(file_path), "time": float(time),
                    "transform_matrix": [[float(v) for v in row] for row in m]})
    return {"camera_angle_x": float(camera_angle_x), "frames": out}
