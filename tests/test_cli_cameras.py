"""End-to-end tests of ``satsweep cameras``: the bad-input cases and a run on the Pleiades pair.

Every bad input must give exit code 2, one ``satsweep: error:`` line on stderr naming the file
(or the option) and the problem, no traceback, and nothing in --out.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile

from satsweep.cli import main
from satsweep.geometry.geodesy import ENUFrame
from satsweep.geometry.rpc import RPCModel
from satsweep.geometry.rpc_formats import write_rpc_txt

# AOI of about 300 m x 300 m around the centre of the pair's first image (55.6503 E, 21.2306 S)
# and the ground heights of the pair's README.
AOI = "55.6488,-21.2320,55.6518,-21.2292"
ALT = ["2300", "2380"]
# The bound for the pair over 300 m x 80 m (measured: about 0.022 px).
MAX_ERROR_PX = 0.05
# A grid small enough to keep the bad-input runs fast where they get that far.
SMALL_GRID = ["--grid", "5", "5", "3"]
# Float64 identities between JSON matrices (K[R|t] = P, det R, P4 vs P; JSON keeps every bit).
ROUND_REL_TOL = 1e-12
# A camera fitted on a crop moved by whole pixels: the same K but its principal point, to float64
# rounding of the normalised DLT (measured: up to 3e-7 px and 1e-12 relative; the bounds leave
# room for other BLAS builds, and stay far below the corrections, tenths of a pixel here).
CROP_MOVE_TOL_PX = 1e-5
CROP_MOVE_RTOL = 1e-9
# The skew warp (a shear by about 0.012) changes pixel distances by about 1 %.
WARPED_ERROR_FACTOR = 1.1
# The shear of the pair (about 0.012 and 0.03 of the rows) opens empty triangles at the left and
# right edges of the corrected images: a few percent of their pixels.
MAX_NAN_FRACTION = 0.05


def _run(capsys, args) -> tuple[int, str, str]:
    rc = main(["cameras", *map(str, args)])
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def _assert_input_error(capsys, args, out_dir, *needles: str) -> str:
    rc, _, err = _run(capsys, [*args, "--out", out_dir])
    assert rc == 2, err
    assert "Traceback" not in err
    errors = [line for line in err.splitlines() if line.startswith("satsweep: error:")]
    assert len(errors) == 1, err
    assert err.rstrip("\n").splitlines()[-1] == errors[0]
    for needle in needles:
        assert needle in errors[0], errors[0]
    assert not out_dir.exists() or not any(out_dir.iterdir())
    return errors[0]


@pytest.fixture
def pair_images(pleiades_pair):
    return [str(pleiades_pair / "img_01.tif"), str(pleiades_pair / "img_02.tif")]


@pytest.fixture
def rpc2(pleiades_pair) -> RPCModel:
    return RPCModel.from_image(pleiades_pair / "img_02.tif")


def test_tiff_without_rpc(capsys, tmp_path, pair_images):
    bad = tmp_path / "norpc.tif"
    tifffile.imwrite(bad, np.zeros((64, 64), np.uint16))
    _assert_input_error(capsys, [pair_images[0], bad, "--aoi", AOI, "--alt-range", *ALT],
                        tmp_path / "out", str(bad), "no RPC")


def test_tiff_without_rpc_when_the_altitude_range_comes_from_the_rpcs(capsys, tmp_path, pair_images):
    bad = tmp_path / "norpc.tif"
    tifffile.imwrite(bad, np.zeros((64, 64), np.uint16))
    _assert_input_error(capsys, [pair_images[0], bad, "--aoi", AOI], tmp_path / "out", str(bad), "no RPC")


def test_truncated_tiff_header(capsys, tmp_path, pair_images):
    bad = tmp_path / "cut.tif"
    bad.write_bytes(open(pair_images[1], "rb").read()[:5000])  # the pair's IFDs lie at the end
    _assert_input_error(capsys, [pair_images[0], bad, "--aoi", AOI, "--alt-range", *ALT],
                        tmp_path / "out", str(bad), "truncated")


def test_truncated_tiff_pixels(capsys, tmp_path, pair_images, rpc2):
    whole = tmp_path / "whole.tif"
    tifffile.imwrite(whole, np.ones((1102, 1031), np.uint16))
    write_rpc_txt(tmp_path / "cut_RPC.TXT", rpc2)
    bad = tmp_path / "cut.tif"
    bad.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])  # header kept, pixels cut
    _assert_input_error(capsys, [pair_images[0], bad, "--aoi", AOI, "--alt-range", *ALT],
                        tmp_path / "out", str(bad), "truncated")


def test_not_a_tiff(capsys, tmp_path, pair_images):
    bad = tmp_path / "notes.tif"
    bad.write_text("these are not pixels\n")
    _assert_input_error(capsys, [pair_images[0], bad, "--aoi", AOI, "--alt-range", *ALT],
                        tmp_path / "out", str(bad), "TIFF")


def _image_with_sidecar(tmp_path, rpc, edit) -> tuple:
    image = tmp_path / "side.tif"
    tifffile.imwrite(image, np.zeros((64, 64), np.uint16))
    sidecar = tmp_path / "side_RPC.TXT"
    write_rpc_txt(sidecar, rpc)
    sidecar.write_text(edit(sidecar.read_text()))
    return image, sidecar


def test_sidecar_with_a_missing_key(capsys, tmp_path, pair_images, rpc2):
    image, sidecar = _image_with_sidecar(
        tmp_path, rpc2, lambda t: "".join(l for l in t.splitlines(True) if not l.startswith("LINE_OFF")))
    _assert_input_error(capsys, [pair_images[0], image, "--aoi", AOI, "--alt-range", *ALT],
                        tmp_path / "out", str(sidecar), "LINE_OFF")


def test_sidecar_with_a_non_numeric_value(capsys, tmp_path, pair_images, rpc2):
    def spoil(text):
        lines = text.splitlines(True)
        i = next(k for k, l in enumerate(lines) if l.startswith("SAMP_NUM_COEFF_4:"))
        lines[i] = "SAMP_NUM_COEFF_4: 1.2e-3x\n"
        return "".join(lines)

    image, sidecar = _image_with_sidecar(tmp_path, rpc2, spoil)
    _assert_input_error(capsys, [pair_images[0], image, "--aoi", AOI, "--alt-range", *ALT],
                        tmp_path / "out", str(sidecar), "SAMP_NUM_COEFF_4", "not a number")


@pytest.mark.parametrize(
    "aoi, needle",
    [
        ("55.6518,-21.2320,55.6488,-21.2292", "lon_min"),  # lon min > max
        ("55.6488,-21.2292,55.6518,-21.2320", "lat_min"),  # lat min > max
        ("185.0,-21.2320,186.0,-21.2292", "[-180, 180]"),
        ("55.6488,-95.0,55.6518,-21.2292", "[-90, 90]"),
    ],
)
def test_bad_aoi(capsys, tmp_path, pair_images, aoi, needle):
    _assert_input_error(capsys, [*pair_images, "--aoi", aoi, "--alt-range", *ALT],
                        tmp_path / "out", "AOI", needle)


def test_inverted_altitude_range(capsys, tmp_path, pair_images):
    _assert_input_error(capsys, [*pair_images, "--aoi", AOI, "--alt-range", "2380", "2300"],
                        tmp_path / "out", "--alt-range", "inverted")


def test_fewer_than_two_images(capsys, tmp_path, pair_images):
    _assert_input_error(capsys, [pair_images[0], "--aoi", AOI, "--alt-range", *ALT],
                        tmp_path / "out", "at least 2 images")


def test_a_fixed_view_needs_the_adjustment(capsys, tmp_path, pair_images):
    _assert_input_error(capsys, [*pair_images, "--aoi", AOI, "--alt-range", *ALT,
                                 "--fixed-view", "img_01.tif"], tmp_path / "out", "needs --adjust")


def test_a_fixed_view_must_be_one_of_the_images(capsys, tmp_path, pair_images):
    _assert_input_error(capsys, [*pair_images, "--aoi", AOI, "--alt-range", *ALT, "--adjust",
                                 "--fixed-view", "img_03.tif"], tmp_path / "out",
                        "fixed_views: 'img_03.tif' names none of the views given")


def test_non_empty_output_folder_needs_overwrite(capsys, tmp_path, pair_images):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine\n")
    rc, _, err = _run(capsys, [*pair_images, "--aoi", AOI, "--alt-range", *ALT, *SMALL_GRID, "--out", out])
    assert rc == 2 and "--overwrite" in err and str(out) in err
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    rc, _, err = _run(capsys, [*pair_images, "--aoi", AOI, "--alt-range", *ALT, *SMALL_GRID, "--out", out,
                               "--overwrite"])
    assert rc == 0, err
    assert (out / "cameras.json").is_file() and (out / "keep.txt").read_text() == "mine\n"


def test_cameras_on_the_pleiades_pair(capsys, tmp_path, pair_images):
    images = pair_images
    out = tmp_path / "out"
    rc, stdout, err = _run(capsys, [*images, "--aoi", AOI, "--alt-range", *ALT, "--out", out, "--skew-correct"])
    assert rc == 0, err
    assert "img_01.tif" in stdout and "img_02.tif" in stdout and "max px" in stdout
    assert "warning" not in err  # 0.02 px is far below the 0.2 px warning level
    doc = json.loads((out / "cameras.json").read_text())
    lon_min, lat_min, lon_max, lat_max = (float(v) for v in AOI.split(","))
    o = doc["enu_origin"]
    assert o["lon0"] == pytest.approx((lon_min + lon_max) / 2, abs=ROUND_REL_TOL)
    assert o["lat0"] == pytest.approx((lat_min + lat_max) / 2, abs=ROUND_REL_TOL)
    assert o["alt0"] == float(ALT[0])
    assert doc["utm_epsg"] == 32740  # La Reunion, UTM zone 40 south (README of the pair)
    frame = ENUFrame(lon0=o["lon0"], lat0=o["lat0"], alt0=o["alt0"])
    rng = np.random.default_rng(0)
    lon = rng.uniform(lon_min, lon_max, 2000)
    lat = rng.uniform(lat_min, lat_max, 2000)
    alt = rng.uniform(float(ALT[0]), float(ALT[1]), 2000)
    e, n, u = frame.from_geodetic(lon=lon, lat=lat, alt=alt)
    X = np.stack([e, n, u, np.ones_like(e)])
    assert [v["image"] for v in doc["views"]] == [str(p) for p in images]
    for v, path in zip(doc["views"], images):
        K, R, t, P, P4 = (np.array(v[k]) for k in ("K", "R", "t", "P", "P4"))
        assert v["approx_error_px"]["max"] <= MAX_ERROR_PX
        assert v["approx_error_px"]["median"] <= v["approx_error_px"]["max"]
        assert K[0, 1] == 0.0 and K[2, 2] == 1.0 and K[0, 0] > 0 and K[1, 1] > 0
        assert np.linalg.det(R) == pytest.approx(1.0, abs=ROUND_REL_TOL)
        assert np.allclose(K @ np.hstack([R, t[:, None]]), P, rtol=ROUND_REL_TOL, atol=0)
        assert np.max(np.abs(P4)) == 1.0
        assert np.allclose(P4[:3] / P4[2, 3], P / P[2, 3], rtol=ROUND_REL_TOL, atol=0)
        # Independent check: the full image's RPC, shifted by the crop offset and the skew warp.
        full = RPCModel.from_image(path)
        col, row = full.projection(lon=lon, lat=lat, alt=alt)
        x0, y0 = v["crop_offset"]
        W = np.array(v["skew_warp"])
        expect = W @ np.stack([col - x0, row - y0, np.ones_like(col)])
        got = P @ X
        err_px = np.hypot(got[0] / got[2] - expect[0] / expect[2], got[1] / got[2] - expect[1] / expect[2])
        assert np.max(err_px) <= MAX_ERROR_PX * WARPED_ERROR_FACTOR
        warped = tifffile.imread(out / v["skew_corrected_image"])
        assert warped.shape == (v["height"], v["width"]) and warped.dtype == np.float32
        # NaN only in the triangles the shear opens at the left and right edges
        assert 0 < np.count_nonzero(np.isnan(warped)) < MAX_NAN_FRACTION * warped.size


def test_cameras_adjust_on_the_pleiades_pair(capsys, tmp_path, pair_images):
    """--adjust writes the adjusted cameras (the sparse stage's corrections, as reconstruct
    applies them) and a 'ba' section whose figures are consistent with them: each view's
    principal point moved by exactly its reported shift (in the full image: the adjusted crops
    are widened by the largest correction), and the adjustment reduced the mean reprojection
    error of the tie points (measured 0.0875 -> 0.0855 px; the median, 0.0690 -> 0.0695 px, is
    the tie points' own noise on this pair of one pass, whose views are 0.36 px apart)."""
    plain, adjusted = tmp_path / "plain", tmp_path / "adjusted"
    common = [*pair_images, "--aoi", AOI, "--alt-range", *ALT, "--grid", "30", "30", "10"]
    rc, _, err = _run(capsys, [*common, "--out", plain])
    assert rc == 0, err
    rc, stdout, err = _run(capsys, [*common, "--out", adjusted, "--adjust"])
    assert rc == 0, err
    assert "bundle adjustment" in stdout
    a = json.loads((plain / "cameras.json").read_text())
    b = json.loads((adjusted / "cameras.json").read_text())
    assert "ba" not in a
    ba = b["ba"]
    err_ba = ba["reprojection_error_px"]
    assert err_ba["after"]["mean"] < err_ba["before"]["mean"]
    for va, vb in zip(a["views"], b["views"]):
        name = vb["image"].rsplit("/", 1)[-1]
        shift = np.array(ba["principal_point_shift_px"][name])
        Ka, Kb = np.array(va["K"]), np.array(vb["K"])
        # principal points in full-image pixels: the crop's (column, row) offset added
        pa = Ka[:2, 2] + np.array(va["crop_offset"])
        pb = Kb[:2, 2] + np.array(vb["crop_offset"])
        assert ba["method"] == "sparse stage" and np.abs(shift).max() > 0.0
        np.testing.assert_allclose(pb - pa, shift, rtol=0, atol=CROP_MOVE_TOL_PX)
        np.testing.assert_allclose(np.delete(Kb.ravel(), [2, 5]), np.delete(Ka.ravel(), [2, 5]),
                                   rtol=CROP_MOVE_RTOL, atol=0)
        # and folded into the RPC written beside cameras.json
        rpc = RPCModel.from_file(adjusted / "rpc" / name.replace(".tif", "_RPC.TXT"))
        assert rpc == RPCModel.from_image(vb["image"]).corrected(shift)
    assert not (plain / "rpc").exists() and "wrote 2 corrected RPCs" in stdout


def test_cameras_adjust_leaves_out_a_blank_view_with_a_warning(capsys, caplog, tmp_path,
                                                               small_town):
    """--adjust ties the views as reconstruct does: a blank view (the town's RPC, no content) is
    dropped with a warning naming its file, and the others' cameras are written, adjusted."""
    from satsweep.geometry.rpc import RPCModel
    from satsweep.geometry.rpc_formats import rpc_tiff_extratag
    from satsweep.io.geotiff import write_tiff
    from satsweep.io.images import read_image

    first = small_town.views[0].image
    blank = tmp_path / "blank.tif"
    write_tiff(blank, np.full(read_image(first).shape, 1000, np.uint16),
               extratags=[rpc_tiff_extratag(RPCModel.from_image(first))])
    a = small_town.aoi
    lo, hi = small_town.alt_range
    out = tmp_path / "out"
    with caplog.at_level("WARNING"):
        rc, stdout, err = _run(capsys, [*(v.image for v in small_town.views), blank, "--aoi",
                                        f"{a.lon_min},{a.lat_min},{a.lon_max},{a.lat_max}",
                                        "--alt-range", lo - 5.0, hi + 5.0, "--out", out,
                                        "--adjust", *SMALL_GRID])
    assert rc == 0, err
    warned = [r.getMessage() for r in caplog.records] + err.splitlines()
    assert any(str(blank) in m and "dropped by the sparse stage" in m for m in warned), warned
    assert any(line.startswith("satsweep: warning: ") and str(blank) in line
               for line in err.splitlines()), err
    written = json.loads((out / "cameras.json").read_text())
    assert [v["image"] for v in written["views"]] == [str(v.image) for v in small_town.views]
    assert set(written["ba"]["principal_point_shift_px"]) == {
        v.image.name for v in small_town.views}
