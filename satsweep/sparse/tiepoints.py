"""Altitude ranges from tie points: the scene's heights when the user gives none.

Two ways. :func:`altitude_range_from_points` bounds the sparse stage's adjusted tie points
(:mod:`satsweep.sparse.stage`): their reprojection errors with the corrected cameras weed out
wrong matches across views, and the range is robust to those left (see its docstring). The
older :func:`altitude_range_for_images` (what the pipeline's "altitude" stage calls until it
moves to the sparse stage) triangulates every pair's matches with the raw RPCs, as follows.

Without ``--alt-range`` or ``--dem``, the only prior on the scene's heights is the RPCs' height
offset +- scale, which spans kilometres (-20..2610 m for the Pleiades pair, whose ground lies
between about 2270 and 2376 m): thousands of planes. As S2P estimates its disparity range from
SIFT matches, satsweep matches SIFT features between the views (cropped to the AOI over that
coarse range), triangulates each verified match with the two RPCs, keeps the points inside the
AOI, and sweeps between quantiles of their altitudes widened by a margin. On the Pleiades pair the
480 tie points span 2273.1..2374.3 m (1% and 99% quantiles; 2271.9..2375.9 m in all), S2P's DSM
2273.8..2373.2 m.

Triangulation: the pixel of the first view is localised (``RPCModel.localization``) at a few
altitudes and each ground point projected into the second view; a straight line fitted through
those projections (a line of sight is nearly straight in the other image) gives the altitude at
which it passes closest to the matched pixel, and the same fit over a bracket of
``REFINE_HALF_M`` around that altitude refines it. The distance left between the line and the
pixel is the point's residual (pointing errors, matching noise).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Callable, Sequence

import numpy as np

from satsweep.errors import InputError
from satsweep.geometry.altitude import AltitudeRange
from satsweep.geometry.aoi import AOI

# Altitudes sampled along a line of sight for the first, coarse fit, and for the refinement.
COARSE_SAMPLES = 5
REFINE_SAMPLES = 3
# Half-width (m) of the bracket of the refinement around the coarse altitude.
REFINE_HALF_M = 50.0
# Fewer tie points than this inside the AOI cannot bound its heights.
MIN_TIE_POINTS = 20
# Points above the supported top that are checked against the views, highest first.
MAX_CONFIRM_CANDIDATES = 16
# Fewest points of fewer than altitude_floor_views views that can set the floor (with the
# fraction altitude_floor_fewer_fraction of them): wrong two-view matches agree in twos and
# threes by chance (a 5-view multi-date stack: two of 136 within 3 m of each other at 11 m, 89 m
# under the ground), a ground seen by two views at a time in dozens.
FEWER_VIEWS_MIN_SUPPORT = 5


@dataclasses.dataclass(frozen=True)
class TiePoints:
    """Triangulated tie points: geodetic coordinates and the residual of each (pixels)."""

    lon: np.ndarray  # (N,) degrees
    lat: np.ndarray  # (N,) degrees
    alt: np.ndarray  # (N,) metres above the WGS84 ellipsoid
    residual_px: np.ndarray  # (N,) distance in the second view between match and line of sight
    pairs: tuple[tuple[int, int, int], ...]  # (view i, view j, verified matches) per pair


def _fit_altitude(rpc1, rpc2, xy1: np.ndarray, xy2: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                  samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Altitude of closest approach of view 1's lines of sight to the pixels of view 2, searched
    per point between ``lo`` and ``hi`` (arrays), and the distance (px) left there."""
    t = np.linspace(0.0, 1.0, samples)
    alts = lo[None, :] + t[:, None] * (hi - lo)[None, :]  # (samples, N)
    proj = np.empty(alts.shape + (2,))
    for k in range(samples):
        lon, lat = rpc1.localization(col=xy1[:, 0], row=xy1[:, 1], alt=alts[k])
        col, row = rpc2.projection(lon=lon, lat=lat, alt=alts[k])
        proj[k, :, 0], proj[k, :, 1] = col, row
    # Per point, the least-squares line proj = q0 + s q1 in s = (alt - mean) / span.
    mid = alts.mean(axis=0)
    span = np.maximum(hi - lo, 1e-9)
    s = (alts - mid[None]) / span[None]
    s2 = (s * s).sum(axis=0)
    q0 = proj.mean(axis=0)
    q1 = (s[:, :, None] * (proj - q0[None])).sum(axis=0) / s2[:, None]
    d = xy2 - q0
    along = (d * q1).sum(axis=1) / np.maximum((q1 * q1).sum(axis=1), 1e-30)
    residual = np.linalg.norm(d - along[:, None] * q1, axis=1)
    return mid + along * span, residual


def triangulate_pair(rpc1, rpc2, xy1, xy2, alt_range: AltitudeRange
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(lon, lat, alt, residual_px) of matched pixels ``xy1`` (view 1) and ``xy2`` (view 2),
    (N, 2) (col, row) arrays in each view's pixels, with altitudes searched over ``alt_range``."""
    xy1 = np.asarray(xy1, np.float64).reshape(-1, 2)
    xy2 = np.asarray(xy2, np.float64).reshape(-1, 2)
    n = xy1.shape[0]
    alt, _ = _fit_altitude(rpc1, rpc2, xy1, xy2, np.full(n, alt_range.min),
                           np.full(n, alt_range.max), COARSE_SAMPLES)
    alt, residual = _fit_altitude(rpc1, rpc2, xy1, xy2, alt - REFINE_HALF_M, alt + REFINE_HALF_M,
                                  REFINE_SAMPLES)
    lon, lat = rpc1.localization(col=xy1[:, 0], row=xy1[:, 1], alt=alt)
    return np.asarray(lon, np.float64), np.asarray(lat, np.float64), alt, residual


def tie_points(views: Sequence, aoi: AOI, alt_range: AltitudeRange, sparse_options) -> TiePoints:
    """SIFT tie points of every pair of views (RANSAC-verified matches, no cameras needed),
    triangulated with the views' RPCs over ``alt_range``; only the points inside the AOI."""
    from satsweep.io.images import tonemap
    from satsweep.sparse.features import detect_features, feature_scale_for
    from satsweep.sparse.matching import match_pair

    o = sparse_options
    feats = [detect_features(tonemap(v.image), max_features=o.max_features,
                             contrast_threshold=o.contrast_threshold,
                             scale=feature_scale_for(np.shape(v.image), o))
             for v in views]
    parts, pairs = [], []
    for i, j in itertools.combinations(range(len(views)), 2):
        (xy_i, d_i), (xy_j, d_j) = feats[i], feats[j]
        if len(xy_i) < 2 or len(xy_j) < 2:
            pairs.append((i, j, 0))
            continue
        a, b = match_pair(d_i, d_j, xy_i, xy_j, o)
        pairs.append((i, j, int(a.size)))
        if a.size:
            parts.append(triangulate_pair(views[i].rpc, views[j].rpc, xy_i[a], xy_j[b], alt_range))
    if parts:
        lon, lat, alt, res = (np.concatenate(c) for c in zip(*parts))
    else:
        lon = lat = alt = res = np.zeros(0)
    inside = ((lon >= aoi.lon_min) & (lon <= aoi.lon_max) & (lat >= aoi.lat_min)
              & (lat <= aoi.lat_max) & np.isfinite(alt))
    return TiePoints(lon=lon[inside], lat=lat[inside], alt=alt[inside], residual_px=res[inside],
                     pairs=tuple(pairs))


def altitude_range_from_tie_points(points: TiePoints, *, quantile: float, margin_m: float,
                                   within: AltitudeRange | None = None,
                                   names: Sequence[str] = ()) -> AltitudeRange:
    """The altitudes between the ``quantile`` and ``1 - quantile`` quantiles of the tie points,
    widened by ``margin_m`` on each side and kept ``within`` a range (the RPCs' heights) when they
    overlap it. InputError when there are too few points."""
    if points.alt.size < MIN_TIE_POINTS:
        which = ", ".join(names) if names else "the images"
        raise InputError(None, f"no altitude range given and only {points.alt.size} tie points "
                               f"between {which} fall inside the AOI (at least {MIN_TIE_POINTS} "
                               "are needed to bound its heights): give --alt-range MIN MAX or "
                               "--dem FILE (alt_range= or dem= in the Python API)")
    lo, hi = np.quantile(points.alt, [quantile, 1.0 - quantile])
    lo, hi = float(lo) - margin_m, float(hi) + margin_m
    if within is not None and max(lo, within.min) < min(hi, within.max):
        lo, hi = max(lo, within.min), min(hi, within.max)
    return AltitudeRange(lo, hi)


def supported_extremes(alt: np.ndarray, support: int, window_m: float) -> tuple[float, float]:
    """The lowest and the highest altitudes at which ``support`` values lie within ``window_m``.

    ``lo`` is the lowest ``a`` with at least ``support`` altitudes in ``[a, a + window_m]``,
    ``hi`` the highest with as many in ``[a - window_m, a]``: a wrong match has a height of its
    own, while the ground and each roof hold several tie points at nearly the same height.
    Falls back to the extremes when no altitude has that support (fewer values than it)."""
    a = np.asarray(alt, np.float64)
    lo = lowest_supported(a, support, window_m)
    neg_hi = lowest_supported(-a, support, window_m)  # the highest, seen upside down
    return float(a.min() if lo is None else lo), float(a.max() if neg_hi is None else -neg_hi)


def lowest_supported(alt: np.ndarray, support: int, window_m: float) -> float | None:
    """The lowest altitude ``a`` with at least ``support`` values in ``[a, a + window_m]``, or
    None when no altitude has that support."""
    a = np.sort(np.asarray(alt, np.float64))
    above = np.searchsorted(a, a + window_m, side="right") - np.arange(len(a))
    ok = np.flatnonzero(above >= support)
    return float(a[ok[0]]) if ok.size else None


def _near_aoi(points: np.ndarray, frame, aoi: AOI, margin_m: float) -> np.ndarray:
    """Which ENU ``points`` lie within ``margin_m`` of the AOI (its ENU bounding box, grown)."""
    lon, lat = aoi.boundary()
    e, n, _ = frame.from_geodetic(lon=lon, lat=lat, alt=np.zeros(lon.shape))
    return ((points[:, 0] >= e.min() - margin_m) & (points[:, 0] <= e.max() + margin_m)
            & (points[:, 1] >= n.min() - margin_m) & (points[:, 1] <= n.max() + margin_m))


def altitude_range_from_points(points: np.ndarray, obs, point_error: np.ndarray, frame, aoi: AOI,
                               options, *, within: AltitudeRange | None = None,
                               confirm: Callable[[int], bool] | None = None
                               ) -> tuple[AltitudeRange | None, dict]:
    """The altitude range of adjusted tie points (the sparse stage's), and a record of it.

    ``points`` (N, 3): ENU points (m) of ``frame``; ``obs``: their observations (to count the
    views of each); ``point_error`` (N,): each point's largest reprojection error (px) with the
    corrected cameras; ``options``: SparseOptions. The points used lie inside the AOI grown by
    ``altitude_aoi_margin_m`` with every error within ``altitude_max_error_px``. The range runs
    from the lowest altitude of the points seen by ``altitude_floor_views`` views or more (all
    points when fewer than ``altitude_min_points`` are; or that of the points of fewer views,
    when it lies more than ``altitude_margin_below_m`` lower and ``altitude_floor_fewer_fraction``
    of them, and FEWER_VIEWS_MIN_SUPPORT at least, share it within ``altitude_support_m``) to
    the highest of all, each the lowest
    or highest altitude supported by ``altitude_support`` points (or
    ``altitude_support_fraction`` of them) within ``altitude_support_m``
    (:func:`supported_extremes`); ``confirm(i)``, when given, is asked about the points above
    that top, highest first (at most ``MAX_CONFIRM_CANDIDATES``), and the first it accepts
    raises the top to its altitude (the sparse stage asks the views,
    :mod:`satsweep.sparse.verify`); both ends widened by ``altitude_margin_below_m`` and
    ``altitude_margin_above_m``, the margins kept ``within`` the prior range when they overlap
    it (an extreme past the prior is kept: :func:`_within_prior`).

    Why the two ends differ: a wrong match that two views accept anywhere along its epipolar
    line gets a height of its own, and more views bring more of them (a 20-view synthetic stack:
    points of two views down to 32 m below the ground, those of three views or more within 8 m
    of it); the ground is seen everywhere, by many views. The highest roofs are seen by few
    views (plain roofs have no features: only their corners, against the ground below), and on
    3-view stacks no point of three views comes within 5-44 m of the highest roof, while points
    of two views come within 1-13 m. Returns (None, record with a "reason") when fewer than
    ``altitude_min_points`` are usable.
    """
    o = options
    n_views = np.bincount(obs.point, minlength=len(points)) if len(points) else np.zeros(0, int)
    if len(points):
        alt = frame.to_geodetic(e=points[:, 0], n=points[:, 1], u=points[:, 2])[2]
        inside = _near_aoi(points, frame, aoi, o.altitude_aoi_margin_m) & np.isfinite(alt)
    else:
        alt = np.zeros(0)
        inside = np.zeros(0, dtype=bool)
    use = inside & (point_error <= o.altitude_max_error_px)
    floor = use & (n_views >= o.altitude_floor_views)
    if floor.sum() < o.altitude_min_points:
        floor = use
    record: dict = {"source": "tie points", "tie_points": int(use.sum()),
                    "tie_points_for_the_lowest": int(floor.sum()),
                    "tie_points_near_aoi": int(inside.sum()),
                    "aoi_margin_m": o.altitude_aoi_margin_m,
                    "views_per_tie_point": {str(k): int(c) for k, c in
                                            enumerate(np.bincount(n_views[use])) if c},
                    "max_error_px": o.altitude_max_error_px}
    if use.sum() < o.altitude_min_points:
        record["reason"] = (f"only {int(use.sum())} adjusted tie points within "
                            f"{o.altitude_aoi_margin_m:g} m of the AOI (at least "
                            f"{o.altitude_min_points} are needed to bound its heights)")
        return None, record
    a = alt[use]

    def support(n: int) -> int:
        return max(o.altitude_support, math.ceil(o.altitude_support_fraction * n))

    lo = supported_extremes(alt[floor], support(int(floor.sum())), o.altitude_support_m)[0]
    fewer = use & ~floor
    if fewer.any() and o.altitude_floor_fewer_fraction > 0.0:
        # A ground that few views tie (each date's texture differs: one view per date) leaves
        # the points of many views on the roofs; the points of fewer views then show it where a
        # good share of them agree on its height (wrong matches scatter theirs), below what the
        # margin adds to the floor of the points of many views.
        need = max(FEWER_VIEWS_MIN_SUPPORT,
                   math.ceil(o.altitude_floor_fewer_fraction * fewer.sum()))
        low = lowest_supported(alt[fewer], need, o.altitude_support_m)
        if low is not None and low < lo - o.altitude_margin_below_m:
            record["floor_from_fewer_views"] = {"altitude_m": low, "points": int(fewer.sum()),
                                                "support": need}
            lo = low
    hi = supported_extremes(a, support(a.size), o.altitude_support_m)[1]
    record["supported_extremes_m"] = [lo, hi]
    if confirm is not None:
        # The points above the supported top, highest first: the first that other views
        # confirm raises it (a lone tower's roof; satsweep.sparse.verify).
        above = np.flatnonzero(use & (alt > hi + o.altitude_support_m))
        above = above[np.argsort(-alt[above])][:MAX_CONFIRM_CANDIDATES]
        tried = 0
        for tried, i in enumerate(above, start=1):
            if confirm(int(i)):
                hi = float(alt[i])
                record["confirmed_top_m"] = hi
                break
        record["unsupported_points_tried"] = tried
    lo, hi = _within_prior(lo, hi, o.altitude_margin_below_m, o.altitude_margin_above_m, within)
    record.update({"min": lo, "max": hi,
                   "tie_point_altitudes_m": [float(x) for x in np.quantile(a, [0.0, 0.5, 1.0])]})
    return AltitudeRange(lo, hi), record


def _within_prior(lo: float, hi: float, below_m: float, above_m: float,
                  prior: AltitudeRange | None) -> tuple[float, float]:
    """The supported extremes ``lo``, ``hi`` widened by the margins, the margins cut at the
    ``prior`` (the RPCs' range) when the range overlaps it, the extremes themselves never: the
    prior holds the scene in the RPCs' frame, while the corrected cameras put it where the
    adjustment's gauge does, metres away when one view of a pair is a pixel or two off along the
    epipolar lines (a same-date pair of the v20 multi-date stacks, seed 1, views 7-8: supported
    ground at 89 m, the prior's floor at 95 m, and more than half of the sweep's pixels at that
    floor). Past the prior the margin is not added: on 5-view multi-date stacks the supported
    floor lies a few metres under the ground (two-view points), and a deeper range lets shadows
    match below it."""
    out_lo, out_hi = lo - below_m, hi + above_m
    if prior is None or not max(out_lo, prior.min) < min(out_hi, prior.max):
        return out_lo, out_hi
    return max(out_lo, min(prior.min, lo)), min(out_hi, max(prior.max, hi))


def altitude_range_for_images(images: Sequence, aoi: AOI, sparse_options, *, quantile: float,
                              margin_m: float, crop_margin_px: int) -> tuple[AltitudeRange, dict]:
    """The altitude range of images that come with no range nor DEM: their RPCs' coarse range
    (``altitude_range_from_rpcs``), narrowed by tie points between crops of that range.
    ``images``: paths or ``ImageSource`` objects. Returns the range and a record for
    report.json."""
    from satsweep.geometry.altitude import altitude_range_from_rpcs
    from satsweep.io.sources import open_sources
    from satsweep.io.views import load_views

    sources = open_sources(images)
    names = [s.name for s in sources]
    coarse = altitude_range_from_rpcs([s.rpc for s in sources], warn=False)
    # Over the RPCs' kilometres of heights the footprints overflow the images: not worth a warning.
    views = load_views(sources, aoi, coarse, margin_px=crop_margin_px, warn_partial=False)
    ties = tie_points(views, aoi, coarse, sparse_options)
    alt = altitude_range_from_tie_points(ties, quantile=quantile, margin_m=margin_m,
                                         within=coarse, names=names)
    record = {
        "min": alt.min, "max": alt.max, "source": "tie points",
        "rpc_range": [coarse.min, coarse.max], "tie_points": int(ties.alt.size),
        "tie_point_altitudes_m": [float(a) for a in np.quantile(ties.alt, [0.0, 0.5, 1.0])],
        "matches_per_pair": [{"views": [names[i], names[j]], "matches": n} for i, j, n in ties.pairs],
        "median_residual_px": float(np.median(ties.residual_px)),
    }
    return alt, record
