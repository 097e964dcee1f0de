"""Plane plus parallax: the 4x4 matrices the kernels see, and the homographies of planes.

A satellite camera is ~700 km from the scene, so anything computed in float32 from camera-centred
depths or ECEF coordinates loses centimetres (float32 spacing at 7e5 m is 0.06 m). The kernels
therefore only see, per view, the scaled 4x4 matrix (:func:`reparametrise`)::

    P4 = s * [[P], [0, 0, Zbar, -Zbar * d]]      (s: largest absolute entry becomes 1)

For an ENU point X = (e, n, u, 1): ``P4 @ X = s * (col * w, row * w, w, Zbar * (u - d))`` with
``w`` the depth of the point (metres, as K[2,2] = 1 and R is a rotation). Divided by its 3rd
entry the 4-vector is ``(col, row, 1, rho)`` with the *parallax* ``rho = Zbar * (u - d) / w``:
approximately the height (m) of the point above the reference plane ``u = d`` (exactly so at
depth ``w = Zbar``; the relative difference is (w - Zbar) / Zbar, about 1e-4 over an AOI). A
pixel and its parallax ``(col, row, 1, rho)`` determine the world point through ``P4^-1``, so
homographies and depth maps need only well-scaled numbers: see :func:`plane_homography`,
:func:`height_from_fourth` and :func:`fourth_from_height`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import numpy as np

from satsweep.errors import CameraError

if TYPE_CHECKING:  # pragma: no cover
    from satsweep.geometry.camera import PerspectiveCamera



# -- plane plus parallax -------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class PlaneParallaxProjection:
    """A view's scaled 4x4 plane-plus-parallax matrix (see the module docstring).

    ``P4 = s [[P], [0, 0, zbar, -zbar d]]`` with ``s`` making the largest absolute entry 1. For
    an ENU point X, ``P4 @ (X, 1) ~ (col, row, 1, rho)`` with ``rho = zbar (u - d) / depth``, about
    the height (m) above the plane ``u = d``.
    """

    P4: np.ndarray  # 4x4 float64, max |entry| = 1
    d: float  # height (m, ENU up) of the reference plane u = d, below the scene
    zbar: float  # mean depth (m) of the scene from this view

    @property
    def scale(self) -> float:
        """The factor ``s`` applied to ``[P; 0 0 zbar -zbar d]``."""
        return float(self.P4[3, 2] / self.zbar)

    @property
    def P(self) -> np.ndarray:
        """The 3x4 projection (ENU -> pixels) up to the scale ``s``."""
        return self.P4[:3]

    @property
    def inverse(self) -> np.ndarray:
        """``P4^-1`` (float64): (col, row, 1, rho) -> homogeneous ENU point."""
        return np.linalg.inv(self.P4)


def reparametrise(camera: PerspectiveCamera, *, d: float, zbar: float) -> PlaneParallaxProjection:
    """The plane-plus-parallax 4x4 matrix of a camera for the plane ``u = d`` and depth ``zbar``.

    ``d`` (m, ENU up) should lie below the scene so that the parallax is positive; ``zbar`` (m)
    is the mean depth of the scene (see :meth:`PerspectiveCamera.depth`).
    """
    d, zbar = float(d), float(zbar)
    if not (math.isfinite(d) and math.isfinite(zbar) and zbar > 0.0):
        raise CameraError(f"reparametrise: d = {d!r} must be finite and zbar = {zbar!r} positive")
    M = np.vstack([camera.P, [0.0, 0.0, zbar, -zbar * d]])
    M = M / np.max(np.abs(M))
    return PlaneParallaxProjection(P4=M, d=d, zbar=zbar)


def _plane_row(inv: np.ndarray, h: np.ndarray) -> np.ndarray:
    """``[q^T, r] = [0, 0, 1, -h] P4^-1`` for each plane height h: shape h.shape + (4,)."""
    return inv[2] - h[..., None] * inv[3]


def plane_homography(ref: PlaneParallaxProjection, src: PlaneParallaxProjection, h,
                     *, dtype=np.float64) -> np.ndarray:
    """Homography of the ENU plane ``u = h`` (m) from reference pixels to source pixels.

    ``H = (P2 P1^-1 [I; -q^T / r])[0:3, 0:3]`` with ``[q^T, r] = [0, 0, 1, -h] P1^-1`` (P1, P2 the
    4x4 matrices of ``ref`` and ``src``): a reference pixel x (homogeneous, pixel (0, 0) = centre
    of the first pixel) and the parallax ``rho = -q.x / r`` of its point on the plane give the
    world point ``P1^-1 (x, rho)``, which P2 projects. Returns a 3x3 matrix (up to scale) for a
    scalar ``h`` and (..., 3, 3) for an array. Computed in ``dtype`` (float64 by default; float32
    only to demonstrate the precision of the reparametrisation).
    """
    dtype = np.dtype(dtype)
    h = np.asarray(h, dtype=dtype)
    P1 = ref.P4.astype(dtype)
    P2 = src.P4.astype(dtype)
    inv = np.linalg.inv(P1)
    G = P2 @ inv  # 4x4: (x, rho) of ref -> (x, rho) of src
    qr = _plane_row(inv, h)
    q, r = qr[..., :3], qr[..., 3]
    H = G[:3, :3] - G[:3, 3][:, None] * (q / r[..., None])[..., None, :]
    return H.astype(dtype, copy=False)


def fourth_from_height(proj: PlaneParallaxProjection, col, row, u) -> np.ndarray:
    """Parallax ``rho`` of the point seen at pixel (col, row) on the ENU plane up = ``u`` (m)."""
    col, row, u = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (col, row, u)))
    qr = _plane_row(proj.inverse, u)
    return -(qr[..., 0] * col + qr[..., 1] * row + qr[..., 2]) / qr[..., 3]


def height_from_fourth(proj: PlaneParallaxProjection, col, row, rho) -> np.ndarray:
    """ENU height ``u`` (m) of the point seen at pixel (col, row) with parallax ``rho``.

    Exact (through ``P4^-1``); ``proj.d + rho`` is its approximation to about 1e-4 relative.
    """
    col, row, rho = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (col, row, rho)))
    inv = proj.inverse
    X = col[..., None] * inv[:, 0] + row[..., None] * inv[:, 1] + inv[:, 2] + rho[..., None] * inv[:, 3]
    return X[..., 2] / X[..., 3]


def enu_from_fourth(proj: PlaneParallaxProjection, col, row, rho) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ENU point (e, n, u) (m) seen at pixel (col, row) with parallax ``rho``."""
    col, row, rho = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (col, row, rho)))
    inv = proj.inverse
    X = col[..., None] * inv[:, 0] + row[..., None] * inv[:, 1] + inv[:, 2] + rho[..., None] * inv[:, 3]
    return X[..., 0] / X[..., 3], X[..., 1] / X[..., 3], X[..., 2] / X[..., 3]
