"""Multi-date synthetic scenes (satsweep synth --acquisitions): acquisitions and their sun, the
metadata files against scene.json (read back through GDAL too), the radiometry applied, the
transients and seasons absent from the truth, pointing biases, options, the CLI, and the
realism check: a cross-date pair degrades where a same-date pair of the same geometry does not."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math
import re
import shutil

import numpy as np
import pytest
import rasterio
import tifffile

from satsweep.cli import main as cli_main
from satsweep.errors import OptionsError
from satsweep.geometry.rpc import RPCModel
from satsweep.io.images import read_image
from satsweep.synth.multidate import (
    PASS_STEP_S,
    TAG_GDAL_METADATA,
    parse_iso_utc,
    radiometric_dn,
    solar_position,
)
from satsweep.synth.scene import (
    DN_MAX,
    DN_PER_RADIANCE,
    MULTIDATE_FIELDS,
    RGB8_CHANNELS,
    RGB8_GREEN,
    SCENE_FILE,
    Scene,
    SynthOptions,
    design_scene,
    generate_scene,
    render_radiance,
    render_radiance_greenness,
    truth_dsm,
)
from satsweep.synth.town import (
    GRASS_GREENNESS,
    PLAZA,
    ROAD,
    TREE,
    TREE_GREENNESS,
    ShadowMap,
    build_surface,
    sun_vector,
)
from tools.diag_multidate_pairs import (
    CROSS_DATE_PAIR,
    SAME_DATE_PAIR,
    pair_scene_options,
    reconstruct_pair,
)

# Five views in three acquisitions (2 + 1 + 2), a large pointing error on one view.
MD = SynthOptions(seed=5, n_views=5, acquisitions=3, views_per_acquisition=(2, 1, 2), size_px=128, gsd_m=1.0,
                  bias_px=1.0, large_bias_px=12.0, max_off_nadir_deg=20.0)

# The metadata round angles to 0.1 degree (as DigitalGlobe's IMD files do); the sun is rendered
# at the rounded value, the satellite's angles are exact in scene.json.
METADATA_ROUNDING_DEG = 0.05 + 1e-9
# A textbook sun position (Cooper's declination, the 9.87/7.53/1.5 equation of time) agrees with
# NOAA's series within 1.4 degrees at mid latitudes in the morning (measured: 1.38 in elevation,
# 0.90 in azimuth over a year at latitude 48.85, 10:00-11:15 local time).
SUN_REFERENCE_TOL_DEG = 1.5
# Solar noon at the June solstice: elevation 90 - latitude + obliquity (23.44 degrees), to the
# accuracy of NOAA's series and of the solstice's date (0.3 degree).
SOLSTICE_TOL_DEG = 0.3
# Acquisitions on different dates: at least one pair of them has suns this far apart.
MIN_SUN_CHANGE_DEG = 3.0
# The RPC written beside a view is its exact camera shifted by the bias, to the fit's residual
# (a few 1e-9 px).
RPC_TOL_PX = 1e-6
# Re-rendered DN against the file: the noise (noise_dn) and the rounding (1/12 DN^2); the mean
# of thousands of residuals within 0.5 DN, their spread within 5 % of the noise.
RESIDUAL_MEAN_TOL_DN = 0.5
RESIDUAL_STD_REL_TOL = 0.05
# Rendering the truth surface (no date changes), or leaving out the radiometry, misses the file by
# far more than the noise (RMS).
MIN_DATE_CHANGE_RMS_DN = 3.0 * 6.0
# Transients are recorded to the millimetre.
TRANSIENT_TOL_M = 2e-3
# The lowest transient (a car's cabin) stands this far above the road it is parked on.
MIN_TRANSIENT_HEIGHT_M = 1.3

# Realism check (tools/diag_multidate_pairs.py): seed 3 at 192 px, views 0 and 1 on 2019-02-28
# (sun 30.5/158.2 deg, trees leafless), view 2 on 2019-09-05 (43.3/144.9, leaves) with view 0's
# angles. Measured: completeness within 1 m 84.4 % for the same-date pair, 57.9 % for the
# cross-date one (a drop of 26.5 points; seeds 0-7 dropped 4 to 28 points, 15 on average); with
# no date effects (the control: only the noise differs) 83.9 % and 86.2 % (seeds 0-7: gaps of
# -4.4 to +0.2 points). A pair's completeness at this size moves by itself: the same-date
# control pair gave 84.0%, 80.3% and 80.9% with plane steps of 0.50, 0.49 and 0.48 px, and
# 80.5% / 84.0% with and without a bundle adjustment that moved the principal points by
# 0.003 px; so the control's gap is bounded at 10 points (the date's drop is 15 or more).
REALISM_SEED = 3
REALISM_SIZE_PX = 192
MIN_DATE_DROP = 0.15
MAX_CONTROL_GAP = 0.10


@pytest.fixture(scope="module")
def md(tmp_path_factory) -> Scene:
    return generate_scene(tmp_path_factory.mktemp("multidate") / "scene", MD)


@pytest.fixture(scope="module")
def md_truth(md):
    return md.surface()


@pytest.fixture(scope="module")
def realism_scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("realism")
    return {name: generate_scene(root / name, pair_scene_options(REALISM_SEED, REALISM_SIZE_PX, effects))
            for name, effects in (("all", SynthOptions().date_effects), ("none", ()))}


def _read_imd(path) -> tuple[dict, dict]:
    """(top-level fields, IMAGE_1 fields) of an IMD file, checking its group structure."""
    top, image, group = {}, {}, None
    lines = path.read_text(encoding="ascii").splitlines()
    assert lines[-1] == "END;"
    for line in lines[:-1]:
        line = line.strip()
        if line.startswith("BEGIN_GROUP = "):
            assert group is None
            group = line.split("= ")[1]
            continue
        if line.startswith("END_GROUP = "):
            assert line.split("= ")[1] == group
            group = None
            continue
        m = re.fullmatch(r'(\w+) = "?([^";]*)"?;', line)
        assert m, f"{path.name}: not DigitalGlobe syntax: {line!r}"
        (image if group == "IMAGE_1" else top)[m.group(1)] = m.group(2)
    assert group is None
    return top, image


# -- acquisitions, dates and the sun -----------------------------------------------------------
def test_views_of_an_acquisition_share_date_and_sun_and_acquisitions_differ(md):
    doc = json.loads(md.scene_file.read_text())
    assert [len(a.views) for a in md.acquisitions] == list(MD.views_per_acquisition)
    assert [k for a in md.acquisitions for k in a.views] == list(range(MD.n_views))
    start = dt.date.fromisoformat(MD.start_date)
    days = []
    for acq in md.acquisitions:
        when = parse_iso_utc(acq.date_time)
        days.append(when.date())
        assert 0 <= (when.date() - start).days < MD.date_span_days + 1
        for pos, k in enumerate(acq.views):
            v = doc["views"][k]
            assert v["acquisition"] == acq.index == md.views[k].acquisition
            assert (v["sun_elevation_deg"], v["sun_azimuth_deg"]) == (acq.sun_elevation_deg, acq.sun_azimuth_deg)
            assert parse_iso_utc(v["date_time"]) == when + dt.timedelta(seconds=PASS_STEP_S * pos)
            assert v["orbit_azimuth_deg"] == acq.orbit_azimuth_deg
        assert acq.sun_elevation_deg >= MD.min_sun_elevation_deg
        # The sun of the date and time, from a textbook formula independent of the generator's.
        lon, lat = MD.location
        el, az = _reference_sun(lon, lat, when)
        assert acq.sun_elevation_deg == pytest.approx(el, abs=SUN_REFERENCE_TOL_DEG)
        assert acq.sun_azimuth_deg == pytest.approx(az, abs=SUN_REFERENCE_TOL_DEG)
    assert days == sorted(days) and len(set(days)) == len(days)
    suns = [(a.sun_elevation_deg, a.sun_azimuth_deg) for a in md.acquisitions]
    assert max(abs(a[0] - b[0]) + abs(a[1] - b[1]) for a in suns for b in suns) > MIN_SUN_CHANGE_DEG
    # Each date has transients of its own.
    boxes = [{(t["e0"], t["n0"]) for t in a.transients} for a in md.acquisitions]
    assert all(len(b) > 10 for b in boxes)
    assert all(len(boxes[i] & boxes[j]) < 0.5 * min(len(boxes[i]), len(boxes[j]))
               for i in range(len(boxes)) for j in range(i + 1, len(boxes)))
    assert Scene.load(md.directory) == md


def _reference_sun(lon: float, lat: float, when: dt.datetime) -> tuple[float, float]:
    n = when.timetuple().tm_yday
    decl = math.radians(23.45) * math.sin(math.radians(360.0 / 365.0 * (284 + n)))
    b = math.radians(360.0 / 364.0 * (n - 81))
    eot_min = 9.87 * math.sin(2 * b) - 7.53 * math.cos(b) - 1.5 * math.sin(b)
    solar_h = when.hour + when.minute / 60 + when.second / 3600 + lon / 15.0 + eot_min / 60.0
    h = math.radians(15.0 * (solar_h - 12.0))
    p = math.radians(lat)
    # The sun's unit vector in east/north/up.
    e = -math.cos(decl) * math.sin(h)
    nn = math.cos(p) * math.sin(decl) - math.sin(p) * math.cos(decl) * math.cos(h)
    u = math.sin(p) * math.sin(decl) + math.cos(p) * math.cos(decl) * math.cos(h)
    return math.degrees(math.asin(u)), math.degrees(math.atan2(e, nn)) % 360.0


def test_solar_position_at_the_solstice_noon():
    lat = 48.85
    # Solar noon at longitude 0 on 2019-06-21 is at 12:00 minus the equation of time (-1.7 min);
    # the azimuth turns by 0.53 degree a minute then.
    noon = dt.datetime(2019, 6, 21, 12, 1, 40)
    el, az = solar_position(lon=0.0, lat=lat, when=noon)
    assert el == pytest.approx(90.0 - lat + 23.44, abs=SOLSTICE_TOL_DEG)
    assert az == pytest.approx(180.0, abs=1.0)
    el, az = solar_position(lon=0.0, lat=-lat, when=noon)
    assert el == pytest.approx(90.0 - lat - 23.44, abs=SOLSTICE_TOL_DEG)
    assert az == pytest.approx(0.0, abs=1.0) or az == pytest.approx(360.0, abs=1.0)


# -- metadata ----------------------------------------------------------------------------------
def test_imd_and_gdal_metadata_match_scene_json_and_gdal_reads_them(md, tmp_path):
    doc = json.loads(md.scene_file.read_text())
    for view, v in zip(md.views, doc["views"]):
        assert view.metadata_file == md.directory / v["metadata"]["imd"] == view.image.with_suffix(".IMD")
        top, image = _read_imd(view.metadata_file)
        assert image["satId"] == "SYNTH"
        assert image["firstLineTime"] == v["date_time"].replace("Z", ".000000Z")
        assert float(image["meanSunAz"]) == pytest.approx(v["sun_azimuth_deg"], abs=METADATA_ROUNDING_DEG)
        assert float(image["meanSunEl"]) == pytest.approx(v["sun_elevation_deg"], abs=METADATA_ROUNDING_DEG)
        assert float(image["meanSatAz"]) == pytest.approx(v["satellite_azimuth_deg"], abs=METADATA_ROUNDING_DEG)
        assert float(image["meanSatEl"]) == pytest.approx(90.0 - v["incidence_deg"], abs=METADATA_ROUNDING_DEG)
        assert float(image["meanOffNadirViewAngle"]) == pytest.approx(v["off_nadir_deg"], abs=METADATA_ROUNDING_DEG)
        assert (int(top["numRows"]), int(top["numColumns"])) == (v["height"], v["width"])
        # The TIFF tag, alone (the IMD moved away) and read by GDAL into its IMAGERY domain.
        alone = tmp_path / view.image.name
        shutil.copy(view.image, alone)
        with rasterio.open(alone) as ds:
            tags = ds.tags(ns="IMAGERY")
        assert tags == {"ACQUISITIONDATETIME": v["date_time"], "SUN_AZIMUTH": f"{v['sun_azimuth_deg']:.1f}",
                        "SUN_ELEVATION": f"{v['sun_elevation_deg']:.1f}", "SATELLITEID": "SYNTH"}
        # With the IMD beside it GDAL's DigitalGlobe reader takes the date and satellite from it.
        with rasterio.open(view.image) as ds:
            assert ds.tags().get("METADATATYPE") == "DG"
            dg = ds.tags(ns="IMAGERY")
        assert dg["ACQUISITIONDATETIME"] == v["date_time"].replace("T", " ").rstrip("Z")
        assert dg["SATELLITEID"] == "SYNTH"
        # The RPC is still read from the image (the IMD is no RPC sidecar).
        assert RPCModel.from_image(view.image) == RPCModel.from_file(view.rpc_file)


def test_without_metadata_neither_sidecar_nor_tag(realism_scenes, tmp_path):
    scene = realism_scenes["all"]  # generated with write_metadata=False
    assert not list(scene.directory.glob("*.IMD"))
    doc = json.loads(scene.scene_file.read_text())
    for view, v in zip(scene.views, doc["views"]):
        assert view.metadata_file is None and v["metadata"] is None
        assert "date_time" in v and "radiometry" in v  # the truth is in scene.json either way
        with tifffile.TiffFile(view.image) as tif:
            assert TAG_GDAL_METADATA not in tif.pages[0].tags
    # Single-date scenes have none either, and their scene.json no multi-date field.
    single = generate_scene(tmp_path / "single", SynthOptions(n_views=1, size_px=48, gsd_m=1.0))
    assert sorted(p.name for p in single.directory.iterdir()) == [
        SCENE_FILE, "truth_dsm.tif", "view_00.tif", "view_00_RPC.TXT"]
    sdoc = json.loads(single.scene_file.read_text())
    assert not set(MULTIDATE_FIELDS) & set(sdoc["options"]) and "acquisitions" not in sdoc
    assert "acquisition" not in sdoc["views"][0] and "sun" in sdoc
    with tifffile.TiffFile(single.views[0].image) as tif:
        assert TAG_GDAL_METADATA not in tif.pages[0].tags
    assert Scene.load(single.directory) == single


# -- what the images show ----------------------------------------------------------------------
def test_views_show_their_date_with_the_declared_radiometry(md, md_truth):
    k = max(range(MD.n_views), key=lambda i: math.hypot(*md.views[i].bias_px))  # the large-bias view
    view = md.views[k]
    acq = md.acquisitions[view.acquisition]
    assert (view.gain, view.offset_dn, view.gamma) != (1.0, 0.0, 1.0)
    rows = (40, 88)
    image = read_image(view.image)[rows[0]:rows[1]].astype(np.float64)

    def residual(surface, sun_el, sun_az, gain, offset, gamma):
        shadows = ShadowMap(surface, sun_vector(elevation_deg=sun_el, azimuth_deg=sun_az))
        rad = render_radiance(surface, shadows, view.camera, supersampling=MD.supersampling, rows=rows)
        model = radiometric_dn(rad, gain=gain, offset_dn=offset, gamma=gamma, dn_per_radiance=DN_PER_RADIANCE,
                               dn_max=DN_MAX)
        ok = (model > 0.5) & (model < DN_MAX - 0.5)  # not clipped
        return (image - model)[ok]

    day = md.acquisition_surface(view.acquisition, grid=md_truth)
    r = residual(day, acq.sun_elevation_deg, acq.sun_azimuth_deg, view.gain, view.offset_dn, view.gamma)
    assert r.size > 0.9 * image.size
    assert abs(r.mean()) < RESIDUAL_MEAN_TOL_DN
    assert r.std() == pytest.approx(math.sqrt(MD.noise_dn ** 2 + 1.0 / 12.0), rel=RESIDUAL_STD_REL_TOL)
    # Without the date's radiometry, or without its surface, the image is not explained.
    def rms(r):
        return float(np.sqrt(np.mean(r ** 2)))
    assert rms(residual(day, acq.sun_elevation_deg, acq.sun_azimuth_deg, 1.0, 0.0, 1.0)) > MIN_DATE_CHANGE_RMS_DN
    assert rms(residual(md_truth, acq.sun_elevation_deg, acq.sun_azimuth_deg, view.gain, view.offset_dn,
                        view.gamma)) > MIN_DATE_CHANGE_RMS_DN


def test_transients_and_seasons_are_in_the_images_not_in_the_truth(md, md_truth):
    for acq in md.acquisitions:
        day = md.acquisition_surface(acq.index, grid=md_truth)
        t = acq.transients
        e = np.array([0.5 * (x["e0"] + x["e1"]) for x in t])
        n = np.array([0.5 * (x["n0"] + x["n1"]) for x in t])
        top = np.array([x["top_u"] for x in t])
        assert np.max(np.abs(day.height(e=e, n=n) - top)) < TRANSIENT_TOL_M
        truth_h = md_truth.height(e=e, n=n)
        assert np.all(top - truth_h > MIN_TRANSIENT_HEIGHT_M)
        cars = np.array([x["kind"] != "stall" for x in t])
        j, i, _ = md_truth.cell_of(e=e[cars], n=n[cars])
        assert np.all(md_truth.material[j, i] == ROAD)
        # Apart from the transients and the trees, the surface is the truth's.
        changed = day.top != md_truth.top
        assert np.any(changed)
        assert np.all(np.isin(md_truth.material[changed], [ROAD, PLAZA, TREE]))
    # Leafless crowns (the first acquisition is in February) let cells of the ground through.
    winter = md.acquisitions[0]
    assert winter.leaf_density < 1.0
    day = md.acquisition_surface(winter.index, grid=md_truth)
    ut = md_truth.under_trees
    through = day.top[ut.j, ut.i] == ut.top
    assert 0.3 * (1 - winter.leaf_density) < through.mean() <= 1 - winter.leaf_density + 0.01


def test_truth_is_the_single_date_truth(realism_scenes):
    scene = realism_scenes["all"]
    o = scene.options
    single = SynthOptions(seed=o.seed, n_views=o.n_views, size_px=o.size_px, gsd_m=o.gsd_m,
                          off_nadir_deg=o.off_nadir_deg, azimuth_deg=o.azimuth_deg)
    d = design_scene(single)
    assert d.world == scene.world and d.aoi_half_m == scene.aoi_half_m
    grid = build_surface(seed=o.seed, e_min=d.world[0], n_min=d.world[1], e_max=d.world[2], n_max=d.world[3],
                         cell_m=o.cell_m, aoi_half_m=d.aoi_half_m)
    expected = truth_dsm(grid, scene.frame, scene.dsm_grid).astype(np.float32)
    for s in realism_scenes.values():
        with rasterio.open(s.truth_dsm) as ds:
            assert np.array_equal(ds.read(1), expected)


def test_pointing_biases_small_and_large(md, md_truth):
    biases = np.array([v.bias_px for v in md.views])
    assert np.all(biases[0] == 0.0)
    big = np.hypot(biases[:, 0], biases[:, 1]) > math.sqrt(2) * MD.bias_px
    assert big.sum() == round(MD.large_bias_fraction * (MD.n_views - 1))
    size = np.hypot(biases[big, 0], biases[big, 1])
    assert np.all(size >= 0.5 * MD.large_bias_px - math.sqrt(2) * MD.bias_px)
    assert np.all(size <= MD.large_bias_px + math.sqrt(2) * MD.bias_px)
    rng = np.random.default_rng(4)
    a = md.aoi_half_m
    e, n = rng.uniform(-a, a, (2, 300))
    u = md_truth.height(e=e, n=n)
    lon, lat, alt = md.frame.to_geodetic(e=e, n=n, u=u)
    for view in md.views:
        col, row = view.camera.project(e=e, n=n, u=u)
        rc, rr = view.rpc().projection(lon=lon, lat=lat, alt=alt)
        assert np.max(np.hypot(rc + view.bias_px[0] - col, rr + view.bias_px[1] - row)) < RPC_TOL_PX
        # The AOI lies inside the image where the RPC puts it too (room for the error).
        corners = np.array([md.aoi.lon_min, md.aoi.lon_max]), np.array([md.aoi.lat_min, md.aoi.lat_max])
        cc, cr = view.rpc().projection(lon=corners[0][[0, 1, 1, 0]], lat=corners[1][[0, 0, 1, 1]],
                                       alt=np.full(4, md.alt_range[0]))
        assert np.all((cc >= 0) & (cc <= MD.size_px - 1) & (cr >= 0) & (cr <= MD.size_px - 1))


# -- options, determinism, CLI -----------------------------------------------------------------
def test_multidate_options_are_checked_naming_the_field():
    for kwargs, field in (
        (dict(n_views=7, acquisitions=2), "acquisitions"),
        (dict(n_views=3, acquisitions=4), "acquisitions"),
        (dict(n_views=4, acquisitions=2, views_per_acquisition=(3, 2)), "views_per_acquisition"),
        (dict(n_views=4, acquisitions=2, views_per_acquisition=(4, 0)), "views_per_acquisition"),
        (dict(acquisitions=1, start_date="2019-13-01"), "start_date"),
        (dict(acquisitions=1, date_effects=("sun", "snow")), "date_effects"),
        (dict(acquisitions=3, date_span_days=2), "date_span_days"),
        (dict(write_metadata=True), "write_metadata"),
        (dict(large_bias_px=-1.0), "large_bias_px"),
        (dict(acquisitions=1, max_off_nadir_deg=60.0), "max_off_nadir_deg"),
    ):
        with pytest.raises(OptionsError, match=field):
            SynthOptions(**kwargs)
    # A sun that never rises high enough is refused when the dates are drawn, naming the option.
    with pytest.raises(OptionsError, match="min_sun_elevation_deg"):
        SynthOptions(acquisitions=2, n_views=2, location=(25.0, 78.0), min_sun_elevation_deg=40.0).plan()


def test_multidate_scene_is_deterministic(tmp_path):
    opts = SynthOptions(seed=2, n_views=2, acquisitions=2, size_px=64, gsd_m=2.0, bias_px=0.5,
                        large_bias_px=5.0, max_off_nadir_deg=15.0)
    a = generate_scene(tmp_path / "a", opts)
    b = generate_scene(tmp_path / "b", opts)
    names = sorted(p.name for p in a.directory.iterdir())
    assert names == sorted(p.name for p in b.directory.iterdir()) and "view_00.IMD" in names
    for name in names:
        assert (a.directory / name).read_bytes() == (b.directory / name).read_bytes(), name
    assert a.options.plan() == opts.plan()
    other = opts.replace(seed=3).plan()
    assert [v.date_time for v in other.views] != [v.date_time for v in a.views]


def test_cli_multidate_flags(tmp_path, capsys):
    out = tmp_path / "cli"
    assert cli_main(["synth", "--out", str(out), "--acquisitions", "2", "--size", "64", "--gsd", "2.0",
                     "--large-bias", "4", "--start-date", "2020-03-01", "--no-metadata"]) == 0
    text = capsys.readouterr().out
    assert "acquisition 1" in text and "within an acquisition" in text
    doc = json.loads((out / SCENE_FILE).read_text())
    assert doc["options"]["acquisitions"] == 2 and doc["options"]["n_views"] == 4  # 2N by default
    assert doc["options"]["write_metadata"] is False and doc["options"]["large_bias_px"] == 4.0
    assert all(a["date_time"] >= "2020-03-01" for a in doc["acquisitions"])
    assert not list(out.glob("*.IMD"))
    assert cli_main(["synth", "--out", str(tmp_path / "bad"), "--acquisitions", "2", "--views", "9"]) == 2
    assert "acquisitions" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_rgb8_views_are_8bit_rgb_stretched_per_image(tmp_path):
    """product="rgb8": every view an 8-bit RGB image whose luminance (the pipeline's reader's
    grey image) is that view's own DN stretched from its 0.5% to its 99.5% quantile (gamma
    RGB8_GAMMA), checked against the same scene in DN: an independent stretch of those numbers,
    within the rounding of 8 bits (vegetation's colour leaves it alone, RGB8_GREEN); the RPC tag
    and the rest of the scene as they are."""
    opts = SynthOptions(seed=2, n_views=2, acquisitions=2, size_px=64, gsd_m=2.0, max_off_nadir_deg=15.0)
    dn = generate_scene(tmp_path / "dn", opts)
    rgb = generate_scene(tmp_path / "rgb", opts.replace(product="rgb8"))
    for a, b in zip(dn.views, rgb.views):
        grey = tifffile.imread(a.image).astype(np.float64)
        img = tifffile.imread(b.image)
        assert img.dtype == np.uint8 and img.shape == grey.shape + (3,)
        lo, hi = np.percentile(grey, (0.5, 99.5))
        x = np.clip((grey - lo) / (hi - lo), 0.0, 1.0) ** (1.0 / 1.6)
        # The luminance of the bands' responses (RGB8_CHANNELS, LUMA_WEIGHTS).
        expected_luma = sum(w * (gain * x + offset) * 255.0
                            for w, (gain, offset) in zip((0.299, 0.587, 0.114), RGB8_CHANNELS))
        luma = read_image(b.image).astype(np.float64)
        # Each band rounded to 8 bits: the luminance within half a level; bands clipped at 0 or
        # 255 (the stretch's ends, a green crown's brightest pixels) are not compared.
        unclipped = np.all((img > 0) & (img < 255), axis=-1)
        assert unclipped.mean() > 0.9
        assert np.abs(luma - expected_luma)[unclipped].max() <= 0.5 + 1e-6
        assert 0.0 < np.mean(img[..., 1] == 0) < 0.02 and 0.0 < np.mean(img[..., 1] == 255) < 0.02
        with tifffile.TiffFile(a.image) as ta, tifffile.TiffFile(b.image) as tb:
            assert tb.pages[0].tags[50844].value == ta.pages[0].tags[50844].value  # the RPC tag
        assert read_image(b.image).shape == grey.shape
    doc = json.loads((rgb.directory / SCENE_FILE).read_text())
    assert doc["options"]["product"] == "rgb8"
    assert "product" not in json.loads((dn.directory / SCENE_FILE).read_text())["options"]
    with pytest.raises(OptionsError, match="product"):
        SynthOptions(product="png")


# A normalised green-red difference of bands of at least COLOUR_MIN_LEVEL (8-bit levels), each
# rounded by half a level at most, is within about 0.5 / COLOUR_MIN_LEVEL of the unrounded one.
COLOUR_MIN_LEVEL = 40
COLOUR_TOL = 0.5 / COLOUR_MIN_LEVEL + 1e-3


def test_rgb8_views_show_vegetation_green(tmp_path):
    """product="rgb8": each pixel's normalised green-red difference (G - R) / (G + R) is that of
    its greenness g (render_radiance_greenness on its date's surface: the share of its light
    that leaves and grass send), the bands' responses plus g times RGB8_GREEN, within the
    rounding of 8 bits; the scene has pixels of crowns (g near 1), of grass (GRASS_GREENNESS)
    and of neither (0)."""
    opts = SynthOptions(seed=2, n_views=2, acquisitions=2, size_px=64, gsd_m=2.0,
                        max_off_nadir_deg=15.0, product="rgb8")
    scene = generate_scene(tmp_path / "rgb", opts)
    truth = scene.surface()
    (gr, _), (gg, _), (gb, _) = RGB8_CHANNELS
    seen = []
    for view in scene.views:
        acq = scene.acquisitions[view.acquisition]
        day = scene.acquisition_surface(view.acquisition, grid=truth)
        shadows = ShadowMap(day, sun_vector(elevation_deg=acq.sun_elevation_deg,
                                            azimuth_deg=acq.sun_azimuth_deg))
        _, g = render_radiance_greenness(day, shadows, view.camera, supersampling=opts.supersampling)
        img = tifffile.imread(view.image).astype(np.float64)
        r, gn = img[..., 0], img[..., 1]
        ok = (r >= COLOUR_MIN_LEVEL) & (gn >= COLOUR_MIN_LEVEL) & (img < 255).all(axis=-1)
        with np.errstate(invalid="ignore"):  # black pixels: not compared
            ngrdi = (gn - r) / (gn + r)
        red, green = gr + RGB8_GREEN[0] * g, gg + RGB8_GREEN[1] * g
        want = (green - red) / (green + red)
        assert ok.mean() > 0.5
        assert np.abs(ngrdi - want)[ok].max() <= COLOUR_TOL
        seen.append(g[ok])
    g = np.concatenate(seen)
    assert (g > 0.9).sum() > 20 and (np.abs(g - GRASS_GREENNESS) < 0.05).sum() > 20
    assert (g == 0.0).sum() > 20


def test_greenness_of_leaves_grass_and_the_rest():
    """town.greenness per hit: TREE_GREENNESS times the cell's leafiness on a crown (1 without
    a leafiness grid), GRASS_GREENNESS on grass and soil, 0 on roads and roofs; a leafless
    date's crowns keep branches of leafiness 0, its evergreens 1."""
    from types import SimpleNamespace

    from satsweep.synth.town import GROUND, ROOF, greenness

    grid = build_surface(seed=3, e_min=-60.0, n_min=-60.0, e_max=60.0, n_max=60.0, cell_m=0.5,
                         aoi_half_m=50.0)
    mat = grid.material
    j, i = np.nonzero(np.ones(mat.shape, bool))
    hits = SimpleNamespace(j=j, i=i)
    g = greenness(grid, hits).reshape(mat.shape)
    assert np.any(mat == TREE) and np.any(mat == GROUND) and np.any(mat == ROOF)
    np.testing.assert_array_equal(g[mat == TREE], TREE_GREENNESS)
    np.testing.assert_array_equal(g[mat == GROUND], GRASS_GREENNESS)
    np.testing.assert_array_equal(g[(mat != TREE) & (mat != GROUND)], 0.0)
    leafy = dataclasses.replace(grid, leafiness=np.full(mat.shape, 0.25, np.float32))
    np.testing.assert_allclose(greenness(leafy, hits).reshape(mat.shape)[mat == TREE],
                               0.25 * TREE_GREENNESS)


def test_leafless_dates_keep_branches_without_leaves(md, md_truth):
    """The winter acquisition's crowns: the cells keeping branches are trees of leafiness 0
    (bare), the evergreens' cells 1; no summer-like date sets any."""
    winter = md.acquisitions[0]
    assert winter.leaf_factor == 0.0  # branches
    day = md.acquisition_surface(winter.index, grid=md_truth)
    tree = day.material == TREE
    leaf = day.leafiness[tree]
    assert np.any(leaf == 0.0) and np.any(leaf == 1.0)
    assert np.all((leaf == 0.0) | (leaf == 1.0))
    assert md_truth.leafiness is None


# -- realism -----------------------------------------------------------------------------------
def test_cross_date_pair_fails_where_the_same_date_pair_succeeds(realism_scenes, tmp_path):
    scene = realism_scenes["all"]
    a0, a1 = scene.acquisitions
    assert scene.views[SAME_DATE_PAIR[0]].acquisition == scene.views[SAME_DATE_PAIR[1]].acquisition == 0
    assert scene.views[CROSS_DATE_PAIR[0]].acquisition == 1
    bh = {(i, j): b for i, j, b in scene.pairs}
    assert bh[tuple(sorted(SAME_DATE_PAIR))] == pytest.approx(bh[tuple(sorted(CROSS_DATE_PAIR))], abs=1e-9)
    same = reconstruct_pair(scene, SAME_DATE_PAIR, tmp_path / "same")["completeness_1m"]
    cross = reconstruct_pair(scene, CROSS_DATE_PAIR, tmp_path / "cross")["completeness_1m"]
    assert same - cross > MIN_DATE_DROP, f"same-date {same:.1%}, cross-date {cross:.1%}"
    # The control: the same scene without date effects, where the pairs differ only by the noise.
    control = realism_scenes["none"]
    c_same = reconstruct_pair(control, SAME_DATE_PAIR, tmp_path / "c_same")["completeness_1m"]
    c_cross = reconstruct_pair(control, CROSS_DATE_PAIR, tmp_path / "c_cross")["completeness_1m"]
    assert abs(c_same - c_cross) < MAX_CONTROL_GAP, f"control: {c_same:.1%} vs {c_cross:.1%}"
