"""AOI footprints, crops and view loading: an exact affine camera, then the real Pleiades pair."""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import pytest
import tifffile

from satsweep.errors import AOIError, ImageFormatError, InputError, RPCError
from satsweep.geometry.altitude import AltitudeRange
from satsweep.geometry.aoi import AOI
from satsweep.io import views as sv

# Pleiades ground sample distance is about 0.5 m (shared data README); a +-150 m box is then
# about 600 px wide. The crop may differ from that by the altitude range's parallax and the
# off-nadir/slope stretch: 20 % is a generous bound that still catches a wrong scale or a bug.
PLEIADES_GSD_M = 0.5
CROP_SIZE_REL_TOL = 0.2
# Projections of our RPC vs rpcm's agree to float64 rounding; a micro-pixel covers it.
RPC_AGREE_PX = 1e-6


@dataclasses.dataclass(frozen=True)
class AffineCamera:
    """An exact stand-in for an RPC: col/row affine in lon, lat and alt (ground truth by hand)."""

    col_offset: float = 0.0
    row_offset: float = 0.0
    px_per_deg: float = 100_000.0  # about 1.1 m pixels
    col_per_m: float = 0.25  # parallax: columns per metre of height

    def projection(self, *, lon, lat, alt):
        lon, lat, alt = (np.asarray(v, np.float64) for v in (lon, lat, alt))
        col = (lon - 10.0) * self.px_per_deg + self.col_per_m * alt - self.col_offset
        row = (20.0 - lat) * self.px_per_deg - self.row_offset
        return np.broadcast_arrays(col, row)

    def cropped(self, *, x0, y0):
        return dataclasses.replace(self, col_offset=self.col_offset + x0, row_offset=self.row_offset + y0)


def _expected_box(cam, box, alt, margin, shape):
    """By hand: project the 8 corners, take the pixels whose centres they span, widen, clip."""
    cols, rows = [], []
    for lon, lat in box.corners():
        for h in (alt.min, alt.max):
            c, r = cam.projection(lon=lon, lat=lat, alt=h)
            cols.append(float(c))
            rows.append(float(r))
    x0 = max(math.floor(min(cols)) - margin, 0)
    y0 = max(math.floor(min(rows)) - margin, 0)
    x1 = min(math.ceil(max(cols)) + 1 + margin, shape[1])
    y1 = min(math.ceil(max(rows)) + 1 + margin, shape[0])
    return x0, y0, x1, y1


CAM = AffineCamera()
ALT = AltitudeRange(100.0, 140.0)  # 40 m of height = 10 columns of parallax


def test_footprint_of_affine_camera():
    # lon 10.001..10.002 -> cols 100..200, +25..35 for the heights; lat 19.999..19.9985 -> rows 100..150.
    box = AOI(10.001, 19.9985, 10.002, 19.999)
    got = sv.aoi_footprint(CAM, box, ALT, (400, 500))
    assert got == _expected_box(CAM, box, ALT, 0, (400, 500))
    c0, _ = CAM.projection(lon=10.001, lat=20.0, alt=ALT.min)
    c1, _ = CAM.projection(lon=10.002, lat=20.0, alt=ALT.max)
    assert got[0] <= c0 and got[2] - 1 >= c1  # both altitude bounds are covered
    with_margin = sv.aoi_footprint(CAM, box, ALT, (400, 500), margin_px=7)
    assert with_margin == (got[0] - 7, got[1] - 7, got[2] + 7, got[3] + 7)


def test_footprint_clips_to_image_and_warns(caplog):
    box = AOI(10.001, 19.9985, 10.002, 19.999)  # cols 125..235, rows 100..150
    shape = (120, 180)
    with caplog.at_level(logging.WARNING, logger="satsweep.io.views"):
        got = sv.aoi_footprint(CAM, box, ALT, shape, margin_px=5, path="img.tif")
    assert got == _expected_box(CAM, box, ALT, 5, shape)
    assert got[2] == 180 and got[3] == 120
    assert "img.tif" in caplog.text and "only about" in caplog.text


def test_footprint_past_the_edge_by_a_sliver_does_not_warn(caplog):
    """An image whose last column's centre lies half a pixel short of the footprint's edge
    sees all but a sliver of it (over 99.5%): no warning; a few columns short, one."""
    box = AOI(10.001, 19.9985, 10.002, 19.999)
    c0, r0, c1, r1 = sv.projected_aoi_box(CAM.projection, box, ALT)
    width = int(np.floor(c1 + 0.5))  # the edge (width - 0.5) at most half a pixel short of c1
    seen = (width - 0.5 - c0) / (c1 - c0)
    assert sv.PARTIAL_AOI_WARN_FRACTION <= seen < 1.0, seen  # the case this test is about
    with caplog.at_level(logging.WARNING, logger="satsweep.io.views"):
        sv.aoi_footprint(CAM, box, ALT, (400, width), path="img.tif")
    assert "only about" not in caplog.text
    with caplog.at_level(logging.WARNING, logger="satsweep.io.views"):
        sv.aoi_footprint(CAM, box, ALT, (400, width - 3), path="img.tif")
    assert "img.tif" in caplog.text and "only about 9" in caplog.text


def test_footprint_outside_image_names_the_image():
    far = AOI(10.01, 19.98, 10.02, 19.99)  # thousands of pixels away
    with pytest.raises(AOIError, match="img_07.tif.*does not see the AOI"):
        sv.aoi_footprint(CAM, far, ALT, (400, 500), path="data/img_07.tif")


def test_crop_to_aoi_slices_and_shifts_the_camera():
    image = np.arange(400 * 500, dtype=np.uint16).reshape(400, 500)
    box = AOI(10.001, 19.9985, 10.002, 19.999)
    view = sv.crop_to_aoi(image, CAM, box, ALT, margin_px=4, path="a.tif")
    x0, y0, x1, y1 = _expected_box(CAM, box, ALT, 4, image.shape)
    assert (view.x0, view.y0, view.width, view.height) == (x0, y0, x1 - x0, y1 - y0)
    np.testing.assert_array_equal(view.image, image[y0:y1, x0:x1])
    assert view.image.dtype == np.uint16 and view.path == "a.tif" and view.name == "a.tif"
    # The crop's camera sees every ground point at the full image's pixel minus the offset.
    lon, lat = np.array([10.0012, 10.0019]), np.array([19.9986, 19.9989])
    c, r = view.rpc.projection(lon=lon, lat=lat, alt=120.0)
    cf, rf = CAM.projection(lon=lon, lat=lat, alt=120.0)
    np.testing.assert_array_equal(c, cf - x0)
    np.testing.assert_array_equal(r, rf - y0)


def test_crop_to_aoi_converts_other_pixel_types_to_float32():
    image = np.arange(400 * 500, dtype=np.float64).reshape(400, 500)
    view = sv.crop_to_aoi(image, CAM, AOI(10.001, 19.9985, 10.002, 19.999), ALT)
    assert view.image.dtype == np.float32


def test_load_views_needs_two_distinct_images(tmp_path, pleiades_pair):
    box = AOI(55.64, -21.24, 55.66, -21.22)
    img = str(pleiades_pair / "img_01.tif")
    with pytest.raises(InputError, match="at least 2 images, got 1"):
        sv.load_views([img], box, ALT)
    with pytest.raises(InputError, match="given twice"):
        sv.load_views([img, img], box, ALT)
    # a folder is named as such, not counted as one image
    with pytest.raises(ImageFormatError, match=f"{pleiades_pair}: is a folder, not an image"):
        sv.load_views([str(pleiades_pair)], box, ALT)


def test_load_views_bad_images_are_named(tmp_path, pleiades_pair):
    box = AOI(55.64, -21.24, 55.66, -21.22)
    good = str(pleiades_pair / "img_01.tif")
    with pytest.raises(ImageFormatError, match="missing.tif"):
        sv.load_views([good, str(tmp_path / "missing.tif")], box, ALT)
    plain = tmp_path / "plain.tif"
    tifffile.imwrite(plain, np.zeros((8, 8), np.uint16))
    with pytest.raises(RPCError, match="plain.tif"):
        sv.load_views([good, str(plain)], box, ALT)


def _pleiades_aoi(pleiades_pair):
    """+-150 m box around the ground seen by the centre of img_01 at 2340 m."""
    from satsweep.geometry.geodesy import ENUFrame
    from satsweep.geometry.rpc import RPCModel

    rpc = RPCModel.from_image(pleiades_pair / "img_01.tif")
    lon, lat = rpc.localization(col=511.5, row=511.5, alt=2340.0)
    frame = ENUFrame(float(lon), float(lat), 2340.0)
    lons, lats, _ = frame.to_geodetic(e=np.array([-150.0, 150.0]), n=np.array([-150.0, 150.0]), u=0.0)
    return AOI(lons[0], lats[0], lons[1], lats[1]), (float(lon), float(lat))


def test_load_views_pleiades_pair(pleiades_pair):
    import rpcm

    box, (lon_c, lat_c) = _pleiades_aoi(pleiades_pair)
    alt = AltitudeRange(2300.0, 2380.0)
    margin = 16
    paths = [str(pleiades_pair / "img_01.tif"), str(pleiades_pair / "img_02.tif")]
    views = sv.load_views(paths, box, alt, margin_px=margin)
    assert [v.path for v in views] == paths
    expected_px = 300.0 / PLEIADES_GSD_M
    for view in views:
        full = tifffile.imread(view.path)
        np.testing.assert_array_equal(view.image, full[view.y0:view.y0 + view.height, view.x0:view.x0 + view.width])
        # Independent oracle: rpcm projects the AOI cube's 8 corners into the full image.
        oracle = rpcm.rpc_from_geotiff(view.path)
        cols, rows = [], []
        for lon, lat in box.corners():
            for h in (alt.min, alt.max):
                c, r = oracle.projection(lon, lat, h)
                cols.append(c)
                rows.append(r)
        # Every corner is inside the crop, with the margin on each side, and the crop is tight.
        assert view.x0 == math.floor(min(cols)) - margin and view.y0 == math.floor(min(rows)) - margin
        assert view.x0 + view.width == math.ceil(max(cols)) + 1 + margin
        assert view.y0 + view.height == math.ceil(max(rows)) + 1 + margin
        for size in (view.width - 2 * margin, view.height - 2 * margin):
            assert abs(size - expected_px) < CROP_SIZE_REL_TOL * expected_px
        # The AOI centre lands inside the crop, where rpcm puts it (minus the crop offset).
        c, r = view.rpc.projection(lon=lon_c, lat=lat_c, alt=2340.0)
        oc, orow = oracle.projection(lon_c, lat_c, 2340.0)
        assert abs(c - (oc - view.x0)) < RPC_AGREE_PX and abs(r - (orow - view.y0)) < RPC_AGREE_PX
        assert margin <= c <= view.width - 1 - margin and margin <= r <= view.height - 1 - margin


def test_load_views_far_aoi_names_the_image(pleiades_pair):
    paths = [str(pleiades_pair / "img_01.tif"), str(pleiades_pair / "img_02.tif")]
    far = AOI(55.70, -21.30, 55.71, -21.29)  # about 8 km away, outside both crops
    with pytest.raises(AOIError, match="img_01.tif.*does not see the AOI"):
        sv.load_views(paths, far, AltitudeRange(2300.0, 2380.0))


def test_validity_mask_finds_nan_nodata_and_border_zero_runs():
    from satsweep.io.views import MIN_ZERO_RUN_PX, validity_mask

    a = np.full((40, 50), 1000.0, np.float32)
    assert validity_mask(a) is None  # all data
    a[0:10, 0:20] = 0.0  # a run of zeros at the border: a delivery's fill
    a[20:22, 20:22] = 0.0  # dark pixels inside the image: data
    a[30, 49] = 0.0  # one zero pixel at the border: too short a run to be fill
    a[5, 40] = np.nan
    a[35, 5] = -9999.0
    mask = validity_mask(a, nodata=-9999.0)
    expected = np.ones(a.shape, bool)
    expected[0:10, 0:20] = False
    expected[5, 40] = expected[35, 5] = False
    np.testing.assert_array_equal(mask, expected)
    assert 10 * 20 >= MIN_ZERO_RUN_PX > 1


def test_tonemap_ignores_no_data_and_flattens_it():
    from satsweep.io.images import tonemap

    rng = np.random.default_rng(0)
    a = rng.uniform(500, 3000, (30, 30))
    valid = np.ones(a.shape, bool)
    valid[:, :10] = False
    with_fill = a.copy()
    with_fill[~valid] = 0.0
    t = tonemap(with_fill, valid=valid)
    np.testing.assert_allclose(t[valid], tonemap(a[:, 10:]).ravel(), atol=1e-6)
    assert np.all(t[~valid] == np.median(t[valid]).astype(np.float32))
