"""Synthetic scenes (satsweep synth): camera exactness, RPC + bias geometry against the renderer,
visibility, shadows, the truth DSM read through GDAL (rasterio), files, determinism, CLI."""

from __future__ import annotations

import dataclasses
import json
import math
import os

import numpy as np
import pyproj
import pytest
import rasterio
import rpcm

from satsweep.cli import main as cli_main
from satsweep.errors import OptionsError, OutputExistsError
from satsweep.geometry.rpc import RPCModel
from satsweep.io.images import read_image
from satsweep.synth.pushbroom import PushbroomCamera, base_to_height
from satsweep.synth.scene import (
    DN_MAX,
    SCENE_FILE,
    TRUTH_DSM_FILE,
    Scene,
    SynthOptions,
    design_scene,
    generate_scene,
    to_dn,
)
from satsweep.synth.town import (
    FACE_TOP,
    MAX_BUILDING_M,
    MIN_BUILDING_M,
    MIN_WALL_M,
    PLAZA,
    ROAD,
    ROOF,
    ROOF_GABLE,
    TREE,
    ShadowMap,
    build_surface,
    cast_rays,
    sun_vector,
    value_noise,
)

# The issue: RPC projection + recorded bias must land where the renderer's ray for that pixel
# hits the same surface point, within 0.01 m horizontally.
GEOMETRY_TOL_M = 0.01
# A hit of cast_rays lies on its ray: projecting it with the exact camera gives back the pixel
# to float64 rounding of a 700 km long ray (~1e-10 relative).
ON_RAY_TOL_PX = 1e-6
# A plane hit lies on its cell's plane to float64 rounding of heights of ~100 m.
ON_PLANE_TOL_M = 1e-6
# Dense sampling along lines of sight and towards the sun (m between samples), the distance
# from the start point below which samples are ignored (the point's own surface), and the
# clearance a truth point needs to count as clearly visible (grazing views are left out).
LINE_STEP_M = 0.02
LINE_START_M = 0.05
CLEAR_VISIBILITY_M = 0.02
# Truth points tried per view, and how many clearly visible ones the test needs at least.
TRUTH_POINTS = 500
MIN_VISIBLE_POINTS = 200
# The shadow map is exact only to about one cell at shadow edges: at most this share of random
# surface points may disagree with brute-force marching towards the sun.
SHADOW_DISAGREEMENT_MAX = 0.03
# Truth DSM: each cell is the max over 5x5 points including the centre, so it is never below
# the surface at the centre (by more than the float32 storage of ~480 m heights, 3e-5 m, and the
# rounding of the coordinate transforms) and never
# above the highest surface point of the cell; the dense reference grid misses the true maximum
# by at most slope x half its spacing (0.0125 m x slope 1 for non-tree cells).
DSM_FLOAT_TOL_M = 1e-4
DSM_DENSE_TOL_M = 0.015
# Noise: the standard deviation of DN noise over many pixels matches noise_dn to 5% (sampling
# error of 40000 samples is 0.4%; rounding to integers adds 1/12 DN^2).
NOISE_REL_TOL = 0.05
# An RPC fitted over a kilometre of heights against its exact pushbroom camera: the fit's
# residual is a few 1e-9 px (scene.json's rpc_fit); this leaves room for float rounding only.
RPC_FIT_TOL_PX = 1e-4
# Bilinear interpolation of unit-variance lattice values in float64, summed in another order.
NOISE_ROUND_TOL = 1e-12

SMALL = SynthOptions(seed=3, n_views=3, size_px=128, gsd_m=1.0, bias_px=1.5,
                     location=(55.45, -21.05), ground_alt_m=480.0)


@pytest.fixture(scope="module")
def scene(synthetic_scene) -> Scene:
    return synthetic_scene(**{f: getattr(SMALL, f) for f in ("seed", "n_views", "size_px",
                                                             "gsd_m", "bias_px", "location",
                                                             "ground_alt_m")})


@pytest.fixture(scope="module")
def surface(scene):
    return scene.surface()


def _aoi_points(scene: Scene, grid, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = scene.aoi_half_m
    e, nn = rng.uniform(-a, a, (2, n))
    return np.stack([e, nn, grid.height(e=e, n=nn)], axis=1)


def _min_clearance(grid, start: np.ndarray, direction: np.ndarray, top: float) -> np.ndarray:
    """Min over samples from LINE_START_M up to height ``top`` of (line height - surface height)."""
    length = (top - start[:, 2]) / direction[:, 2]
    t = np.arange(LINE_START_M, float(length.max()) + LINE_STEP_M, LINE_STEP_M)
    p = start[:, None, :] + t[None, :, None] * direction[:, None, :]
    clear = p[..., 2] - grid.height(e=p[..., 0], n=p[..., 1])
    clear = np.where(t[None, :] <= length[:, None], clear, np.inf)
    return np.nanmin(np.where(np.isnan(clear), np.inf, clear), axis=1)


# -- the exact camera ----------------------------------------------------------------------------
def test_pushbroom_projection_inverts_its_rays_and_has_the_requested_gsd():
    cam = PushbroomCamera.from_angles(off_nadir_deg=17.0, azimuth_deg=230.0, orbit_azimuth_deg=190.0,
                                      orbit_height_m=650e3, gsd_m=0.5, width=300, height=200)
    rng = np.random.default_rng(0)
    col, row = rng.uniform(-0.5, 299.5, 100), rng.uniform(-0.5, 199.5, 100)
    origin, d = cam.ray(col=col, row=row)
    t = rng.uniform(6.0e5, 7.0e5, 100)[:, None]
    p = origin + t * d
    pc, pr = cam.project(e=p[:, 0], n=p[:, 1], u=p[:, 2])
    assert np.max(np.hypot(pc - col, pr - row)) < ON_RAY_TOL_PX
    # The scene centre is at the image centre, and the satellite where the angles say.
    c0, r0 = cam.project(e=0.0, n=0.0, u=0.0)
    assert (c0, r0) == pytest.approx(((300 - 1) / 2, (200 - 1) / 2), abs=1e-9)
    assert cam.viewing_angles() == pytest.approx((17.0, 230.0), abs=1e-9)
    assert cam.position(row=r0)[2] == pytest.approx(650e3, rel=1e-12)
    # Ground sample distance at the centre: along-track (rows) and across-track (cols).
    e0, n0 = cam.ground_point(col=c0, row=r0, u=0.0)
    e1, n1 = cam.ground_point(col=c0 + 1.0, row=r0, u=0.0)
    e2, n2 = cam.ground_point(col=c0, row=r0 + 1.0, u=0.0)
    assert math.hypot(e1 - e0, n1 - n0) == pytest.approx(0.5, rel=1e-5)
    assert math.hypot(e2 - e0, n2 - n0) == pytest.approx(0.5, rel=1e-9)
    assert PushbroomCamera.from_dict(json.loads(json.dumps(cam.to_dict()))) == cam


# -- geometry: RPC + bias vs the renderer --------------------------------------------------------
def test_rpc_plus_bias_lands_where_the_renderer_ray_hits_the_same_point(scene, surface):
    top = surface.max_height() + 0.1
    for view in scene.views:
        cam = view.camera
        rpc = RPCModel.from_image(view.image)
        pts = _aoi_points(scene, surface, TRUTH_POINTS, seed=view.index)
        # Clearly visible truth points: the segment towards the satellite stays above the surface.
        _, row = cam.project(e=pts[:, 0], n=pts[:, 1], u=pts[:, 2])
        to_sat = cam.position(row=row) - pts
        to_sat /= np.linalg.norm(to_sat, axis=1, keepdims=True)
        visible = _min_clearance(surface, pts, to_sat, top) >= CLEAR_VISIBILITY_M
        pts = pts[visible]
        assert len(pts) >= MIN_VISIBLE_POINTS, f"{view.image.name}: only {len(pts)} visible truth points"
        lon, lat, alt = scene.frame.to_geodetic(e=pts[:, 0], n=pts[:, 1], u=pts[:, 2])
        col, row = rpc.projection(lon=lon, lat=lat, alt=alt)
        col, row = col + view.bias_px[0], row + view.bias_px[1]
        hits = cast_rays(surface, *cam.ray(col=col, row=row))
        horizontal = np.hypot(hits.point[:, 0] - pts[:, 0], hits.point[:, 1] - pts[:, 1])
        assert horizontal.max() < GEOMETRY_TOL_M, f"{view.image.name}: {horizontal.max():.4f} m"
        assert np.abs(hits.point[:, 2] - pts[:, 2]).max() < GEOMETRY_TOL_M
    # The biases are real: without them, the shifted views would miss by about the bias.
    assert max(abs(b) for v in scene.views for b in v.bias_px) > 0.3


def test_renderer_rays_stop_at_the_first_surface_point(scene, surface):
    top = surface.max_height() + 0.1
    rng = np.random.default_rng(9)
    walls = 0
    for view in scene.views:
        cam = view.camera
        col = rng.integers(0, cam.width, 400).astype(float)
        row = rng.integers(0, cam.height, 400).astype(float)
        origin, d = cam.ray(col=col, row=row)
        hits = cast_rays(surface, origin, d)
        p = hits.point
        pc, pr = cam.project(e=p[:, 0], n=p[:, 1], u=p[:, 2])
        assert np.max(np.hypot(pc - col, pr - row)) < ON_RAY_TOL_PX
        is_top = hits.face == FACE_TOP
        assert np.max(np.abs(p[is_top, 2] - surface.height(e=p[is_top, 0], n=p[is_top, 1]))) < ON_PLANE_TOL_M
        # Wall hits lie on a cell edge, between the heights of the two cells meeting there.
        wall = ~is_top
        back = -hits.normal[wall, :2] * 1e-7
        front = hits.normal[wall, :2] * 1e-7
        h_in = surface.height(e=p[wall, 0] + back[:, 0], n=p[wall, 1] + back[:, 1])
        h_out = surface.height(e=p[wall, 0] + front[:, 0], n=p[wall, 1] + front[:, 1])
        assert np.all(p[wall, 2] <= h_in + ON_PLANE_TOL_M) and np.all(p[wall, 2] >= h_out - ON_PLANE_TOL_M)
        walls += int(np.sum(wall & (hits.wall_depth >= MIN_WALL_M)))
        # Nothing of the surface rises above the line of sight before the hit.
        clearance = _min_clearance(surface, p, -d, top)
        assert clearance.min() > 0.0
    assert walls > 0, "no facade seen in any view"



@pytest.mark.parametrize("fraction", [0.0, 1.0])
def test_the_walks_compaction_schedule_changes_no_hit(scene, surface, monkeypatch, fraction):
    """Finished rays stay in the walk's arrays until few walk: the hits are those of a walk
    that never compacts (0) and of one that compacts at every step (1), bit for bit."""
    from satsweep.synth import town

    cam = scene.views[0].camera
    r, c = np.meshgrid(np.arange(0, cam.height, 3.0), np.arange(0, cam.width, 3.0), indexing="ij")
    origin, d = cam.ray(col=c.ravel(), row=r.ravel())
    hits = cast_rays(surface, origin, d)
    monkeypatch.setattr(town, "WALK_COMPACT_FRACTION", fraction)
    other = cast_rays(surface, origin, d)
    for field in dataclasses.fields(hits):
        assert np.array_equal(getattr(hits, field.name), getattr(other, field.name)), field.name
    assert np.any(hits.face != FACE_TOP)  # walls too


def test_rendering_in_threads_gives_the_image_of_one_thread(scene, surface, monkeypatch):
    from satsweep.synth import scene as scene_module

    sun = sun_vector(elevation_deg=scene.options.sun_elevation_deg, azimuth_deg=scene.options.sun_azimuth_deg)
    shadows = ShadowMap(surface, sun)
    cam = scene.views[1].camera
    monkeypatch.setattr(scene_module, "RENDER_CHUNK_RAYS", 4 * cam.width)  # many chunks
    threaded = scene_module.render_radiance_greenness(surface, shadows, cam, supersampling=2)
    monkeypatch.setattr(scene_module, "RENDER_THREADS", 1)
    alone = scene_module.render_radiance_greenness(surface, shadows, cam, supersampling=2)
    assert np.array_equal(threaded[0], alone[0]) and np.array_equal(threaded[1], alone[1])


def test_cast_shadows_match_brute_force_marching_towards_the_sun(scene, surface):
    sun = sun_vector(elevation_deg=scene.options.sun_elevation_deg, azimuth_deg=scene.options.sun_azimuth_deg)
    shadows = ShadowMap(surface, sun)
    pts = _aoi_points(scene, surface, 1000, seed=21)
    ref_lit = _min_clearance(surface, pts, np.repeat(sun[None], len(pts), 0), surface.max_height() + 0.1) > 0.0
    lit = shadows.lit(pts)
    assert 0.05 < np.mean(~ref_lit) < 0.95, "the scene should have both sunlit and shadowed ground"
    assert np.mean(lit != ref_lit) <= SHADOW_DISAGREEMENT_MAX


# -- truth DSM through GDAL --------------------------------------------------------------------
def test_truth_dsm_reads_back_through_gdal_with_crs_transform_and_values(scene, surface):
    lon0, lat0 = scene.options.location
    zone = int(math.floor((lon0 + 180.0) / 6.0)) + 1
    epsg = (32600 if lat0 >= 0 else 32700) + zone
    res = scene.options.dsm_resolution_m
    with rasterio.open(scene.truth_dsm) as ds:
        assert ds.crs.to_epsg() == epsg
        t = ds.transform
        assert (t.a, t.b, t.d, t.e) == (res, 0.0, 0.0, -res)
        assert t.c / res == round(t.c / res) and t.f / res == round(t.f / res)
        assert ds.nodata is not None and math.isnan(ds.nodata)
        dsm = ds.read(1)
        height, width = ds.height, ds.width
    # The grid covers the AOI.
    to_utm = pyproj.Transformer.from_crs(4326, epsg, always_xy=True)
    a = scene.aoi
    x, y = to_utm.transform([a.lon_min, a.lon_max, a.lon_max, a.lon_min], [a.lat_min, a.lat_min, a.lat_max, a.lat_max])
    assert t.c <= min(x) and t.c + width * res >= max(x) and t.f >= max(y) and t.f - height * res <= min(y)
    assert np.all(np.isfinite(dsm))
    # Surface altitude at UTM points, through pyproj's own topocentric (ENU) conversion.
    to_lonlat = pyproj.Transformer.from_crs(epsg, 4326, always_xy=True)
    f = scene.frame
    topo = pyproj.Transformer.from_pipeline(
        "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad +step +proj=cart +ellps=WGS84 "
        f"+step +proj=topocentric +ellps=WGS84 +lon_0={f.lon0!r} +lat_0={f.lat0!r} +h_0={f.alt0!r}")

    def truth_alt(xs, ys):
        lon, lat = to_lonlat.transform(xs, ys)
        alt = np.full(np.shape(lon), f.alt0)
        for _ in range(4):
            e, n, u = topo.transform(lon, lat, alt)
            alt = alt + (surface.height(e=e, n=n) - u)
        return alt

    rows, cols = np.mgrid[0:height, 0:width]
    xc, yc = rasterio.transform.xy(t, rows.ravel(), cols.ravel(), offset="center")
    centre = truth_alt(np.asarray(xc), np.asarray(yc)).reshape(height, width)
    assert np.all(dsm >= centre - DSM_FLOAT_TOL_M), "DSM below the surface at a cell centre"
    # Upper bound on random cells (not under trees, whose flanks are steeper than 1).
    rng = np.random.default_rng(2)
    pick = rng.choice(height * width, 300, replace=False)
    r, c = np.unravel_index(pick, (height, width))
    k = np.linspace(0.0, 1.0, 21)
    fx, fy = np.meshgrid(k, k)
    xs = t.c + (c[:, None] + fx.ravel()[None]) * res
    ys = t.f - (r[:, None] + fy.ravel()[None]) * res
    dense = truth_alt(xs, ys)
    lon, lat = to_lonlat.transform(xs, ys)
    e, n, _ = topo.transform(lon, lat, dense)
    treeless = ~np.any(surface.material[surface.cell_of(e=e, n=n)[:2]] == TREE, axis=1)
    assert treeless.sum() > 100
    assert np.all(dsm[r, c][treeless] <= dense.max(axis=1)[treeless] + DSM_DENSE_TOL_M)
    # Cells that are flat throughout (roofs, plazas) hold exactly the surface height.
    flat = np.ptp(dense, axis=1) < DSM_FLOAT_TOL_M
    assert flat.sum() >= 10
    assert np.all(np.abs(dsm[r, c][flat] - centre[r, c][flat]) < DSM_FLOAT_TOL_M)
    # Buildings stand out of the DSM by their heights.
    assert dsm.max() - dsm.min() > MIN_BUILDING_M


# -- files ---------------------------------------------------------------------------------------
def test_views_are_uint16_with_rpc_tag_and_sidecar_that_rpcm_reads_alike(scene):
    rng = np.random.default_rng(1)
    for view in scene.views:
        img = read_image(view.image)
        assert img.dtype == np.uint16 and img.shape == (SMALL.size_px, SMALL.size_px)
        assert img.max() <= DN_MAX and img.std() > 50
        from_tag = RPCModel.from_image(view.image)
        from_txt = RPCModel.from_file(view.rpc_file)
        assert np.array_equal(from_tag.to_tag_values(), from_txt.to_tag_values())
        a = scene.aoi
        lon, lat = rng.uniform(a.lon_min, a.lon_max, 200), rng.uniform(a.lat_min, a.lat_max, 200)
        alt = rng.uniform(*scene.alt_range, 200)
        c0, r0 = from_tag.projection(lon=lon, lat=lat, alt=alt)
        for other in (rpcm.rpc_from_geotiff(str(view.image)), rpcm.rpc_from_rpc_file(str(view.rpc_file))):
            c1, r1 = other.projection(lon, lat, alt)
            assert np.max(np.hypot(c1 - c0, r1 - r0)) < ON_RAY_TOL_PX
        assert view.rpc_fit_max_px < 1e-4 and view.rpc_check_max_px < 1e-4


def test_scene_json_describes_the_scene_and_loads_back(scene):
    doc = json.loads(scene.scene_file.read_text())
    a = doc["aoi"]
    ring = doc["aoi"]["geojson"]["coordinates"][0]
    assert doc["aoi"]["geojson"]["type"] == "Polygon" and ring[0] == ring[-1] and len(ring) == 5
    assert {p[0] for p in ring} == {a["lon_min"], a["lon_max"]}
    assert doc["truth_dsm"]["file"] == TRUTH_DSM_FILE
    assert "RPC(X) + bias_px" in doc["bias_convention"]
    assert len(doc["views"]) == SMALL.n_views and len(doc["pairs"]) == 3
    biases = np.array([v["bias_px"] for v in doc["views"]])
    assert np.all(biases[0] == 0.0) and np.all(np.abs(biases) <= SMALL.bias_px)
    for v in doc["views"]:
        assert (scene.directory / v["image"]).is_file() and (scene.directory / v["rpc_file"]).is_file()
        assert {"off_nadir_deg", "azimuth_deg", "incidence_deg", "bias_px"} <= set(v)
    # Base-to-height ratios of the built-in views: between 0.1 and 0.5, recomputed from cameras.
    for p in doc["pairs"]:
        i, j = p["views"]
        ci = PushbroomCamera.from_dict(doc["views"][i]["camera"])
        cj = PushbroomCamera.from_dict(doc["views"][j]["camera"])
        assert p["base_to_height"] == pytest.approx(base_to_height(ci, cj))
        assert 0.1 <= p["base_to_height"] <= 0.5
    loaded = Scene.load(scene.directory)
    assert loaded == scene
    lo, hi = doc["altitude_range"]
    with rasterio.open(scene.truth_dsm) as ds:
        dsm = ds.read(1)
    assert lo <= dsm.min() and dsm.max() <= hi


def test_same_seed_same_files_other_seed_other_scene(tmp_path):
    opts = SynthOptions(seed=8, n_views=2, size_px=64, gsd_m=1.0, bias_px=0.7)
    generate_scene(tmp_path / "a", opts)
    generate_scene(tmp_path / "b", opts)
    generate_scene(tmp_path / "c", opts.replace(seed=9))
    names = sorted(os.listdir(tmp_path / "a"))
    assert names == sorted(os.listdir(tmp_path / "b"))
    assert {"view_00.tif", "view_01_RPC.TXT", TRUTH_DSM_FILE, SCENE_FILE} <= set(names)
    for name in names:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    assert (tmp_path / "a" / "view_00.tif").read_bytes() != (tmp_path / "c" / "view_00.tif").read_bytes()
    assert (tmp_path / "a" / TRUTH_DSM_FILE).read_bytes() != (tmp_path / "c" / TRUTH_DSM_FILE).read_bytes()


def test_non_empty_folder_is_refused_unless_overwrite(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("user file")
    opts = SynthOptions(n_views=1, size_px=48, gsd_m=1.0)
    with pytest.raises(OutputExistsError, match="not empty"):
        generate_scene(out, opts)
    assert os.listdir(out) == ["keep.txt"]
    scene = generate_scene(out, opts, overwrite=True)
    assert scene.views[0].image.is_file() and (out / "keep.txt").read_text() == "user file"


# -- CLI -----------------------------------------------------------------------------------------
def test_cli_writes_a_scene_and_refuses_a_non_empty_folder(tmp_path, capsys):
    out = tmp_path / "cli"
    args = ["synth", "--out", str(out), "--seed", "4", "--views", "2", "--size", "64", "--gsd", "1.0",
            "--bias", "1.0", "--location=-70.5,-33.4"]
    assert cli_main(args) == 0
    assert "base-to-height" in capsys.readouterr().out
    doc = json.loads((out / SCENE_FILE).read_text())
    assert doc["options"]["location"] == [-70.5, -33.4] and doc["options"]["seed"] == 4
    assert len(doc["views"]) == 2 and doc["views"][0]["width"] == 64
    assert doc["truth_dsm"]["epsg"] == 32719
    before = {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in out.iterdir()}
    assert cli_main(args) == 2
    assert "not empty" in capsys.readouterr().err
    assert {p.name: (p.stat().st_mtime_ns, p.read_bytes()) for p in out.iterdir()} == before
    assert cli_main(["synth", "--out", str(tmp_path / "bad"), "--location", "north"]) == 2
    assert "--location" in capsys.readouterr().err
    assert cli_main(["synth", "--out", str(tmp_path / "bad"), "--views", "0"]) == 2
    assert "n_views" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_cli_samples_the_surface_finely_enough_for_a_fine_gsd(tmp_path, capsys):
    """--gsd 0.3 (WorldView-3) runs: the true surface's cells follow the GSD down (0.15 m), where
    the default 0.25 m cells would fail SynthOptions' check."""
    out = tmp_path / "wv3"
    assert cli_main(["synth", "--out", str(out), "--views", "2", "--size", "96", "--gsd", "0.3"]) == 0
    capsys.readouterr()
    doc = json.loads((out / SCENE_FILE).read_text())
    assert doc["options"]["gsd_m"] == 0.3 and doc["options"]["cell_m"] == pytest.approx(0.15)


def test_cli_fits_the_rpcs_over_a_real_deliverys_span_of_heights(tmp_path, capsys):
    """--rpc-height-scale 500: each RPC's HEIGHT_SCALE spans 500 m about the scene's middle, as
    WorldView's and Pleiades' do, and it still is the exact camera shifted by the bias wherever
    in that span (RPC_FIT_TOL_PX: the fit's residual over a kilometre of a pushbroom's heights,
    measured 6e-9 px); the images are the same as without it."""
    out, plain = tmp_path / "wide", tmp_path / "plain"
    args = ["synth", "--seed", "4", "--views", "2", "--size", "64", "--gsd", "1.0", "--bias", "1.0"]
    assert cli_main(args + ["--out", str(out), "--rpc-height-scale", "500"]) == 0
    assert cli_main(args + ["--out", str(plain)]) == 0
    capsys.readouterr()
    scene, other = Scene.load(out), Scene.load(plain)
    rng = np.random.default_rng(2)
    for view, same in zip(scene.views, other.views):
        rpc = view.rpc()
        assert abs(rpc.alt_scale) >= 500.0 and abs(same.rpc().alt_scale) < 100.0
        assert rpc.alt_offset == pytest.approx(same.rpc().alt_offset)  # the scene's middle
        u = rng.uniform(rpc.alt_offset - 450.0, rpc.alt_offset + 450.0, 200) - scene.frame.alt0
        e = rng.uniform(-10.0, 10.0, 200)
        n = rng.uniform(-10.0, 10.0, 200)
        col, row = view.camera.project(e=e, n=n, u=u)
        lon, lat, alt = scene.frame.to_geodetic(e=e, n=n, u=u)
        rc, rr = rpc.projection(lon=lon, lat=lat, alt=alt)
        err = np.hypot(rc + view.bias_px[0] - col, rr + view.bias_px[1] - row)
        assert err.max() < RPC_FIT_TOL_PX, err.max()
        np.testing.assert_array_equal(read_image(view.image), read_image(same.image))
    assert cli_main(["synth", "--out", str(tmp_path / "bad"), "--rpc-height-scale", "-5"]) == 2
    assert "rpc_height_scale_m" in capsys.readouterr().err


# -- options and scene content -------------------------------------------------------------------
def test_options_are_checked_naming_the_field():
    with pytest.raises(OptionsError, match="size_px"):
        SynthOptions(size_px=8)
    with pytest.raises(OptionsError, match="off_nadir_deg"):
        SynthOptions(n_views=2, off_nadir_deg=(5.0,), azimuth_deg=(0.0,))
    with pytest.raises(OptionsError, match="cell_m"):
        SynthOptions(cell_m=0.5)
    with pytest.raises(OptionsError, match="location"):
        SynthOptions(location=(10.0, 85.0))
    with pytest.raises(OptionsError, match="bias_px"):
        SynthOptions(bias_px=-1.0)


def test_default_scene_has_the_town_the_issue_describes():
    opts = SynthOptions()
    d = design_scene(opts)
    e0, n0, e1, n1 = d.world
    assert 250.0 <= e1 - e0 <= 400.0 and 250.0 <= n1 - n0 <= 400.0
    grid = build_surface(seed=opts.seed, e_min=e0, n_min=n0, e_max=e1, n_max=n1, cell_m=opts.cell_m,
                         aoi_half_m=d.aoi_half_m)
    heights = np.array([b.height_m for b in grid.buildings])
    assert heights.min() >= MIN_BUILDING_M and heights.max() <= MAX_BUILDING_M
    assert heights.max() >= 40.0 and heights.min() <= 8.0
    assert {b.roof for b in grid.buildings} == {"flat", "gable"}
    # Adjacent buildings: two footprints sharing a wall with different roof heights.
    def touching(a, b):
        share_e = (abs(a.e1 - b.e0) < 1e-9 or abs(b.e1 - a.e0) < 1e-9) and min(a.n1, b.n1) - max(a.n0, b.n0) > 2.0
        share_n = (abs(a.n1 - b.n0) < 1e-9 or abs(b.n1 - a.n0) < 1e-9) and min(a.e1, b.e1) - max(a.e0, b.e0) > 2.0
        return share_e or share_n
    bs = grid.buildings
    assert any(touching(a, b) and abs((a.base_u + a.height_m) - (b.base_u + b.height_m)) > 1.0
               for k, a in enumerate(bs) for b in bs[k + 1:])
    materials = set(np.unique(grid.material).tolist())
    assert {ROAD, PLAZA, ROOF, ROOF_GABLE, TREE} <= materials
    # Gentle ground: slopes of ground cells stay below 5 %.
    ground = grid.material == 0
    assert np.max(np.hypot(grid.slope_e[ground], grid.slope_n[ground])) < 0.05


def test_noise_has_the_requested_sigma():
    radiance = np.full((200, 200), 0.3)
    dn = to_dn(radiance, noise_dn=6.0, rng=np.random.default_rng(0)).astype(float)
    assert dn.mean() == pytest.approx(0.3 * 4000.0, abs=0.2)
    assert dn.std() == pytest.approx(math.sqrt(6.0 ** 2 + 1.0 / 12.0), rel=NOISE_REL_TOL)


@pytest.mark.parametrize("shape,scale", [((37, 53), 4.5), ((20, 9), 1.0), ((3, 40), 17.0)])
def test_value_noise_interpolates_its_lattice_bilinearly(shape, scale):
    """Each cell from its lattice square's four corners (the lattice drawn from the same
    generator state), one cell at a time."""
    ny, nx = shape
    gy, gx = math.ceil(ny / scale) + 2, math.ceil(nx / scale) + 2
    lattice = np.random.default_rng(5).standard_normal((gy, gx))
    got = value_noise(np.random.default_rng(5), shape, scale)
    expect = np.empty(shape)
    for j in range(ny):
        for i in range(nx):
            y, x = j / scale, i / scale
            y0, x0 = math.floor(y), math.floor(x)
            fy, fx = y - y0, x - x0
            expect[j, i] = ((1 - fy) * ((1 - fx) * lattice[y0, x0] + fx * lattice[y0, x0 + 1])
                            + fy * ((1 - fx) * lattice[y0 + 1, x0] + fx * lattice[y0 + 1, x0 + 1]))
    assert np.max(np.abs(got - expect)) < NOISE_ROUND_TOL


def test_rays_parallel_to_the_grid_axes_are_cast_exactly():
    # A nadir view from an orbit heading due north: every ray has a zero north component.
    cam = PushbroomCamera.from_angles(off_nadir_deg=0.0, azimuth_deg=0.0, orbit_azimuth_deg=0.0,
                                      orbit_height_m=600e3, gsd_m=0.5, width=32, height=32)
    grid = build_surface(seed=1, e_min=-30.0, n_min=-30.0, e_max=30.0, n_max=30.0, cell_m=0.25, aoi_half_m=10.0)
    col, row = np.meshgrid(np.arange(32.0), np.arange(32.0))
    origin, d = cam.ray(col=col.ravel(), row=row.ravel())
    assert np.all(d[:, 1] == 0.0)
    hits = cast_rays(grid, origin, d)
    top = hits.face == FACE_TOP
    p = hits.point
    assert np.max(np.abs(p[top, 2] - grid.height(e=p[top, 0], n=p[top, 1]))) < ON_PLANE_TOL_M
    assert np.all(_min_clearance(grid, p, -d, grid.max_height() + 0.1) > 0.0)


@pytest.mark.parametrize("heading", [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)])
def test_a_ray_that_leaves_the_grid_without_a_hit_is_an_error(heading):
    """A ray 1 m inside an edge, falling 1 mm per metre towards it, leaves the grid above the
    ground: the error counts that ray alone (a nadir ray cast with it hits the ground when cast
    without it)."""
    grid = build_surface(seed=1, e_min=-30.0, n_min=-30.0, e_max=30.0, n_max=30.0, cell_m=0.25,
                         aoi_half_m=10.0)
    de, dn = heading
    top = grid.max_height() + 1.0
    start = np.array([[29.0 * de, 29.0 * dn, top], [0.0, 0.0, top]])
    direction = np.array([[de, dn, -1e-3], [0.0, 0.0, -1.0]])
    with pytest.raises(RuntimeError, match="1 ray\\(s\\) left the"):
        cast_rays(grid, start, direction)
    assert cast_rays(grid, start[1:], direction[1:]).face[0] == FACE_TOP


def test_parse_location():
    from satsweep.synth.scene import parse_location

    assert parse_location("-81.66,30.32") == (-81.66, 30.32)
    for bad in ("north", "1,2,3", "1", "1;2"):
        with pytest.raises(OptionsError, match="LON,LAT"):
            parse_location(bad)
