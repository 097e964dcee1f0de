"""DSM accuracy against a ground-truth DSM: the IARPA MVS3DM protocol.

The protocol of the IARPA Multi-View Stereo 3D Mapping challenge (Bosch et al., "A multiple view
stereo benchmark for satellite imagery", AIPR 2016; "Metric evaluation pipeline for 3D modeling of
urban scenes", ISPRS 2017), as S2P and later satellite MVS papers report it:

1. The prediction is resampled onto the truth grid (same EPSG code required; extents and cell
   sizes may differ). Resampling is nearest neighbour by default: a truth cell takes the
   prediction cell holding its centre, which never blends a roof with the ground beside it;
   ``bilinear`` is available and yields a value only where every neighbour it weighs is valid.
2. Alignment: every horizontal shift of the prediction by an integer number of truth cells with
   ``|dx|, |dy| <= max_shift_m`` is tried; for each, the vertical offset is the median of
   (truth - shifted prediction) over the cells valid in both, and the score is the median
   absolute error after removing it. The shift with the least score wins (ties: the smallest
   shift). Shifted predictions are sampled from the prediction's own data beyond the truth
   extent where it has any.
3. Metrics over the aligned prediction: ``median_abs_error_m`` and ``rmse_m`` over cells valid in
   both; ``completeness_1m`` = fraction of valid truth cells whose aligned error is below
   ``threshold_m`` (1 m), a missing prediction counting as a failure.

Both the aligned and the unaligned (no shift, no offset) metrics are reported. ``shift`` is the
translation applied to the prediction, in metres: ``aligned(x + dx, y + dy) = pred(x, y) + dz``
(x east, y north). A constant vertical datum difference (geoid vs ellipsoid) shows up in dz.

``protocol = "dfc"``: the IEEE GRSS Data Fusion Contest 2019 / US3D protocol (Bosch et al., "Semantic
stereo for incidental satellite images", WACV 2019), as S2P, Sat-NeRF and EO-NeRF report it (mean
absolute altitude error, water masked, horizontal shift by NCC, mean vertical offset removed, holes
not counted):

1. The prediction is resampled onto the truth grid as above.
2. An optional classification raster on the truth grid masks cells whose class is in
   ``water_classes`` (ASPRS LAS class 9 = water in the DFC2019 / US3D ``CLS`` rasters): they are
   left out of everything below, the truth cells counted included.
3. Every integer horizontal shift with ``|dx|, |dy| <= dfc_max_shift_cells`` truth cells is tried;
   the one whose normalised cross-correlation between truth and shifted prediction is largest
   wins (ties: the smallest shift). The NCC of a shift is taken over the cells valid in both
   (holes are never filled), with its own means and deviations; a shift that compares fewer than
   ``NCC_MIN_OVERLAP_FRACTION`` of the most cells any shift compares is not considered.
4. The vertical offset dz is the mean of (truth - shifted prediction) over the cells valid in
   both; ``mean_abs_error_m``, ``median_abs_error_m`` and ``rmse_m`` are taken over those cells
   after adding it; ``valid_fraction`` is the fraction of (unmasked, valid) truth cells that the
   aligned prediction has; ``completeness_1m`` is MVS3DM's figure on the same cells (fraction of
   truth cells whose aligned error is below ``threshold_m``, a missing prediction a failure), so
   that it compares with the MVS3DM protocol's; ``compared_within_1m`` is that fraction among
   the compared cells only.

Its report is flat (no aligned / unaligned parts); ``shift`` holds dx_cells, dy_cells besides
dx_m, dy_m, dz_m, with the convention above.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any, Literal

import numpy as np

from satsweep.errors import InputError, OptionsError
from satsweep.options import Options
from satsweep.threads import map_in_threads

PROTOCOL = "IARPA MVS3DM (Bosch et al. 2016/2017)"
DFC_PROTOCOL = "IEEE GRSS DFC2019 / US3D (Bosch et al. 2019)"

# ASPRS LAS class code of water, as the DFC2019 / US3D CLS rasters label it.
ASPRS_WATER = 9

# dfc: a shift is scored only if it compares at least this fraction of the most cells any shift
# compares. Shifts of a few cells change the overlap by a few rows and columns; one that loses
# half of the cells (to holes in the prediction at its edge) compares another area, and its
# correlation is not comparable with the others'.
NCC_MIN_OVERLAP_FRACTION = 0.5

# A resampling position within this many pixels of an integer is snapped to it, so that the
# prediction and truth on the same grid compare cell for cell despite float rounding.
SNAP_PIXELS = 1e-6

# Threads that score the alignment's shifts at once: each holds two arrays of the compared cells
# (16 bytes a cell), so more would cost memory on large DSMs for little more speed.
SEARCH_THREADS_MAX = 4

# Range of the error histogram, in multiples of threshold_m, and its bins per threshold_m.
HISTOGRAM_HALF_RANGE = 5.0
HISTOGRAM_BINS_PER_THRESHOLD = 10
# The error map saturates at +-this multiple of threshold_m.
ERROR_MAP_HALF_RANGE = 2.0

# Output file names of write_error_report.
ERROR_MAP_PNG = "error_map.png"
ERROR_HISTOGRAM_PNG = "error_histogram.png"
ERROR_TIF = "error.tif"
REPORT_JSON = "evaluation.json"


@dataclasses.dataclass(frozen=True)
class EvaluateOptions(Options):
    """Options of ``satsweep evaluate``."""

    max_shift_m: float = 2.0  # search horizontal shifts up to +-this in x and y (integer truth cells), metres
    threshold_m: float = 1.0  # completeness: fraction of truth cells with |aligned error| below this, metres
    resampling: Literal["nearest", "bilinear"] = "nearest"  # how the prediction is sampled onto the truth grid
    protocol: Literal["mvs3dm", "dfc"] = "mvs3dm"  # mvs3dm: IARPA MVS3DM (median-based alignment); dfc: DFC2019 / US3D (NCC shift, mean offset, mean absolute error)
    dfc_max_shift_cells: int = 4  # dfc: search horizontal shifts up to +-this many truth cells in x and y (4: the mvs3dm search's 2 m on 0.5 m cells)
    water_classes: tuple[int, ...] = (ASPRS_WATER,)  # dfc: classification codes masked out (ASPRS LAS 9 = water in the DFC2019 / US3D CLS rasters)

    def check(self) -> None:
        self._require(math.isfinite(self.max_shift_m) and self.max_shift_m >= 0.0, "max_shift_m", "must be >= 0 metres")
        self._require(math.isfinite(self.threshold_m) and self.threshold_m > 0.0, "threshold_m", "must be > 0 metres")
        self._require(self.dfc_max_shift_cells >= 0, "dfc_max_shift_cells", "must be >= 0 cells")


def completeness_key(threshold_m: float) -> str:
    """Report key of the completeness at a threshold: ``completeness_1m`` for 1.0."""
    return f"completeness_{threshold_m:g}m"


# -- core on arrays ----------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Evaluation:
    """A finished evaluation: the report and the aligned signed error map on the truth grid."""

    report: dict[str, Any]  # JSON-ready metrics (see the module docstring)
    error: np.ndarray  # aligned prediction - truth (m), NaN where either is missing
    truth_valid: np.ndarray  # bool, cells with a truth value


def _metrics(aligned: np.ndarray, truth: np.ndarray, truth_valid: np.ndarray, *, dx: float, dy: float,
             dz: float, threshold_m: float) -> tuple[dict[str, Any], np.ndarray]:
    """Metrics of an aligned prediction (already shifted, offset dz not yet added)."""
    both = truth_valid & np.isfinite(aligned)
    error = np.full(truth.shape, np.nan)
    error[both] = aligned[both] + dz - truth[both]
    e = error[both]
    n_truth = int(np.count_nonzero(truth_valid))
    n_both = int(e.size)
    good = int(np.count_nonzero(np.abs(e) < threshold_m))
    metrics = {
        "median_abs_error_m": float(np.median(np.abs(e))) if n_both else None,
        completeness_key(threshold_m): good / n_truth if n_truth else 0.0,
        "rmse_m": float(np.sqrt(np.mean(e * e))) if n_both else None,
        "mean_error_m": float(np.mean(e)) if n_both else None,
        "shift": {"dx_m": float(dx), "dy_m": float(dy), "dz_m": float(dz)},
        "compared_cells": n_both,
        "prediction_coverage": n_both / n_truth if n_truth else 0.0,
    }
    return metrics, error


def _evaluate_padded(pred_pad: np.ndarray, truth: np.ndarray, *, cell_x: float, cell_y: float,
                     radius_x: int, radius_y: int, options: EvaluateOptions) -> Evaluation:
    """Search the shifts on a prediction sampled over the truth grid grown by the radii.

    ``pred_pad[radius_y + i, radius_x + j]`` is the prediction at the centre of truth cell (i, j);
    shifting the prediction by (sx, sy) cells (east, north) samples it at cell (i + sy, j - sx).
    """
    h, w = truth.shape
    truth_valid = np.isfinite(truth)
    if not truth_valid.any():
        raise ValueError("the truth has no valid cell")

    def shifted(sx: int, sy: int) -> np.ndarray:
        r0, c0 = radius_y + sy, radius_x - sx
        return pred_pad[r0:r0 + h, c0:c0 + w]

    def score(shift: tuple[int, int]) -> tuple[float, float] | None:
        """(median |error| after the offset, the offset dz) of one shift; None if no overlap."""
        a = shifted(*shift)
        both = truth_valid & np.isfinite(a)
        if not both.any():
            return None
        d = truth[both] - a[both]
        dz = _median_in_place(d)
        d -= dz
        np.abs(d, out=d)
        return _median_in_place(d), dz

    shifts = [(sx, sy) for sy in range(-radius_y, radius_y + 1) for sx in range(-radius_x, radius_x + 1)]
    shifts.sort(key=lambda s: (s[0] * cell_x) ** 2 + (s[1] * cell_y) ** 2)
    # The shifts are scored in threads (numpy's partition and array arithmetic release the GIL),
    # then compared in the order above, so the choice is the sequential search's.
    scores = map_in_threads(score, shifts, max_threads=SEARCH_THREADS_MAX, name="evaluate")
    best = None
    for (sx, sy), found in zip(shifts, scores):
        if found is not None and (best is None or found[0] < best[0]):
            best = (found[0], sx, sy, found[1])
    if best is None:
        best = (math.nan, 0, 0, 0.0)
    _, sx, sy, dz = best
    aligned, error = _metrics(shifted(sx, sy), truth, truth_valid, dx=sx * cell_x, dy=sy * cell_y, dz=dz,
                              threshold_m=options.threshold_m)
    unaligned, _ = _metrics(shifted(0, 0), truth, truth_valid, dx=0.0, dy=0.0, dz=0.0,
                            threshold_m=options.threshold_m)
    report = {
        "protocol": PROTOCOL,
        "resampling": options.resampling,
        "max_shift_m": options.max_shift_m,
        "threshold_m": options.threshold_m,
        "cell_size_m": [cell_x, cell_y],
        "shifts_searched": len(shifts),
        "truth_cells": int(np.count_nonzero(truth_valid)),
        "aligned": aligned,
        "unaligned": unaligned,
    }
    return Evaluation(report=report, error=error, truth_valid=truth_valid)


def _evaluate_dfc_padded(pred_pad: np.ndarray, truth: np.ndarray, masked: np.ndarray | None, *,
                         cell_x: float, cell_y: float, radius: int, options: EvaluateOptions) -> Evaluation:
    """The DFC2019 / US3D protocol on a prediction sampled over the truth grid grown by ``radius``
    cells on every side (``pred_pad`` as in ``_evaluate_padded``); ``masked``: cells to leave out."""
    h, w = truth.shape
    finite = np.isfinite(truth)
    truth_valid = finite if masked is None else finite & ~masked
    n_truth = int(np.count_nonzero(truth_valid))
    if n_truth == 0:
        raise ValueError("the truth has no valid cell outside the masked classes")

    def shifted(a: np.ndarray, sx: int, sy: int) -> np.ndarray:
        r0, c0 = radius + sy, radius - sx
        return a[r0:r0 + h, c0:c0 + w]

    shifts = [(sx, sy) for sy in range(-radius, radius + 1) for sx in range(-radius, radius + 1)]
    shifts.sort(key=lambda s: (s[0] * cell_x) ** 2 + (s[1] * cell_y) ** 2)
    ncc, overlap = _ncc_of_shifts(pred_pad, truth, truth_valid, shifts, shifted)
    best = None
    if overlap.max() > 0:
        eligible = (overlap >= NCC_MIN_OVERLAP_FRACTION * overlap.max()) & np.isfinite(ncc)
        for k in np.flatnonzero(eligible):  # in the order of the shifts: ties keep the smallest
            if best is None or ncc[k] > ncc[best]:
                best = int(k)
    sx, sy = shifts[best] if best is not None else (0, 0)
    aligned = shifted(pred_pad, sx, sy)
    both = truth_valid & np.isfinite(aligned)
    n_both = int(np.count_nonzero(both))
    error = np.full(truth.shape, np.nan)
    dz = 0.0
    if n_both:
        d = truth[both] - aligned[both]
        dz = float(np.mean(d))
        error[both] = aligned[both] + dz - truth[both]
    e = error[both]
    a = np.abs(e)
    good = int(np.count_nonzero(a < options.threshold_m))
    report = {
        "protocol": DFC_PROTOCOL,
        "resampling": options.resampling,
        "threshold_m": options.threshold_m,
        "cell_size_m": [cell_x, cell_y],
        "max_shift_cells": radius,
        "shifts_searched": len(shifts),
        "water_classes": list(options.water_classes) if masked is not None else [],
        "truth_cells": n_truth,
        "masked_cells": int(np.count_nonzero(finite & ~truth_valid)),
        "compared_cells": n_both,
        "mean_abs_error_m": float(np.mean(a)) if n_both else None,
        "median_abs_error_m": float(np.median(a)) if n_both else None,
        "rmse_m": float(np.sqrt(np.mean(e * e))) if n_both else None,
        completeness_key(options.threshold_m): good / n_truth,
        f"compared_within_{options.threshold_m:g}m": good / n_both if n_both else None,
        "valid_fraction": n_both / n_truth,
        "ncc": float(ncc[best]) if best is not None else None,
        "shift": {"dx_cells": sx, "dy_cells": sy, "dx_m": float(sx * cell_x), "dy_m": float(sy * cell_y),
                  "dz_m": dz},
    }
    return Evaluation(report=report, error=error, truth_valid=truth_valid)


def _ncc_of_shifts(pred_pad, truth, truth_valid, shifts, shifted) -> tuple[np.ndarray, np.ndarray]:
    """(normalised cross-correlation, cells compared) of each shift, over the cells valid in both.

    Each shift's six sums (count, sums, sums of squares and of products) are dot products of
    zero-filled arrays with the other side's validity, so that a hole contributes nothing.
    Heights are taken relative to the truth's mean so that the sums of squares keep their
    precision.
    """
    ref = float(np.mean(truth[truth_valid]))
    t = np.where(truth_valid, truth - ref, 0.0)
    tt = t * t
    vt = truth_valid.astype(np.float64)
    pred_valid = np.isfinite(pred_pad)
    p = np.where(pred_valid, pred_pad - ref, 0.0)
    pp = p * p
    vp = pred_valid.astype(np.float64)

    def dot(x: np.ndarray, y: np.ndarray) -> float:
        return float(np.einsum("ij,ij->", x, y))

    def one(shift: tuple[int, int]) -> tuple[float, int]:
        ps, pps, vps = (shifted(a, *shift) for a in (p, pp, vp))
        n = dot(vt, vps)
        if n < 2:
            return math.nan, int(n)
        st, sp = dot(t, vps), dot(ps, vt)
        var_t = dot(tt, vps) - st * st / n
        var_p = dot(pps, vt) - sp * sp / n
        cov = dot(t, ps) - st * sp / n
        denominator = math.sqrt(var_t * var_p) if var_t > 0.0 and var_p > 0.0 else 0.0
        return (cov / denominator if denominator > 0.0 else math.nan), int(round(n))

    # Scored in threads as the MVS3DM search is: on 1700^2 cells, 81 shifts took 0.56-0.71 s
    # against 0.69-0.99 s in one thread on the 2-core CI machine (the sums are memory-bound).
    found = map_in_threads(one, shifts, max_threads=SEARCH_THREADS_MAX, name="evaluate")
    return np.array([f[0] for f in found]), np.array([f[1] for f in found])


def _median_in_place(values: np.ndarray) -> float:
    """``np.median`` of a 1-D float64 array without NaN, the same value bit for bit, partitioning
    the array itself instead of a copy (its order is lost)."""
    n = values.size
    half = n // 2
    if n % 2:
        values.partition(half)
        return float(values[half])
    values.partition((half - 1, half))
    return float((values[half - 1] + values[half]) / 2.0)


def _radius(max_shift_m: float, cell: float) -> int:
    """Largest integer number of cells whose length stays within max_shift_m."""
    return int(math.floor(max_shift_m / cell + 1e-9))


def evaluate_arrays(pred: np.ndarray, truth: np.ndarray, resolution: float,
                    options: EvaluateOptions | None = None, *,
                    classification: np.ndarray | None = None) -> dict[str, Any]:
    """Evaluate a prediction against the truth on the same grid (square cells of ``resolution`` m).

    Arrays: 2D, row 0 north, column 0 west, NaN = no data. Shifted predictions have no data
    beyond the array. ``classification`` (dfc protocol only): class codes on the same grid, cells
    of ``options.water_classes`` masked. Returns the report dict (see the module docstring).
    """
    return _evaluate_same_grid(pred, truth, resolution, options or EvaluateOptions(),
                               classification=classification).report


def _evaluate_same_grid(pred, truth, resolution, options, *, classification=None) -> Evaluation:
    p = np.asarray(pred, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    if p.ndim != 2 or p.shape != t.shape:
        raise ValueError(f"prediction {p.shape} and truth {t.shape} must be 2D arrays of one shape")
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise OptionsError(f"resolution = {resolution!r}: must be > 0 metres")
    masked = None
    if classification is not None:
        _require_dfc(options)
        c = np.asarray(classification)
        if c.shape != t.shape:
            raise ValueError(f"classification {c.shape} and truth {t.shape} must have one shape")
        masked = _water(c, options)
    t = np.where(np.isfinite(t), t, np.nan)
    r = options.dfc_max_shift_cells if options.protocol == "dfc" else _radius(options.max_shift_m, resolution)
    pad = np.full((p.shape[0] + 2 * r, p.shape[1] + 2 * r), np.nan)
    pad[r:r + p.shape[0], r:r + p.shape[1]] = np.where(np.isfinite(p), p, np.nan)
    if options.protocol == "dfc":
        return _evaluate_dfc_padded(pad, t, masked, cell_x=resolution, cell_y=resolution, radius=r,
                                    options=options)
    return _evaluate_padded(pad, t, cell_x=resolution, cell_y=resolution, radius_x=r, radius_y=r,
                            options=options)


def _require_dfc(options: EvaluateOptions) -> None:
    if options.protocol != "dfc":
        raise OptionsError(f"a classification raster is used by the dfc protocol only (protocol = "
                           f"{options.protocol!r}): give protocol = 'dfc' (--protocol dfc)")


def _water(classes: np.ndarray, options: EvaluateOptions) -> np.ndarray:
    """Cells whose class is one of ``options.water_classes`` (NaN classes are not)."""
    codes = np.asarray(options.water_classes, dtype=np.float64 if classes.dtype.kind == "f" else np.int64)
    return np.isin(classes, codes)


# -- resampling --------------------------------------------------------------------------------
def _snap(pos: np.ndarray) -> np.ndarray:
    near = np.round(pos)
    return np.where(np.abs(pos - near) < SNAP_PIXELS, near, pos)


def resample_to_grid(src: np.ndarray, src_info, *, x_min: float, y_max: float, cell_x: float,
                     cell_y: float, shape: tuple[int, int], method: str = "nearest") -> np.ndarray:
    """Sample a north-up raster (NaN = no data) at the cell centres of another north-up grid.

    ``src_info``: the source ``imageio.GeoInfo``; the target grid has its outer top-left corner
    at (x_min, y_max), cells of cell_x by cell_y, ``shape`` (rows, cols). ``nearest`` takes the
    source cell holding each centre; ``bilinear`` weighs the four nearest source centres and is
    NaN where a neighbour with non-zero weight is missing. Outside the source: NaN.
    """
    rows, cols = shape
    xs = x_min + (np.arange(cols) + 0.5) * cell_x
    ys = y_max - (np.arange(rows) + 0.5) * cell_y
    c, _ = src_info.xy_to_pixel(x=xs, y=np.zeros_like(xs))
    _, r = src_info.xy_to_pixel(x=np.zeros_like(ys), y=ys)
    c, r = _snap(c), _snap(r)
    sh, sw = src.shape
    if method == "nearest":
        ci = np.floor(c + 0.5).astype(np.int64)
        ri = np.floor(r + 0.5).astype(np.int64)
        okc, okr = (ci >= 0) & (ci < sw), (ri >= 0) & (ri < sh)
        out = src[np.ix_(np.clip(ri, 0, sh - 1), np.clip(ci, 0, sw - 1))].astype(np.float64)
        out[~okr, :] = np.nan
        out[:, ~okc] = np.nan
        return out
    if method != "bilinear":
        raise OptionsError(f"resampling = {method!r}: must be 'nearest' or 'bilinear'")
    c0, r0 = np.floor(c).astype(np.int64), np.floor(r).astype(np.int64)
    fc, fr = c - c0, r - r0
    out = np.zeros(shape)
    bad = np.zeros(shape, dtype=bool)
    for dr, wr in ((0, 1.0 - fr), (1, fr)):
        for dc, wc in ((0, 1.0 - fc), (1, fc)):
            ri, ci = r0 + dr, c0 + dc
            okr, okc = (ri >= 0) & (ri < sh), (ci >= 0) & (ci < sw)
            v = src[np.ix_(np.clip(ri, 0, sh - 1), np.clip(ci, 0, sw - 1))].astype(np.float64)
            v[~okr, :] = np.nan
            v[:, ~okc] = np.nan
            weight = wr[:, None] * wc[None, :]
            needed = weight > 0.0
            bad |= needed & ~np.isfinite(v)
            out += np.where(needed & np.isfinite(v), weight * v, 0.0)
    out[bad] = np.nan
    return out


def _require_one_band(path: str | os.PathLike, what: str) -> None:
    """InputError naming the file unless its TIFF holds one band (``read_geotiff`` would take the
    first band of an RGB image silently)."""
    from satsweep.io.images import _open_tiff

    with _open_tiff(path) as (_, page):
        bands = int(page.samplesperpixel)
    if bands != 1:
        raise InputError(path, f"has {bands} bands per pixel (an RGB or multispectral image?): "
                               f"a {what} has one band")


def read_dsm(path: str | os.PathLike):
    """Read a DSM GeoTIFF as float64 with NaN for no data; InputError naming the file if unusable."""
    import pyproj

    from satsweep.io.geotiff import read_geotiff

    _require_one_band(path, "DSM")
    array, info = read_geotiff(path)
    a = np.asarray(array, dtype=np.float64)
    a[info.is_nodata(array)] = np.nan
    a[~np.isfinite(a)] = np.nan
    try:
        crs = pyproj.CRS.from_epsg(info.epsg)
    except pyproj.exceptions.CRSError:
        raise InputError(path, f"unknown CRS EPSG:{info.epsg}") from None
    unit = crs.axis_info[0].unit_name if crs.axis_info else ""
    if not crs.is_projected or unit not in ("metre", "meter"):
        raise InputError(
            path, f"CRS EPSG:{info.epsg} is not a projected CRS in metres: reproject it to UTM (gdalwarp -t_srs EPSG:326zz)"
        )
    return a, info


def _read_classification(path: str | os.PathLike, truth_path: str | os.PathLike, tinfo,
                         shape: tuple[int, int]) -> np.ndarray:
    """A classification GeoTIFF that lies on the truth's grid exactly; InputError naming it if not."""
    from satsweep.io.geotiff import read_geotiff

    _require_one_band(path, "classification raster")
    classes, info = read_geotiff(path)
    cell = min(tinfo.pixel_size)
    same = (info.epsg == tinfo.epsg and classes.shape == tuple(shape)
            and all(abs(a - b) <= SNAP_PIXELS * cell for a, b in
                    ((info.x_min, tinfo.x_min), (info.y_max, tinfo.y_max),
                     (info.pixel_size[0], tinfo.pixel_size[0]), (info.pixel_size[1], tinfo.pixel_size[1]))))
    if not same:
        raise InputError(
            path, f"its grid (EPSG:{info.epsg}, {classes.shape[1]}x{classes.shape[0]} cells of "
            f"{info.pixel_size[0]:g} x {info.pixel_size[1]:g} from ({info.x_min:.3f}, {info.y_max:.3f})) is not "
            f"the truth's (EPSG:{tinfo.epsg}, {shape[1]}x{shape[0]} cells of {tinfo.pixel_size[0]:g} x "
            f"{tinfo.pixel_size[1]:g} from ({tinfo.x_min:.3f}, {tinfo.y_max:.3f}), {os.fspath(truth_path)}): "
            "a classification must be on the truth grid"
        )
    return classes


def evaluate_dsm(pred_path: str | os.PathLike, truth_path: str | os.PathLike,
                 options: EvaluateOptions | None = None, *, out_dir: str | os.PathLike | None = None,
                 classification: str | os.PathLike | None = None) -> dict[str, Any]:
    """Evaluate a predicted DSM GeoTIFF against a ground-truth DSM GeoTIFF (IARPA MVS3DM protocol,
    or DFC2019 / US3D with ``options.protocol = "dfc"``).

    Both must be north-up one-band GeoTIFFs in the same projected EPSG CRS with metre units; their
    extents and cell sizes may differ (the prediction is resampled onto the truth grid).
    ``classification`` (dfc only): a one-band GeoTIFF of class codes on the truth's grid; cells of
    ``options.water_classes`` are masked. Missing files, unreadable or multi-band rasters, a CRS
    mismatch, an empty truth, rasters that do not overlap or a classification off the truth grid
    raise an InputError naming the file. With ``out_dir``, ``write_error_report`` writes the error
    map, histogram, error GeoTIFF and the JSON report there. Returns the report dict.
    """
    options = options or EvaluateOptions()
    if classification is not None:
        _require_dfc(options)
    truth, tinfo = read_dsm(truth_path)
    pred, pinfo = read_dsm(pred_path)
    if pinfo.epsg != tinfo.epsg:
        raise InputError(
            pred_path, f"CRS EPSG:{pinfo.epsg} differs from the truth's EPSG:{tinfo.epsg} ({os.fspath(truth_path)}); "
            f"reproject it first (gdalwarp -t_srs EPSG:{tinfo.epsg})"
        )
    if not np.isfinite(truth).any():
        raise InputError(truth_path, "has no valid cell (all no data)")
    cell_x, cell_y = tinfo.pixel_size
    pw, ph = pinfo.pixel_size
    px0, py1 = pinfo.x_min, pinfo.y_max
    px1, py0 = px0 + pred.shape[1] * pw, py1 - pred.shape[0] * ph
    tx1, ty0 = tinfo.x_min + truth.shape[1] * cell_x, tinfo.y_max - truth.shape[0] * cell_y
    if px0 >= tx1 or px1 <= tinfo.x_min or py0 >= tinfo.y_max or py1 <= ty0:
        raise InputError(pred_path, f"does not overlap the truth {os.fspath(truth_path)} "
                         f"(x {px0:.1f}..{px1:.1f} vs {tinfo.x_min:.1f}..{tx1:.1f}, "
                         f"y {py0:.1f}..{py1:.1f} vs {ty0:.1f}..{tinfo.y_max:.1f})")
    if options.protocol == "dfc":
        rx = ry = options.dfc_max_shift_cells
    else:
        rx, ry = _radius(options.max_shift_m, cell_x), _radius(options.max_shift_m, cell_y)
    masked = None
    if classification is not None:
        masked = _water(_read_classification(classification, truth_path, tinfo, truth.shape), options)
        if not (np.isfinite(truth) & ~masked).any():
            raise InputError(classification, f"masks every valid cell of the truth {os.fspath(truth_path)} "
                                              f"(classes {list(options.water_classes)})")
    pad = resample_to_grid(
        pred, pinfo, x_min=tinfo.x_min - rx * cell_x, y_max=tinfo.y_max + ry * cell_y, cell_x=cell_x,
        cell_y=cell_y, shape=(truth.shape[0] + 2 * ry, truth.shape[1] + 2 * rx), method=options.resampling,
    )
    if options.protocol == "dfc":
        ev = _evaluate_dfc_padded(pad, truth, masked, cell_x=cell_x, cell_y=cell_y, radius=rx, options=options)
        extra = {"classification": None if classification is None else os.fspath(classification)}
    else:
        ev = _evaluate_padded(pad, truth, cell_x=cell_x, cell_y=cell_y, radius_x=rx, radius_y=ry, options=options)
        extra = {}
    report = {"prediction": os.fspath(pred_path), "truth": os.fspath(truth_path), "epsg": tinfo.epsg,
              **extra, **ev.report}
    if out_dir is not None:
        write_error_report(out_dir, report, ev.error, ev.truth_valid, geo=tinfo)
    return report


# -- report files ------------------------------------------------------------------------------
def write_error_report(out_dir: str | os.PathLike, report: dict[str, Any], error: np.ndarray,
                       truth_valid: np.ndarray, *, geo=None) -> list[str]:
    """Write the evaluation files into ``out_dir`` (created if needed) and return their paths.

    - ``error_map.png``: aligned signed error (prediction - truth, m) on a blue-white-red scale
      saturating at +-2 x threshold_m, with a colour bar; black = truth cell without prediction
      (a completeness failure), grey = no truth (or a cell the dfc protocol masks).
    - ``error_histogram.png``: histogram of the aligned errors over +-5 x threshold_m with the
      +-threshold_m limits marked.
    - ``error.tif``: the signed error as a float32 GeoTIFF on the truth grid (only with ``geo``,
      the truth's ``imageio.GeoInfo`` with square cells).
    - ``evaluation.json``: the report.
    Existing files of these names are replaced (each written to a temporary name, then renamed).
    """
    from satsweep.io.atomic import atomic_output
    from satsweep.io.geotiff import write_geotiff
    from satsweep.pipeline.report import to_json
    from satsweep.products import quicklook as render

    out_dir = os.fspath(out_dir)
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise OptionsError(f"--out {out_dir}: exists and is not a folder")
    os.makedirs(out_dir, exist_ok=True)
    thr = float(report["threshold_m"])
    shift = report["aligned"]["shift"] if "aligned" in report else report["shift"]  # mvs3dm, dfc
    missing = np.asarray(truth_valid, bool) & ~np.isfinite(error)
    written = []
    path = os.path.join(out_dir, ERROR_MAP_PNG)
    title = (f"aligned error (prediction - truth), shift dx={shift['dx_m']:+.2f} dy={shift['dy_m']:+.2f} "
             f"dz={shift['dz_m']:+.2f} m")
    render.height_png(path, error, title=title, units="m", vmin=-ERROR_MAP_HALF_RANGE * thr,
                      vmax=ERROR_MAP_HALF_RANGE * thr, cmap=render.diverging_lut(),
                      overlays=[(missing, (0, 0, 0), "black: no prediction")])
    written.append(path)
    path = os.path.join(out_dir, ERROR_HISTOGRAM_PNG)
    half = HISTOGRAM_HALF_RANGE * thr
    render.histogram_png(path, error[np.isfinite(error)],
                         bins=int(round(2 * HISTOGRAM_HALF_RANGE * HISTOGRAM_BINS_PER_THRESHOLD)),
                         title=f"aligned error (prediction - truth); red: +-{thr:g} m", units="m",
                         value_range=(-half, half), markers=(-thr, thr))
    written.append(path)
    if geo is not None and geo.resolution_y in (None, geo.resolution):
        path = os.path.join(out_dir, ERROR_TIF)
        write_geotiff(path, error.astype(np.float32), epsg=geo.epsg, x_min=geo.x_min, y_max=geo.y_max,
                      resolution=geo.resolution, nodata=math.nan)
        written.append(path)
    path = os.path.join(out_dir, REPORT_JSON)
    with atomic_output(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(to_json(report) + "\n")
    written.append(path)
    return written
