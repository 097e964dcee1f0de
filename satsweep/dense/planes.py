"""The planes of a sweep and their homographies.

Planes are ``u = h`` in the ENU frame of the scene. ``plane_heights`` spaces them so that one
step moves a reference pixel by at most ``step_px`` in the widest-baseline source;
``view_homographies`` gives each plane's reference -> source homographies (float64, from the
plane-plus-parallax matrices); ``ellipsoid_heights`` turns a height map's ``u`` into heights
above the ellipsoid; ``visible_at`` tells where a source sees a reference pixel at its plane.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from satsweep.errors import InputError

# Heights probed (over the altitude range) when measuring the parallax rate for plane spacing.
_N_PROBE_HEIGHTS = 9
# Reference pixels probed per axis (a regular grid including the corners) for the parallax rate.
_N_PROBE_PER_AXIS = 5


# -- plane spacing ------------------------------------------------------------------------------
def plane_heights_for(homography_fn: Callable[[np.ndarray], np.ndarray],
                      ref_shape: tuple[int, int], alt_range: tuple[float, float],
                      step_px: float = 0.5) -> np.ndarray:
    """Uniformly spaced plane heights (metres, increasing) over ``alt_range``.

    ``homography_fn(h)`` takes an array of n heights and returns (n, n_src, 3, 3) float64
    homographies (reference pixel -> source pixel). The spacing is chosen so that between two
    consecutive planes no probed reference pixel (a grid over the image, corners included) moves
    by more than ``step_px`` pixels in any source: the widest-baseline source sets the spacing.
    """
    lo, hi = float(alt_range[0]), float(alt_range[1])
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise InputError(None, f"alt_range = {alt_range!r}: needs finite min < max (metres)")
    if not (math.isfinite(step_px) and step_px > 0):
        raise InputError(None, f"step_px = {step_px!r}: must be > 0")
    h_img, w_img = ref_shape
    xs = np.linspace(0.0, w_img - 1.0, _N_PROBE_PER_AXIS)
    ys = np.linspace(0.0, h_img - 1.0, _N_PROBE_PER_AXIS)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)])  # (3, n_pts)
    probes = np.linspace(lo, hi, _N_PROBE_HEIGHTS)
    hom = np.asarray(homography_fn(probes), dtype=np.float64)
    if hom.ndim != 4 or hom.shape[0] != probes.size or hom.shape[2:] != (3, 3):
        raise InputError(None, f"homography_fn returned shape {hom.shape}, expected "
                               f"({probes.size}, n_src, 3, 3)")
    mapped = hom @ pts  # (n_h, n_src, 3, n_pts)
    uv = mapped[:, :, :2] / mapped[:, :, 2:3]
    moves = np.linalg.norm(np.diff(uv, axis=0), axis=2)  # (n_h - 1, n_src, n_pts)
    rate = float(np.max(moves)) / (probes[1] - probes[0])  # pixels per metre, widest baseline
    if not (math.isfinite(rate) and rate > 0):
        raise InputError(None, "the sources show no parallax over alt_range (zero baseline?)")
    n = int(math.ceil((hi - lo) * rate / step_px)) + 1
    return np.linspace(lo, hi, max(n, 2))


def plane_heights(ref, srcs: Sequence, alt_range: tuple[float, float], step_px: float = 0.5, *,
                  ref_shape: tuple[int, int]) -> np.ndarray:
    """Plane heights for projections (``satsweep.geometry.camera``): see ``plane_heights_for``."""
    return plane_heights_for(lambda h: view_homographies(ref, srcs, h), ref_shape, alt_range,
                             step_px)


def translation_homographies(shifts_px_per_m: np.ndarray, heights: np.ndarray) -> np.ndarray:
    """(n_planes, n_src, 3, 3) homographies translating by ``shift * h`` (pixels) per source.

    ``shifts_px_per_m`` is (n_src, 2): the (x, y) parallax in pixels per metre of each source; the
    homography of height h maps (x, y) to (x + sx h, y + sy h). Used for synthetic scenes.
    """
    s = np.asarray(shifts_px_per_m, dtype=np.float64).reshape(-1, 2)
    h = np.asarray(heights, dtype=np.float64).reshape(-1)
    out = np.zeros((h.size, s.shape[0], 3, 3))
    out[:, :, 0, 0] = out[:, :, 1, 1] = out[:, :, 2, 2] = 1.0
    out[:, :, 0, 2] = h[:, None] * s[None, :, 0]
    out[:, :, 1, 2] = h[:, None] * s[None, :, 1]
    return out


def ellipsoid_heights(height: np.ndarray, ref_proj, frame) -> np.ndarray:
    """Heights above the WGS84 ellipsoid (m) of the points found by a sweep.

    ``height`` is the ENU up coordinate ``u`` (m) of the point seen at each reference pixel (the
    plane parameter of ``HeightMap.height``, NaN where invalid); the point is where the pixel's
    ray crosses the plane ``u = height`` (through ``ref_proj``'s 4x4 matrix, ``satsweep.geometry.camera``),
    converted from the ENU ``frame`` (``satsweep.geo.ENUFrame``) to geodetic coordinates. The
    difference from ``u`` is the Earth curvature (a few millimetres over 300 m, 2 m at 5 km).
    """
    from satsweep.geometry.parallax import enu_from_fourth, fourth_from_height  # noqa: PLC0415

    height = np.asarray(height, dtype=np.float64)
    out = np.full(height.shape, np.nan)
    rows, cols = np.nonzero(np.isfinite(height))
    if rows.size:
        u = height[rows, cols]
        rho = fourth_from_height(ref_proj, cols, rows, u)
        e, n, uu = enu_from_fourth(ref_proj, cols, rows, rho)
        out[rows, cols] = frame.to_geodetic(e=e, n=n, u=uu)[2]
    return out


def _seen_per_plane(homographies, plane_index, n_src: int, hit) -> np.ndarray:
    """(H, W) bool: whether, at its plane, a reference pixel maps with a positive homogeneous
    scale to a source position (u, v) for which ``hit(s, u, v)`` holds, for some source s. The
    pixels of each plane are mapped together (float64)."""
    hom = np.asarray(homographies, dtype=np.float64)
    idx = np.asarray(plane_index)
    h, w = idx.shape
    out = np.zeros(idx.shape, bool)
    ys, xs = np.mgrid[0:h, 0:w]
    flat = idx.ravel()
    # The same order from 16-bit keys where they hold every index (numpy's radix sort).
    short = flat.size > 0 and 0 <= flat.min() and flat.max() < 1 << 16
    key = flat.astype(np.uint16) if short else flat
    order = np.argsort(key, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(hom.shape[0] + 1))
    for p in range(hom.shape[0]):
        pix = order[bounds[p]:bounds[p + 1]]
        if pix.size == 0:
            continue
        x, y = xs.ravel()[pix].astype(np.float64), ys.ravel()[pix].astype(np.float64)
        for s in range(n_src):  # each source maps only the pixels no earlier one saw
            H = hom[p, s] / hom[p, s, 2, 2]
            wz = H[2, 0] * x + H[2, 1] * y + H[2, 2]
            ok = wz > 0
            safe = np.where(ok, wz, 1.0)
            u = (H[0, 0] * x + H[0, 1] * y + H[0, 2]) / safe
            v = (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / safe
            seen = ok & hit(s, u, v)
            out.ravel()[pix[seen]] = True
            pix, x, y = pix[~seen], x[~seen], y[~seen]
            if pix.size == 0:
                break
    return out


def visible_at(homographies, plane_index, src_shapes: Sequence[tuple[int, int]]) -> np.ndarray:
    """Where a reference pixel maps into at least one source at its plane (H, W) bool.

    homographies: (n_planes, n_src, 3, 3) reference pixel -> source pixel, as the sweep takes
    them; plane_index: (H, W) integer plane of each pixel; src_shapes: (rows, cols) of each
    source. The rule of the sweep's winner-take-all (wta.cl): the homogeneous scale is positive
    and the point lies in [0, cols - 1] x [0, rows - 1] (computed here in float64).
    """
    hom = np.asarray(homographies, dtype=np.float64)
    idx = np.asarray(plane_index)
    if not np.issubdtype(idx.dtype, np.integer) or idx.ndim != 2:
        raise InputError(None, f"plane_index: expected a 2-D integer array, got {idx.dtype} "
                               f"{idx.shape}")
    if hom.ndim != 4 or hom.shape[1:] != (len(src_shapes), 3, 3):
        raise InputError(None, f"homographies: shape {hom.shape}, expected (n_planes, "
                               f"{len(src_shapes)}, 3, 3)")
    if idx.size and (idx.min() < 0 or idx.max() >= hom.shape[0]):
        raise InputError(None, f"plane_index: values must be in [0, {hom.shape[0] - 1}]")

    def inside(s, u, v):
        rows, cols = src_shapes[s]
        return (u >= 0) & (u <= cols - 1) & (v >= 0) & (v <= rows - 1)

    return _seen_per_plane(hom, idx, len(src_shapes), inside)


def seen_with_data(homographies, plane_index, src_valid: Sequence[np.ndarray]) -> np.ndarray:
    """Where a reference pixel maps, at its plane, onto a pixel that holds data in at least one
    source (H, W) bool: ``visible_at``'s rule with each source's data mask (``src_valid``, (rows,
    cols) bool, True where the pixel and every pixel its matching window reads hold data) read
    at the nearest pixel."""

    def on_data(s, u, v):
        mask = src_valid[s]
        rows, cols = mask.shape
        inside = (u >= 0) & (u <= cols - 1) & (v >= 0) & (v <= rows - 1)
        iu = np.clip(np.floor(u + 0.5), 0, cols - 1).astype(np.int64)
        iv = np.clip(np.floor(v + 0.5), 0, rows - 1).astype(np.int64)
        return inside & mask[iv, iu]

    return _seen_per_plane(homographies, plane_index, len(src_valid), on_data)


def view_homographies(ref_proj, src_projs: Sequence, heights) -> np.ndarray:
    """(n_planes, n_src, 3, 3) float64 homographies, reference pixel -> source pixel, of the planes
    ``heights`` for projections from ``satsweep.geometry.camera`` (``plane_homography``)."""
    from satsweep.geometry.parallax import plane_homography  # noqa: PLC0415

    h = np.asarray(heights, dtype=np.float64)
    return np.stack([np.asarray(plane_homography(ref_proj, p, h)).reshape(-1, 3, 3)
                     for p in src_projs], axis=1)
