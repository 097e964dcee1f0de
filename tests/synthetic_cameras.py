"""Synthetic satellite pinhole cameras and scene points shared by the sparse and bundle tests."""

from __future__ import annotations

import numpy as np

from satsweep.geometry.camera import PerspectiveCamera


def look_at(center: np.ndarray, roll: float) -> np.ndarray:
    """Rotation ENU -> camera (x right, y down, z forward) looking from ``center`` at the origin."""
    z = -center / np.linalg.norm(center)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.stack([x, y, z])


def satellite_camera(off_east: float, off_north: float, *, roll: float = 0.0, skew: float = 0.0,
                     size: int = 1000) -> PerspectiveCamera:
    """A pinhole camera 700 km up, offset by (off_east, off_north) x 700 km, GSD ~0.5 m."""
    f = 1.4e6
    K = np.array([[f, skew * f, size / 2.0 + 0.3], [0.0, f, size / 2.0 - 0.7], [0.0, 0.0, 1.0]])
    C = np.array([off_east * 7e5, off_north * 7e5, 7e5])
    R = look_at(C, roll)
    t = -R @ C
    return PerspectiveCamera(K=K, R=R, t=t, P=K @ np.column_stack([R, t]), width=size, height=size)


def three_cameras() -> list[PerspectiveCamera]:
    """Along-track-like triplet: base-to-height ratios 0.15 .. 0.3, small rolls, one with skew."""
    return [satellite_camera(0.0, -0.15, roll=0.01), satellite_camera(0.02, 0.0, roll=-0.02, skew=0.01),
            satellite_camera(-0.01, 0.14, roll=0.03)]


def scene_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """Random ENU points over 400 m x 400 m x 60 m around the origin."""
    return rng.uniform([-200.0, -200.0, 0.0], [200.0, 200.0, 60.0], size=(n, 3))


def project(camera: PerspectiveCamera, X: np.ndarray) -> np.ndarray:
    return np.column_stack(camera.project(X[:, 0], X[:, 1], X[:, 2]))
