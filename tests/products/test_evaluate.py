"""DSM evaluation (IARPA MVS3DM protocol) on exact synthetic truths, GeoTIFFs and the CLI."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from satsweep.cli import main
from satsweep.errors import InputError, OptionsError
from satsweep.io.geotiff import write_geotiff
from satsweep.products import evaluate as ev

# Recovered offsets and errors of exact synthetic cases: float64 sums of heights near 2400 m.
EXACT_TOL_M = 1e-9
# GeoTIFF files hold float32 heights: at 2400 m their spacing is 2.4e-4 m.
FLOAT32_TOL_M = 5e-4

EPSG = 32740
X0, Y1 = 338_000.0, 7_651_000.0


def _scene(rows: int = 40, cols: int = 50, seed: int = 0) -> np.ndarray:
    """Terrain with buildings: distinct values everywhere so that only the true shift fits."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:rows, 0:cols]
    z = 2340.0 + 0.03 * xx - 0.02 * yy + rng.normal(0, 0.05, (rows, cols))
    for _ in range(6):
        r, c = rng.integers(0, rows - 8), rng.integers(0, cols - 8)
        z[r:r + rng.integers(3, 8), c:c + rng.integers(3, 8)] += rng.uniform(5, 20)
    return z


def test_recovers_injected_shift_and_offset_exactly():
    truth = _scene()
    a, b, off = 1, 2, 3.25  # pred content moved 1 row south, 2 columns east, 3.25 m up
    pred = np.full_like(truth, np.nan)
    pred[a:, b:] = truth[:-a, :-b] + off
    res = 0.5
    r = ev.evaluate_arrays(pred, truth, res, ev.EvaluateOptions())
    al = r["aligned"]
    assert al["shift"] == {"dx_m": -b * res, "dy_m": a * res, "dz_m": -off}
    assert al["median_abs_error_m"] <= EXACT_TOL_M and al["rmse_m"] <= EXACT_TOL_M
    # After alignment the prediction exists on all truth cells but the last row and 2 columns.
    assert math.isclose(al["completeness_1m"], (40 - a) * (50 - b) / (40 * 50))
    assert r["shifts_searched"] == 81  # +-2 m at 0.5 m: 9 x 9
    # Unaligned metrics against an independent numpy computation.
    d = pred - truth
    d = d[np.isfinite(d)]
    un = r["unaligned"]
    assert un["shift"] == {"dx_m": 0.0, "dy_m": 0.0, "dz_m": 0.0}
    assert math.isclose(un["median_abs_error_m"], float(np.median(np.abs(d))), rel_tol=1e-12)
    assert math.isclose(un["rmse_m"], float(np.sqrt(np.mean(d ** 2))), rel_tol=1e-12)
    assert math.isclose(un["completeness_1m"], np.count_nonzero(np.abs(d) < 1.0) / truth.size)
    assert un["median_abs_error_m"] > 1.0


@pytest.mark.parametrize("n", [1, 2, 7, 10, 1001, 1000])
def test_median_in_place_is_numpys_median(n):
    rng = np.random.default_rng(n)
    values = np.round(rng.normal(0, 3, n), 1)  # rounded: repeated values too
    expected = float(np.median(values))
    assert ev._median_in_place(values.copy()) == expected  # the same float, bit for bit


def _sequential_search(pred, truth, radius):
    """The alignment search written out plainly: shifts by distance, np.median, first best."""
    h, w = truth.shape
    shifts = sorted(((sx, sy) for sy in range(-radius, radius + 1)
                     for sx in range(-radius, radius + 1)), key=lambda s: s[0] ** 2 + s[1] ** 2)
    best = None
    for sx, sy in shifts:
        a = np.full_like(truth, np.nan)  # prediction sampled at cell (i + sy, j - sx)
        rows = slice(max(0, -sy), min(h, h - sy))
        cols = slice(max(0, sx), min(w, w + sx))
        a[rows, cols] = pred[rows.start + sy:rows.stop + sy, cols.start - sx:cols.stop - sx]
        both = np.isfinite(truth) & np.isfinite(a)
        d = truth[both] - a[both]
        dz = float(np.median(d))
        score = float(np.median(np.abs(d - dz)))
        if best is None or score < best[0]:
            best = (score, sx, sy, dz)
    return best


@pytest.mark.parametrize("seed, ties", [(1, False), (2, False), (3, True)])
def test_threaded_search_is_the_sequential_search(seed, ties):
    # A noisy prediction with holes: the scores of neighbouring shifts are close, so any change
    # in the order of comparison or in the medians would show. With ties, a flat scene makes
    # every shift score the same and the smallest must win.
    rng = np.random.default_rng(seed)
    if ties:
        truth = np.full((30, 40), 2340.0)
        pred = truth + 0.7
    else:
        truth = _scene(30, 40, seed)
        pred = np.roll(truth, (1, -1), axis=(0, 1)) + rng.normal(0, 0.3, truth.shape) + 0.7
    pred[rng.random(pred.shape) < 0.1] = np.nan
    res = 0.5
    got = ev.evaluate_arrays(pred, truth, res, ev.EvaluateOptions())["aligned"]
    score, sx, sy, dz = _sequential_search(pred, truth, radius=4)
    assert got["shift"] == {"dx_m": sx * res, "dy_m": sy * res, "dz_m": dz}
    # The reported median is recomputed on the aligned prediction (pred + dz - truth).
    assert math.isclose(got["median_abs_error_m"], score, abs_tol=EXACT_TOL_M)
    if ties:
        assert (sx, sy) == (0, 0) and score == 0.0


def test_shift_outside_the_radius_is_not_found():
    truth = _scene()
    pred = np.full_like(truth, np.nan)
    pred[:, 3:] = truth[:, :-3]  # 3 cells = 1.5 m east
    r = ev.evaluate_arrays(pred, truth, 0.5, ev.EvaluateOptions(max_shift_m=1.0))
    assert abs(r["aligned"]["shift"]["dx_m"]) <= 1.0
    assert r["aligned"]["median_abs_error_m"] > EXACT_TOL_M
    r2 = ev.evaluate_arrays(pred, truth, 0.5, ev.EvaluateOptions(max_shift_m=1.5))
    assert r2["aligned"]["shift"]["dx_m"] == -1.5


def test_completeness_on_a_known_pattern():
    rows, cols = 20, 30
    truth = _scene(rows, cols, seed=5)
    k = np.arange(rows * cols).reshape(rows, cols) % 20
    # Per 20 cells: 6 exact, 2 at +0.5, 2 at -0.5, 3 at +1.5, 3 at -1.5, 4 missing.
    err = np.select([k < 6, k < 8, k < 10, k < 13, k < 16], [0.0, 0.5, -0.5, 1.5, -1.5], np.nan)
    truth[0, :3] = np.nan  # missing truth cells leave the denominator (pattern cells k = 0, 1, 2)
    pred = truth + err
    pred[0, :3] = 2000.0
    r = ev.evaluate_arrays(pred, truth, 1.0, ev.EvaluateOptions(max_shift_m=0.0))
    al = r["aligned"]
    assert al["shift"] == {"dx_m": 0.0, "dy_m": 0.0, "dz_m": 0.0}  # symmetric errors: median 0
    n_truth = rows * cols - 3
    good = np.count_nonzero(np.isfinite(truth) & (np.abs(err) < 1.0))
    assert good == 10 * rows * cols // 20 - 3
    assert math.isclose(al["completeness_1m"], good / n_truth)
    e = err[np.isfinite(truth) & np.isfinite(err)]
    assert math.isclose(al["rmse_m"], float(np.sqrt(np.mean(e ** 2))), rel_tol=1e-9)
    assert math.isclose(al["median_abs_error_m"], float(np.median(np.abs(e))), abs_tol=EXACT_TOL_M)
    assert math.isclose(al["prediction_coverage"], e.size / n_truth)
    assert r["truth_cells"] == n_truth
    # Another threshold changes the key and the count.
    r2 = ev.evaluate_arrays(pred, truth, 1.0, ev.EvaluateOptions(max_shift_m=0.0, threshold_m=2.0))
    assert math.isclose(r2["aligned"]["completeness_2m"], e.size / n_truth)


def test_options_are_checked():
    with pytest.raises(OptionsError, match="EvaluateOptions.threshold_m"):
        ev.EvaluateOptions(threshold_m=0.0)
    with pytest.raises(OptionsError, match="EvaluateOptions.max_shift_m"):
        ev.EvaluateOptions(max_shift_m=-1.0)
    with pytest.raises(OptionsError, match="resampling"):
        ev.EvaluateOptions(resampling="cubic")


def test_empty_prediction_counts_as_total_failure():
    truth = _scene(10, 10)
    r = ev.evaluate_arrays(np.full_like(truth, np.nan), truth, 0.5)
    assert r["aligned"]["completeness_1m"] == 0.0 and r["aligned"]["median_abs_error_m"] is None


# -- GeoTIFF files ------------------------------------------------------------------------------
def _write(path, array, *, x_min=X0, y_max=Y1, res=0.5, epsg=EPSG):
    write_geotiff(path, array, epsg=epsg, x_min=x_min, y_max=y_max, resolution=res)
    return path


def test_evaluate_dsm_with_different_extents_and_resolution(tmp_path):
    truth = _scene(40, 50)
    t_path = _write(tmp_path / "truth.tif", truth)
    # A prediction covering more ground: 6 extra cells west, 4 north, same values on the overlap.
    big = np.full((50, 62), np.nan)
    big[4:44, 6:56] = truth
    p_path = _write(tmp_path / "big.tif", big, x_min=X0 - 3.0, y_max=Y1 + 2.0)
    r = ev.evaluate_dsm(p_path, t_path)
    assert r["epsg"] == EPSG and r["resampling"] == "nearest"
    for key in ("aligned", "unaligned"):
        assert r[key]["median_abs_error_m"] <= EXACT_TOL_M
        assert r[key]["completeness_1m"] == 1.0
    assert r["aligned"]["shift"] == {"dx_m": 0.0, "dy_m": 0.0, "dz_m": 0.0}
    # A twice finer prediction (each truth cell as 2 x 2 cells), its georeference moved 1 m east
    # and 0.5 m south: the alignment moves it back.
    fine = np.repeat(np.repeat(truth.astype(np.float32), 2, axis=0), 2, axis=1)
    f_path = _write(tmp_path / "fine.tif", fine, x_min=X0 + 1.0, y_max=Y1 - 0.5, res=0.25)
    r = ev.evaluate_dsm(f_path, t_path)
    assert r["aligned"]["shift"]["dx_m"] == -1.0 and r["aligned"]["shift"]["dy_m"] == 0.5
    assert abs(r["aligned"]["shift"]["dz_m"]) <= EXACT_TOL_M
    assert r["aligned"]["median_abs_error_m"] <= EXACT_TOL_M
    assert math.isclose(r["aligned"]["completeness_1m"], 1.0)
    assert r["unaligned"]["median_abs_error_m"] > 0.01


def test_bilinear_resampling_reproduces_a_plane(tmp_path):
    rows, cols = 30, 40
    yy, xx = np.mgrid[0:rows, 0:cols]
    # Truth: a tilted plane on 1 m cells; prediction: the same plane on 0.7 m cells, offset.
    def plane(x, y):
        return 100.0 + 0.3 * (x - X0) - 0.2 * (Y1 - y)

    truth = plane(X0 + (xx + 0.5) * 1.0, Y1 - (yy + 0.5) * 1.0)
    py, px = np.mgrid[0:60, 0:70]
    px0, py1 = X0 - 3.13, Y1 + 2.71
    pred = plane(px0 + (px + 0.5) * 0.7, py1 - (py + 0.5) * 0.7)
    t_path = _write(tmp_path / "t.tif", truth, res=1.0)
    p_path = _write(tmp_path / "p.tif", pred, x_min=px0, y_max=py1, res=0.7)
    opts = ev.EvaluateOptions(resampling="bilinear", max_shift_m=0.0)
    r = ev.evaluate_dsm(p_path, t_path, opts)
    assert r["unaligned"]["median_abs_error_m"] <= FLOAT32_TOL_M
    assert r["unaligned"]["rmse_m"] <= FLOAT32_TOL_M
    nearest = ev.evaluate_dsm(p_path, t_path, ev.EvaluateOptions(max_shift_m=0.0))
    assert nearest["unaligned"]["median_abs_error_m"] > 0.01  # nearest is off by up to half a cell


def test_bilinear_and_nearest_are_identity_on_the_same_grid(tmp_path):
    truth = _scene(20, 25)
    pred = truth.copy()
    pred[3:5, 4:9] = np.nan
    t_path = _write(tmp_path / "t.tif", truth)
    p_path = _write(tmp_path / "p.tif", pred)
    for method in ("nearest", "bilinear"):
        r = ev.evaluate_dsm(p_path, t_path, ev.EvaluateOptions(resampling=method))
        assert r["unaligned"]["median_abs_error_m"] == 0.0
        assert r["unaligned"]["compared_cells"] == truth.size - 10


def test_nodata_value_other_than_nan(tmp_path):
    truth = _scene(20, 20)
    t = truth.copy()
    t[:5] = -9999.0
    t_path = tmp_path / "t.tif"
    write_geotiff(t_path, t, epsg=EPSG, x_min=X0, y_max=Y1, resolution=0.5, nodata=-9999.0)
    p_path = _write(tmp_path / "p.tif", truth)
    r = ev.evaluate_dsm(p_path, t_path)
    assert r["truth_cells"] == 15 * 20 and r["aligned"]["completeness_1m"] == 1.0


def test_input_errors_name_the_file(tmp_path):
    truth = _scene(10, 10)
    t_path = _write(tmp_path / "t.tif", truth)
    other = _write(tmp_path / "zone39.tif", truth, epsg=32739)
    with pytest.raises(InputError, match=r"zone39.tif.*EPSG:32739.*EPSG:32740"):
        ev.evaluate_dsm(other, t_path)
    far = _write(tmp_path / "far.tif", truth, x_min=X0 + 1000.0)
    with pytest.raises(InputError, match=r"far.tif: does not overlap"):
        ev.evaluate_dsm(far, t_path)
    geographic = tmp_path / "geo.tif"
    write_geotiff(geographic, truth, epsg=4326, x_min=55.6, y_max=-21.2, resolution=1e-5)
    with pytest.raises(InputError, match=r"geo.tif.*not a projected CRS"):
        ev.evaluate_dsm(t_path, geographic)
    empty = _write(tmp_path / "empty.tif", np.full((5, 5), np.nan))
    with pytest.raises(InputError, match=r"empty.tif.*no valid cell"):
        ev.evaluate_dsm(t_path, empty)
    with pytest.raises(InputError, match=r"missing.tif"):
        ev.evaluate_dsm(tmp_path / "missing.tif", t_path)


def test_error_report_files(tmp_path):
    truth = _scene(40, 50)
    pred = truth + 0.3
    pred[10:14, 10:20] = np.nan
    t_path = _write(tmp_path / "t.tif", truth)
    p_path = _write(tmp_path / "p.tif", pred)
    out = tmp_path / "report"
    r = ev.evaluate_dsm(p_path, t_path, out_dir=out)
    for name in (ev.ERROR_MAP_PNG, ev.ERROR_HISTOGRAM_PNG):
        img = cv2.imread(str(out / name))
        assert img is not None and img.ndim == 3
    from satsweep.products import quicklook as render

    hist = cv2.imread(str(out / ev.ERROR_HISTOGRAM_PNG))
    assert hist.shape == (render.HIST_HEIGHT, render.HIST_WIDTH, 3)
    emap = cv2.imread(str(out / ev.ERROR_MAP_PNG))
    scale = render.MIN_MAP_SIDE // 50
    assert emap.shape[0] > render.TITLE_HEIGHT + 40 * scale and emap.shape[1] > 50 * scale
    # Missing predictions are black in the map.
    region = emap[render.TITLE_HEIGHT:render.TITLE_HEIGHT + 40 * scale, render.MARGIN:render.MARGIN + 50 * scale]
    assert np.all(region[10 * scale:14 * scale, 10 * scale:20 * scale] == 0)
    assert json.loads((out / ev.REPORT_JSON).read_text()) == json.loads(json.dumps(r))
    from satsweep.io.geotiff import read_geotiff

    err, info = read_geotiff(out / ev.ERROR_TIF)
    assert info.epsg == EPSG and err.shape == truth.shape
    assert np.isnan(err[10:14, 10:20]).all()
    np.testing.assert_allclose(err[0, 0], 0.0, atol=FLOAT32_TOL_M)  # aligned: the 0.3 m offset removed


# -- command line -------------------------------------------------------------------------------
def test_cli_prints_json_with_the_documented_keys(tmp_path, capsys):
    truth = _scene(30, 30)
    pred = np.full_like(truth, np.nan)
    pred[:, 2:] = truth[:, :-2] + 1.0
    t_path = _write(tmp_path / "t.tif", truth)
    p_path = _write(tmp_path / "p.tif", pred)
    code = main(["evaluate", str(p_path), str(t_path)])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    for key in ("aligned", "unaligned"):
        assert {"median_abs_error_m", "completeness_1m", "rmse_m", "shift"} <= set(report[key])
        assert set(report[key]["shift"]) == {"dx_m", "dy_m", "dz_m"}
    assert report["aligned"]["shift"] == {"dx_m": -1.0, "dy_m": 0.0, "dz_m": -1.0}
    assert not (tmp_path / "out").exists()
    code = main(["evaluate", str(p_path), str(t_path), "--out", str(tmp_path / "out"), "--max-shift", "1",
                 "--threshold", "0.5"])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert "completeness_0.5m" in report["aligned"] and report["max_shift_m"] == 1.0
    assert (tmp_path / "out" / ev.ERROR_MAP_PNG).is_file()


def test_cli_missing_file_is_one_line_exit_2(tmp_path, capsys):
    t_path = _write(tmp_path / "t.tif", _scene(10, 10))
    code = main(["evaluate", str(tmp_path / "nope.tif"), str(t_path)])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "nope.tif" in lines[0] and lines[0].startswith("satsweep: error:")
    code = main(["evaluate", str(t_path), str(t_path), "--threshold", "-1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "threshold_m" in err[0]


# -- real data ----------------------------------------------------------------------------------
def test_s2p_dsm_moved_by_rasterio_is_realigned(shared_data, tmp_path):
    """A DSM from another tool, rewritten by rasterio with its origin moved 1 m east, 0.5 m up."""
    rasterio = pytest.importorskip("rasterio")
    src_path = shared_data / "pleiades_pair" / "s2p_dsm.tif"
    if not src_path.is_file():
        pytest.skip(f"{src_path} is absent")
    with rasterio.open(src_path) as src:
        data = src.read(1)
        profile = src.profile
        transform = src.transform
    moved = profile.copy()
    moved["transform"] = rasterio.Affine(transform.a, transform.b, transform.c + 1.0,
                                         transform.d, transform.e, transform.f)
    p_path = tmp_path / "moved.tif"
    with rasterio.open(p_path, "w", **moved) as dst:
        dst.write(data + np.float32(0.5), 1)
    r = ev.evaluate_dsm(p_path, src_path, ev.EvaluateOptions(max_shift_m=1.0))
    al = r["aligned"]
    assert r["epsg"] == 32740
    assert al["shift"]["dx_m"] == -1.0 and al["shift"]["dy_m"] == 0.0
    assert abs(al["shift"]["dz_m"] + 0.5) <= FLOAT32_TOL_M
    assert al["median_abs_error_m"] <= FLOAT32_TOL_M
    assert al["completeness_1m"] == 1.0
    assert r["unaligned"]["completeness_1m"] < 1.0


# -- DFC2019 / US3D protocol ----------------------------------------------------------------------
WATER = 9  # ASPRS LAS water, as the DFC2019 / US3D CLS rasters label it
LAND = 6  # ASPRS building, any other class


def _moved(truth: np.ndarray, a: int, b: int) -> np.ndarray:
    """The truth's content moved a rows south and b columns east (NaN where nothing moved in)."""
    out = np.full_like(truth, np.nan)
    out[a:, b:] = truth[:-a, :-b]
    return out


def _aligned_back(pred: np.ndarray, a: int, b: int) -> np.ndarray:
    """The prediction moved back a rows north and b columns west: aligned[i, j] = pred[i + a, j + b]."""
    out = np.full_like(pred, np.nan)
    out[:-a, :-b] = pred[a:, b:]
    return out


def _dfc_reference(aligned: np.ndarray, truth: np.ndarray, keep: np.ndarray, threshold: float = 1.0):
    """The DFC figures at a known shift, in plain numpy: mean offset, then errors over cells valid in both."""
    both = keep & np.isfinite(truth) & np.isfinite(aligned)
    dz = np.mean(truth[both] - aligned[both])
    e = aligned[both] + dz - truth[both]
    n_truth = np.count_nonzero(keep & np.isfinite(truth))
    return {"dz": dz, "mae": np.mean(np.abs(e)), "median": np.median(np.abs(e)), "rmse": np.sqrt(np.mean(e ** 2)),
            "completeness": np.count_nonzero(np.abs(e) < threshold) / n_truth,
            "within": np.count_nonzero(np.abs(e) < threshold) / both.sum(), "valid": both.sum() / n_truth,
            "compared": int(both.sum()), "truth_cells": int(n_truth)}


def test_dfc_recovers_shift_offset_and_mae_with_holes_and_water():
    rng = np.random.default_rng(7)
    truth = _scene(60, 70, seed=7)
    classes = np.full(truth.shape, LAND, np.uint8)
    classes[35:55, 5:30] = WATER
    truth[35:55, 5:30] = 2335.0  # a flat water surface
    a, b, off, noise = 2, 3, 1.75, 0.2  # content moved 2 rows south, 3 columns east, 1.75 m up
    pred = _moved(truth, a, b) + off + rng.normal(0, noise, truth.shape)
    pred[_moved(classes == WATER, a, b) == 1] = rng.uniform(2300, 2400, np.count_nonzero(
        _moved(classes == WATER, a, b) == 1))  # garbage on the water, where the mask must hide it
    pred[rng.random(truth.shape) < 0.15] = np.nan  # holes
    pred[5:15, 40:60] = np.nan
    opts = ev.EvaluateOptions(protocol="dfc")
    r = ev.evaluate_arrays(pred, truth, 0.5, opts, classification=classes)
    assert r["protocol"] == ev.DFC_PROTOCOL
    assert r["shift"]["dx_cells"] == -b and r["shift"]["dy_cells"] == a
    assert (r["shift"]["dx_m"], r["shift"]["dy_m"]) == (-b * 0.5, a * 0.5)
    ref = _dfc_reference(_aligned_back(pred, a, b), truth, classes != WATER)
    assert math.isclose(r["shift"]["dz_m"], ref["dz"], abs_tol=EXACT_TOL_M)
    # The offset is the injected one, up to the mean of the noise over the compared cells.
    assert abs(r["shift"]["dz_m"] + off) <= 5 * noise / math.sqrt(ref["compared"])
    assert math.isclose(r["mean_abs_error_m"], ref["mae"], rel_tol=1e-12)
    assert math.isclose(r["median_abs_error_m"], ref["median"], rel_tol=1e-12)
    assert math.isclose(r["rmse_m"], ref["rmse"], rel_tol=1e-12)
    assert math.isclose(r["completeness_1m"], ref["completeness"], rel_tol=1e-12)
    assert math.isclose(r["compared_within_1m"], ref["within"], rel_tol=1e-12)
    assert math.isclose(r["valid_fraction"], ref["valid"], rel_tol=1e-12)
    assert r["compared_cells"] == ref["compared"] and r["truth_cells"] == ref["truth_cells"]
    assert r["masked_cells"] == np.count_nonzero(classes == WATER) and r["water_classes"] == [WATER]
    assert r["shifts_searched"] == 81 and r["max_shift_cells"] == 4 and 0.99 < r["ncc"] <= 1.0
    # The noise alone: the mean |N(0, s)| is s * sqrt(2 / pi).
    assert abs(r["mean_abs_error_m"] - noise * math.sqrt(2 / math.pi)) < 0.1 * noise
    # Without the mask the water's garbage is compared too.
    unmasked = ev.evaluate_arrays(pred, truth, 0.5, opts)
    assert unmasked["masked_cells"] == 0 and unmasked["mean_abs_error_m"] > 10 * r["mean_abs_error_m"]


def _naive_ncc_shift(pred, truth, radius):
    """NCC with the holes filled by zeros, over the whole overlap: what the masked NCC must not do."""
    h, w = truth.shape
    t0 = np.nan_to_num(truth, nan=0.0)
    best = None
    for sy in range(-radius, radius + 1):
        for sx in range(-radius, radius + 1):
            rows = slice(max(0, -sy), min(h, h - sy))
            cols = slice(max(0, sx), min(w, w + sx))
            a = np.nan_to_num(pred[rows.start + sy:rows.stop + sy, cols.start - sx:cols.stop - sx], nan=0.0)
            c = np.corrcoef(t0[rows, cols].ravel(), a.ravel())[0, 1]
            if best is None or c > best[0]:
                best = (c, sx, sy)
    return best[1], best[2]


def test_dfc_ncc_is_not_fooled_by_holes():
    rng = np.random.default_rng(3)
    truth = _scene(60, 70, seed=3)
    a, b = 1, 2  # true shift: dx = -2 cells, dy = +1 cell
    pred = _moved(truth, a, b) + 0.5 + rng.normal(0, 0.1, truth.shape)
    pred[np.isnan(pred)] = 2340.0  # the edge the move left empty: plausible heights, not holes
    truth[20:40, 25:45] = np.nan  # a hole in the truth...
    wrong_sx, wrong_sy = 3, -3  # ... and one in the prediction where this wrong shift lays it on it
    pred[20 + wrong_sy:40 + wrong_sy, 25 - wrong_sx:45 - wrong_sx] = np.nan
    assert _naive_ncc_shift(pred, truth, 4) == (wrong_sx, wrong_sy)  # zero-filled holes do fool NCC
    r = ev.evaluate_arrays(pred, truth, 0.5, ev.EvaluateOptions(protocol="dfc"))
    assert (r["shift"]["dx_cells"], r["shift"]["dy_cells"]) == (-b, a)


def test_dfc_options_and_arrays_are_checked():
    with pytest.raises(OptionsError, match="dfc_max_shift_cells"):
        ev.EvaluateOptions(protocol="dfc", dfc_max_shift_cells=-1)
    with pytest.raises(OptionsError, match="protocol"):
        ev.EvaluateOptions(protocol="us3d")
    truth = _scene(10, 10)
    with pytest.raises(OptionsError, match="dfc protocol only"):
        ev.evaluate_arrays(truth, truth, 0.5, ev.EvaluateOptions(), classification=np.zeros((10, 10)))
    with pytest.raises(ValueError, match="classification"):
        ev.evaluate_arrays(truth, truth, 0.5, ev.EvaluateOptions(protocol="dfc"), classification=np.zeros((9, 10)))


def test_mvs3dm_report_keys_are_unchanged():
    r = ev.evaluate_arrays(_scene(10, 10), _scene(10, 10), 0.5)
    assert set(r) == {"protocol", "resampling", "max_shift_m", "threshold_m", "cell_size_m", "shifts_searched",
                      "truth_cells", "aligned", "unaligned"}
    assert set(r["aligned"]) == {"median_abs_error_m", "completeness_1m", "rmse_m", "mean_error_m", "shift",
                                 "compared_cells", "prediction_coverage"}


def _write_rgb_geotiff(path):
    from satsweep.io import geotiff
    from satsweep.io.geotiff import write_tiff

    tags = [(geotiff.TAG_MODEL_PIXEL_SCALE, "d", 3, (0.5, 0.5, 0.0), True),
            (geotiff.TAG_MODEL_TIEPOINT, "d", 6, (0.0, 0.0, 0.0, X0, Y1, 0.0), True),
            (geotiff.TAG_GEO_KEY_DIRECTORY, "H", 16, tuple(geotiff._geokeys(EPSG)), True)]
    write_tiff(path, np.zeros((10, 10, 3), np.uint8), extratags=tags)
    return path


def test_dfc_files_input_errors(tmp_path):
    truth = _scene(20, 20)
    t_path = _write(tmp_path / "t.tif", truth)
    classes = np.full(truth.shape, LAND, np.uint8)
    dfc = ev.EvaluateOptions(protocol="dfc")
    off_grid = tmp_path / "cls_moved.tif"
    write_geotiff(off_grid, classes, epsg=EPSG, x_min=X0 + 0.5, y_max=Y1, resolution=0.5, dtype=np.uint8, nodata=None)
    with pytest.raises(InputError, match=r"cls_moved.tif: its grid .* is not the truth's"):
        ev.evaluate_dsm(t_path, t_path, dfc, classification=off_grid)
    small = tmp_path / "cls_small.tif"
    write_geotiff(small, classes[:19], epsg=EPSG, x_min=X0, y_max=Y1, resolution=0.5, dtype=np.uint8, nodata=None)
    with pytest.raises(InputError, match=r"cls_small.tif: its grid"):
        ev.evaluate_dsm(t_path, t_path, dfc, classification=small)
    all_water = tmp_path / "cls_water.tif"
    write_geotiff(all_water, np.full(truth.shape, WATER, np.uint8), epsg=EPSG, x_min=X0, y_max=Y1, resolution=0.5,
                  dtype=np.uint8, nodata=None)
    with pytest.raises(InputError, match=r"cls_water.tif: masks every valid cell"):
        ev.evaluate_dsm(t_path, t_path, dfc, classification=all_water)
    rgb = _write_rgb_geotiff(tmp_path / "rgb.tif")
    for options in (dfc, ev.EvaluateOptions()):
        with pytest.raises(InputError, match=r"rgb.tif: has 3 bands per pixel"):
            ev.evaluate_dsm(rgb, t_path, options)
    with pytest.raises(InputError, match=r"rgb.tif: has 3 bands per pixel"):
        ev.evaluate_dsm(t_path, t_path, dfc, classification=rgb)
    with pytest.raises(OptionsError, match="dfc protocol only"):
        ev.evaluate_dsm(t_path, t_path, ev.EvaluateOptions(), classification=all_water)


def test_dfc_files_report_and_cli(tmp_path, capsys):
    truth = _scene(40, 50, seed=4)
    classes = np.full(truth.shape, LAND, np.uint8)
    classes[:10, :10] = WATER
    pred = _moved(truth, 1, 1) + 0.25
    pred[:11, :11] = 0.0  # nonsense over the water (rows and columns 0-9 once moved back)
    t_path = _write(tmp_path / "t.tif", truth)
    p_path = _write(tmp_path / "p.tif", pred)
    c_path = tmp_path / "cls.tif"
    write_geotiff(c_path, classes, epsg=EPSG, x_min=X0, y_max=Y1, resolution=0.5, dtype=np.uint8, nodata=None)
    out = tmp_path / "out"
    code = main(["evaluate", str(p_path), str(t_path), "--protocol", "dfc", "--classification", str(c_path),
                 "--out", str(out)])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    assert report == json.loads(json.dumps(ev.evaluate_dsm(p_path, t_path, ev.EvaluateOptions(protocol="dfc"),
                                                           classification=c_path)))
    assert report["classification"] == str(c_path) and report["epsg"] == EPSG
    assert report["shift"] == {"dx_cells": -1, "dy_cells": 1, "dx_m": -0.5, "dy_m": 0.5, "dz_m": -0.25}
    assert report["mean_abs_error_m"] <= FLOAT32_TOL_M and report["completeness_1m"] == report["valid_fraction"]
    ref = _dfc_reference(_aligned_back(pred.astype(np.float32).astype(np.float64), 1, 1),
                         truth.astype(np.float32).astype(np.float64), classes != WATER)
    assert report["compared_cells"] == ref["compared"] and math.isclose(report["valid_fraction"], ref["valid"])
    assert (out / ev.ERROR_MAP_PNG).is_file() and (out / ev.ERROR_TIF).is_file()
    assert json.loads((out / ev.REPORT_JSON).read_text()) == report
    # Another water code, and a smaller search: the flags reach the options.
    code = main(["evaluate", str(p_path), str(t_path), "--protocol", "dfc", "--classification", str(c_path),
                 "--water-class", "6", "--max-shift-cells", "2"])
    report = json.loads(capsys.readouterr().out)
    assert code == 0 and report["water_classes"] == [LAND] and report["shifts_searched"] == 25
    # Flags of the other protocol are refused with one line.
    for argv in (["--protocol", "dfc", "--max-shift", "1"], ["--classification", str(c_path)],
                 ["--max-shift-cells", "2"]):
        code = main(["evaluate", str(p_path), str(t_path), *argv])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and "is an option of --protocol" in err[0]
