"""From per-view height maps to a DSM on a UTM grid.

Stages (host code, float64 numpy, vectorised):

1. ``height_map_to_points``: each valid reference pixel (col, row) with its surface height u (ENU
   up, metres) becomes a 3D point: the ENU (e, n) solving ``P @ [e, n, u, 1] ~ [col, row, 1]``
   exactly (a 2x2 linear system per pixel), then WGS84 lon/lat/ellipsoidal height.
   ``cross_check_heights`` first keeps only the pixels whose 3D point another reference view's
   height map confirms; ``height_map_to_enu`` stops at the ENU points (and their pixels).
2. ``points_to_utm`` + ``rasterise_max``: points to UTM easting/northing, highest point per cell
   (a DSM is the top surface: a roof point beats a wall point falling in the same cell).
   ``ENUToMap`` maps ENU points to UTM and ellipsoidal height directly with polynomials fitted
   to the exact transform over the points' box (checked to 1 mm, else the exact transform).
3. ``fuse_dsms``: per cell, median of the per-reference-view DSMs after discarding values farther
   than ``outlier_m`` from their first median (a consistency filter across views).
4. ``fill_small_holes``: optional; fills enclosed holes of a few cells and returns how many cells
   it filled, so the caller reports it.

Grid convention (``DSMGrid``): north up, square cells of ``resolution`` metres, ``x_min``/``y_max``
the outer corner of the top-left cell (GDAL's geotransform origin, as ``imageio.write_geotiff``
takes it); cell (i, j) (row i, column j) has its centre at
``(x_min + (j + 0.5) * resolution, y_max - (i + 0.5) * resolution)``.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Literal, Sequence

import numpy as np

from .errors import CameraError, OptionsError
from .options import Options

# Points per AOI edge when projecting its outline to UTM: the edges of a lon/lat box are curved
# in UTM, so the corners alone can miss the true extent by up to a few metres on large AOIs.
AOI_EDGE_SAMPLES = 65

# |det| below this (relative to the product of the row norms) marks a pixel whose 2x2 system is
# degenerate: its viewing ray is parallel to the horizontal plane.
DEGENERATE_RELATIVE_DET = 1e-12

# ENUToMap: total degree of the polynomials, fitting nodes per axis (Chebyshev), largest error
# accepted against the exact map (m; 1/500 of a 0.5 m cell, else the exact map is used), smallest
# half-size of the fitted box (m; keeps a flat box well conditioned) and points per evaluation block
# (its 20 monomials in float64 stay in a CPU's L2 cache: 8192 points took 0.16-0.24 s per 2.6 M
# points where 262144 took 0.21-0.69 s).
ENU_MAP_DEGREE = 3
ENU_MAP_NODES = 7
ENU_MAP_TOL_M = 1e-3
ENU_MAP_MIN_HALF_M = 1.0
ENU_MAP_BLOCK = 1 << 13
# footprint_splats: the largest distance (m) accepted between a sub-sample moved from its pixel
# centre by one Jacobian per view and the exact point (else the exact points are computed).
SPLAT_TOL_M = 1e-3
# Points per block of solve_ground_en (its float64 temporaries stay in a CPU's L2 cache).
GROUND_BLOCK = 1 << 15
_MONOMIAL_POWERS = tuple((i, j, k) for i in range(ENU_MAP_DEGREE + 1) for j in range(ENU_MAP_DEGREE + 1)
                         for k in range(ENU_MAP_DEGREE + 1) if i + j + k <= ENU_MAP_DEGREE)

# fuse_dsms works on row blocks of at most this many values (views x cells): ~64 MB per float64
# temporary, whatever the DSM size.
FUSE_BLOCK_VALUES = 8_000_000


@dataclasses.dataclass(frozen=True)
class DSMOptions(Options):
    """Options of the DSM stage (rasterisation, fusion across reference views, hole filling)."""

    resolution: float = 0.5  # DSM cell size in metres (UTM)
    subsamples: int = 2  # each reference pixel is splatted as subsamples x subsamples points over its footprint (1: centre only, which leaves empty cells between the pixels' centres)
    cross_check_m: float = 2.0  # keep a reference view's pixel only where another reference view's height map agrees within this (m); 0: no check
    cross_check_views: int = 1  # how many other reference views must agree (at most all the others; a single reference view is not checked)
    outlier_m: float = 2.0  # fusion: discard per-view heights farther than this (m) from the first per-cell median
    min_views: int = 1  # fusion: cells kept by fewer reference views are left empty
    fill_max_hole_cells: int = 1000  # fill enclosed holes of at most this many cells (0: no filling); the
    # holes left by occlusions and by the cross-check are mostly ground hidden by a wall (filled cells are counted in report.json)
    fill_method: Literal["min", "median"] = "min"  # value given to a filled hole: min or median of its rim

    def check(self) -> None:
        self._require(math.isfinite(self.resolution) and self.resolution > 0.0, "resolution", "must be > 0 metres")
        self._require(1 <= self.subsamples <= 8, "subsamples", "must be 1..8")
        self._require(math.isfinite(self.cross_check_m) and self.cross_check_m >= 0.0, "cross_check_m",
                      "must be >= 0 metres (0 disables the check)")
        self._require(self.cross_check_views >= 1, "cross_check_views", "must be >= 1")
        self._require(math.isfinite(self.outlier_m) and self.outlier_m > 0.0, "outlier_m", "must be > 0 metres")
        self._require(self.min_views >= 1, "min_views", "must be >= 1")
        self._require(self.fill_max_hole_cells >= 0, "fill_max_hole_cells", "must be >= 0 (0 disables filling)")


# -- points ------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Points:
    """A set of 3D points: WGS84 lon/lat (degrees), height above the ellipsoid (m), attributes."""

    lon: np.ndarray  # (N,) float64 degrees
    lat: np.ndarray  # (N,) float64 degrees
    alt: np.ndarray  # (N,) float64 metres above the WGS84 ellipsoid
    colors: np.ndarray | None = None  # (N, 3) uint8 RGB, or None
    confidence: np.ndarray | None = None  # (N,) float32, or None

    def __len__(self) -> int:
        return int(self.lon.size)

    @staticmethod
    def concatenate(parts: Sequence["Points"]) -> "Points":
        """Join point sets; colours/confidence are kept only when every part has them."""
        parts = list(parts)
        if not parts:
            empty = np.zeros(0, np.float64)
            return Points(lon=empty, lat=empty.copy(), alt=empty.copy())
        colors = None
        if all(p.colors is not None for p in parts):
            colors = np.concatenate([p.colors for p in parts])
        confidence = None
        if all(p.confidence is not None for p in parts):
            confidence = np.concatenate([p.confidence for p in parts])
        return Points(
            lon=np.concatenate([p.lon for p in parts]),
            lat=np.concatenate([p.lat for p in parts]),
            alt=np.concatenate([p.alt for p in parts]),
            colors=colors,
            confidence=confidence,
        )


def _rgb_of(colors: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) grey or (H, W, 3) RGB uint8 -> (H, W, 3) uint8."""
    c = np.asarray(colors)
    if c.dtype != np.uint8:
        raise ValueError(f"colors must be uint8 (tone-map the image first), got {c.dtype}")
    if c.shape == shape:
        return np.repeat(c[..., None], 3, axis=2)
    if c.shape == shape + (3,):
        return c
    raise ValueError(f"colors must have shape {shape} or {shape + (3,)}, got {c.shape}")


def solve_ground_en(P: np.ndarray, *, col, row, u) -> tuple[np.ndarray, np.ndarray]:
    """ENU (e, n) of the points at height ``u`` that ``P`` projects to pixels (col, row).

    ``P``: 3x4 matrix mapping homogeneous ENU ``[e, n, u, 1]`` to homogeneous pixel coordinates
    ((0, 0) = centre of the first pixel). With ``q = P @ X``, ``col * q[2] = q[0]`` and
    ``row * q[2] = q[1]`` are two linear equations in (e, n), solved by Cramer's rule in float64.
    Pixels whose system is degenerate (ray parallel to the plane u = const) get NaN. The points
    are solved in blocks of ``GROUND_BLOCK`` so that the temporaries stay in the CPU's cache.
    """
    P = np.asarray(P, dtype=np.float64)
    if P.shape != (3, 4) or not np.all(np.isfinite(P)):
        raise CameraError(f"projection matrix must be a finite 3x4 array, got shape {P.shape}")
    P = P / np.linalg.norm(P)  # scale-free: keeps intermediate magnitudes near 1
    col, row, u = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (col, row, u)))
    shape = col.shape
    col, row, u = col.ravel(), row.ravel(), u.ravel()
    e = np.empty(col.size)
    n = np.empty(col.size)
    for s in range(0, col.size, GROUND_BLOCK):
        blk = slice(s, s + GROUND_BLOCK)
        c, r, h = col[blk], row[blk], u[blk]
        a11 = P[0, 0] - c * P[2, 0]
        a12 = P[0, 1] - c * P[2, 1]
        a21 = P[1, 0] - r * P[2, 0]
        a22 = P[1, 1] - r * P[2, 1]
        b1 = -((P[0, 2] - c * P[2, 2]) * h + (P[0, 3] - c * P[2, 3]))
        b2 = -((P[1, 2] - r * P[2, 2]) * h + (P[1, 3] - r * P[2, 3]))
        det = a11 * a22 - a12 * a21
        scale = np.hypot(a11, a12) * np.hypot(a21, a22)
        ok = np.abs(det) > DEGENERATE_RELATIVE_DET * scale
        safe = np.where(ok, det, 1.0)
        e[blk] = np.where(ok, (b1 * a22 - a12 * b2) / safe, np.nan)
        n[blk] = np.where(ok, (a11 * b2 - b1 * a21) / safe, np.nan)
    return e.reshape(shape), n.reshape(shape)


def height_map_to_points(
    height: np.ndarray,
    valid: np.ndarray,
    P: np.ndarray,
    frame,
    *,
    colors: np.ndarray | None = None,
    confidence: np.ndarray | None = None,
    subsamples: int = 1,
) -> Points:
    """3D points of the valid pixels of a reference-view height map.

    ``height``: (H, W) ENU up coordinate (metres) of the surface seen at each pixel of the
    (cropped) reference image; ``valid``: (H, W) bool (non-finite heights are skipped too); ``P``:
    the reference camera's 3x4 ENU -> pixel matrix; ``frame``: the ``geo.ENUFrame`` of P.
    ``colors``: optional (H, W) grey or (H, W, 3) RGB uint8 image; ``confidence``: optional (H, W).
    ``subsamples`` = s > 1 places s x s points per pixel at offsets ``(k + 0.5) / s - 0.5`` pixel
    inside its footprint, all at the pixel's height, so that rasterising them covers the ground
    footprint of the pixel instead of its centre only. Points are ordered row-major by pixel.
    """
    h = np.asarray(height, dtype=np.float64)
    e, n, u, pixel = height_map_to_enu(h, valid, P, subsamples=subsamples)
    lon, lat, alt = frame.to_geodetic(e=e, n=n, u=u)
    rgb = None
    if colors is not None:
        rgb = _rgb_of(colors, h.shape).reshape(-1, 3)[pixel]
    conf = None
    if confidence is not None:
        c = np.asarray(confidence, dtype=np.float32)
        if c.shape != h.shape:
            raise ValueError(f"confidence has shape {c.shape}, height has {h.shape}")
        conf = c.ravel()[pixel]
    return Points(
        lon=np.asarray(lon, np.float64).ravel(),
        lat=np.asarray(lat, np.float64).ravel(),
        alt=np.asarray(alt, np.float64).ravel(),
        colors=rgb,
        confidence=conf,
    )


def project_points(P: np.ndarray, *, e, n, u) -> tuple[np.ndarray, np.ndarray]:
    """(col, row) pixels of ENU points (m) through a 3x4 matrix; NaN behind the camera."""
    P = np.asarray(P, dtype=np.float64)
    e, n, u = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (e, n, u)))
    w = P[2, 0] * e + P[2, 1] * n + P[2, 2] * u + P[2, 3]
    ok = w > 0 if np.linalg.det(P[:, :3]) > 0 else w < 0  # in front: positive depth for K[R|t]
    safe = np.where(ok, w, 1.0)
    col = np.where(ok, (P[0, 0] * e + P[0, 1] * n + P[0, 2] * u + P[0, 3]) / safe, np.nan)
    row = np.where(ok, (P[1, 0] * e + P[1, 1] * n + P[1, 2] * u + P[1, 3]) / safe, np.nan)
    return col, row


def cross_check_heights(heights: Sequence[np.ndarray], projections: Sequence[np.ndarray], *,
                        tolerance_m: float, min_agreeing: int = 1,
                        points: Sequence[tuple[np.ndarray, ...]] | None = None) -> list[np.ndarray]:
    """Consistency of the height maps of several reference views (a geometric cross-check).

    ``heights[k]``: (H_k, W_k) ENU up coordinate (m) of the surface seen at each pixel of
    reference view k, NaN where unknown; ``projections[k]``: that view's 3x4 ENU -> pixel matrix.
    Each known pixel of view k becomes its 3-D point (the pixel's ray at its height); the point is
    projected into every other view j, whose height at the nearest pixel (``floor(x + 0.5)``)
    must lie within ``tolerance_m`` of the point's height. A pixel is kept when at least
    ``min_agreeing`` other views confirm it (all the others when there are fewer): a wrong match
    (occlusion, low texture, fattened edge) rarely lands on the same 3-D point from another
    viewpoint. Returns one boolean mask per view (True = known and confirmed). With a single view
    nothing can be checked and its known pixels are returned as they are. ``points``: each
    view's ``height_map_to_enu(heights[k], isfinite(heights[k]), projections[k])``, when the
    caller has them already (they are then not solved again; the same masks).
    """
    maps = [np.asarray(h, dtype=np.float64) for h in heights]
    if len(maps) != len(projections):
        raise ValueError(f"cross_check_heights: {len(maps)} height maps, {len(projections)} projections")
    if not (math.isfinite(tolerance_m) and tolerance_m > 0.0):
        raise OptionsError(f"tolerance_m = {tolerance_m!r}: must be > 0 metres")
    if not (isinstance(min_agreeing, int) and min_agreeing >= 1):
        raise OptionsError(f"min_agreeing = {min_agreeing!r}: must be an integer >= 1")
    known = [np.isfinite(h) for h in maps]
    if points is not None and len(points) != len(maps):
        raise ValueError(f"cross_check_heights: {len(maps)} height maps, {len(points)} point sets")
    if len(maps) < 2:
        return known
    need = min(min_agreeing, len(maps) - 1)
    out = []
    for k, (h, P) in enumerate(zip(maps, projections)):
        if points is None:
            rows, cols = np.nonzero(known[k])
            u = h[rows, cols]
            e, n = solve_ground_en(P, col=cols.astype(np.float64), row=rows.astype(np.float64),
                                   u=u)
        else:
            e, n, u, pixel = points[k]
            rows, cols = np.divmod(pixel, h.shape[1])
        agree = np.zeros(u.size, dtype=np.int64)
        for j, (hj, Pj) in enumerate(zip(maps, projections)):
            if j == k:
                continue
            col, row = project_points(Pj, e=e, n=n, u=u)
            with np.errstate(invalid="ignore"):
                ic = np.floor(col + 0.5)
                ir = np.floor(row + 0.5)
                inside = (ic >= 0) & (ic < hj.shape[1]) & (ir >= 0) & (ir < hj.shape[0])
            idx = np.nonzero(inside)[0]
            other = hj[ir[idx].astype(np.int64), ic[idx].astype(np.int64)]
            with np.errstate(invalid="ignore"):
                agree[idx] += np.abs(other - u[idx]) <= tolerance_m
        mask = np.zeros(h.shape, dtype=bool)
        mask[rows, cols] = agree >= need
        out.append(mask)
    return out


def _exact_enu_to_map(frame, epsg: int, e, n, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ENU (m) -> (easting, northing, ellipsoidal height) (m) through geodetic coordinates."""
    from .geo import lonlat_to_utm

    lon, lat, alt = frame.to_geodetic(e=e, n=n, u=u)
    x, y = lonlat_to_utm(lon=lon, lat=lat, epsg=epsg)
    return np.asarray(x, np.float64), np.asarray(y, np.float64), np.asarray(alt, np.float64)


def _monomials(t: np.ndarray) -> np.ndarray:
    """(3, N) normalised coordinates -> (n_terms, N) monomials of total degree <= ENU_MAP_DEGREE."""
    powers = [[np.ones(t.shape[1])] for _ in range(3)]
    for axis in range(3):
        for _ in range(ENU_MAP_DEGREE):
            powers[axis].append(powers[axis][-1] * t[axis])
    out = np.empty((len(_MONOMIAL_POWERS), t.shape[1]))
    for c, (i, j, k) in enumerate(_MONOMIAL_POWERS):
        np.multiply(powers[0][i], powers[1][j], out=out[c])
        out[c] *= powers[2][k]
    return out


@dataclasses.dataclass(frozen=True, eq=False)
class ENUToMap:
    """ENU (m) -> map coordinates of a projected CRS and ellipsoidal height, as polynomials.

    Over an AOI the exact map (ENU -> ECEF -> geodetic -> UTM, through pyproj) is so smooth that
    polynomials of total degree ``ENU_MAP_DEGREE`` in the normalised ENU coordinates reproduce it
    to well under a millimetre; they cost a few multiply-adds per point instead of two geodetic
    transforms, which matters for the millions of points of a DSM. ``fit`` checks the polynomials
    against the exact map on points between its fitting nodes and reports the largest error.
    """

    frame: object  # the geo.ENUFrame of the ENU coordinates
    epsg: int  # the projected CRS (metres)
    center: np.ndarray  # (3,) ENU centre of the fitted box (m)
    half: np.ndarray  # (3,) half-sizes of the box (m)
    coef: np.ndarray  # (n_terms, 3) coefficients of x, y, alt
    max_error_m: float  # largest distance to the exact map at the check points (m)

    @classmethod
    def fit(cls, frame, epsg: int, *, e_range: tuple[float, float], n_range: tuple[float, float],
            u_range: tuple[float, float]) -> "ENUToMap":
        """Least-squares fit over the ENU box; checked at the centres of the fitting cells."""
        lo = np.array([e_range[0], n_range[0], u_range[0]], dtype=np.float64)
        hi = np.array([e_range[1], n_range[1], u_range[1]], dtype=np.float64)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi >= lo)):
            raise ValueError(f"ENUToMap.fit: bad box {lo} .. {hi}")
        center = 0.5 * (lo + hi)
        half = np.maximum(0.5 * (hi - lo), ENU_MAP_MIN_HALF_M)
        k = ENU_MAP_NODES
        nodes = np.cos(np.pi * (np.arange(k) + 0.5) / k)[::-1]  # Chebyshev nodes in (-1, 1)
        check = 0.5 * (nodes[1:] + nodes[:-1])

        def box(s):
            g = np.stack(np.meshgrid(s, s, s, indexing="ij"), axis=-1).reshape(-1, 3)
            return g, center + g * half

        t_fit, p_fit = box(nodes)
        target = np.stack(_exact_enu_to_map(frame, epsg, *p_fit.T), axis=1)
        coef, *_ = np.linalg.lstsq(_monomials(t_fit.T).T, target, rcond=None)
        t_chk, p_chk = box(check)
        exact = np.stack(_exact_enu_to_map(frame, epsg, *p_chk.T), axis=1)
        err = float(np.max(np.linalg.norm(_monomials(t_chk.T).T @ coef - exact, axis=1)))
        return cls(frame=frame, epsg=int(epsg), center=center, half=half, coef=coef,
                   max_error_m=err)

    @property
    def accurate(self) -> bool:
        """Whether the polynomials reproduce the exact map within ENU_MAP_TOL_M."""
        return self.max_error_m <= ENU_MAP_TOL_M

    def __call__(self, *, e, n, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(easting, northing, ellipsoidal height) in metres; the exact map when not accurate."""
        e, n, u = (np.asarray(a, dtype=np.float64).ravel() for a in np.broadcast_arrays(e, n, u))
        if not self.accurate:
            return _exact_enu_to_map(self.frame, self.epsg, e, n, u)
        out = np.empty((3, e.size))
        for s in range(0, e.size, ENU_MAP_BLOCK):
            t = np.stack([e[s:s + ENU_MAP_BLOCK], n[s:s + ENU_MAP_BLOCK], u[s:s + ENU_MAP_BLOCK]])
            t = (t - self.center[:, None]) / self.half[:, None]
            out[:, s:s + ENU_MAP_BLOCK] = self.coef.T @ _monomials(t)
        return out[0], out[1], out[2]


def height_map_to_enu(height: np.ndarray, valid: np.ndarray, P: np.ndarray, *,
                      subsamples: int = 1) -> tuple[np.ndarray, ...]:
    """ENU points (e, n, u) of the valid pixels of a height map, and their pixels' flat indices.

    The sub-sample placement and order of ``height_map_to_points`` (which goes on to geodetic
    coordinates): returns (e, n, u, pixel) with ``pixel`` the row-major index of each point's
    pixel; points whose ray is parallel to the plane are dropped.
    """
    h = np.asarray(height, dtype=np.float64)
    if h.ndim != 2:
        raise ValueError(f"height must be 2D, got shape {h.shape}")
    v = np.asarray(valid, dtype=bool)
    if v.shape != h.shape:
        raise ValueError(f"valid has shape {v.shape}, height has {h.shape}")
    v = v & np.isfinite(h)
    if not (isinstance(subsamples, int) and subsamples >= 1):
        raise ValueError(f"subsamples = {subsamples!r}: must be a positive integer")
    rows, cols = np.nonzero(v)
    s = subsamples
    ox, oy = _subsample_offsets(s)
    pc = (cols[:, None] + ox[None, :]).ravel()
    pr = (rows[:, None] + oy[None, :]).ravel()
    u = np.repeat(h[rows, cols], s * s)
    pixel = np.repeat(rows * h.shape[1] + cols, s * s)
    e, n = solve_ground_en(P, col=pc, row=pr, u=u)
    keep = np.isfinite(e) & np.isfinite(n)
    return e[keep], n[keep], u[keep], pixel[keep]


def _subsample_offsets(subsamples: int) -> tuple[np.ndarray, np.ndarray]:
    """(dx, dy) pixel offsets of the s x s footprint sub-samples, row-major (as ``height_map_to_enu``)."""
    offsets = (np.arange(subsamples) + 0.5) / subsamples - 0.5
    oy, ox = np.meshgrid(offsets, offsets, indexing="ij")
    return ox.ravel(), oy.ravel()


def footprint_jacobian(P: np.ndarray, to_map, *, col, row, u) -> np.ndarray | None:
    """d(x, y, alt) / d(col, row) (3, 2) of pixel -> map at fixed height, or None if it varies.

    ``to_map``: an ``ENUToMap``; (col, row, u): the pixel centres and heights of a view's points.
    The derivatives (central differences of half a pixel through ``solve_ground_en`` and
    ``to_map``) are taken at the points' median and at the four corners of their (pixel, height)
    box; they are returned (those at the median) when no corner's differ from them by more than
    ``SPLAT_TOL_M`` over half a pixel, the farthest a footprint sub-sample lies from its centre.
    """
    col, row, u = (np.asarray(a, np.float64).ravel() for a in (col, row, u))
    if col.size == 0:
        return None
    c0, c1, r0, r1 = col.min(), col.max(), row.min(), row.max()
    uc = float(np.median(u))
    at = np.array([[np.median(col), np.median(row), uc],
                   [c0, r0, u.min()], [c1, r0, u.max()], [c0, r1, u.max()], [c1, r1, u.min()]])
    d = 0.5
    cc = np.concatenate([at[:, 0] + d, at[:, 0] - d, at[:, 0], at[:, 0]])
    rr = np.concatenate([at[:, 1], at[:, 1], at[:, 1] + d, at[:, 1] - d])
    uu = np.tile(at[:, 2], 4)
    e, n = solve_ground_en(P, col=cc, row=rr, u=uu)
    xyz = np.stack(to_map(e=e, n=n, u=uu)).reshape(3, 4, len(at))  # (coord, step, point)
    jac = np.stack([(xyz[:, 0] - xyz[:, 1]) / (2 * d), (xyz[:, 2] - xyz[:, 3]) / (2 * d)], axis=1)
    if not np.all(np.isfinite(jac)):
        return None
    spread = np.abs(jac[:, :, 1:] - jac[:, :, :1]).sum(axis=1).max()  # per half a pixel: *0.5
    return jac[:, :, 0] if 0.5 * spread <= SPLAT_TOL_M else None


def footprint_splats(x, y, z, pixel, jacobian: np.ndarray, subsamples: int):
    """The s x s footprint sub-samples of mapped pixel centres, through a constant Jacobian.

    (x, y, z, pixel): map coordinates, heights and pixel indices of a view's pixel centres (as
    ``height_map_to_enu`` with ``subsamples = 1``, mapped); ``jacobian``: ``footprint_jacobian``.
    Returns (x, y, z, pixel) of subsamples^2 points per centre in ``height_map_to_enu``'s order,
    each the centre moved by the Jacobian times its pixel offset: the same points as mapping
    ``height_map_to_enu(subsamples=s)`` to within ``SPLAT_TOL_M``, at a fraction of the cost.
    """
    dx, dy = _subsample_offsets(subsamples)
    out = []
    for k, v in enumerate((x, y, z)):
        shift = jacobian[k, 0] * dx + jacobian[k, 1] * dy
        out.append((np.asarray(v, np.float64)[:, None] + shift[None, :]).ravel())
    return out[0], out[1], out[2], np.repeat(pixel, subsamples * subsamples)


def map_view_points(centres, height: np.ndarray, valid: np.ndarray, P: np.ndarray, to_map, *,
                    subsamples: int = 1):
    """A view's points on the map: its pixel centres and its footprint sub-samples.

    ``centres``: ``height_map_to_enu(height, valid, P)`` (subsamples 1); ``to_map``: an
    ``ENUToMap`` whose box holds the points with half a pixel's footprint around them. Returns
    ((x, y, z, pixel) of the centres, (x, y, z, pixel) of the s x s sub-samples in
    ``height_map_to_enu``'s order): moved from their centres by ``footprint_jacobian`` where it
    holds to ``SPLAT_TOL_M``, else solved and mapped one by one.
    """
    e, n, u, pixel = centres
    x, y, z = to_map(e=e, n=n, u=u)
    if subsamples == 1:
        return (x, y, z, pixel), (x, y, z, pixel)
    rows, cols = np.divmod(pixel, np.shape(height)[1])
    jac = footprint_jacobian(P, to_map, col=cols, row=rows, u=u)
    if jac is not None:
        return (x, y, z, pixel), footprint_splats(x, y, z, pixel, jac, subsamples)
    e, n, u, spix = height_map_to_enu(height, valid, P, subsamples=subsamples)
    return (x, y, z, pixel), (*to_map(e=e, n=n, u=u), spix)


def points_to_utm(points: Points, epsg: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(easting, northing, height) in metres: lon/lat to the UTM ``epsg``, heights unchanged."""
    from .geo import lonlat_to_utm

    x, y = lonlat_to_utm(lon=points.lon, lat=points.lat, epsg=epsg)
    return np.asarray(x, np.float64), np.asarray(y, np.float64), np.asarray(points.alt, np.float64)


# -- grid --------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class DSMGrid:
    """A north-up raster grid in a projected CRS (see the module docstring for the convention)."""

    epsg: int  # EPSG code of the projected CRS (UTM: 326zz / 327zz)
    x_min: float  # west edge of the grid (outer edge of column 0), metres
    y_max: float  # north edge of the grid (outer edge of row 0), metres
    resolution: float  # cell size, metres
    width: int  # number of columns
    height: int  # number of rows

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution) and self.resolution > 0.0):
            raise OptionsError(f"DSMGrid.resolution = {self.resolution!r}: must be > 0 metres")
        if not (math.isfinite(self.x_min) and math.isfinite(self.y_max)):
            raise OptionsError(f"DSMGrid origin ({self.x_min!r}, {self.y_max!r}): must be finite")
        if self.width < 1 or self.height < 1:
            raise OptionsError(f"DSMGrid size {self.width}x{self.height}: must be at least 1x1")

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns)."""
        return self.height, self.width

    @property
    def x_max(self) -> float:
        return self.x_min + self.width * self.resolution

    @property
    def y_min(self) -> float:
        return self.y_max - self.height * self.resolution

    @property
    def geotransform(self) -> tuple[float, float, float, float, float, float]:
        """GDAL geotransform (x_min, res, 0, y_max, 0, -res)."""
        return (self.x_min, self.resolution, 0.0, self.y_max, 0.0, -self.resolution)

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """(x of the column centres (width,), y of the row centres (height,)), metres."""
        r = self.resolution
        return self.x_min + (np.arange(self.width) + 0.5) * r, self.y_max - (np.arange(self.height) + 0.5) * r

    def cell_of(self, *, x, y) -> tuple[np.ndarray, np.ndarray]:
        """(row, column) integer indices of the cells holding map points (may be out of range)."""
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        j = np.floor((x - self.x_min) / self.resolution)
        i = np.floor((self.y_max - y) / self.resolution)
        return i, j


def dsm_grid_for_aoi(aoi, resolution: float, epsg: int | None = None) -> DSMGrid:
    """The DSM grid covering an AOI: UTM zone of the AOI centre unless ``epsg`` is given.

    The AOI outline (lon/lat box, densified with ``AOI_EDGE_SAMPLES`` points per edge) is
    projected, and its bounding box is snapped outward to multiples of ``resolution`` metres, so
    grids of the same zone and resolution share cell boundaries.
    """
    from .geo import lonlat_to_utm, utm_epsg

    resolution = float(resolution)
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise OptionsError(f"resolution = {resolution!r}: must be > 0 metres")
    lon0, lon1 = float(aoi.lon_min), float(aoi.lon_max)
    lat0, lat1 = float(aoi.lat_min), float(aoi.lat_max)
    if epsg is None:
        lon_c, lat_c = aoi.center
        epsg = utm_epsg(lon=lon_c, lat=lat_c)
    t = np.linspace(0.0, 1.0, AOI_EDGE_SAMPLES)
    lons = np.concatenate([lon0 + t * (lon1 - lon0), np.full_like(t, lon1), lon1 - t * (lon1 - lon0), np.full_like(t, lon0)])
    lats = np.concatenate([np.full_like(t, lat0), lat0 + t * (lat1 - lat0), np.full_like(t, lat1), lat1 - t * (lat1 - lat0)])
    x, y = lonlat_to_utm(lon=lons, lat=lats, epsg=int(epsg))
    x_min = math.floor(float(np.min(x)) / resolution) * resolution
    x_max = math.ceil(float(np.max(x)) / resolution) * resolution
    y_min = math.floor(float(np.min(y)) / resolution) * resolution
    y_max = math.ceil(float(np.max(y)) / resolution) * resolution
    return DSMGrid(
        epsg=int(epsg), x_min=x_min, y_max=y_max, resolution=resolution,
        width=max(1, int(round((x_max - x_min) / resolution))),
        height=max(1, int(round((y_max - y_min) / resolution))),
    )


# -- rasterisation -----------------------------------------------------------------------------
def rasterise_max(points_x, points_y, values, grid: DSMGrid) -> np.ndarray:
    """Highest value per grid cell: (grid.height, grid.width) float32, NaN where no point fell.

    ``points_x``/``points_y``: map coordinates (metres, the grid's CRS); a point belongs to the
    cell whose half-open square ``[x0, x0 + res) x (y1 - res, y1]`` holds it (so a point on a cell
    boundary goes to the cell east / south of it). Points outside the grid and non-finite values
    are ignored. The maximum is taken in float64, then rounded to float32.
    """
    x = np.asarray(points_x, np.float64).ravel()
    y = np.asarray(points_y, np.float64).ravel()
    if x.size != y.size:
        raise ValueError(f"rasterise_max: lengths differ ({x.size}, {y.size})")
    return rasterise_max_cells(flat_cells(x, y, grid), values, grid)


def flat_cells(points_x, points_y, grid: DSMGrid) -> np.ndarray:
    """Row-major index of the grid cell of each point (``rasterise_max``'s rule), -1 outside."""
    i, j = grid.cell_of(x=np.ravel(points_x), y=np.ravel(points_y))
    inside = (i >= 0) & (i < grid.height) & (j >= 0) & (j < grid.width)
    return np.where(inside, i * grid.width + j, -1).astype(np.int64)


def rasterise_max_cells(cells: np.ndarray, values, grid: DSMGrid) -> np.ndarray:
    """``rasterise_max`` of points whose cells (``flat_cells``) are already known: several value
    sets over the same points (heights, confidences) share them."""
    c = np.asarray(cells, np.int64).ravel()
    z = np.asarray(values, np.float64).ravel()
    if c.size != z.size:
        raise ValueError(f"rasterise_max: lengths differ ({c.size} cells, {z.size} values)")
    ok = np.isfinite(z) & (c >= 0)
    out = np.full(grid.width * grid.height, -np.inf)
    np.maximum.at(out, c[ok], z[ok])
    out[np.isneginf(out)] = np.nan
    return out.reshape(grid.shape).astype(np.float32)


def value_at_highest(cells: np.ndarray, heights, values, grid: DSMGrid) -> np.ndarray:
    """Per grid cell, the ``values`` of its highest point (``rasterise_max_cells``' rule: the
    point that sets the cell's height): what a true orthophoto shows, the surface seen from
    above. (grid.height, grid.width) float32, NaN where no point fell; points without a finite
    height or value are ignored; of points tied for the highest, the largest value."""
    c = np.asarray(cells, np.int64).ravel()
    z = np.asarray(heights, np.float64).ravel()
    v = np.asarray(values, np.float64).ravel()
    if not (c.size == z.size == v.size):
        raise ValueError(f"value_at_highest: lengths differ ({c.size} cells, {z.size} heights, "
                         f"{v.size} values)")
    ok = np.isfinite(z) & np.isfinite(v) & (c >= 0)
    c, z, v = c[ok], z[ok], v[ok]
    top = np.full(grid.width * grid.height, -np.inf)
    np.maximum.at(top, c, z)
    highest = z == top[c]
    out = np.full(grid.width * grid.height, -np.inf)
    np.maximum.at(out, c[highest], v[highest])
    out[np.isneginf(out)] = np.nan
    return out.reshape(grid.shape).astype(np.float32)


# Cells two views must share for match_radiometry to fit one to the other.
RADIOMETRY_MIN_CELLS = 100


def match_radiometry(reference: np.ndarray, other: np.ndarray) -> np.ndarray:
    """``other`` with the gain and offset that bring it to ``reference``'s radiometry, fitted on
    the cells both have (finite): the gain matches their interquartile ranges, the offset their
    medians (robust to the cells where they see different things). ``other`` unchanged when
    they share fewer than ``RADIOMETRY_MIN_CELLS`` cells or ``other`` is flat there."""
    both = np.isfinite(reference) & np.isfinite(other)
    if np.count_nonzero(both) < RADIOMETRY_MIN_CELLS:
        return other
    r = np.asarray(reference, np.float64)[both]
    o = np.asarray(other, np.float64)[both]
    r25, r50, r75 = np.percentile(r, [25, 50, 75])
    o25, o50, o75 = np.percentile(o, [25, 50, 75])
    if not o75 > o25:
        return other
    gain = (r75 - r25) / (o75 - o25)
    return (gain * (np.asarray(other, np.float64) - o50) + r50).astype(np.float32)


def rasterise_points(points: Points, grid: DSMGrid) -> np.ndarray:
    """DSM of one point set on ``grid``: ``points_to_utm`` then ``rasterise_max`` of the heights."""
    x, y, z = points_to_utm(points, grid.epsg)
    return rasterise_max(x, y, z, grid)


# -- fusion ------------------------------------------------------------------------------------
def _nanmedian_first_axis(stack: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median over axis 0 ignoring NaN (NaN where all are NaN) and the count of finite values.

    Sorting puts NaN last, so the finite values of each cell are the first ``k`` of its column and
    the median is the mean of entries ``(k - 1) // 2`` and ``k // 2``.
    """
    s = np.sort(stack, axis=0)
    k = np.count_nonzero(np.isfinite(stack), axis=0)
    lo = np.take_along_axis(s, np.maximum((k - 1) // 2, 0)[None], axis=0)[0]
    hi = np.take_along_axis(s, np.maximum(k // 2 - (k == 0), 0)[None], axis=0)[0]
    med = 0.5 * (lo.astype(np.float64) + hi.astype(np.float64))
    med[k == 0] = np.nan
    return med, k


def fuse_dsms(
    dsms: Sequence[np.ndarray], *, outlier_m: float = 2.0, min_views: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Robust per-cell fusion of per-reference-view DSMs on the same grid.

    For each cell: m0 = median of the finite values; values with ``|v - m0| > outlier_m`` are
    discarded; the result is the median of the rest (NaN when fewer than ``min_views`` remain).
    With two views that disagree by more than ``2 * outlier_m`` both are discarded: neither can be
    trusted. Returns (fused float32, count of values kept per cell as int32).
    """
    if not dsms:
        raise ValueError("fuse_dsms needs at least one DSM")
    if not (math.isfinite(outlier_m) and outlier_m > 0.0):
        raise OptionsError(f"outlier_m = {outlier_m!r}: must be > 0 metres")
    shape = np.asarray(dsms[0]).shape
    if len(shape) != 2:
        raise ValueError(f"fuse_dsms needs 2D rasters, got shape {shape}")
    for k, d in enumerate(dsms):
        if np.asarray(d).shape != shape:
            raise ValueError(f"fuse_dsms: DSM {k} has shape {np.asarray(d).shape}, DSM 0 has {shape}")
    fused = np.full(shape, np.nan, dtype=np.float32)
    count = np.zeros(shape, dtype=np.int32)
    # Row blocks bound the temporary memory to about FUSE_BLOCK_VALUES float64 values per copy.
    rows_per_block = max(1, FUSE_BLOCK_VALUES // max(1, len(dsms) * int(np.prod(shape[1:], dtype=np.int64))))
    for r0 in range(0, shape[0], rows_per_block):
        block = slice(r0, r0 + rows_per_block)
        stack = np.stack([np.asarray(d)[block].astype(np.float64) for d in dsms])
        stack[~np.isfinite(stack)] = np.nan
        m0, _ = _nanmedian_first_axis(stack)
        with np.errstate(invalid="ignore"):
            far = np.abs(stack - m0[None]) > outlier_m
        stack[far] = np.nan
        f, k = _nanmedian_first_axis(stack)
        low = k < min_views
        f[low] = np.nan
        k[low] = 0
        fused[block] = f
        count[block] = k
    return fused, count


# -- hole filling ------------------------------------------------------------------------------
def fill_small_holes(
    dsm: np.ndarray, *, max_hole_cells: int, method: Literal["min", "median"] = "min"
) -> tuple[np.ndarray, int]:
    """Fill enclosed no-data holes of at most ``max_hole_cells`` 4-connected cells.

    A hole is a 4-connected set of NaN cells that does not touch the raster border (a gap at the
    border is not known to be closed). Each hole gets one value from its rim (the valid cells
    4-adjacent to it): the minimum by default, because small holes in satellite DSMs are mostly
    ground occluded by a wall, i.e. the lower side; or the median. Returns (filled float32 copy,
    number of cells filled), which the caller must report.
    """
    import cv2

    # float32 throughout (a copy): the fill values are the rim's own float32 values (min) or
    # their mean rounded to float32 on assignment (median), as the float32 result needs anyway;
    # a float64 copy would double the memory of a large AOI's grid.
    a = np.array(dsm, dtype=np.float32)
    if a.ndim != 2:
        raise ValueError(f"fill_small_holes needs a 2D array, got shape {a.shape}")
    if not (isinstance(max_hole_cells, int) and max_hole_cells >= 0):
        raise OptionsError(f"max_hole_cells = {max_hole_cells!r}: must be an integer >= 0")
    if method not in ("min", "median"):
        raise OptionsError(f"fill method = {method!r}: must be 'min' or 'median'")
    hole = ~np.isfinite(a)
    if max_hole_cells == 0 or not hole.any() or hole.all():
        return a, 0
    n, labels = cv2.connectedComponents(hole.astype(np.uint8), connectivity=4, ltype=cv2.CV_32S)
    n -= 1  # label 0 is the background (the valid cells)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    eligible = (sizes <= max_hole_cells)
    eligible[0] = False
    eligible[border] = False
    if not eligible[1:].any():
        return a, 0
    # Rim pairs (hole label, rim value) from the four neighbour directions.
    pair_labels, pair_values = [], []
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        lab = labels[max(dy, 0):a.shape[0] + min(dy, 0), max(dx, 0):a.shape[1] + min(dx, 0)]
        nb = a[max(-dy, 0):a.shape[0] + min(-dy, 0), max(-dx, 0):a.shape[1] + min(-dx, 0)]
        sel = (lab > 0) & np.isfinite(nb)
        pair_labels.append(lab[sel])
        pair_values.append(nb[sel])
    pl = np.concatenate(pair_labels)
    pv = np.concatenate(pair_values).astype(np.float64)
    keep = eligible[pl]
    pl, pv = pl[keep], pv[keep]
    fill = np.full(n + 1, np.nan)
    if method == "min":
        fill_min = np.full(n + 1, np.inf)
        np.minimum.at(fill_min, pl, pv)
        fill = np.where(np.isfinite(fill_min), fill_min, np.nan)
    else:
        order = np.lexsort((pv, pl))
        pl, pv = pl[order], pv[order]
        starts = np.searchsorted(pl, np.arange(n + 1), side="left")
        ends = np.searchsorted(pl, np.arange(n + 1), side="right")
        cnt = ends - starts
        has = cnt > 0
        lo_idx = starts + np.maximum(cnt - 1, 0) // 2
        hi_idx = starts + cnt // 2
        lo_idx = np.minimum(lo_idx, max(pv.size - 1, 0))
        hi_idx = np.minimum(hi_idx, max(pv.size - 1, 0))
        if pv.size:
            fill[has] = 0.5 * (pv[lo_idx[has]] + pv[hi_idx[has]])
    target = eligible[labels] & np.isfinite(fill[labels])
    a[target] = fill[labels[target]]
    return a, int(np.count_nonzero(target))


def write_dsm_geotiff(path: str | os.PathLike, array: np.ndarray, grid: DSMGrid) -> None:
    """Write a raster on ``grid`` as a float32 GeoTIFF with NaN nodata (atomically)."""
    from .imageio import write_geotiff

    a = np.asarray(array)
    if a.shape != grid.shape:
        raise ValueError(f"array shape {a.shape} does not match the grid {grid.shape}")
    write_geotiff(path, a.astype(np.float32), epsg=grid.epsg, x_min=grid.x_min, y_max=grid.y_max,
                  resolution=grid.resolution, nodata=math.nan)
