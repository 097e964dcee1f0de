"""Cameras: local perspective approximation of RPC models over the AOI cube.

Frames and units
----------------
- World points are in a local ENU frame (metres, :class:`satsweep.geo.ENUFrame`) whose origin is
  the AOI centre at the bottom of the altitude range; ``u`` is "up" along the ellipsoid normal at
  the origin (it differs from the ellipsoidal height by the Earth curvature, a few mm over 300 m).
- Pixels are (col, row) of the image crop a view holds; pixel (0, 0) is the centre of the first
  pixel (the RPC convention of rpcm and S2P). A full-image pixel is crop pixel + (x0, y0).

Perspective approximation
-------------------------
Over a small AOI an RPC model is very close to a pinhole camera (a satellite push-broom sensor
seen from 700 km over a few hundred metres). :func:`approximate_camera` samples the AOI cube (AOI
lon/lat box x altitude range) on a grid, projects the samples with the RPC, fits the 3x4 matrix
``P`` by normalised DLT (Hartley normalisation of both point sets: without it the 2N x 12 system
is hopelessly ill-conditioned at these scales), refines it by Gauss-Newton on the reprojection
error and factorises it as ``K [R | t]`` (positive focal lengths, ``det R = +1``, ``K[2,2] = 1``,
``K`` keeps its skew). The approximation error against the RPC is reported per view. This is
the approach of VisSat (Zhang, Li and Snavely, 2019), whose published figure is 0.194 px (the
average of per-view maxima, WorldView-3, 0.46 km2 AOI); on the Pleiades pair over 300 m x 80 m it
is about 0.02 px. It grows with the AOI: tile large AOIs.

The skew is removed by :mod:`satsweep.geometry.skew`; the kernels see the cameras through the
plane-plus-parallax matrices of :mod:`satsweep.geometry.parallax`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from satsweep.errors import CameraError, InputError
from satsweep.geometry.geodesy import ENUFrame, utm_epsg
from satsweep.options import Options

if TYPE_CHECKING:  # pragma: no cover
    from satsweep.geometry.altitude import AltitudeRange
    from satsweep.geometry.aoi import AOI
from satsweep.geometry.parallax import PlaneParallaxProjection, reparametrise

# Fewer grid samples than this inside an image cannot support an 11-parameter fit with any
# confidence (DLT needs 6; we ask for a margin of redundancy).
MIN_GRID_POINTS = 20
# Seed of the random subset of grid samples that a camera fit uses (CameraOptions.fit_samples):
# fixed, so that a run is repeatable.
FIT_SUBSET_SEED = 0
# The DLT system is declared degenerate (coplanar or collinear samples) when its second smallest
# singular value is below this fraction of the largest one: the null space is then not unique.
DEGENERATE_SV_RATIO = 1e-10
# Gauss-Newton stops when an iteration lowers the squared reprojection error by less than this
# fraction (the cost is then at its float64 floor).
REFINE_REL_TOL = 1e-12
REFINE_MAX_ITERATIONS = 20
# Rows per block of the tall-skinny QR of the DLT and Gauss-Newton systems (_tall_qr_r).
QR_BLOCK_ROWS = 16384

CAMERAS_JSON_VERSION = 1
# An innermost JSON list of numbers spread over several lines by json.dumps(indent=...).
_INNER_LIST = re.compile(r"\[\s*([-+0-9.eE,\s]*?)\s*\]")


# -- options -------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class CameraOptions(Options):
    """Options of the RPC -> perspective approximation and of the parallax reparametrisation."""

    warn_error_px: float = 0.2  # a camera further than this (px) from its RPC gets a warning
    grid_size: tuple[int, int, int] = (100, 100, 20)  # samples of the AOI cube along east,
    # north and up
    fit_samples: int = 20_000  # grid samples the fit uses (a seeded random subset); the errors
    # are reported over all of them
    refine: bool = True  # refine the normalised DLT by Gauss-Newton on the reprojection error
    plane_margin_m: float = 10.0  # distance (m) of the parallax plane u = d below the lowest
    # sample of the AOI cube

    ADVANCED = ("grid_size", "fit_samples", "refine", "plane_margin_m")

    def check(self) -> None:
        self._require(all(n >= 2 for n in self.grid_size), "grid_size",
                      "needs at least 2 samples along each of east, north and up")
        self._require(self.grid_size[0] * self.grid_size[1] * self.grid_size[2] <= 10_000_000,
                      "grid_size", "more than 1e7 samples is wasteful (the default is 2e5)")
        self._require(self.fit_samples >= MIN_GRID_POINTS, "fit_samples",
                      f"must be at least {MIN_GRID_POINTS}")
        self._require(math.isfinite(self.plane_margin_m) and self.plane_margin_m > 0.0,
                      "plane_margin_m", "must be a positive number of metres")
        self._require(math.isfinite(self.warn_error_px) and self.warn_error_px > 0.0,
                      "warn_error_px", "must be a positive number of pixels")


# -- cameras -------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ApproxError:
    """Error of a perspective camera against the RPC it approximates, over the AOI grid.

    Reprojection errors are distances (px) between the RPC and the camera projections of each
    grid sample; back-projection errors are horizontal distances (m) between a grid sample and the
    intersection of the camera ray through its RPC pixel with the horizontal plane of the sample.
    """

    mean_px: float
    median_px: float
    max_px: float
    backprojection_mean_m: float
    backprojection_max_m: float
    n_points: int  # grid samples inside the image that the fit used

    def to_dict(self) -> dict[str, float]:
        return {"mean": self.mean_px, "median": self.median_px, "max": self.max_px}


@dataclasses.dataclass(frozen=True, eq=False)
class PerspectiveCamera:
    """A pinhole camera ``P = K [R | t]`` mapping ENU points (m) to pixels of one image.

    ``K`` is upper triangular with positive focal lengths (px), ``K[2,2] = 1`` and possibly a
    skew ``K[0,1]``; ``R`` is a rotation (``det R = +1``) from ENU to the camera frame (x along
    columns, y along rows, z forward); ``t`` (m) puts the ENU origin in the camera frame. The
    3rd row of ``P`` gives the depth (m) of a point along the optical axis.
    """

    K: np.ndarray  # 3x3 intrinsics, pixels
    R: np.ndarray  # 3x3 rotation ENU -> camera
    t: np.ndarray  # (3,) translation, metres
    P: np.ndarray  # 3x4, K [R | t]
    width: int  # image columns
    height: int  # image rows
    error: ApproxError | None = None  # error against the RPC (None for a synthetic camera)

    @classmethod
    def from_projection(cls, P: np.ndarray, *, width: int, height: int,
                        error: ApproxError | None = None) -> "PerspectiveCamera":
        """Factorise a 3x4 matrix (any scale or sign) into a camera; see decompose_projection."""
        P, K, R, t = decompose_projection(P)
        return cls(K=K, R=R, t=t, P=P, width=int(width), height=int(height), error=error)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in ENU (m), shape (3,): ``-R^T t``."""
        return -self.R.T @ self.t

    def project(self, e, n, u) -> tuple[np.ndarray, np.ndarray]:
        """ENU points (m, broadcast arrays) -> (col, row) pixels, float64."""
        e, n, u = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (e, n, u)))
        P = self.P
        w = P[2, 0] * e + P[2, 1] * n + P[2, 2] * u + P[2, 3]
        col = (P[0, 0] * e + P[0, 1] * n + P[0, 2] * u + P[0, 3]) / w
        row = (P[1, 0] * e + P[1, 1] * n + P[1, 2] * u + P[1, 3]) / w
        return col, row

    def depth(self, e, n, u) -> np.ndarray:
        """Depth (m) of ENU points along the optical axis (positive in front of the camera)."""
        e, n, u = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (e, n, u)))
        P = self.P
        return P[2, 0] * e + P[2, 1] * n + P[2, 2] * u + P[2, 3]

    def backproject(self, col, row, *, u) -> tuple[np.ndarray, np.ndarray]:
        """Pixels -> (e, n) (m) where their rays cross the horizontal ENU plane at height ``u`` (m)."""
        return _backproject(self.P, col, row, u)


def _backproject(P: np.ndarray, col, row, u) -> tuple[np.ndarray, np.ndarray]:
    """Intersect the rays of pixels through 3x4 ``P`` with the planes up = u; returns (e, n)."""
    col, row, u = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (col, row, u)))
    # col * (P2 . X) = P0 . X and row * (P2 . X) = P1 . X, linear in (e, n) for a known u.
    a = P[0] - col[..., None] * P[2]
    b = P[1] - row[..., None] * P[2]
    ra = -(a[..., 2] * u + a[..., 3])
    rb = -(b[..., 2] * u + b[..., 3])
    det = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    e = (ra * b[..., 1] - a[..., 1] * rb) / det
    n = (a[..., 0] * rb - ra * b[..., 0]) / det
    return e, n


def ground_sample_distance(P: np.ndarray, X) -> float:
    """Metres per pixel (the square root of a pixel's ground area) of the 3 x 4 camera ``P``
    (ENU -> pixels) on the horizontal plane through ENU point ``X``."""
    P = np.asarray(P, np.float64)
    Xh = np.append(np.asarray(X, np.float64), 1.0)
    s = P[2] @ Xh
    xy = P[:2] @ Xh / s
    J = (P[:2, :2] - np.outer(xy, P[2, :2])) / s  # d(pixel) / d(east, north)
    return float(1.0 / np.sqrt(max(abs(np.linalg.det(J)), 1e-12)))


# -- the AOI grid --------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class AOIGrid:
    """Samples of the AOI cube: geodetic coordinates and their exact ENU coordinates (flat arrays)."""

    lon: np.ndarray  # degrees
    lat: np.ndarray  # degrees
    alt: np.ndarray  # metres above the WGS84 ellipsoid
    e: np.ndarray  # metres, ENU
    n: np.ndarray
    u: np.ndarray


def frame_for(aoi: "AOI", alt_range: "AltitudeRange") -> ENUFrame:
    """The ENU frame of an AOI: origin at the AOI centre, at the bottom of the altitude range."""
    return ENUFrame(lon0=0.5 * (aoi.lon_min + aoi.lon_max), lat0=0.5 * (aoi.lat_min + aoi.lat_max),
                    alt0=float(alt_range.min))


def aoi_grid(frame: ENUFrame, aoi: "AOI", alt_range: "AltitudeRange",
             grid_size: tuple[int, int, int] = (100, 100, 20)) -> AOIGrid:
    """Sample the AOI cube uniformly in lon, lat and altitude; each sample also in ENU.

    Sampling in geodetic coordinates covers exactly the AOI box times the altitude range at every
    horizontal position (an ENU box would miss the bottom of the range at the AOI corners, where
    the ellipsoid curves below the tangent plane).
    """
    ne, nn, nu = grid_size
    lon, lat, alt = np.meshgrid(
        np.linspace(aoi.lon_min, aoi.lon_max, ne),
        np.linspace(aoi.lat_min, aoi.lat_max, nn),
        np.linspace(alt_range.min, alt_range.max, nu),
        indexing="ij",
    )
    lon, lat, alt = lon.ravel(), lat.ravel(), alt.ravel()
    e, n, u = frame.from_geodetic(lon=lon, lat=lat, alt=alt)
    return AOIGrid(lon=lon, lat=lat, alt=alt, e=e, n=n, u=u)


# -- DLT, refinement, decomposition --------------------------------------------------------------
def _normalisation_3d(X: np.ndarray) -> np.ndarray:
    """Hartley's 4x4 similarity: centroid to the origin, mean distance to it sqrt(3)."""
    c = X.mean(axis=0)
    scale = math.sqrt(3.0) / np.mean(np.linalg.norm(X - c, axis=1))
    T = np.diag([scale, scale, scale, 1.0])
    T[:3, 3] = -scale * c
    return T


def _normalisation_2d(x: np.ndarray) -> np.ndarray:
    """Hartley's 3x3 similarity: centroid to the origin, mean distance to it sqrt(2)."""
    c = x.mean(axis=0)
    scale = math.sqrt(2.0) / np.mean(np.linalg.norm(x - c, axis=1))
    T = np.diag([scale, scale, 1.0])
    T[:2, 2] = -scale * c
    return T


def _apply(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a homogeneous similarity to (N, k) points, returning (N, k) points."""
    return pts @ T[:-1, :-1].T + T[:-1, -1]


def _tall_qr_r(A: np.ndarray) -> np.ndarray:
    """R of a QR factorisation of a tall (N, k) matrix (R^T R = A^T A, as stable as QR).

    Blocks of ``QR_BLOCK_ROWS`` rows are reduced to their own R factors, which are stacked and
    factored again (tall-skinny QR): the same R up to row signs, about 2.5 times faster than one
    LAPACK QR of the whole matrix on the 400,000 x 12 systems of the default grid.
    """
    if A.shape[0] <= QR_BLOCK_ROWS:
        return np.linalg.qr(A, mode="r")
    blocks = [np.linalg.qr(A[i:i + QR_BLOCK_ROWS], mode="r")
              for i in range(0, A.shape[0], QR_BLOCK_ROWS)]
    return np.linalg.qr(np.vstack(blocks), mode="r")


def _dlt_normalised(Xn: np.ndarray, xn: np.ndarray) -> np.ndarray:
    """Unit 12-vector minimising the algebraic error of normalised correspondences."""
    N = Xn.shape[0]
    Xh = np.hstack([Xn, np.ones((N, 1))])
    A = np.zeros((2 * N, 12))
    A[:N, 0:4] = Xh
    A[:N, 8:12] = -xn[:, 0:1] * Xh
    A[N:, 4:8] = Xh
    A[N:, 8:12] = -xn[:, 1:2] * Xh
    # The thin QR first keeps the SVD at 12x12 whatever the number of points.
    _, s, vt = np.linalg.svd(_tall_qr_r(A))
    if s[-2] <= DEGENERATE_SV_RATIO * s[0]:
        raise CameraError(
            "the grid samples seen by the image are degenerate (coplanar or collinear): "
            "the projection matrix is not determined"
        )
    return vt[-1]


def _gauss_newton(p: np.ndarray, Xn: np.ndarray, xn: np.ndarray) -> np.ndarray:
    """Minimise the (normalised) reprojection error over unit 12-vectors p, from a start p."""
    N = Xn.shape[0]
    Xh = np.hstack([Xn, np.ones((N, 1))])

    def residuals(q):
        w = Xh @ q[8:12]
        cu = Xh @ q[0:4] / w
        cv = Xh @ q[4:8] / w
        return w, cu, cv, np.concatenate([cu - xn[:, 0], cv - xn[:, 1]])

    w, cu, cv, r = residuals(p)
    cost = r @ r
    for _ in range(REFINE_MAX_ITERATIONS):
        # Steps orthogonal to p: the overall scale of p is not observable.
        basis = np.linalg.svd(p[None, :])[2][1:].T  # 12x11, orthonormal, orthogonal to p
        Xw = Xh / w[:, None]
        J = np.empty((2 * N, 11))
        J[:N] = Xw @ basis[0:4] - (cu[:, None] * Xw) @ basis[8:12]
        J[N:] = Xw @ basis[4:8] - (cv[:, None] * Xw) @ basis[8:12]
        # Least squares through the R factor of [J | r]: R[:11, :11] s = -R[:11, 11].
        R = _tall_qr_r(np.column_stack([J, r]))
        step = np.linalg.lstsq(R[:11, :11], -R[:11, 11], rcond=None)[0]
        q = p + basis @ step
        q /= np.linalg.norm(q)
        wq, cuq, cvq, rq = residuals(q)
        new_cost = rq @ rq
        if not new_cost < cost:
            break
        decrease = cost - new_cost
        p, w, cu, cv, r, cost = q, wq, cuq, cvq, rq, new_cost
        if decrease <= REFINE_REL_TOL * cost:
            break
    return p


def normalized_dlt(points: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """3x4 projection matrix (up to scale) from (N, 3) world points and (N, 2) pixels.

    Hartley-normalised DLT: both point sets are moved to their centroid and scaled to a mean
    distance of sqrt(3) (3D) and sqrt(2) (2D) before the linear solve, then denormalised.
    """
    points, pixels = _check_correspondences(points, pixels)
    T3, T2 = _normalisation_3d(points), _normalisation_2d(pixels)
    p = _dlt_normalised(_apply(T3, points), _apply(T2, pixels))
    return np.linalg.solve(T2, p.reshape(3, 4)) @ T3


def refine_projection(P: np.ndarray, points: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Refine a 3x4 matrix by Gauss-Newton on the reprojection error (px) of the correspondences.

    The minimisation runs in Hartley-normalised coordinates (the same minimiser: the 2D
    normalisation is an isotropic scaling of the pixel errors) over the unit sphere of matrices.
    """
    points, pixels = _check_correspondences(points, pixels)
    T3, T2 = _normalisation_3d(points), _normalisation_2d(pixels)
    Pn = T2 @ np.asarray(P, dtype=np.float64) @ np.linalg.inv(T3)
    p = Pn.ravel() / np.linalg.norm(Pn)
    p = _gauss_newton(p, _apply(T3, points), _apply(T2, pixels))
    return np.linalg.solve(T2, p.reshape(3, 4)) @ T3


def _check_correspondences(points, pixels) -> tuple[np.ndarray, np.ndarray]:
    points = np.asarray(points, dtype=np.float64)
    pixels = np.asarray(pixels, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or pixels.shape != (points.shape[0], 2):
        raise CameraError(f"correspondences must be (N, 3) points and (N, 2) pixels, got "
                          f"{points.shape} and {pixels.shape}")
    if points.shape[0] < 6:
        raise CameraError(f"{points.shape[0]} correspondences: a projection matrix needs 6 or more")
    return points, pixels


def _rq3(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """RQ decomposition ``A = R Q`` of a 3x3 matrix (R upper triangular, Q orthogonal), from
    numpy's QR of the reversed transpose: with E the row reversal, E A^T = Q' R' gives
    A = (E R'^T E) (E Q'^T), the first factor upper triangular."""
    Qp, Rp = np.linalg.qr(A[::-1].T)
    return Rp.T[::-1, ::-1], Qp.T[::-1]


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """RQ-factorise a 3x4 matrix (any scale and sign) into ``K [R | t]``.

    Returns ``(P', K, R, t)`` with ``P' = K [R | t]`` the input rescaled so that ``K[2,2] = 1``:
    ``K`` upper triangular with positive diagonal (focal lengths, px) and its skew kept, ``R`` a
    rotation (``det R = +1``), ``t`` in metres. The sign of P is chosen to make ``det R = +1``;
    with positive focal lengths this puts the scene in front of the camera only for an image that
    is not mirrored (checked by the callers that know the scene).
    """
    P = np.asarray(P, dtype=np.float64)
    if P.shape != (3, 4) or not np.all(np.isfinite(P)):
        raise CameraError(f"a projection matrix must be a finite 3x4 array, got shape {P.shape}")
    K, R = _rq3(P[:, :3])
    if np.any(np.abs(np.diag(K)) == 0.0):
        raise CameraError("the projection matrix is singular (its left 3x3 block has rank < 3)")
    signs = np.sign(np.diag(K))
    K = K * signs[None, :]  # K D
    R = signs[:, None] * R  # D R, so that (K D)(D R) = K R
    if np.linalg.det(R) < 0.0:
        P, R = -P, -R
    scale = K[2, 2]
    K = np.triu(K / scale)  # exact (positive) zeros below the diagonal
    P = P / scale
    t = np.linalg.solve(K, P[:, 3])
    return P, K, R, t


def fit_camera(rpc, grid: AOIGrid, image_shape: Sequence[int], options: CameraOptions = CameraOptions(),
               *, name: str | None = None) -> PerspectiveCamera:
    """Fit a perspective camera to an RPC over the samples of an AOI grid inside the image.

    ``rpc`` is the RPC of the image (crop) of shape ``image_shape`` (rows, cols[, bands]);
    samples projecting outside ``[-0.5, cols - 0.5] x [-0.5, rows - 0.5]`` are dropped. ``name``
    (the image path) goes into error messages.
    """
    where = f"{name}: " if name is not None else ""
    height, width = int(image_shape[0]), int(image_shape[1])
    col, row = rpc.projection(lon=grid.lon, lat=grid.lat, alt=grid.alt)
    col, row = np.asarray(col, dtype=np.float64), np.asarray(row, dtype=np.float64)
    inside = (np.isfinite(col) & np.isfinite(row) & (col >= -0.5) & (col <= width - 0.5)
              & (row >= -0.5) & (row <= height - 0.5))
    n_inside = int(np.count_nonzero(inside))
    if n_inside < MIN_GRID_POINTS:
        raise CameraError(
            f"{where}only {n_inside} of {col.size} AOI grid samples project inside the "
            f"{width}x{height} image: it does not see the AOI"
        )
    points = np.stack([grid.e[inside], grid.n[inside], grid.u[inside]], axis=1)
    pixels = np.stack([col[inside], row[inside]], axis=1)
    fit_points, fit_pixels = points, pixels
    if n_inside > options.fit_samples:
        fit = np.sort(np.random.default_rng(FIT_SUBSET_SEED).choice(n_inside, options.fit_samples,
                                                                    replace=False))
        fit_points, fit_pixels = points[fit], pixels[fit]
    try:
        P = normalized_dlt(fit_points, fit_pixels)
        if options.refine:
            P = refine_projection(P, fit_points, fit_pixels)
    except CameraError as exc:
        raise CameraError(f"{where}{exc}") from None
    P, K, R, t = decompose_projection(P)
    depth = points @ P[2, :3] + P[2, 3]
    if not np.all(depth > 0.0):
        raise CameraError(
            f"{where}the fitted camera with positive focal lengths and det R = +1 sees the AOI "
            "behind it: the image is mirrored (flip it)"
        )
    error = _approx_error(P, points, pixels)
    return PerspectiveCamera(K=K, R=R, t=t, P=P, width=width, height=height, error=error)


def _approx_error(P: np.ndarray, points: np.ndarray, pixels: np.ndarray) -> ApproxError:
    """Reprojection (px) and back-projection (m) errors of P against RPC correspondences."""
    Xh = np.hstack([points, np.ones((points.shape[0], 1))])
    proj = Xh @ P.T
    reproj = np.hypot(proj[:, 0] / proj[:, 2] - pixels[:, 0], proj[:, 1] / proj[:, 2] - pixels[:, 1])
    e, n = _backproject(P, pixels[:, 0], pixels[:, 1], points[:, 2])
    back = np.hypot(e - points[:, 0], n - points[:, 1])
    return ApproxError(
        mean_px=float(np.mean(reproj)), median_px=float(np.median(reproj)), max_px=float(np.max(reproj)),
        backprojection_mean_m=float(np.mean(back)), backprojection_max_m=float(np.max(back)),
        n_points=int(points.shape[0]),
    )


def approximate_camera(rpc, frame: ENUFrame, aoi: "AOI", alt_range: "AltitudeRange",
                       image_shape: Sequence[int], options: CameraOptions = CameraOptions(),
                       *, name: str | None = None) -> PerspectiveCamera:
    """Perspective approximation of an RPC over the AOI cube, in the ENU ``frame``.

    The AOI lon/lat box times ``alt_range`` is sampled on ``options.grid_size`` samples, projected
    with the RPC (samples outside the image are dropped), and a 3x4 matrix is fitted by
    normalised DLT then refined by Gauss-Newton (``options.refine``). The returned camera carries
    its error against the RPC over the grid (see :class:`ApproxError`).
    """
    grid = aoi_grid(frame, aoi, alt_range, options.grid_size)
    return fit_camera(rpc, grid, image_shape, options, name=name)


# -- all views -----------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, eq=False)
class ViewCamera:
    """The camera of one view, in the pixels of its crop (or of its skew-corrected image)."""

    path: str  # the source image file
    x0: int  # crop offset: full-image col = crop col + x0 (before any skew correction)
    y0: int  # full-image row = crop row + y0
    camera: PerspectiveCamera
    projection: PlaneParallaxProjection
    # Skew-correction warp W (pixel of the corrected image = W @ crop pixel), None if not applied.
    warp: np.ndarray | None = None
    # The skew-corrected image file, relative to the folder of cameras.json, None if not written.
    corrected_image: str | None = None


@dataclasses.dataclass(frozen=True, eq=False)
class CameraSet:
    """Perspective cameras of all views in one ENU frame (the content of cameras.json)."""

    frame: ENUFrame  # origin: AOI centre at the bottom of the altitude range
    utm_epsg: int  # UTM zone of the AOI centre (the DSM grid's CRS)
    aoi: "AOI"
    alt_range: "AltitudeRange"
    d: float  # the parallax reference plane u = d (m, ENU up), shared by all views
    views: tuple[ViewCamera, ...]
    warnings: tuple[str, ...] = ()  # views whose approximation error exceeds the warning level
    # The bundle adjustment's report (satsweep.bundle.BundleReport.to_dict()) when the cameras
    # were adjusted; their K/P/P4 are then the adjusted ones.
    ba: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (the cameras.json format; float64 values round-trip exactly)."""
        views = []
        for v in self.views:
            c, err = v.camera, v.camera.error
            entry: dict[str, Any] = {
                "image": v.path,
                "crop_offset": [v.x0, v.y0],
                "width": c.width,
                "height": c.height,
                "K": c.K.tolist(),
                "R": c.R.tolist(),
                "t": c.t.tolist(),
                "P": c.P.tolist(),
                "P4": v.projection.P4.tolist(),
                "zbar": v.projection.zbar,
            }
            if err is not None:
                entry["approx_error_px"] = err.to_dict()
                entry["backprojection_error_m"] = {"mean": err.backprojection_mean_m,
                                                   "max": err.backprojection_max_m}
                entry["grid_points"] = err.n_points
            if v.warp is not None:
                entry["skew_warp"] = v.warp.tolist()
            if v.corrected_image is not None:
                entry["skew_corrected_image"] = v.corrected_image
            views.append(entry)
        return {
            "format": "satsweep-cameras",
            "version": CAMERAS_JSON_VERSION,
            "conventions": "ENU metres (origin lon0/lat0/alt0, alt above WGS84 ellipsoid); pixel "
                           "(0,0) = centre of the first pixel of the crop (full image = crop + "
                           "crop_offset); P = K[R|t] maps ENU to pixels; P4 = s[P; 0 0 zbar "
                           "-zbar*d] with max |entry| = 1; skew_warp maps crop pixels to the "
                           "pixels of the skew-corrected image that K, P and P4 then refer to",
            "enu_origin": {"lat0": self.frame.lat0, "lon0": self.frame.lon0, "alt0": self.frame.alt0},
            "utm_epsg": self.utm_epsg,
            "aoi": [self.aoi.lon_min, self.aoi.lat_min, self.aoi.lon_max, self.aoi.lat_max],
            "alt_range": [self.alt_range.min, self.alt_range.max],
            "plane_d": self.d,
            "views": views,
            "warnings": list(self.warnings),
            **({"ba": self.ba} if self.ba is not None else {}),
        }

    def to_json(self) -> str:
        """JSON text: indented, with each innermost list of numbers (a matrix row) on one line."""
        text = json.dumps(self.to_dict(), indent=2)
        return _INNER_LIST.sub(lambda m: "[" + ", ".join(m.group(1).split()).replace(",,", ",") + "]", text)

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: str | os.PathLike | None = None) -> "CameraSet":
        """Inverse of :meth:`to_dict`; a malformed mapping is an InputError naming ``source``."""
        from satsweep.geometry.altitude import AltitudeRange
        from satsweep.geometry.aoi import AOI

        try:
            if data.get("format") != "satsweep-cameras":
                raise ValueError("not a satsweep cameras file (missing format: satsweep-cameras)")
            if data.get("version") != CAMERAS_JSON_VERSION:
                raise ValueError(f"version {data.get('version')!r} is not {CAMERAS_JSON_VERSION}")
            o = data["enu_origin"]
            frame = ENUFrame(lon0=float(o["lon0"]), lat0=float(o["lat0"]), alt0=float(o["alt0"]))
            views = []
            for v in data["views"]:
                err = None
                if "approx_error_px" in v:
                    a, b = v["approx_error_px"], v["backprojection_error_m"]
                    err = ApproxError(mean_px=float(a["mean"]), median_px=float(a["median"]),
                                      max_px=float(a["max"]), backprojection_mean_m=float(b["mean"]),
                                      backprojection_max_m=float(b["max"]), n_points=int(v["grid_points"]))
                cam = PerspectiveCamera(
                    K=_array(v["K"], (3, 3)), R=_array(v["R"], (3, 3)), t=_array(v["t"], (3,)),
                    P=_array(v["P"], (3, 4)), width=int(v["width"]), height=int(v["height"]), error=err)
                proj = PlaneParallaxProjection(P4=_array(v["P4"], (4, 4)), d=float(data["plane_d"]),
                                               zbar=float(v["zbar"]))
                warp = _array(v["skew_warp"], (3, 3)) if "skew_warp" in v else None
                views.append(ViewCamera(path=str(v["image"]), x0=int(v["crop_offset"][0]),
                                        y0=int(v["crop_offset"][1]), camera=cam, projection=proj,
                                        warp=warp, corrected_image=v.get("skew_corrected_image")))
            aoi = AOI(*(float(x) for x in data["aoi"]))
            alt = AltitudeRange(float(data["alt_range"][0]), float(data["alt_range"][1]))
            return cls(frame=frame, utm_epsg=int(data["utm_epsg"]), aoi=aoi, alt_range=alt,
                       d=float(data["plane_d"]), views=tuple(views),
                       warnings=tuple(str(w) for w in data.get("warnings", ())),
                       ba=data.get("ba"))
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            what = f"missing key {exc}" if isinstance(exc, KeyError) else str(exc)
            raise InputError(source, f"malformed cameras file: {what}") from None

    @classmethod
    def from_json(cls, text: str, *, source: str | os.PathLike | None = None) -> "CameraSet":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(source, f"not valid JSON: {exc}") from None
        if not isinstance(data, dict):
            raise InputError(source, "malformed cameras file: not a JSON object")
        return cls.from_dict(data, source=source)

    @classmethod
    def read(cls, path: str | os.PathLike) -> "CameraSet":
        """Read a cameras.json file."""
        try:
            with open(path, encoding="utf-8") as fh:
                text = fh.read()
        except OSError as exc:
            raise InputError(path, f"cannot read: {exc.strerror or exc}") from None
        return cls.from_json(text, source=path)

    def table(self) -> str:
        """A readable per-view summary (focal lengths, skew, errors)."""
        head = (f"{'view':<24} {'size':>11} {'fx (px)':>12} {'fy (px)':>12} {'skew':>9} "
                f"{'mean px':>8} {'median px':>9} {'max px':>8} {'back m':>7} {'zbar km':>8}")
        lines = [head, "-" * len(head)]
        for v in self.views:
            c, e = v.camera, v.camera.error
            name = os.path.basename(v.path)
            name = name if len(name) <= 24 else "..." + name[-21:]
            errs = (f"{e.mean_px:8.4f} {e.median_px:9.4f} {e.max_px:8.4f} {e.backprojection_max_m:7.3f}"
                    if e is not None else f"{'-':>8} {'-':>9} {'-':>8} {'-':>7}")
            lines.append(f"{name:<24} {c.width:>5}x{c.height:<5} {c.K[0, 0]:12.1f} {c.K[1, 1]:12.1f} "
                         f"{c.K[0, 1]:9.2f} {errs} {v.projection.zbar / 1e3:8.2f}")
        return "\n".join(lines)


def _array(value, shape: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise ValueError(f"expected a finite array of shape {shape}, got {a.shape}")
    return a


def build_cameras(views: Sequence[Any], aoi: "AOI", alt_range: "AltitudeRange",
                  options: CameraOptions = CameraOptions()) -> CameraSet:
    """Approximate every view's RPC by a perspective camera and reparametrise it.

    ``views`` are :class:`satsweep.views.View` (``path``, ``image``, ``rpc`` of the crop, ``x0``,
    ``y0``). The frame is the AOI's (:func:`frame_for`); all views share one grid of the AOI cube
    and one reference plane ``d`` (``options.plane_margin_m`` below the lowest grid sample); each
    view's ``zbar`` is the mean depth of the grid samples it sees.
    """
    frame = frame_for(aoi, alt_range)
    epsg = utm_epsg(lon=frame.lon0, lat=frame.lat0)
    grid = aoi_grid(frame, aoi, alt_range, options.grid_size)
    d = float(np.min(grid.u)) - options.plane_margin_m
    out, warnings = [], []
    for view in views:
        path = os.fspath(view.path)
        cam = fit_camera(view.rpc, grid, np.shape(view.image), options, name=path)
        col, row = cam.project(grid.e, grid.n, grid.u)
        inside = (col >= -0.5) & (col <= cam.width - 0.5) & (row >= -0.5) & (row <= cam.height - 0.5)
        zbar = float(np.mean(cam.depth(grid.e[inside], grid.n[inside], grid.u[inside])))
        out.append(ViewCamera(path=path, x0=int(view.x0), y0=int(view.y0), camera=cam,
                              projection=reparametrise(cam, d=d, zbar=zbar)))
        if cam.error.max_px > options.warn_error_px:
            warnings.append(
                f"{path}: perspective approximation error up to {cam.error.max_px:.3f} px "
                f"(> {options.warn_error_px:g} px) over the AOI; use a smaller AOI (satsweep "
                f"reconstruct tiles it: a smaller [reconstruct] tile_m)"
            )
    return CameraSet(frame=frame, utm_epsg=epsg, aoi=aoi, alt_range=alt_range, d=d,
                     views=tuple(out), warnings=tuple(warnings))


def write_cameras(out_dir: str | os.PathLike, cameras: CameraSet,
                  images: Sequence[np.ndarray] | None = None) -> CameraSet:
    """Write ``out_dir/cameras.json`` (and skew-corrected ``images`` to ``out_dir/images/``).

    Every file is written to a temporary name and renamed; the corrected images are named after
    their source (``images/STEM.tif``, prefixed by the view number when stems collide) and
    recorded in the returned set's ``corrected_image`` fields, relative to ``out_dir``.
    """
    from satsweep.io.atomic import atomic_output
    from satsweep.io.geotiff import write_tiff

    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    if images is not None:
        if len(images) != len(cameras.views):
            raise CameraError(f"write_cameras: {len(images)} images for {len(cameras.views)} views")
        stems = [os.path.splitext(os.path.basename(v.path))[0] for v in cameras.views]
        unique = len(set(stems)) == len(stems)
        names = [f"{s}.tif" if unique else f"{i:02d}_{s}.tif" for i, s in enumerate(stems)]
        os.makedirs(os.path.join(out_dir, "images"), exist_ok=True)
        views = []
        for v, image, name in zip(cameras.views, images, names):
            rel = f"images/{name}"
            write_tiff(os.path.join(out_dir, rel), image)
            views.append(dataclasses.replace(v, corrected_image=rel))
        cameras = dataclasses.replace(cameras, views=tuple(views))
    with atomic_output(os.path.join(out_dir, "cameras.json")) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(cameras.to_json())
            fh.write("\n")
    return cameras
