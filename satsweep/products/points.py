"""From height maps to 3D points: ENU points of each valid pixel, then UTM and ellipsoidal
height over each pixel's footprint.

``height_map_to_enu`` solves ``P @ [e, n, u, 1] ~ [col, row, 1]`` for (e, n) per pixel (a 2x2
linear system). ``ENUToMap`` maps ENU points to UTM and ellipsoidal height with polynomials
fitted to the exact transform over the points' box (checked to 1 mm, else the exact transform).
``map_view_points`` gives a view's pixel centres (the cloud) and footprint sub-samples (the
rasters).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from satsweep.errors import CameraError

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


def _exact_enu_to_map(frame, epsg: int, e, n, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ENU (m) -> (easting, northing, ellipsoidal height) (m) through geodetic coordinates."""
    from satsweep.geometry.geodesy import lonlat_to_utm

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


def spread_to_footprint_edges(centres, samples, selected: np.ndarray, subsamples: int,
                              edge_px: float):
    """The footprint sub-samples of the pixels ``selected`` moved out to ``edge_px`` pixels from
    their centres (the outermost sub-sample of ``_subsample_offsets`` at ``edge_px``, the others
    in proportion), the others' as they are.

    ``centres``, ``samples``: (x, y, z, pixel) of a view's mapped pixel centres (pixel indices
    ascending, as ``height_map_to_enu`` gives them) and of their sub-samples
    (``map_view_points``); ``selected``: (H * W,) bool per pixel index. Each sub-sample moves
    along the line from its pixel's centre, so a pixel's sub-samples keep their pattern and
    reach ``edge_px`` of its footprint's edge at 0.5. With one sub-sample per pixel there is
    nothing to move. Returns (x, y, z, pixel) of the sub-samples."""
    sx, sy, sz, spix = samples
    if subsamples < 2 or spix.size == 0:
        return samples
    half = 0.5 - 0.5 / subsamples  # the outermost sub-sample's offset (pixels)
    if not (math.isfinite(edge_px) and 0.0 < edge_px <= 0.5):
        raise ValueError(f"edge_px = {edge_px!r}: must be in (0, 0.5] pixels")
    x, y, z, pixel = centres
    move = np.asarray(selected, bool)[spix]
    if not move.any():
        return samples
    at = np.searchsorted(pixel, spix[move])
    if np.any(at >= pixel.size) or np.any(pixel[np.minimum(at, pixel.size - 1)] != spix[move]):
        raise ValueError("spread_to_footprint_edges: a sub-sample's pixel has no centre")
    factor = edge_px / half
    out = []
    for c, v in ((x, sx), (y, sy), (z, sz)):
        v = np.array(v, dtype=np.float64, copy=True)
        base = np.asarray(c, np.float64)[at]
        v[move] = base + factor * (v[move] - base)
        out.append(v)
    return out[0], out[1], out[2], spix


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
    from satsweep.geometry.geodesy import lonlat_to_utm

    x, y = lonlat_to_utm(lon=points.lon, lat=points.lat, epsg=epsg)
    return np.asarray(x, np.float64), np.asarray(y, np.float64), np.asarray(points.alt, np.float64)
