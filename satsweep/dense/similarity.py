"""How alike two views look: the appearance similarity that ranks a reference's sources.

Views of one place taken on different dates differ where the sun moved the shadows, where
vegetation changed with the season, where cars and other transients moved, and in radiometry;
matching a reference against such a source fails exactly there. So, beside the base-to-height
ratio, sources are ranked by a similarity in [0, 1] (1: alike):

- from the acquisition metadata when both views have it (``metadata_similarity``): 1 within one
  pass (acquired less than ``SAME_PASS_S`` apart), else a Gaussian of the angle between the two
  sun directions (shadows) times one of the days between them within a year (season);
- otherwise from the sparse stage's tie points when it ran (``similarity_from_matches``): the
  matches between the strongest features of the two views (its probe of the pair), over the
  stack's largest such count. Views of one date share several times more than views of two
  dates (the multi-date scenes of tools/bench_multidate.py, 10 views, seed 4: 77-122 against
  9-37), where the measured similarity below does not separate them (0.08-0.27 within a date,
  0-0.78 between dates, the highest a pair of nearly one viewpoint);
- otherwise measured from the images (``image_similarity``): both views are projected onto the
  plane at the middle of the altitude range over the AOI, on a coarse grid (``GRID_CELL_M``),
  and compared by zero-mean normalised cross-correlation of their gradient magnitudes
  (insensitive to gain and offset; shadow edges, vegetation and transients lower it).

``appearance_similarity`` takes the metadata where both views have it, then the tie points,
and measures the rest.

Apart from how alike two views look, a view's date says how much of the vegetation it sees
(``leaf_season``): a DSM holds the top of the canopy (an airborne lidar's first return, the
highest point of each cell), which deciduous trees show only in leaf; a leafless crown shows
the ground through its branches, and a height map matched on a winter date puts most of a
crown at the ground's height. Where no view has a date but every image has colour,
``leaf_state_from_vegetation`` estimates it from the images: the share of each view's pixels
among the greenest of the stack (crowns in leaf), scaled from the pale views' level to the
green views'.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Sequence

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    import datetime

    from satsweep.geometry.aoi import AOI
    from satsweep.geometry.camera import CameraSet
    from satsweep.io.metadata import AcquisitionMetadata

# Two acquisitions less than this far apart (seconds) are one pass: same sun, same scene.
SAME_PASS_S = 600.0
# Sun directions this far apart (degrees) lower the similarity to exp(-1/2): shadows cast from
# directions 15 degrees apart move by a quarter of a building's height.
SUN_SCALE_DEG = 15.0
# Dates this many days apart within a year (the shorter way round) lower it to exp(-1/2): the
# vegetation of mid-latitude cities changes over a season.
SEASON_SCALE_DAYS = 45.0
# Temperate deciduous phenology (northern hemisphere days of year; the southern one is half a
# year off): leafless until LEAF_OUT_DOY[0] (1 April) and from LEAF_FALL_DOY[1] (1 December),
# in full leaf from LEAF_OUT_DOY[1] (1 June) to LEAF_FALL_DOY[0] (1 October), linear between.
# Broad on purpose: leaf-out and leaf fall move by weeks with latitude, altitude and species;
# the dates inside both ramps are the ones it cannot tell.
LEAF_OUT_DOY = (91.0, 152.0)
LEAF_FALL_DOY = (274.0, 335.0)
# Within this latitude (degrees) there is no leafless season to avoid (the tropics: 1).
TROPICS_LAT_DEG = 23.44
# Side (m) of the cells of the grid the images are compared on: coarse enough that the
# parallax of a few metres of height between two views stays within about a cell.
GRID_CELL_M = 2.0
# Fewer common grid cells than this leave the measured similarity unknown (then 1: no
# preference).
MIN_COMMON_CELLS = 64
# Leaf state from colour (leaf_state_from_vegetation). The stack's greenest level: this
# quantile of every view's vegetation index pooled (leaves in full leaf where some view has
# them); a pixel counts as canopy green from halfway between the vegetation threshold
# (io.images.VEGETATION_INDEX_MIN: leaves, grass) and that level, which leaves out the paler
# grass and the autumn and winter crowns. Issue-form synthetic stacks (8-bit RGB, one view per
# date, docs/measurements.md): greenest level 0.345, threshold 0.22; the share 0.02-0.03 of a
# view's pixels in winter and autumn, 0.08-0.14 from April to early October.
CANOPY_QUANTILE = 0.99
# Each view's index is first taken relative to its own neutral level, this quantile of it (the
# crops of a town are mostly roofs, roads and soil): a colour cast or haze that differs between
# the dates (each image is stretched on its own) moves every pixel's index alike. Synthetic
# stacks have none (neutral 0.014-0.015 in every view; the estimates move by under 0.01).
NEUTRAL_QUANTILE = 0.25
# A stack whose green views' level is under LEAF_SHARE_RATIO times its pale views', or exceeds
# it by less than LEAF_SHARE_SPREAD of the pixels, shows no season in its colours (all dates in
# leaf, evergreen, or all leafless): its leaf state stays unknown.
LEAF_SHARE_RATIO = 2.0
LEAF_SHARE_SPREAD = 0.02


def _sun_vector(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])


def same_pass(ta: "datetime.datetime", tb: "datetime.datetime") -> bool:
    """Whether two acquisition times are one pass (less than ``SAME_PASS_S`` apart)."""
    return abs((ta - tb).total_seconds()) < SAME_PASS_S


def acquisition_passes(acquisitions: Sequence["AcquisitionMetadata | None"]) -> list[int | None]:
    """Per acquisition, a label of its pass (``same_pass``: in time order, an acquisition within
    ``SAME_PASS_S`` of the previous one shares its pass); None where the metadata give no
    date-time. Two views of one pass see one scene (the same transients, the same leaves), so
    their agreement is one measurement."""
    times = [None if a is None else a.acquisition_datetime for a in acquisitions]
    order = sorted((i for i, t in enumerate(times) if t is not None), key=lambda i: times[i])
    passes: list[int | None] = [None] * len(times)
    label, previous = -1, None
    for i in order:
        if previous is None or not same_pass(times[previous], times[i]):
            label += 1
        passes[i], previous = label, i
    return passes


def metadata_similarity(a: "AcquisitionMetadata | None",
                        b: "AcquisitionMetadata | None") -> float | None:
    """The similarity of two acquisitions from their metadata (see the module docstring), or
    None when either lacks the date or the sun angles."""
    if a is None or b is None:
        return None
    ta, tb = a.acquisition_datetime, b.acquisition_datetime
    if ta is None or tb is None:
        return None
    if same_pass(ta, tb):
        return 1.0
    if None in (a.sun_azimuth_deg, a.sun_elevation_deg, b.sun_azimuth_deg, b.sun_elevation_deg):
        return None
    cos = float(np.dot(_sun_vector(a.sun_azimuth_deg, a.sun_elevation_deg),
                       _sun_vector(b.sun_azimuth_deg, b.sun_elevation_deg)))
    sun = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
    days = abs((ta - tb).total_seconds()) / 86400.0 % 365.25
    season = min(days, 365.25 - days)
    return math.exp(-0.5 * (sun / SUN_SCALE_DEG) ** 2 - 0.5 * (season / SEASON_SCALE_DAYS) ** 2)


def leaf_season(acquisition: "AcquisitionMetadata | None", lat: float) -> float | None:
    """How fully deciduous trees are in leaf on an acquisition's date at latitude ``lat``
    (degrees): 1 in full leaf (and anywhere in the tropics), 0 leafless, a linear ramp in
    between (``LEAF_OUT_DOY``, ``LEAF_FALL_DOY``); None when the metadata give no date."""
    if acquisition is None or acquisition.acquisition_datetime is None:
        return None
    if abs(lat) < TROPICS_LAT_DEG:
        return 1.0
    t = acquisition.acquisition_datetime
    doy = t.timetuple().tm_yday + (t.hour + t.minute / 60.0) / 24.0
    if lat < 0.0:
        doy = (doy + 365.25 / 2.0) % 365.25
    if doy < LEAF_OUT_DOY[0] or doy >= LEAF_FALL_DOY[1]:
        return 0.0
    if doy < LEAF_OUT_DOY[1]:
        return (doy - LEAF_OUT_DOY[0]) / (LEAF_OUT_DOY[1] - LEAF_OUT_DOY[0])
    if doy < LEAF_FALL_DOY[0]:
        return 1.0
    return (LEAF_FALL_DOY[1] - doy) / (LEAF_FALL_DOY[1] - LEAF_FALL_DOY[0])


def leaf_state_from_vegetation(indices: Sequence[np.ndarray | None],
                                valid: Sequence[np.ndarray | None] | None = None
                                ) -> list[float] | None:
    """Each view's leaf state in [0, 1] estimated from its vegetation index image
    (``satsweep.io.images.vegetation_index``; ``valid``: per view, the pixels holding data, None
    for all), each relative to its own neutral level (``NEUTRAL_QUANTILE``): the share of its
    pixels at least as green as canopy (``CANOPY_QUANTILE``), scaled from the pale views' level
    (0) to the green ones' (1): the median share of the views below and above halfway between
    the least and the most share, clipped to [0, 1] (an oblique view sees more of the crowns'
    sides than a steep one of the same date). None where some view has
    no index, where the stack has no vegetation, or where the two levels show no season
    (``LEAF_SHARE_RATIO``, ``LEAF_SHARE_SPREAD``). A stand-in for ``leaf_season`` on stacks
    without dates: it cannot tell early spring's green but thin leaves from summer's."""
    from satsweep.io.images import VEGETATION_INDEX_MIN

    if not indices or any(x is None for x in indices):
        return None
    masks = [None] * len(indices) if valid is None else list(valid)
    if len(masks) != len(indices):
        raise ValueError(f"{len(indices)} vegetation images but {len(masks)} masks")
    values = []
    for x, m in zip(indices, masks):
        x = np.asarray(x, np.float64)
        keep = np.isfinite(x) if m is None else (np.asarray(m, bool) & np.isfinite(x))
        if not keep.any():
            return None
        values.append(x[keep] - np.quantile(x[keep], NEUTRAL_QUANTILE))
    greenest = float(np.quantile(np.concatenate(values), CANOPY_QUANTILE))
    if greenest <= VEGETATION_INDEX_MIN:
        return None
    threshold = 0.5 * (VEGETATION_INDEX_MIN + greenest)
    share = np.array([float(np.mean(v >= threshold)) for v in values])
    # The two groups' levels: the views' shares split halfway between the least and the most.
    middle = 0.5 * (float(share.min()) + float(share.max()))
    low = float(np.median(share[share <= middle]))
    high = float(np.median(share[share > middle])) if (share > middle).any() else low
    if high < LEAF_SHARE_RATIO * low or high - low < LEAF_SHARE_SPREAD:
        return None
    return [float(v) for v in np.clip((share - low) / (high - low), 0.0, 1.0)]


def _ground_grid(cameras: "CameraSet", aoi: "AOI", height: float) -> tuple[np.ndarray, ...]:
    """ENU (e, n) of a GRID_CELL_M grid over the AOI box, on the plane u = height."""
    frame = cameras.frame
    lon = np.array([aoi.lon_min, aoi.lon_max, aoi.lon_min, aoi.lon_max])
    lat = np.array([aoi.lat_min, aoi.lat_min, aoi.lat_max, aoi.lat_max])
    e, n, _ = frame.from_geodetic(lon=lon, lat=lat, alt=np.full(4, frame.alt0))
    es = np.arange(e.min(), e.max() + GRID_CELL_M, GRID_CELL_M)
    ns = np.arange(n.min(), n.max() + GRID_CELL_M, GRID_CELL_M)
    ee, nn = np.meshgrid(es, ns)
    return ee, nn, np.full(ee.shape, float(height))


def _projected_gradients(image: np.ndarray, P: np.ndarray, ground) -> np.ndarray:
    """Gradient magnitude of ``image`` (blurred to the grid's cell) sampled at the ground grid's
    projection by ``P``; NaN where it falls outside the image."""
    import cv2

    ee, nn, uu = ground
    X = np.stack([ee.ravel(), nn.ravel(), uu.ravel(), np.ones(ee.size)])
    x = P @ X
    col, row = x[0] / x[2], x[1] / x[2]
    img = np.nan_to_num(np.asarray(image, np.float32))
    # The image's pixels per grid cell, from the projection of one cell step.
    step = np.hypot(*(P[:2, :2] @ np.array([GRID_CELL_M, 0.0]) / np.median(x[2])))
    sigma = max(0.5, 0.5 * float(step))
    blurred = cv2.GaussianBlur(img, (0, 0), sigma)
    gx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3)
    magnitude = np.hypot(gx, gy)
    h, w = img.shape
    inside = (col >= 0) & (col <= w - 1) & (row >= 0) & (row <= h - 1)
    sampled = cv2.remap(magnitude, col.astype(np.float32).reshape(ee.shape),
                        row.astype(np.float32).reshape(ee.shape), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return np.where(inside.reshape(ee.shape), sampled, np.nan)


def _zncc(a: np.ndarray, b: np.ndarray) -> float | None:
    both = np.isfinite(a) & np.isfinite(b)
    if both.sum() < MIN_COMMON_CELLS:
        return None
    x, y = a[both] - a[both].mean(), b[both] - b[both].mean()
    denom = math.sqrt(float(np.dot(x, x)) * float(np.dot(y, y)))
    return None if denom == 0.0 else float(np.dot(x, y)) / denom


def image_similarity(images: Sequence[np.ndarray], cameras: "CameraSet", aoi: "AOI",
                     height: float) -> np.ndarray:
    """(n, n) similarity measured from the images (see the module docstring), in [0, 1]; NaN
    where two views share too little of the grid to say."""
    ground = _ground_grid(cameras, aoi, height)
    grads = [_projected_gradients(im, v.camera.P, ground) for im, v in zip(images, cameras.views)]
    n = len(grads)
    out = np.eye(n)
    for i in range(n):
        for j in range(i + 1, n):
            z = _zncc(grads[i], grads[j])
            out[i, j] = out[j, i] = np.nan if z is None else max(0.0, z)
    return out


def similarity_from_matches(counts: np.ndarray) -> np.ndarray:
    """(n, n) similarity from the sparse stage's probe matches ``counts`` (n, n; NaN: the pair
    was not probed): each count over the largest. A pair not probed takes the best over a third
    view k of the smaller of (i, k) and (k, j) (views of one date are alike to each other and
    to the same others); NaN where no third view links the two."""
    c = np.array(counts, dtype=np.float64)
    n = c.shape[0]
    off = ~np.eye(n, dtype=bool)
    finite = np.isfinite(c) & off
    top = float(np.max(c[finite])) if finite.any() else 0.0
    if top <= 0.0:
        out = np.full((n, n), np.nan)
        np.fill_diagonal(out, 1.0)
        return out
    s = np.where(finite, np.clip(c / top, 0.0, 1.0), np.nan)
    np.fill_diagonal(s, 1.0)
    known = np.nan_to_num(s, nan=0.0)
    via = np.max(np.minimum(known[:, :, None], known[None, :, :]), axis=1)
    return np.where(np.isfinite(s), s, np.where(via > 0.0, via, np.nan))


def known_similarity(acquisitions: Sequence["AcquisitionMetadata | None"], *,
                     matches: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(similarity, source) of every pair of views from what is known before the images are
    compared: the metadata where both views have it, else ``matches`` (the sparse stage's probe
    counts, :func:`similarity_from_matches`) where given and known; "images" (similarity 1)
    where neither says (:func:`appearance_similarity` measures those)."""
    n = len(acquisitions)
    sim = np.eye(n)
    source = np.full((n, n), "images", dtype=object)
    for i in range(n):
        for j in range(i + 1, n):
            s = metadata_similarity(acquisitions[i], acquisitions[j])
            if s is not None:
                sim[i, j] = sim[j, i] = s
                source[i, j] = source[j, i] = "metadata"
    if matches is not None:
        from_matches = similarity_from_matches(matches)
        use = (source != "metadata") & np.isfinite(from_matches)
        sim = np.where(use, from_matches, sim)
        source[use] = "tie points"
    rest = (source == "images") & ~np.eye(n, dtype=bool)
    sim = np.where(rest, 1.0, sim)
    return sim, source


def appearance_similarity(acquisitions: Sequence["AcquisitionMetadata | None"],
                          images: Sequence[np.ndarray], cameras: "CameraSet", aoi: "AOI",
                          height: float, *, matches: np.ndarray | None = None
                          ) -> tuple[np.ndarray, np.ndarray]:
    """(similarity, source): the (n, n) similarity of every pair of views, and where each came
    from ("metadata", "tie points" or "images"): :func:`known_similarity`, and for the pairs
    that neither the metadata nor ``matches`` tell, measured from the images (1 where nothing
    can say)."""
    sim, source = known_similarity(acquisitions, matches=matches)
    return with_measured_similarity(sim, source, images, cameras, aoi, height)


def with_measured_similarity(sim: np.ndarray, source: np.ndarray,
                             images: Sequence[np.ndarray], cameras: "CameraSet", aoi: "AOI",
                             height: float) -> tuple[np.ndarray, np.ndarray]:
    """``known_similarity``'s (similarity, source) with the pairs it left to the images
    ("images") measured from them (:func:`image_similarity`; 1 where nothing can say)."""
    rest = source == "images"
    np.fill_diagonal(rest, False)
    if rest.any():
        measured = image_similarity(images, cameras, aoi, height)
        fill = np.where(np.isfinite(measured), measured, 1.0)
        sim = np.where(rest, fill, sim)
    return sim, source
