"""End to end: `satsweep reconstruct` / `satsweep demo` on a tiny synthetic scene with exact truth,
the configuration file, and the bad-input cases of the command line."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import rasterio

from satsweep.cli import main
from satsweep.config import PipelineConfig
from satsweep.dense.mrf import MRFOptions
from satsweep.dense.sgm import sgm_label_capacity
from satsweep.dense.sweep import SweepOptions
from satsweep.errors import AOIError, InputError, OptionsError, OutputExistsError
from satsweep.geometry.altitude import AltitudeRange
from satsweep.pipeline.run import reconstruct
from satsweep.pipeline.sweeps import (
    NARROW_FILTER_MIN_REFERENCES,
    area_mrf_options,
    area_sweep_options,
    reference_options,
)
from satsweep.products.fusion import CONSENSUS_MIN_REFERENCES
from satsweep.products.ply import read_ply

# A small camera-fit grid keeps the test fast; the approximation error stays far below 0.01 px.
FAST_CAMERA = {"camera": {"grid_size": [20, 20, 6]}}
# Accuracy bounds on the tiny scene (96 m square at 0.5 m, 2 views, B/H 0.2). The issue's
# targets (0.10 m, 93%) are measured on larger scenes by tools/bench_e2e.py; a 96 m scene is
# mostly building edges and image borders, so the bounds here only catch a broken pipeline
# (a wrong frame or axis, a lost half-pixel, a swapped view would give metres of error).
MAX_MEDIAN_ABS_ERROR_M = 0.5
MIN_COMPLETENESS_1M = 0.6
# What the alignment search may gain over the unaligned DSM when the DSM is in place. Measured
# on the demo town: moving its DSM by one 0.5 m cell costs 1.1 points of completeness unaligned
# (two cells: 2.8 points) but only 0.004 m of median error, so completeness is the sensitive
# figure; the median bound only catches gross misplacement.
MAX_ALIGNMENT_GAIN_M = 0.05
MAX_ALIGNMENT_GAIN_COMPLETENESS = 0.01
# A run from the corrected RPCs of another run of the same views: their corrections again,
# the adjustment's precision on this 192 px pair (hundredths of a pixel).
RPC_ROUND_TRIP_PX = 0.05
# The synthetic scene's altitude range, widened so that the true surface is never at its edge.
ALT_MARGIN_M = 5.0


@pytest.fixture(scope="module")
def scene(small_town):
    return small_town


def _alt(scene) -> AltitudeRange:
    lo, hi = scene.alt_range
    return AltitudeRange(lo - ALT_MARGIN_M, hi + ALT_MARGIN_M)


def _aoi_arg(scene) -> str:
    a = scene.aoi
    return f"{a.lon_min},{a.lat_min},{a.lon_max},{a.lat_max}"


def _reconstruct(scene, out: Path, mapping: dict, *, with_range: bool = True):
    """reconstruct the scene's views into ``out`` with the config ``mapping``, evaluated against
    its truth; with the scene's altitude range (widened) unless ``with_range`` is False."""
    return reconstruct([v.image for v in scene.views], scene.aoi, out,
                       alt_range=_alt(scene) if with_range else None,
                       config=PipelineConfig.from_mapping(mapping), truth=scene.truth_dsm,
                       verbose=False)


def _check_accuracy(result) -> None:
    """The aligned accuracy bounds of every reconstruction of the scene."""
    a = result.evaluation["aligned"]
    assert a["median_abs_error_m"] <= MAX_MEDIAN_ABS_ERROR_M, result.evaluation
    assert a["completeness_1m"] >= MIN_COMPLETENESS_1M, result.evaluation


@pytest.fixture(scope="module")
def reconstruction(scene, tmp_path_factory):
    return _reconstruct(scene, tmp_path_factory.mktemp("rec") / "out", FAST_CAMERA)


def test_reconstruct_writes_every_output(reconstruction):
    out = reconstruction.out_dir
    names = {p.name for p in out.iterdir()}
    assert {"dsm.tif", "confidence.tif", "ortho.tif", "cloud.ply", "dsm.png", "cameras.json",
            "config.toml", "report.json", "evaluation"} <= names
    assert not [n for n in names if n.startswith(".satsweep-partial")]


def test_reconstruct_writes_the_corrected_rpcs(reconstruction, scene):
    """rpc/<stem>_RPC.TXT: each view's RPC with the correction the run applied (report.json)
    folded into its offsets, readable as a GDAL sidecar."""
    from satsweep.geometry.rpc import RPCModel

    shifts = reconstruction.report["ba"]["principal_point_shift_px"]
    assert sorted(p.name for p in (reconstruction.out_dir / "rpc").iterdir()) == [
        f"{v.image.stem}_RPC.TXT" for v in scene.views]
    for v in scene.views:
        written = RPCModel.from_file(reconstruction.out_dir / "rpc" / f"{v.image.stem}_RPC.TXT")
        original = RPCModel.from_image(v.image)
        dc, dr = shifts[v.image.name]
        assert written.col_offset == original.col_offset + dc
        assert written.row_offset == original.row_offset + dr
        assert written == original.corrected((dc, dr))



def test_views_of_one_file_name_keep_their_own_corrections(reconstruction, scene, tmp_path):
    """Two views named alike in two folders (a/view.tif, b/view.tif): each keeps its own
    correction in the report (keyed by path, as its other per-view entries) and in its rpc/ file
    (prefixed by its index)."""
    from satsweep.geometry.rpc import RPCModel

    copies = []
    for folder, v in zip("ab", scene.views):
        (tmp_path / folder).mkdir()
        copies.append(tmp_path / folder / "view.tif")
        shutil.copy(v.image, copies[-1])
        shutil.copy(v.rpc_file, tmp_path / folder / "view_RPC.TXT")
    result = reconstruct(copies, scene.aoi, tmp_path / "out", alt_range=_alt(scene),
                         config=PipelineConfig.from_mapping(FAST_CAMERA), verbose=False)
    shifts = result.report["ba"]["principal_point_shift_px"]
    alone = reconstruction.report["ba"]["principal_point_shift_px"]
    assert sorted(shifts) == sorted(str(c) for c in copies)
    for k, (copy, v) in enumerate(zip(copies, scene.views)):
        assert shifts[str(copy)] == alone[v.image.name]  # the same views, the same shifts
        written = RPCModel.from_file(tmp_path / "out" / "rpc" / f"{k:02d}_view_RPC.TXT")
        assert written == RPCModel.from_image(v.image).corrected(tuple(shifts[str(copy)]))
    assert alone[scene.views[0].image.name] != alone[scene.views[1].image.name]
    # The report's other per-view entries name the two views apart too.
    assert sorted(result.report["cameras"]["approx_error_px"]) == sorted(shifts)
    assert sorted(result.report["tiling"]["aoi_seen_share"]) == sorted(shifts)

def test_a_run_takes_the_rpcs_of_another_runs_rpc_folder(reconstruction, scene, tmp_path):
    """--rpc-dir: a second run from the first run's rpc/ reads those RPCs (the report says
    where each came from), needs corrections of hundredths of a pixel, and is as accurate."""
    rpc_dir = reconstruction.out_dir / "rpc"
    again = reconstruct([v.image for v in scene.views], scene.aoi, tmp_path / "out",
                        alt_range=_alt(scene), config=PipelineConfig.from_mapping(FAST_CAMERA),
                        truth=scene.truth_dsm, verbose=False, rpc_dir=rpc_dir)
    _check_accuracy(again)
    inputs = again.report["inputs"]
    assert inputs["rpc_dir"] == str(rpc_dir)
    assert inputs["rpcs"] == [str(rpc_dir / f"{v.image.stem}_RPC.TXT") for v in scene.views]
    assert reconstruction.report["inputs"]["rpcs"] == [str(v.image) for v in scene.views]
    shifts = np.array(list(again.report["ba"]["principal_point_shift_px"].values()))
    assert np.abs(shifts).max() < RPC_ROUND_TRIP_PX
    with pytest.raises(InputError, match="the RPC folder does not exist"):
        reconstruct([v.image for v in scene.views], scene.aoi, tmp_path / "out2",
                    rpc_dir=tmp_path / "nowhere")
    assert not (tmp_path / "out2").exists()


def test_dsm_georeferencing_read_by_gdal(reconstruction, scene):
    """rasterio (GDAL) reads dsm.tif with the scene's UTM CRS, its 0.5 m north-up transform on
    the same cell lattice as the truth, and NaN nodata."""
    with rasterio.open(reconstruction.out_dir / "dsm.tif") as pred, rasterio.open(scene.truth_dsm) as truth:
        assert pred.crs.to_epsg() == truth.crs.to_epsg() == scene.dsm_grid.epsg
        assert pred.dtypes[0] == "float32" and np.isnan(pred.nodata)
        a, t = pred.transform, truth.transform
        assert (a.a, a.e, a.b, a.d) == (0.5, -0.5, 0.0, 0.0)
        # both grids snap to multiples of the cell size: same lattice
        assert ((a.c - t.c) / 0.5) == pytest.approx(round((a.c - t.c) / 0.5), abs=1e-9)
        assert ((a.f - t.f) / 0.5) == pytest.approx(round((a.f - t.f) / 0.5), abs=1e-9)
        data = pred.read(1)
    assert np.isfinite(data).mean() > MIN_COMPLETENESS_1M


def test_rasters_are_tiled_compressed_with_overviews_and_say_what_they_hold(reconstruction):
    """Every raster streams as GDAL expects (tiles, deflate, internal overviews); the DSM says
    it holds heights above the ellipsoid in metres; interpolated.tif marks the filled cells."""
    from satsweep.io.cog import TILE_PX, overview_shapes

    out = reconstruction.out_dir
    for name in ("dsm.tif", "confidence.tif", "ortho.tif", "interpolated.tif"):
        with rasterio.open(out / name) as src:
            levels = overview_shapes(src.shape, TILE_PX)  # none when the grid fits one tile
            assert src.block_shapes == [(TILE_PX, TILE_PX)], name
            assert src.compression.name == "deflate", name
            assert src.overviews(1) == [2 ** (k + 1) for k in range(len(levels))], name
    with rasterio.open(out / "dsm.tif") as dsm, rasterio.open(out / "interpolated.tif") as mask:
        assert dsm.units == ("m",) and "ellipsoid" in dsm.tags()["VERTICAL_REFERENCE"]
        heights, flags = dsm.read(1), mask.read(1)
    assert mask.nodata == 255 and set(np.unique(flags)) <= {0, 1, 255}
    np.testing.assert_array_equal(flags == 255, np.isnan(heights))
    assert int((flags == 1).sum()) == reconstruction.report["dsm"]["holes_filled_cells"]


def test_accuracy_against_the_exact_truth(reconstruction):
    ev = reconstruction.evaluation
    a = ev["aligned"]
    assert a["median_abs_error_m"] <= MAX_MEDIAN_ABS_ERROR_M, ev
    assert a["completeness_1m"] >= MIN_COMPLETENESS_1M, ev
    # The estimated cameras put the DSM in place: the alignment search gains little over the
    # unaligned DSM. (Which shift wins is not a stable statistic: neighbouring shifts score within
    # a fraction of a millimetre of each other on a small scene.)
    u = ev["unaligned"]
    assert u["median_abs_error_m"] - a["median_abs_error_m"] <= MAX_ALIGNMENT_GAIN_M, ev
    assert a["completeness_1m"] - u["completeness_1m"] <= MAX_ALIGNMENT_GAIN_COMPLETENESS, ev


# The orthophoto against each view sampled where its RPC projects the DSM's cells (bilinear, in
# the images' own units): measured correlation 0.990, median |difference| 0.0039 of the
# reference's 1-99% range. The same orthophoto moved by one 0.5 m cell (a row or a column)
# measured 0.955-0.962 and 0.0075-0.0077: the bounds sit between, so a misplaced orthophoto
# fails, not only a wrong one.
ORTHO_MIN_CORRELATION = 0.975
ORTHO_MAX_MEDIAN_DIFF = 0.0055  # of the reference's 1-99% range
# View 1 given another gain and offset; the orthophoto against the one of the unchanged views,
# in fractions of its 1-99% range: measured bias 0.0001 and median |difference| 0.0002; without
# the radiometric matching 0.073 and 0.073 (matched to the first reference swept, view 1: 0.148).
ORTHO_TEST_GAIN, ORTHO_TEST_OFFSET = 1.5, 100.0
ORTHO_RADIOMETRY_MAX_BIAS = 0.01
ORTHO_RADIOMETRY_MAX_DIFF = 0.02


def _rpc_sampled(scene, lon, lat, alt):
    """Each view's image sampled bilinearly where its RPC projects (lon, lat, alt)."""
    import cv2

    from satsweep.geometry.rpc import RPCModel
    from satsweep.io.images import read_image

    out = []
    for v in scene.views:
        col, row = RPCModel.from_image(v.image).projection(lon=lon, lat=lat, alt=alt)
        image = read_image(v.image).astype(np.float32)
        out.append(cv2.remap(image, col.astype(np.float32)[None], row.astype(np.float32)[None],
                             cv2.INTER_LINEAR, borderValue=np.nan)[0])
    return out


def test_orthophoto_shows_each_cell_where_the_views_see_it(reconstruction, scene):
    from satsweep.geometry.geodesy import utm_to_lonlat

    with rasterio.open(reconstruction.out_dir / "ortho.tif") as o, \
            rasterio.open(reconstruction.dsm_path) as d:
        assert o.crs == d.crs and o.transform == d.transform and o.shape == d.shape
        ortho, dsm, t = o.read(1), d.read(1), d.transform
    assert np.isfinite(ortho).mean() >= MIN_COMPLETENESS_1M
    rows, cols = np.nonzero(np.isfinite(ortho) & np.isfinite(dsm))
    lon, lat = utm_to_lonlat(x=t.c + (cols + 0.5) * t.a, y=t.f + (rows + 0.5) * t.e,
                             epsg=o.crs.to_epsg())
    for ref in _rpc_sampled(scene, lon, lat, dsm[rows, cols]):
        ok = np.isfinite(ref)
        got = ortho[rows, cols][ok]
        span = np.percentile(ref[ok], 99) - np.percentile(ref[ok], 1)
        assert np.corrcoef(got, ref[ok])[0, 1] >= ORTHO_MIN_CORRELATION
        assert np.median(np.abs(got - ref[ok])) <= ORTHO_MAX_MEDIAN_DIFF * span


def test_orthophoto_brings_the_views_to_one_radiometry(scene, reconstruction, tmp_path):
    """View 1 with another gain and offset (as from another date): the orthophoto stays in
    view 0's radiometry, as when the views agree."""
    from satsweep.geometry.rpc import RPCModel
    from satsweep.geometry.rpc_formats import rpc_tiff_extratag
    from satsweep.io.geotiff import write_tiff
    from satsweep.io.images import read_image

    src = scene.views[1].image
    brighter = tmp_path / "bright" / src.name
    brighter.parent.mkdir()
    dn = read_image(src).astype(np.float64) * ORTHO_TEST_GAIN + ORTHO_TEST_OFFSET
    write_tiff(brighter, np.clip(dn, 0, 65535).astype(np.uint16),
               extratags=[rpc_tiff_extratag(RPCModel.from_image(src))])
    res = reconstruct([scene.views[0].image, brighter], scene.aoi, tmp_path / "out",
                      alt_range=_alt(scene), config=PipelineConfig.from_mapping(FAST_CAMERA),
                      verbose=False)
    with rasterio.open(res.out_dir / "ortho.tif") as a, \
            rasterio.open(reconstruction.out_dir / "ortho.tif") as b:
        got, ref = a.read(1), b.read(1)
    both = np.isfinite(got) & np.isfinite(ref)
    span = np.percentile(ref[both], 99) - np.percentile(ref[both], 1)
    assert abs(np.median(got[both] - ref[both])) <= ORTHO_RADIOMETRY_MAX_BIAS * span
    assert np.median(np.abs(got - ref)[both]) <= ORTHO_RADIOMETRY_MAX_DIFF * span


def test_report_records_settings_device_timings_and_views(reconstruction):
    rep = json.loads((reconstruction.out_dir / "report.json").read_text())
    for stage in ("views", "cameras", "select", "sweep", "dsm", "outputs", "evaluate", "total"):
        assert rep["timings_s"][stage] >= 0
    assert rep["device"]["can_build"] is True
    builds = rep["device"]["kernel_builds"]  # what this run compiled (other tests may have first)
    assert isinstance(builds["programs"], int) and builds["programs"] >= 0
    assert builds["seconds"] >= 0.0 and (builds["programs"] > 0 or builds["seconds"] == 0.0)
    assert rep["settings"]["camera"]["grid_size"] == [20, 20, 6]
    refs = rep["view_selection"]["references"]
    assert sorted(r["reference"] for r in refs) == ["view_00.tif", "view_01.tif"]  # 2 views: each once
    assert rep["evaluation"]["prediction"] == str(reconstruction.out_dir / "dsm.tif")


def test_the_evaluation_gives_the_dfc_protocol_beside_mvs3dm(scene, reconstruction):
    """With a truth, the report holds the DFC2019 figures too (the protocol of published
    multi-date results): those of ``satsweep evaluate --protocol dfc`` on the outputs."""
    from satsweep.products.evaluate import EvaluateOptions, evaluate_dsm

    rep = json.loads((reconstruction.out_dir / "report.json").read_text())
    alone = evaluate_dsm(reconstruction.dsm_path, scene.truth_dsm, EvaluateOptions(protocol="dfc"))
    got = rep["evaluation"]["dfc"]
    for key in ("mean_abs_error_m", "median_abs_error_m", "completeness_1m", "valid_fraction"):
        assert got[key] == pytest.approx(alone[key], rel=0, abs=0), key
    assert got["shift"] == alone["shift"] and "DFC2019" in got["protocol"]


# How far inside its reference window a point of the AOI cube may project, in pixels, less than
# the window's own context: the window is found with the pipeline's perspective cameras, the
# check uses the exact RPCs, which they approximate to well under 0.05 px, and the adjustment's
# principal-point shifts, a fraction of a pixel on this unbiased scene.
FOOTPRINT_TOLERANCE_PX = 1.0


def test_each_reference_is_swept_over_its_aoi_footprint_only(reconstruction, scene):
    """The sweep covers every pixel that sees the AOI cube (its corners and random points of it
    projected by the exact RPCs, then into the skew-corrected crop) with REFERENCE_CONTEXT_PX
    around them, and leaves out the rest of the crop's margin."""
    from satsweep.geometry.rpc import RPCModel
    from satsweep.pipeline.sweeps import REFERENCE_CONTEXT_PX

    rep = json.loads((reconstruction.out_dir / "report.json").read_text())
    cams = {Path(v["image"]).name: v for v in
            json.loads((reconstruction.out_dir / "cameras.json").read_text())["views"]}
    rng = np.random.default_rng(0)
    a, alt = scene.aoi, _alt(scene)
    lon = rng.uniform(a.lon_min, a.lon_max, 20000)
    lat = rng.uniform(a.lat_min, a.lat_max, 20000)
    h = rng.uniform(alt.min, alt.max, 20000)
    # with the cube's 8 corners, where its image reaches furthest
    lon = np.concatenate([lon, np.tile([a.lon_min, a.lon_max, a.lon_min, a.lon_max], 2)])
    lat = np.concatenate([lat, np.tile([a.lat_min, a.lat_min, a.lat_max, a.lat_max], 2)])
    h = np.concatenate([h, np.repeat([alt.min, alt.max], 4)])
    paths = {Path(v.image).name: v.image for v in scene.views}
    for entry in rep["sweep"]:
        cam = cams[entry["reference"]]
        col, row = RPCModel.from_image(paths[entry["reference"]]).projection(lon=lon, lat=lat, alt=h)
        ox, oy = cam["crop_offset"]
        x = np.array(cam["skew_warp"]) @ np.stack([col - ox, row - oy, np.ones_like(col)])
        col, row = x[0] / x[2], x[1] / x[2]
        x0, y0, x1, y1 = entry["window"]
        w, h_img = cam["width"], cam["height"]
        inner = REFERENCE_CONTEXT_PX - FOOTPRINT_TOLERANCE_PX
        # every side: at least the context beyond the cube's pixels, unless at the crop's edge
        assert x0 == 0 or x0 <= col.min() - inner, (entry, col.min())
        assert y0 == 0 or y0 <= row.min() - inner, (entry, row.min())
        assert x1 == w or x1 - 1 >= col.max() + inner, (entry, col.max())
        assert y1 == h_img or y1 - 1 >= row.max() + inner, (entry, row.max())
        # and not much more: the crop's margin (32 px) is left out
        slack = REFERENCE_CONTEXT_PX + 2 + FOOTPRINT_TOLERANCE_PX
        assert x0 >= col.min() - slack and y0 >= row.min() - slack, entry
        assert x1 - 1 <= col.max() + slack and y1 - 1 <= row.max() + slack, entry
        assert (x1 - x0) * (y1 - y0) < w * h_img, entry


def test_tiled_mrf_reconstruction_is_as_accurate_and_reports_its_tiles(scene, reconstruction,
                                                                          tmp_path):
    """mrf.tile_px small enough to cut each reference into several tiles: same accuracy bounds,
    the tiles and the MRF's own time in the report."""
    tiled = _reconstruct(scene, tmp_path / "out",
                         {**FAST_CAMERA, "mrf": {"tile_px": 96, "tile_overlap_px": 32}})
    _check_accuracy(tiled)
    rep = json.loads((tiled.out_dir / "report.json").read_text())
    assert all(v["mrf"]["tiles"] >= 4 for v in rep["sweep"])
    assert rep["timings_s"]["mrf"] > 0
    one = json.loads((reconstruction.out_dir / "report.json").read_text())
    assert all(v["mrf"]["tiles"] == 1 for v in one["sweep"])
    # a median fusion of few references: the sweep under SGM filters with sgm_sweep_gf_radius
    assert one["dsm"]["fusion"] == "median"
    assert all(v["mrf"]["sweep_gf_radius"] == MRFOptions().sgm_sweep_gf_radius
               for v in one["sweep"])


# AOI tiles for the test town (its AOI is 59 m square): the smallest tile side gives 2 x 2 tiles.
AOI_TILE_M = 50.0
AOI_TILE_OVERLAP_M = 16.0
# The tiled DSM against the untiled one (the same views, other cameras per tile and less context
# at the tile seams): measured 0.09 m median difference, 98.6% of the common cells within 1 m.
TILED_MAX_MEDIAN_DIFF_M = 0.15
TILED_MIN_AGREEMENT_1M = 0.9
# The tiled cloud holds each tile's core points only: without that, the 16 m overlaps around
# 30 m cores would bring up to (62 / 30)^2 = 4 times as many points (fewer at the AOI's edges).
TILED_MAX_CLOUD_RATIO = 1.2


# Below the camera errors of the test town (about 0.003 px), so that any area is cut again.
TINY_MAX_ERROR_PX = 1e-4
# A smaller minimum tile side for that case, so that the 59 m AOI can be cut once (into 30 m).
TEST_MIN_TILE_M = 20.0


@pytest.mark.parametrize("how", ["tile_m", "max_error"])
def test_aoi_tiles_each_with_their_cameras_make_one_dsm(scene, reconstruction, tmp_path,
                                                        monkeypatch, how):
    """The AOI reconstructed in 2 x 2 tiles, each with its own cameras: planned from [reconstruct]
    tile_m below the AOI's side, or cut after the AOI's cameras came out further from the RPCs
    than tile_max_error_px. Their cores fill one DSM on the untiled run's grid, as accurate and
    in agreement with it; the report and the output folder hold each tile's cameras."""
    table = {"tile_overlap_m": AOI_TILE_OVERLAP_M}
    if how == "tile_m":
        table["tile_m"] = AOI_TILE_M
    else:
        import satsweep.pipeline.tiling

        monkeypatch.setattr(satsweep.pipeline.tiling, "MIN_TILE_M", TEST_MIN_TILE_M)
        table["tile_max_error_px"] = TINY_MAX_ERROR_PX
    tiled = _reconstruct(scene, tmp_path / "out", {**FAST_CAMERA, "reconstruct": table})
    _check_accuracy(tiled)
    rep = json.loads((tiled.out_dir / "report.json").read_text())
    assert rep["tiling"]["tiles"] == 4 and len(rep["aoi_tiles"]) == 4
    alt = _alt(scene)
    assert rep["altitude_range"] == {"min": alt.min, "max": alt.max, "source": "user"}
    if how == "tile_m":
        assert rep["tiling"]["splits"] == [] and all(t["level"] == 0 for t in rep["aoi_tiles"])
    else:
        (split,) = rep["tiling"]["splits"]
        assert split["into"] == 4 and split["max_error_px"] > TINY_MAX_ERROR_PX
        assert all(t["level"] == 1 for t in rep["aoi_tiles"])
    whole = json.loads((reconstruction.out_dir / "report.json").read_text())
    assert whole["tiling"]["tiles"] == 1 and whole["tiling"]["splits"] == []
    assert "aoi_tiles" not in whole and {"views", "cameras", "ba", "sweep"} <= set(whole)
    for key in ("epsg", "resolution_m", "width", "height", "x_min", "y_max"):
        assert rep["dsm"][key] == whole["dsm"][key]
    for k, tile in enumerate(rep["aoi_tiles"]):
        assert {"views", "cameras", "ba", "view_selection", "sweep", "dsm"} <= set(tile)
        assert tile["cameras_file"] == f"tiles/tile_{k:02d}/cameras.json"
        assert (tiled.out_dir / tile["cameras_file"]).is_file()
        # each tile's own corrections, folded into the RPCs beside its cameras
        rpcs = sorted(p.name for p in (tiled.out_dir / f"tiles/tile_{k:02d}/rpc").iterdir())
        assert rpcs == [f"{v.image.stem}_RPC.TXT" for v in scene.views]
    assert not (tiled.out_dir / "cameras.json").exists() and not (tiled.out_dir / "rpc").exists()

    with rasterio.open(tiled.dsm_path) as a, rasterio.open(reconstruction.dsm_path) as b:
        t, w = a.read(1), b.read(1)
    both = np.isfinite(t) & np.isfinite(w)
    diff = np.abs(t - w)[both]
    assert np.median(diff) <= TILED_MAX_MEDIAN_DIFF_M
    assert np.mean(diff < 1.0) >= TILED_MIN_AGREEMENT_1M
    n_tiled = len(read_ply(tiled.out_dir / "cloud.ply")["x"])
    n_whole = len(read_ply(reconstruction.out_dir / "cloud.ply")["x"])
    assert n_tiled <= TILED_MAX_CLOUD_RATIO * n_whole


def test_a_tile_without_matches_takes_the_other_tiles_pointing_corrections(scene, tmp_path,
                                                                         monkeypatch):
    """A tile whose views cannot be adjusted (its first adjustment and its second fail here)
    waits for the others, then takes the median of their principal-point shifts."""
    import satsweep.sparse.stage
    from satsweep.errors import CameraError

    real = satsweep.sparse.stage.sparse_stage
    calls = []

    def flaky(*args, **kwargs):
        calls.append(len(calls))
        if len(calls) in (1, 5):  # the first tile, at its first and at its second turn
            raise CameraError("too few matches (planted by the test)")
        return real(*args, **kwargs)

    monkeypatch.setattr(satsweep.sparse.stage, "sparse_stage", flaky)
    res = _reconstruct(scene, tmp_path / "out", {**FAST_CAMERA, "reconstruct": {
        "tile_m": AOI_TILE_M, "tile_overlap_m": AOI_TILE_OVERLAP_M}})
    _check_accuracy(res)
    tiles = json.loads((res.out_dir / "report.json").read_text())["aoi_tiles"]
    assert len(calls) == 5 and len(tiles) == 4
    assert tiles[-1]["core_cells"][:3:2] == [0, 0]  # the north-west tile, done last
    own = [[t["ba"]["principal_point_shift_px"][n] for n in ("view_00.tif", "view_01.tif")]
           for t in tiles[:3]]
    borrowed = tiles[-1]["ba"]["borrowed_principal_point_shift_px"]
    np.testing.assert_array_equal(borrowed, np.median(np.array(own), axis=0))


def _cropped_view(scene, tmp_path, columns: int, *, view: int = 1, start: int = 0) -> Path:
    """The scene's view ``view`` cut to ``columns`` columns from column ``start`` (its RPC
    cropped alike)."""
    from satsweep.geometry.rpc import RPCModel
    from satsweep.geometry.rpc_formats import rpc_tiff_extratag
    from satsweep.io.geotiff import write_tiff
    from satsweep.io.images import read_image

    src = scene.views[view].image
    out = tmp_path / "narrow" / src.name
    out.parent.mkdir(parents=True)
    rpc = RPCModel.from_image(src).cropped(x0=start, y0=0)
    write_tiff(out, read_image(src)[:, start:start + columns],
               extratags=[rpc_tiff_extratag(rpc)])
    return out


# The cut view sees the tiles it keeps only in part: of their cells, those it sees get heights
# (measured 67% and 43% of the two tiles' cells, 0.06 and 0.11 m from the untiled DSM).
SEEN_TILE_MIN_COVERAGE = 0.25
# The run's share of the AOI a cut view sees (its tiles' cells at their fused heights, those
# without a height at the middle of the range; 64 samples per tile side) against every DSM cell
# at its true height: 30.2% (tiled) and 30.7% (in one piece) against 28.5% here (measured),
# where the tiles seen by the cut view match a third of their reference's pixels at the
# range's top (warned), so their heights are not the truth's. "About N%" is what the figure
# is for; the bound: three points.
SEEN_SHARE_TOLERANCE = 0.03


def _seen_share(scene, image: Path, grid: dict) -> float:
    """The share of the DSM grid's cells (report.json's ``dsm``) whose true point projects into
    ``image`` by its RPC: the reference for the run's ``tiling.aoi_seen_share``."""
    from satsweep.geometry.geodesy import utm_to_lonlat
    from satsweep.geometry.rpc import RPCModel
    from satsweep.io.images import read_image

    res = grid["resolution_m"]
    x = grid["x_min"] + (np.arange(grid["width"]) + 0.5) * res
    y = grid["y_max"] - (np.arange(grid["height"]) + 0.5) * res
    xx, yy = np.meshgrid(x, y)
    with rasterio.open(scene.truth_dsm) as t:
        rows, cols = rasterio.transform.rowcol(t.transform, xx.ravel(), yy.ravel())
        truth = t.read(1)
    z = truth[np.clip(rows, 0, truth.shape[0] - 1), np.clip(cols, 0, truth.shape[1] - 1)]
    lon, lat = utm_to_lonlat(x=xx.ravel(), y=yy.ravel(), epsg=grid["epsg"])
    col, row = RPCModel.from_image(image).projection(lon=lon, lat=lat, alt=z)
    height, width = read_image(image).shape[:2]
    return float(np.mean((col >= -0.5) & (col <= width - 0.5) & (row >= -0.5)
                         & (row <= height - 0.5)))


def test_tiles_take_the_images_that_see_them(scene, reconstruction, tmp_path):
    """A large AOI need not lie in every image: with view 1 cut to a third of its width, the
    tiles it no longer sees are left without heights (reported), the others are reconstructed;
    the run says once how much of the AOI the cut view sees (not once per tile at its edge,
    and not of a tile's footprint), and each tile's warnings name its cells; when no tile is
    seen by two images the run fails with one line naming the images (and an image that sees
    none of the AOI, with the error naming it)."""
    # The AOI spans about columns 37..155 of view 1: its first 70 columns see the tiles of one
    # side only, once the tiles' context is small.
    narrow = _cropped_view(scene, tmp_path, columns=70)
    config = PipelineConfig.from_mapping({**FAST_CAMERA, "reconstruct": {
        "tile_m": AOI_TILE_M, "tile_overlap_m": 2.0}})
    res = reconstruct([scene.views[0].image, narrow], scene.aoi, tmp_path / "out",
                      alt_range=_alt(scene), config=config, verbose=False)
    rep = json.loads((res.out_dir / "report.json").read_text())
    unseen, tiles = rep["tiling"]["unseen"], rep["aoi_tiles"]
    assert unseen and tiles and len(unseen) + len(tiles) == 4, rep["tiling"]
    assert all(u["images"] == [scene.views[0].image.name] for u in unseen)
    with rasterio.open(res.dsm_path) as a, rasterio.open(reconstruction.dsm_path) as b:
        dsm, whole = a.read(1), b.read(1)
    for u in unseen:
        r0, r1, c0, c1 = u["core_cells"]
        assert np.isnan(dsm[r0:r1, c0:c1]).all()
    for t in tiles:
        r0, r1, c0, c1 = t["core_cells"]
        part, ref = dsm[r0:r1, c0:c1], whole[r0:r1, c0:c1]
        both = np.isfinite(part) & np.isfinite(ref)
        assert both.mean() >= SEEN_TILE_MIN_COVERAGE
        assert np.median(np.abs(part - ref)[both]) <= TILED_MAX_MEDIAN_DIFF_M

    shares = rep["tiling"]["aoi_seen_share"]
    assert shares[scene.views[0].image.name] == 1.0
    expected = _seen_share(scene, narrow, rep["dsm"])
    assert 0.1 < expected < 0.9  # the case this test is about: a view that sees part of the AOI
    assert abs(shares[narrow.name] - expected) <= SEEN_SHARE_TOLERANCE, (shares, expected)
    said = [w["message"] for w in rep["warnings"] if "the image sees only" in w["message"]]
    assert said == [f"{narrow}: the image sees only about {100 * shares[narrow.name]:.0f}% of "
                    "the AOI"]
    # in one piece: the same warning, from the one area's share
    whole_config = PipelineConfig.from_mapping({**FAST_CAMERA, "reconstruct": {"tile_m": 0.0}})
    one = reconstruct([scene.views[0].image, narrow], scene.aoi, tmp_path / "one",
                      alt_range=_alt(scene), config=whole_config, verbose=False)
    one_rep = json.loads((one.out_dir / "report.json").read_text())
    one_share = one_rep["tiling"]["aoi_seen_share"][narrow.name]
    assert abs(one_share - expected) <= SEEN_SHARE_TOLERANCE, (one_share, expected)
    assert [w["message"] for w in one_rep["warnings"] if "sees only" in w["message"]] == [
        f"{narrow}: the image sees only about {100 * one_share:.0f}% of the AOI"]
    cells = tuple(tuple(t["core_cells"]) for t in tiles)
    others = [w["message"] for w in rep["warnings"] if w["message"] not in said
              and "are seen by fewer than two images" not in w["message"]]
    assert all(m.startswith(tuple(f"cells {c}: " for c in cells)) for m in others), others

    # view 0 cut to its first 70 columns and view 1 to its last ones: each sees the tiles of
    # its own side only
    west = _cropped_view(scene, tmp_path / "west", columns=70, view=0)
    east = _cropped_view(scene, tmp_path / "east", columns=100, start=125)
    with pytest.raises(InputError, match="no tile of the AOI is seen by two"):
        reconstruct([west, east], scene.aoi, tmp_path / "none",
                    alt_range=_alt(scene), config=config, verbose=False)
    blind = _cropped_view(scene, tmp_path / "blind", columns=8)
    with pytest.raises(AOIError, match="blind/narrow/view_01.tif.*does not see the AOI"):
        reconstruct([scene.views[0].image, blind], scene.aoi, tmp_path / "none",
                    alt_range=_alt(scene), config=config, verbose=False)


@pytest.mark.parametrize("search,block", [("coarse_to_fine", 32), ("coarse_to_fine", 1),
                                          ("full", 32)])
def test_either_search_is_as_accurate_and_reports_its_windows(scene, tmp_path, search, block):
    """[sweep] search = "coarse_to_fine" (the default: a half-resolution pass, then plane windows
    per block, here blocks small enough for the tiny scene to have several, or per pixel) and
    "full" (every plane everywhere): the same accuracy bounds, and each reference's window size
    and share of the planes swept in the report, below its planes and 1 (None for the full
    search)."""
    res = _reconstruct(scene, tmp_path / "out", {**FAST_CAMERA, "sweep": {
        "search": search, "window_block_px": block, "window_max_fraction": 1.0}})
    _check_accuracy(res)
    rep = json.loads((res.out_dir / "report.json").read_text())
    if search == "full":
        assert all(v["window_planes"] is None and v["window_share"] is None
                   for v in rep["sweep"]), rep["sweep"]
    else:
        assert all(v["window_planes"] is not None and v["window_planes"] <= v["planes"]
                   and 0 < v["window_share"] < 1 for v in rep["sweep"]), rep["sweep"]


def test_without_an_altitude_range_the_tie_points_set_it(scene, tmp_path):
    """No --alt-range and no DEM: the RPCs' coarse range is narrowed by tie points (reported),
    and the reconstruction still succeeds against the truth."""
    res = _reconstruct(scene, tmp_path / "out", FAST_CAMERA, with_range=False)
    alt = res.report["altitude_range"]
    assert alt["source"] == "tie points" and alt["tie_points"] >= 20
    lo, hi = scene.alt_range
    # the range holds the ground, within the RPCs' heights (these synthetic RPCs are fitted over
    # the relief alone, so theirs is not the kilometres of a real RPC)
    assert alt["min"] <= lo and alt["max"] > lo + 1.0
    prior = res.report["sparse"]["prior_range"]  # the RPCs' range the views were tied over
    assert prior[0] <= alt["min"] and alt["max"] <= prior[1]
    assert "sparse" in res.report["timings_s"]
    _check_accuracy(res)  # the bounds of the run given the range


def test_cameras_and_reconstruct_take_one_range_from_the_tie_points(scene, tmp_path, capsys):
    """Without a range, ``choose_altitude_range`` (what ``satsweep cameras`` and the range-end
    warning ask) runs the sparse stage over the RPCs' range as reconstruct does: the same range,
    reported as the tie points', no longer quantiles of pairs triangulated with the raw RPCs."""
    from satsweep.io.sources import open_sources
    from satsweep.pipeline.altitude import choose_altitude_range, prior_altitude_range
    from satsweep.pipeline.prepare import tie_sources

    config = PipelineConfig()
    sources = open_sources([v.image for v in scene.views])
    choice = choose_altitude_range(sources, scene.aoi, alt_range=None, dem=None, config=config)
    prior = prior_altitude_range(sources, scene.aoi, alt_range=None, dem=None)
    sparse = tie_sources(sources, scene.aoi, prior, config)
    assert choice.source == "tie points" and choice.range == sparse.altitude_range
    assert choice.details["tie_points"] == sparse.altitude["tie_points"] >= 20
    assert choice.doubt is None and choice.range.min <= scene.alt_range[0]
    rc = main(["cameras", *map(str, (v.image for v in scene.views)), "--aoi", _aoi_arg(scene),
               "--out", str(tmp_path / "cams"), "--grid", "10", "10", "4"])
    out = capsys.readouterr().out
    assert rc == 0 and f"altitudes {choice.range} (tie points)" in out


def _record_builds(monkeypatch) -> tuple[set, set, list]:
    """(forecast, asked, foreground): the programs prebuilt (``Device.prebuild``), those the
    run asked for (``Device.build``), and those of them it had to build itself (neither built
    nor pending when asked), as the run fills them in."""
    from satsweep.opencl import device as sdev

    forecast, asked, foreground = set(), set(), []
    real_build, real_prebuild = sdev.Device.build, sdev.Device.prebuild

    def build(self, source, defines=None):
        key = self._key(source, defines)
        asked.add(key)
        with self._lock:
            if key not in self._programs and key not in self._pending:
                foreground.append(key)
        return real_build(self, source, defines)

    def prebuild(self, requests):
        requests = list(requests)
        forecast.update(self._key(s, d) for s, d in requests)
        return real_prebuild(self, requests)

    monkeypatch.setattr(sdev.Device, "build", build)
    monkeypatch.setattr(sdev.Device, "prebuild", prebuild)
    return forecast, asked, foreground


@pytest.mark.parametrize("mrf, search", [("sgm", "coarse_to_fine"), ("sgm", "full"),
                                         ("none", "full")])
def test_programs_forecast_before_adjustment_are_those_the_sweep_builds(scene, tmp_path,
                                                                         monkeypatch, mrf,
                                                                         search):
    """The kernels prebuilt while the cameras are adjusted are exactly the ones the sweep stage
    then asks for (none built in the foreground, none built for nothing), bundle adjustment and
    skew correction included; with the coarse-to-fine search, its coarse pass's programs too."""
    forecast, asked, foreground = _record_builds(monkeypatch)
    res = _reconstruct(scene, tmp_path / "out", {**FAST_CAMERA, "reconstruct": {"adjust": "on"},
                                                 "mrf": {"method": mrf},
                                                 "sweep": {"search": search}})
    assert "skipped" not in res.report["ba"]
    # SGM over every plane (the windows of a coarse-to-fine search too), and for its coarse
    # pass over every coarse_plane_stride-th plane
    sgm_labels = {dict(k[1])["SGM_NL"] for k in asked if k[0] == "sgm"}
    planes = {v["planes"] for v in res.report["sweep"]}
    stride = PipelineConfig().sweep.coarse_plane_stride  # the default's
    counts = set() if mrf == "none" else planes | ({-(-n // stride) for n in planes}
                                                   if search == "coarse_to_fine" else set())
    want = {sgm_label_capacity(n) for n in counts}  # sgm.cl serves counts up to its capacity
    assert sgm_labels == want, (sgm_labels, planes)
    assert foreground == [] and forecast == asked, (foreground, forecast ^ asked)
    assert {k[0] for k in forecast} == ({"census", "sweep", "guided_filter", "sgm", "wta"}
                                        if mrf == "sgm" else {"census", "sweep", "guided_filter", "wta"})


# A stack of 7 views of 6 dates with their metadata (0.3 m pixels: finer than the DSM's
# cells): 7 references fused by the consensus, each map through the weighted median. On this
# seed the references' sources chosen with the dates' similarity and leaf states differ from
# those of the geometry alone (checked below), as on the issue-form stacks.
MULTIDATE_FORECAST = dict(seed=0, n_views=7, acquisitions=6, size_px=256, gsd_m=0.3, cell_m=0.15,
                          bias_px=1.0, max_off_nadir_deg=20.0)


def test_programs_forecast_on_a_multidate_stack_are_those_the_sweep_builds(tmp_path,
                                                                          monkeypatch):
    """On a stack of several dates the forecast chooses the references and their sources as
    the selection stage does (the dates' similarity and leaf states, known from the metadata
    before the images are compared): every program the sweep stage asks for (each source
    count's sweep, each plane count's SGM, the weighted median) was prebuilt, none for
    nothing."""
    from satsweep.dense import selection as sel
    from satsweep.synth.scene import SynthOptions, generate_scene

    scene = generate_scene(tmp_path / "scene", SynthOptions(**MULTIDATE_FORECAST))
    choices = []  # (with similarity, selection, geometry-only selection) per select_views call
    real_select = sel.select_views

    def select_views(cameras, **kwargs):
        got = real_select(cameras, **kwargs)
        alone = real_select(cameras, mid_height=kwargs["mid_height"], options=kwargs["options"])
        choices.append((kwargs.get("similarity") is not None, got, alone))
        return got

    monkeypatch.setattr(sel, "select_views", select_views)
    forecast, asked, foreground = _record_builds(monkeypatch)
    res = reconstruct([v.image for v in scene.views], scene.aoi, tmp_path / "out",
                      config=PipelineConfig(), verbose=False)
    assert res.report["dsm"]["fusion"] == "consensus"
    assert all(v["median_radius_px"] for v in res.report["sweep"])
    (f_sim, f_sel, f_alone), (r_sim, r_sel, _) = choices  # the forecast's, then the stage's
    assert f_sim and r_sim
    assert (f_sel.references, f_sel.sources) == (r_sel.references, r_sel.sources)
    assert (f_alone.references, f_alone.sources) != (r_sel.references, r_sel.sources)
    assert {k[0] for k in asked} >= {"sweep", "sgm", "median"}
    assert foreground == [] and forecast == asked, (foreground, forecast ^ asked)


@pytest.mark.parametrize("crown_rules", [True, False])
def test_the_consensus_takes_crowns_tops_from_views_of_dates(tmp_path, monkeypatch,
                                                             crown_rules):
    """On the stack of several dates above, the rule of ``[dsm] leaf_on_crowns`` gets the
    rasters of the references whose metadata date is in leaf (leaf_season >= LEAF_ON_SEASON),
    that of ``[dsm] crown_holes`` every reference's, each with its acquisition's pass, and the
    report counts the cells each changed; off, they do not run. Of 8-bit RGB images, ``[dsm]
    green_crowns`` gets every reference's raster and its vegetation index, leaves seen on the
    crowns; of grey images (with the rule on) it does not run."""
    from satsweep.dense.selection import LEAF_ON_SEASON
    from satsweep.products import fusion
    from satsweep.synth.scene import SynthOptions, generate_scene

    product = "rgb8" if crown_rules else "dn16"
    scene = generate_scene(tmp_path / "scene", SynthOptions(**MULTIDATE_FORECAST, product=product))
    calls = {}

    def recording(name):
        real = getattr(fusion, name)

        def record(fused, rasters, passes, **kwargs):
            out = real(fused, rasters, passes, **kwargs)
            calls.setdefault(name, []).append((len(rasters), list(passes), int(out[1].sum())))
            return out
        return record

    for name in ("leaf_on_crown_tops", "crown_hole_tops"):
        monkeypatch.setattr(fusion, name, recording(name))
    green_tops = fusion.green_crown_tops

    def record_green(fused, rasters, vegetation, **kwargs):
        out = green_tops(fused, rasters, vegetation, **kwargs)
        leafy = max(float(np.mean(np.asarray(v) >= fusion.VEGETATION_INDEX_MIN)) for v in vegetation)
        calls.setdefault("green_crown_tops", []).append((len(rasters), len(vegetation), leafy,
                                                         int(out[1].sum())))
        return out

    monkeypatch.setattr(fusion, "green_crown_tops", record_green)
    visibility = fusion.visibility_check_heights

    def record_visibility(heights, projections, **kwargs):
        green = kwargs["green"]
        calls.setdefault("visibility", []).append((
            kwargs["trusted_far_m"], list(kwargs["trusted_views"]), kwargs["bare_far_m"],
            list(kwargs["bare_views"]),
            None if green is None else [float(np.mean(g)) for g in green]))
        return visibility(heights, projections, **kwargs)

    monkeypatch.setattr(fusion, "visibility_check_heights", record_visibility)
    thin_minority = fusion.thin_raised_minority

    def record_thin(fused, count, n_views, **kwargs):
        out = thin_minority(fused, count, n_views, **kwargs)
        calls.setdefault("thin_raised_minority", []).append((n_views, kwargs["max_share"],
                                                             int(out.sum())))
        calls["thin_mask"] = out.copy()
        return out

    monkeypatch.setattr(fusion, "thin_raised_minority", record_thin)
    count_valleys = fusion.raised_count_valleys

    def record_valleys(fused, count, n_views, **kwargs):
        out = count_valleys(fused, count, n_views, **kwargs)
        calls.setdefault("raised_count_valleys", []).append((n_views, kwargs["min_share"], out))
        return out

    monkeypatch.setattr(fusion, "raised_count_valleys", record_valleys)
    config = PipelineConfig().override("dsm", leaf_on_crowns=crown_rules,
                                       crown_holes=crown_rules)
    res = reconstruct([v.image for v in scene.views], scene.aoi, tmp_path / "out",
                      config=config, verbose=False)
    rep = res.report
    assert rep["dsm"]["fusion"] == "consensus"
    # The free-space check trusts the references of dates in leaf from visibility_leaf_on_far_m
    # on: the scene's 0.3 m pixels are finer than the 0.5 m cells.
    (far_m, trusted, bare_far_m, bare, green), = calls.pop("visibility")
    seasons = {v["name"]: v["leaf_season"] for v in rep["view_selection"]["views"]}
    refs = [r["reference"] for r in rep["view_selection"]["references"]]
    # The thin raised cells' rule runs once on the consensus, over every reference.
    (n, share, thin), = calls.pop("thin_raised_minority")
    assert n == len(refs) and share == config.dsm.thin_raised_max_share > 0.0
    assert rep["dsm"]["thin_raised_cells"] == thin
    # ... and so does the rule of the counts' valleys; the report counts the cells it adds.
    (n, share, valleys), = calls.pop("raised_count_valleys")
    assert n == len(refs) and share == config.dsm.valley_min_share > 0.0
    assert rep["dsm"]["valley_cells"] == int((valleys & ~calls.pop("thin_mask")).sum())
    assert far_m == config.dsm.visibility_leaf_on_far_m > 0.0
    assert trusted == [seasons[r] is not None and seasons[r] >= LEAF_ON_SEASON for r in refs]
    assert any(trusted) and not all(trusted)
    assert rep["dsm"]["cross_check"]["leaf_on_fine"] == trusted
    # The references (all of fine pixels) matched with a source of their own pass see far past
    # the points their image does not show green, from visibility_bare_far_m on; grey images
    # show none, and the rule is off there.
    # The scene's own record of each view's acquisition (pass).
    acquisition = {v.image.name: v.acquisition for v in scene.views}
    same_date = [any(acquisition[s] == acquisition[r["reference"]] for s in r["sources"])
                 for r in rep["view_selection"]["references"]]
    assert bare == same_date == rep["dsm"]["cross_check"]["bare_views"]
    assert any(same_date) and not all(same_date), same_date  # the scene exercises both
    if product == "rgb8":
        assert bare_far_m == config.dsm.visibility_bare_far_m > 0.0
        assert len(green) == len(refs) and all(0.0 < g < 0.5 for g in green), green
    else:
        assert bare_far_m == 0.0 and green is None
    assert rep["dsm"]["cross_check"]["bare_far_m"] == bare_far_m
    if not crown_rules:
        assert calls == {}
        assert rep["dsm"]["leaf_on_crown_cells"] is None
        assert rep["dsm"]["crown_hole_cells"] is None
        assert rep["dsm"]["green_crown_cells"] is None  # no colour
        assert all(v["vegetation_share"] is None for v in rep["views"])
        return
    in_leaf = [r for r in refs if seasons[r] is not None and seasons[r] >= LEAF_ON_SEASON]
    assert len(in_leaf) >= 2  # the stack exercises the rule
    # The labels each rule gets must group the references as the scene's acquisitions do.

    def same_grouping(labels, names):
        return all((labels[i] == labels[j]) == (acquisition[a] == acquisition[b])
                   for i, a in enumerate(names) for j, b in enumerate(names))

    (n, passes, raised), = calls["leaf_on_crown_tops"]
    assert n == len(in_leaf) and None not in passes and same_grouping(passes, in_leaf)
    assert rep["dsm"]["leaf_on_crown_cells"] == raised
    (n, passes, filled), = calls["crown_hole_tops"]
    assert n == len(refs) and None not in passes and same_grouping(passes, refs)
    assert len(set(passes)) >= 2  # references of several passes
    assert rep["dsm"]["crown_hole_cells"] == filled
    (n, n_vegetation, leafy, raised), = calls["green_crown_tops"]
    assert n == n_vegetation == len(refs)
    assert leafy > 0.01  # some reference sees leaves
    assert rep["dsm"]["green_crown_cells"] == raised
    # Each view's share of vegetation pixels, against the index read again over its crop.
    from satsweep.io.images import read_vegetation_index

    for v in rep["views"]:
        x0, y0, w, h = v["crop"]
        index = read_vegetation_index(v["image"], window=(x0, y0, x0 + w, y0 + h))
        want = float(np.mean(index >= fusion.VEGETATION_INDEX_MIN))
        assert v["vegetation_share"] == pytest.approx(want, abs=1e-4)
    assert max(v["vegetation_share"] for v in rep["views"]) > 0.01


@pytest.mark.parametrize("from_colour", [True, False])
def test_leaf_state_from_colour_without_dates(tmp_path, from_colour):
    """A stack like the one above in 8-bit RGB without its metadata: no view has a date, so the
    selection's leaf state comes from the images' colour (``[views] leaf_from_colour``; report:
    ``leaf_season_from``), each view's the estimate from the index read again over its reported
    crop, and every view of a date whose deciduous crowns are green (the scene's own record:
    neither leafless nor autumn) ranks above every other. Off, the leaf state is unknown."""
    from satsweep.dense.similarity import leaf_state_from_vegetation
    from satsweep.io.images import read_vegetation_index
    from satsweep.synth.multidate import AUTUMN_LEAF_FACTOR
    from satsweep.synth.scene import SynthOptions, generate_scene

    # At Jacksonville's latitude (the default, Paris, has no winter dates with the sun high
    # enough), seed 2: two green dates (June, August), three of autumn, two leafless.
    options = dict(MULTIDATE_FORECAST, seed=2, product="rgb8", write_metadata=False,
                   location=(-81.66, 30.32))
    scene = generate_scene(tmp_path / "scene", SynthOptions(**options))
    # Without the sparse stage (the scene's range given), which at this size cannot tie the
    # December view to the others: every view reaches the selection.
    config = (PipelineConfig().override("views", leaf_from_colour=from_colour)
              .override("reconstruct", adjust="off"))
    rep = reconstruct([v.image for v in scene.views], scene.aoi, tmp_path / "out",
                      alt_range=_alt(scene), config=config, verbose=False).report
    selected = rep["view_selection"]
    assert len(selected["views"]) == len(scene.views)
    if not from_colour:
        assert selected["leaf_season_from"] is None
        assert all(v["leaf_season"] is None for v in selected["views"])
        return
    assert selected["leaf_season_from"] == "colour"
    indices = []
    for v in rep["views"]:
        x0, y0, w, h = v["crop"]
        indices.append(read_vegetation_index(v["image"], window=(x0, y0, x0 + w, y0 + h)))
    want = leaf_state_from_vegetation(indices)
    got = [v["leaf_season"] for v in selected["views"]]
    assert got == pytest.approx(want, abs=1e-9)
    factor = {Path(v.image).name: scene.acquisitions[v.acquisition].leaf_factor
              for v in scene.views}
    green = [s for v, s in zip(selected["views"], got)
             if factor[v["name"]] not in (0.0, AUTUMN_LEAF_FACTOR)]
    other = [s for v, s in zip(selected["views"], got)
             if factor[v["name"]] in (0.0, AUTUMN_LEAF_FACTOR)]
    assert green and other  # the stack has both
    assert min(green) > max(other)


def test_config_written_is_the_config_used(reconstruction):
    again = PipelineConfig.from_toml(reconstruction.out_dir / "config.toml")
    assert again == PipelineConfig.from_mapping(FAST_CAMERA)


def test_point_cloud_is_utm_with_colour_and_epsg(reconstruction, scene):
    ply = read_ply(reconstruction.out_dir / "cloud.ply")
    assert any(f"EPSG:{scene.dsm_grid.epsg}" in c for c in ply["comments"])
    x, y, z = ply["x"], ply["y"], ply["z"]
    assert x.dtype == np.float64 and len(x) > 1000
    with rasterio.open(scene.truth_dsm) as truth:
        b = truth.bounds
        lo, hi = scene.alt_range
    # the cloud covers the AOI's grid (the truth grid is the same AOI's)
    assert x.min() >= b.left - 0.5 and x.max() <= b.right + 0.5
    assert y.min() >= b.bottom - 0.5 and y.max() <= b.top + 0.5
    assert lo - ALT_MARGIN_M <= np.median(z) <= hi + ALT_MARGIN_M
    assert {"red", "green", "blue"} <= set(ply)


def test_existing_output_is_refused_and_left_untouched(scene, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    rc = main(["reconstruct", *map(str, (v.image for v in scene.views)), "--aoi", _aoi_arg(scene),
               "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "not empty" in err and "--overwrite" in err
    assert [p.name for p in out.iterdir()] == ["mine.txt"]


def test_failing_run_writes_nothing(scene, tmp_path):
    """A failure after the outputs' folder was created (here: a device that does not exist,
    found before any stage) removes what the run created."""
    out = tmp_path / "new"
    config = PipelineConfig.from_mapping({"reconstruct": {"device": "9:9"}})
    with pytest.raises(Exception):
        reconstruct([v.image for v in scene.views], scene.aoi, out, alt_range=_alt(scene),
                    config=config, verbose=False)
    assert not out.exists()


@pytest.mark.parametrize(
    "table, needle",
    [
        ({"sweep": {"gf_radius": -1}}, "SweepOptions.gf_radius"),
        ({"sweep": {"gf_radus": 3}}, "unknown key(s) gf_radus"),
        ({"sweeps": {}}, "unknown table(s) [sweeps]"),
        ({"mrf": {"method": "magic"}}, "MRFOptions.method"),
        ({"dsm": {"resolution": "half"}}, "DSMOptions.resolution"),
    ],
)
def test_config_errors_name_the_key(table, needle):
    with pytest.raises(OptionsError) as info:
        PipelineConfig.from_mapping(table, source="my.toml")
    assert needle in str(info.value)


def test_cli_overrides_the_config_file(tmp_path):
    from satsweep.cli import _pipeline_config, build_parser

    cfg = tmp_path / "c.toml"
    cfg.write_text('[mrf]\nmethod = "graphcut"\n[dsm]\nresolution = 1.0\n')
    args = build_parser().parse_args(["reconstruct", "a.tif", "b.tif", "--aoi", "0,0,1,1", "--out",
                                      "o", "--config", str(cfg), "--mrf", "none"])
    config = _pipeline_config(args)
    assert config.mrf.method == "none" and config.dsm.resolution == 1.0


def test_fixed_views_from_the_command_line_or_the_config(tmp_path):
    from satsweep.cli import _pipeline_config, build_parser

    cfg = tmp_path / "c.toml"
    cfg.write_text('[bundle]\nfixed_views = ["a.tif"]\n')
    base = ["reconstruct", "a.tif", "b.tif", "c.tif", "--aoi", "0,0,1,1", "--out", "o"]
    parse = build_parser().parse_args
    assert _pipeline_config(parse(base + ["--config", str(cfg)])).bundle.fixed_views == ("a.tif",)
    args = parse(base + ["--config", str(cfg), "--fixed-view", "b.tif", "--fixed-view", "c.tif"])
    assert _pipeline_config(args).bundle.fixed_views == ("b.tif", "c.tif")
    assert _pipeline_config(parse(base)).bundle.fixed_views == ()


def test_a_fixed_view_among_no_input_stops_the_run_first(scene, tmp_path):
    with pytest.raises(OptionsError, match="fixed_views: 'view_07.tif' names none of the views"):
        _reconstruct(scene, tmp_path / "out", {"bundle": {"fixed_views": ["view_07.tif"]}})
    assert not (tmp_path / "out").exists()


def test_cli_config_prints_the_explained_defaults(capsys):
    import tomllib

    assert main(["config"]) == 0
    text = capsys.readouterr().out
    assert PipelineConfig.from_mapping(tomllib.loads(text)) == PipelineConfig()
    lines = text.splitlines()
    for table, options in PipelineConfig().to_dict().items():
        for key, value in options.items():
            if value is None:
                continue
            # every key is preceded by its explanation (a comment line)
            at = next(i for i, line in enumerate(lines) if line.startswith(f"{key} = "))
            assert lines[at - 1].startswith("# "), key
    assert "# census bits the truncated intensity difference adds (AD-census)" in text


def test_cli_config_shows_and_checks_a_file(tmp_path, capsys):
    import tomllib

    cfg = tmp_path / "c.toml"
    cfg.write_text("[sweep]\nad_weight = 0.0\n")
    assert main(["config", "--config", str(cfg)]) == 0
    shown = tomllib.loads(capsys.readouterr().out)
    assert shown["sweep"]["ad_weight"] == 0.0 and shown["sweep"]["advanced"]["gf_radius"] == 5
    cfg.write_text("[sweep]\ngf_radius = 1000\n")
    assert main(["config", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert f"{cfg} [sweep]: SweepOptions.gf_radius = 1000" in err and err.count("\n") == 1


def _cli_error(capsys, args) -> str:
    rc = main(args)
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("satsweep: error:"), err
    return lines[0]


def _view_elsewhere(scene, folder: Path) -> Path:
    """The scene's view 1 with an RPC one degree of longitude east: a view of another place."""
    from satsweep.geometry.rpc import RPCModel
    from satsweep.geometry.rpc_formats import rpc_tiff_extratag
    from satsweep.io.geotiff import write_tiff
    from satsweep.io.images import read_image

    src = scene.views[1].image
    rpc = RPCModel.from_image(src)
    out = folder / f"elsewhere_{src.name}"
    folder.mkdir(parents=True, exist_ok=True)
    write_tiff(out, read_image(src),
               extratags=[rpc_tiff_extratag(rpc._replace(lon_offset=rpc.lon_offset + 1.0))])
    return out


def test_a_view_of_another_place_is_left_out_with_a_warning(scene, reconstruction, tmp_path):
    """An image whose RPC does not see the AOI (at its own heights) among others that do is left
    out, named in a warning and in report.json's inputs: the run is the one without it, to the
    bit. Alone with one other image, it stops the run with the error naming it."""
    elsewhere = _view_elsewhere(scene, tmp_path / "elsewhere")
    images = [v.image for v in scene.views]
    res = reconstruct([*images, elsewhere], scene.aoi, tmp_path / "out",
                      alt_range=_alt(scene), config=PipelineConfig.from_mapping(FAST_CAMERA),
                      verbose=False)
    rep = json.loads((res.out_dir / "report.json").read_text())
    (left,) = rep["inputs"]["left_out"]
    assert left["image"] == str(elsewhere) and "does not see the AOI" in left["reason"]
    assert [w["message"] for w in rep["warnings"]
            if str(elsewhere) in w["message"]] == [f"{left['reason']}: left out"]
    assert rep["inputs"]["images"] == [str(p) for p in [*images, elsewhere]]
    with rasterio.open(res.dsm_path) as a, rasterio.open(reconstruction.dsm_path) as b:
        np.testing.assert_array_equal(a.read(1), b.read(1))
    with pytest.raises(AOIError, match=f"{elsewhere.name}.*does not see the AOI"):
        reconstruct([images[0], elsewhere], scene.aoi, tmp_path / "two",
                    alt_range=_alt(scene), config=PipelineConfig.from_mapping(FAST_CAMERA),
                    verbose=False)
    assert not (tmp_path / "two").exists()


def test_an_rpc_whose_heights_miss_the_scene_is_kept_at_the_given_range():
    """Whether an image sees the AOI is asked at its RPC's own heights and at the range the user
    (or a DEM) gives: an RPC whose offset +- scale misses the scene is no view of another
    place when the given range sees it (stand-ins: footprints that meet the image only at
    heights above 2000 m)."""
    from satsweep.errors import AOIError
    from satsweep.pipeline.prepare import sources_seeing_the_aoi

    class Source:
        def __init__(self, name, alt_offset, alt_scale):
            self.path = self.name = name
            self.rpc = dataclasses.make_dataclass("R", ["alt_offset", "alt_scale"])(alt_offset,
                                                                                     alt_scale)

        def footprint(self, aoi, alt_range, warn_partial=True):
            if alt_range.max < 2000.0:  # the AOI lies in the image only at its true heights
                raise AOIError(f"{self.path}: does not see the AOI at {alt_range}")
            return 0, 0, 10, 10

    ok = [Source("a.tif", 2300.0, 500.0), Source("b.tif", 2300.0, 500.0)]
    low = Source("low.tif", 0.0, 500.0)  # its RPC's heights: -500..500 m
    config = PipelineConfig()
    kept, left = sources_seeing_the_aoi([*ok, low], "AOI", config)
    assert [s.name for s in kept] == ["a.tif", "b.tif"] and left[0]["image"] == "low.tif"
    kept, left = sources_seeing_the_aoi([*ok, low], "AOI", config,
                                        alt_range=AltitudeRange(2250.0, 2400.0))
    assert [s.name for s in kept] == ["a.tif", "b.tif", "low.tif"] and left == []


def test_cli_bad_inputs(scene, tmp_path, capsys):
    imgs = [str(v.image) for v in scene.views]
    aoi = _aoi_arg(scene)
    out = tmp_path / "out"
    not_tiff = tmp_path / "notes.tif"
    not_tiff.write_text("hello")
    fine_steps = tmp_path / "fine.toml"
    fine_steps.write_text("[camera]\ngrid_size = [20, 20, 6]\n[sweep]\nstep_px = 0.01\n")
    cases = [
        (["reconstruct", imgs[0], "--aoi", aoi, "--out", str(out)], "stereo needs at least 2 images"),
        (["reconstruct", str(Path(imgs[0]).parent), "--aoi", aoi, "--out", str(out)],
         f"{Path(imgs[0]).parent}: is a folder, not an image: give the images in it"),
        (["reconstruct", *imgs, "--aoi", "3,1,2,2", "--out", str(out)], "lon_min = 3.0 >= lon_max"),
        (["reconstruct", *imgs, "--aoi", aoi, "--alt-range", "200", "100", "--out", str(out)],
         "--alt-range 200 100"),
        (["reconstruct", str(not_tiff), imgs[1], "--aoi", aoi, "--alt-range", "90", "160", "--out",
          str(out)], "notes.tif"),
        (["reconstruct", *imgs, "--aoi", aoi, "--out", str(out), "--config", str(tmp_path / "no.toml")],
         "no.toml"),
        (["reconstruct", *imgs, "--aoi", aoi, "--out", str(out), "--device", "7:7"], "7:7"),
        # more planes than SGM takes (here from a tiny plane step): refused before the sweep
        (["reconstruct", *imgs, "--aoi", aoi, "--alt-range", "90", "170", "--out", str(out),
          "--config", str(fine_steps)], "more than SGM's 1024; give a tighter"),
    ]
    for args, needle in cases:
        line = _cli_error(capsys, args + ["--quiet"])
        assert needle in line, (args, line)
        assert not out.exists(), args


def test_demo_command(tmp_path, capsys):
    """The README's first command ends with `satsweep demo`: it must run and print the metrics."""
    rc = main(["demo", "--out", str(tmp_path / "demo"), "--size", "128", "--quiet",
               "--config", str(_fast_config(tmp_path))])
    out = capsys.readouterr().out
    assert rc == 0
    assert "median |error|" in out and "completeness_1m" in out
    assert (tmp_path / "demo" / "reconstruction" / "dsm.tif").is_file()
    assert (tmp_path / "demo" / "scene" / "truth_dsm.tif").is_file()
    with pytest.raises(OutputExistsError):
        from satsweep.demo import run_demo

        run_demo(tmp_path / "demo", verbose=False)


def _fast_config(tmp_path: Path) -> Path:
    path = tmp_path / "fast.toml"
    path.write_text("[camera]\ngrid_size = [20, 20, 6]\n")
    return path


def test_preloading_imports_the_listed_modules():
    """The background import of the later stages' libraries ends, with every one imported (a
    misspelt or missing module would stop the thread before the rest)."""
    import sys

    from satsweep.pipeline.preload import PRELOADED_MODULES, start_preloading

    thread = start_preloading()
    thread.join(timeout=120)
    assert not thread.is_alive() and thread.daemon
    assert all(name in sys.modules for name in PRELOADED_MODULES)


@pytest.mark.parametrize("n_references,fusion,narrow,gradient", [
    (NARROW_FILTER_MIN_REFERENCES, "auto", True, True),
    (NARROW_FILTER_MIN_REFERENCES - 1, "auto", False, True),
    (NARROW_FILTER_MIN_REFERENCES, "median", False, False), (12, "consensus", True, True),
    (3, "auto", False, False), (3, "consensus", False, True),
])
def test_many_references_of_a_consensus_are_swept_with_the_narrower_filter(n_references, fusion,
                                                                          narrow, gradient):
    config = PipelineConfig().override("dsm", fusion=fusion)
    mrf = area_mrf_options(config, n_references)
    want = config.mrf.sgm_consensus_gf_radius if narrow else config.mrf.sgm_sweep_gf_radius
    # ... and the height maps' weighted median (satsweep.dense.median) there, none elsewhere
    median = config.mrf.consensus_median_radius_m if narrow else 0.0
    assert mrf == config.mrf.replace(sgm_sweep_gf_radius=want, median_radius_m=median)
    assert config.mrf.sgm_consensus_gf_radius != config.mrf.sgm_sweep_gf_radius
    # and the gradient term of any area the consensus fuses (area_sweep_options)
    sweep = area_sweep_options(config, n_references)
    weight = config.sweep.consensus_grad_weight if gradient else config.sweep.grad_weight
    ring = (config.sweep.consensus_census_ring_weight if gradient
            else config.sweep.census_ring_weight)
    mask = (config.sweep.consensus_census_mask_threshold if gradient
            else config.sweep.census_mask_threshold)
    assert sweep == config.sweep.replace(grad_weight=weight, census_ring_weight=ring,
                                         census_mask_threshold=mask)
    assert config.sweep.consensus_grad_weight != config.sweep.grad_weight
    assert config.sweep.consensus_census_ring_weight != config.sweep.census_ring_weight
    assert config.sweep.consensus_census_mask_threshold != config.sweep.census_mask_threshold


@pytest.mark.parametrize("n_references,resolution,gsd_m,finer", [
    (NARROW_FILTER_MIN_REFERENCES, 0.5, 0.3, True),   # (0.5 / 0.3)^2 = 2.8 pixels per cell
    (NARROW_FILTER_MIN_REFERENCES, 0.5, 0.5, False),  # one pixel per cell
    (NARROW_FILTER_MIN_REFERENCES, 0.5, 0.36, False),  # 1.93 per cell: under the 2 of the rule
    (NARROW_FILTER_MIN_REFERENCES, 1.0, 0.5, True),
    (NARROW_FILTER_MIN_REFERENCES - 1, 0.5, 0.3, True),  # a consensus, no narrower filter
    (CONSENSUS_MIN_REFERENCES - 1, 0.5, 0.3, True),  # a median fusion: the area's options
])
def test_references_finer_than_the_cells_sweep_without_the_filter_and_weigh_the_ring(
        n_references, resolution, gsd_m, finer):
    """A reference of pixels finer than the DSM's cells: no cost filter where the area narrows
    it, the census's ring weighted more and windows of one pixel after blocks wherever the
    area makes a consensus; any other reference takes the area's options
    (reference_options)."""
    config = PipelineConfig().override("dsm", resolution=resolution)
    area_mrf = area_mrf_options(config, n_references)
    area_sweep = area_sweep_options(config, n_references)
    sweep, mrf = reference_options(config, area_sweep, area_mrf, n_references, gsd_m)
    dense_mrf = finer and n_references >= NARROW_FILTER_MIN_REFERENCES
    want = config.mrf.sgm_dense_consensus_gf_radius if dense_mrf else area_mrf.sgm_sweep_gf_radius
    assert mrf == area_mrf.replace(sgm_sweep_gf_radius=want)
    dense_sweep = finer and n_references >= CONSENSUS_MIN_REFERENCES
    ring = (config.sweep.dense_consensus_census_ring_weight if dense_sweep
            else area_sweep.census_ring_weight)
    fallback = (config.sweep.dense_consensus_window_pixel_fallback if dense_sweep
                else area_sweep.window_pixel_fallback)
    assert sweep == area_sweep.replace(census_ring_weight=ring, window_pixel_fallback=fallback)
    # the rules change something
    assert (config.sweep.dense_consensus_window_pixel_fallback
            != config.sweep.window_pixel_fallback)
    assert config.mrf.sgm_dense_consensus_gf_radius != config.mrf.sgm_consensus_gf_radius
    assert (config.sweep.dense_consensus_census_ring_weight
            != config.sweep.consensus_census_ring_weight)
    for bad in (0.0, float("nan")):
        with pytest.raises(InputError, match="ground sample distance"):
            reference_options(config, area_sweep, area_mrf, n_references, bad)


def test_consensus_fusion_writes_the_count_of_agreeing_views(scene, tmp_path):
    """With the consensus, every measured cell is the agreement of at least consensus_min_views
    reference views, as count.tif says; the others have no height or an interpolated one."""
    result = _reconstruct(scene, tmp_path / "out", {**FAST_CAMERA, "dsm": {"fusion": "consensus"}})
    assert result.report["dsm"]["fusion"] == "consensus"
    # a consensus of 3 references: too few for the narrower filter (area_mrf_options), but
    # swept with the consensus's gradient term (area_sweep_options)
    assert all(v["mrf"]["sweep_gf_radius"] == MRFOptions().sgm_sweep_gf_radius
               and v["mrf"]["sweep_grad_weight"] == SweepOptions().consensus_grad_weight
               and v["mrf"]["sweep_census_ring_weight"]
               == SweepOptions().consensus_census_ring_weight
               and v["mrf"]["sweep_census_mask_threshold"]
               == SweepOptions().consensus_census_mask_threshold
               for v in result.report["sweep"])
    out = result.out_dir
    with rasterio.open(out / "count.tif") as c, rasterio.open(out / "interpolated.tif") as m:
        count, flags = c.read(1), m.read(1)
    assert set(np.unique(count)) <= {0, 1, 2}
    np.testing.assert_array_equal(flags == 0, count >= 2)  # measured = two views agreeing
    _check_accuracy(result)


def test_stages_in_threads_give_the_sequential_result(scene, reconstruction, tmp_path,
                                                     monkeypatch):
    """The skew correction shears the views, and the DSM stage checks its references' height maps
    against each other, in threads (a view each): the same DSM, counts and cloud as one thread
    gives."""
    import satsweep.geometry.skew as skew
    import satsweep.products.fusion as fusion

    monkeypatch.setattr(skew, "SKEW_THREADS_MAX", 1)
    monkeypatch.setattr(fusion, "FUSION_THREADS_MAX", 1)
    alone = _reconstruct(scene, tmp_path / "out", FAST_CAMERA)
    assert alone.report["dsm"]["cross_check"] == reconstruction.report["dsm"]["cross_check"]
    for name in ("dsm.tif", "confidence.tif", "count.tif", "ortho.tif"):
        with rasterio.open(alone.out_dir / name) as a, \
                rasterio.open(reconstruction.out_dir / name) as b:
            np.testing.assert_array_equal(a.read(), b.read(), err_msg=name)
    np.testing.assert_array_equal(read_ply(alone.out_dir / "cloud.ply")["vertex"],
                                  read_ply(reconstruction.out_dir / "cloud.ply")["vertex"])


def test_the_height_maps_median_is_applied_and_reported(scene, reconstruction, tmp_path):
    """``[mrf] median_radius_m`` set: each reference's map takes the weighted median, its window
    in pixels of the view's ground sample distance (the scene's 0.5 m pixels, 0.5-0.6 m on the
    ground off nadir: 1 m is 2 px), and the result stays as accurate; by default two references
    make no consensus and run no median (the reconstruction fixture)."""
    result = _reconstruct(scene, tmp_path / "out", {**FAST_CAMERA, "mrf": {"median_radius_m": 1.0}})
    assert [v["median_radius_px"] for v in result.report["sweep"]] == [2, 2]
    assert [v["median_radius_px"] for v in reconstruction.report["sweep"]] == [None, None]
    _check_accuracy(result)


def test_a_median_wider_than_the_kernel_says_so(scene, tmp_path):
    """A median radius past the kernel's largest window (MEDIAN_MAX_RADIUS_PX) is not taken
    silently: the report's warnings name each reference and the radius used."""
    from satsweep.dense.median import MEDIAN_MAX_RADIUS_PX

    wide = 2.0 * MEDIAN_MAX_RADIUS_PX * 0.5  # twice the kernel's reach on 0.5 m pixels
    result = _reconstruct(scene, tmp_path / "out", {**FAST_CAMERA, "mrf": {"median_radius_m": wide}})
    sweeps = result.report["sweep"]
    assert [v["median_radius_px"] for v in sweeps] == [MEDIAN_MAX_RADIUS_PX] * len(sweeps)
    said = [w["message"] for w in result.report["warnings"] if "weighted median" in w["message"]]
    assert len(said) == len(sweeps)
    assert all(f"reaches {MEDIAN_MAX_RADIUS_PX} px" in m for m in said)
    assert {m.split(":")[0] for m in said} == {v["reference"] for v in sweeps}


@pytest.mark.parametrize("tie_range,warned", [
    ((-65.0, -25.0), True), ((253.0, 294.0), True),
    ((148.0, 184.0), True),  # shares 17 of its 36 m with the RPCs' range
    ((89.0, 161.0), False), ((95.0, 165.0), False), ((100.0, 140.0), False),
])
def test_a_tie_point_range_outside_the_rpcs_is_a_doubtful_warning(tie_range, warned):
    from satsweep.pipeline.altitude import range_outside_prior

    prior = AltitudeRange(95.0, 165.0)
    message = range_outside_prior(AltitudeRange(*tie_range), prior, 2)
    assert (message is not None) == warned
    if warned:
        assert f"{tie_range[0]:.0f}..{tie_range[1]:.0f} m" in message and "95..165 m" in message
        assert "--alt-range" in message and "two views" in message
        assert "two views" not in range_outside_prior(AltitudeRange(*tie_range), prior, 5)


def _stub_sparse(cameras, kept, corrections):
    """What pointing_gauge_doubt reads of a SparseResult: the views kept, their corrections,
    cameras and tie points (one, at the origin) and the paths."""
    from types import SimpleNamespace

    tied = SimpleNamespace(kept=tuple(kept), cameras=tuple(cameras), points=np.zeros((1, 3)))
    return SimpleNamespace(tied=tied, corrections_px=np.asarray(corrections, float),
                           paths=tuple(f"/data/view_{v}.tif" for v in range(len(cameras))))


def test_two_views_far_off_leave_the_scene_in_doubt():
    """Two tied views, one corrected by tens of pixels: a doubtful warning naming it, with the
    smallest motion of the scene that would make its RPC right: the motion dX0 that made its
    correction, less its part along the view's line of sight (which moves nothing in that
    view), from finite differences of the camera, not the adjustment's Jacobians. Small
    corrections, or three views (the gauge of most views), give none."""
    from satsweep.pipeline.altitude import GAUGE_DOUBT_PX, pointing_gauge_doubt
    from tests.synthetic_cameras import three_cameras

    cams = three_cameras()

    def project(P, X):
        h = P @ np.append(X, 1.0)
        return h[:2] / h[2]

    P0 = np.asarray(cams[0].P)
    A0 = np.column_stack([(project(P0, 1e-3 * e) - project(P0, -1e-3 * e)) / 2e-3
                          for e in np.eye(3)])
    dX0 = np.array([8.0, -6.0, 25.0])
    s0 = A0 @ dX0
    assert np.abs(s0).max() > GAUGE_DOUBT_PX
    message = pointing_gauge_doubt(_stub_sparse(cams[:2], [0, 1], [s0, [0.0, 0.0]]))
    ray = np.cross(A0[0], A0[1])  # the direction that view 0 does not see
    ray /= np.linalg.norm(ray)
    expected = np.linalg.norm(dX0 - (dX0 @ ray) * ray)
    assert message is not None and "view_0.tif, view_1.tif" in message
    assert f"view_0.tif's pointing correction is {s0[0]:+.1f}, {s0[1]:+.1f} px" in message
    assert f"its DSM may lie {expected:.0f} m or more" in message
    assert pointing_gauge_doubt(_stub_sparse(cams[:2], [0, 1], [[2.0, -3.0], [1.0, 4.0]])) is None
    assert pointing_gauge_doubt(_stub_sparse(cams, [0, 1, 2], [s0, [0.0, 0.0], [0.0, 0.0]])) is None


def test_tie_and_range_gives_its_doubts_once_where_the_run_reports(scene, monkeypatch, caplog):
    """A tie-point range outside the RPCs' is a doubtful warning given by tie_and_range itself:
    in the run's report when there is one, logged without (satsweep cameras), and not at all
    when choose_altitude_range only measures the range (the range-end warning's figure)."""
    import dataclasses
    import logging

    import satsweep.pipeline.prepare as prepare
    from satsweep.io.sources import open_sources
    from satsweep.pipeline.altitude import choose_altitude_range, tie_and_range

    real = prepare.tie_sources

    def far_off(*args, **kwargs):  # the scene moved 5 km up by the adjustment's gauge
        result = real(*args)  # (the stub report below times no stage)
        rng = result.altitude_range
        return dataclasses.replace(result, altitude_range=AltitudeRange(rng.min + 5e3,
                                                                        rng.max + 5e3))

    monkeypatch.setattr(prepare, "tie_sources", far_off)

    class Report:
        def __init__(self):
            self.warnings = []

        def warn(self, message, *, doubtful=False):
            self.warnings.append((message, doubtful))

    config = PipelineConfig()
    sources = open_sources([v.image for v in scene.views])
    report = Report()
    tied = tie_and_range(sources, scene.aoi, alt_range=None, dem=None, config=config,
                         adjust=False, report=None)
    assert tied.altitude.doubt is not None
    assert [r.getMessage() for r in caplog.records
            if r.levelno == logging.WARNING] == [tied.altitude.doubt]
    caplog.clear()
    choice = choose_altitude_range(sources, scene.aoi, alt_range=None, dem=None, config=config)
    assert choice.doubt == tied.altitude.doubt and not caplog.records
    tied = tie_and_range(sources, scene.aoi, alt_range=None, dem=None, config=config,
                         adjust=False, report=report)
    assert report.warnings == [(tied.altitude.doubt, True)]
