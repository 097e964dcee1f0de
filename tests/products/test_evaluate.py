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
