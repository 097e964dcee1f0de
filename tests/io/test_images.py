"""Image reading, tone mapping, GeoTIFF writing/reading (checked with rasterio) and atomic outputs."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
import rasterio
import tifffile

from satsweep.errors import ImageFormatError, OptionsError
from satsweep.io import atomic, geotiff
from satsweep.io import images as sio

# GeoTIFF numbers are stored as float64 and read back exactly.
EXACT = 0.0
# tonemap output is float32: compare with the float64 reference to float32 rounding.
TONEMAP_TOL = 1e-6


# -- read_image --------------------------------------------------------------------------------
def _ramp(shape, dtype):
    return (np.arange(int(np.prod(shape))) % 4093).reshape(shape).astype(dtype)


# The luminance is computed in float32 (three products and two sums): relative rounding of a
# few float32 epsilons (1.2e-7) against the float64 reference below.
LUMA_RTOL = 1e-6


def _luma(rgb):
    """Reference luminance (BT.601) of (..., 3) samples in float64; grey samples unchanged."""
    r, g, b = (rgb[..., k].astype(np.float64) for k in range(3))
    return np.where((r == g) & (g == b), r, 0.299 * r + 0.587 * g + 0.114 * b).astype(np.float32)


def _same(got, expected):
    assert got.dtype == expected.dtype.newbyteorder("=") and got.dtype.isnative
    if expected.dtype == np.float32 and got.shape == expected.shape:
        np.testing.assert_allclose(got, expected, rtol=LUMA_RTOL, atol=0)
    else:
        np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize(
    "kwargs, data, band0",
    [
        ({}, _ramp((37, 53), np.uint16), lambda a: a),
        ({"byteorder": ">"}, _ramp((37, 53), np.int16), lambda a: a),
        ({"tile": (16, 16)}, _ramp((37, 53), np.float32), lambda a: a),
        ({"photometric": "rgb"}, _ramp((37, 53, 3), np.uint8), _luma),
        ({"photometric": "rgb", "planarconfig": "separate"}, _ramp((3, 37, 53), np.uint16),
         lambda a: _luma(np.moveaxis(a, 0, -1))),
        ({"photometric": "minisblack", "planarconfig": "separate"}, _ramp((3, 37, 53), np.uint16),
         lambda a: a[0]),
    ],
    ids=["uint16", "bigendian-int16", "tiled-float32", "rgb-contig", "rgb-separate",
         "planar-separate"],
)
def test_read_image_first_band_and_windows(tmp_path, kwargs, data, band0):
    path = tmp_path / "img.tif"
    tifffile.imwrite(path, data, **kwargs)
    expected = band0(data)
    got = sio.read_image(path)
    assert got.shape == expected.shape
    _same(got, expected)
    window = (5, 7, 41, 30)
    part = sio.read_image(path, window=window)
    _same(part, expected[7:30, 5:41])
    assert sio.image_shape(path) == expected.shape


# Windows of tiled and stripped files, read segment by segment, against tifffile's decoding of the
# whole image: windows inside one segment, across several, over the partial segments at the right
# and bottom edges, and the whole image.
_SEGMENT_WINDOWS = [(3, 2, 9, 7), (10, 14, 75, 50), (60, 40, 90, 70), (0, 0, 90, 70), (0, 69, 1, 70)]


@pytest.mark.parametrize(
    "kwargs, data, band0",
    [
        ({"tile": (16, 32)}, _ramp((70, 90), np.uint16), lambda a: a),
        ({"tile": (16, 16), "compression": "zlib"}, _ramp((70, 90), np.float32), lambda a: a),
        ({"tile": (32, 16), "compression": "zlib", "predictor": True, "byteorder": ">"},
         _ramp((70, 90), np.int16), lambda a: a),
        ({"rowsperstrip": 8, "compression": "zlib"}, _ramp((70, 90), np.uint16), lambda a: a),
        ({"rowsperstrip": 5, "compression": "zlib", "predictor": True}, _ramp((70, 90), np.uint16),
         lambda a: a),
        ({"photometric": "rgb", "tile": (16, 16), "compression": "zlib"},
         _ramp((70, 90, 3), np.uint8), _luma),
        ({"photometric": "rgb", "planarconfig": "separate", "rowsperstrip": 8,
          "compression": "zlib"}, _ramp((3, 70, 90), np.uint8),
         lambda a: _luma(np.moveaxis(a, 0, -1))),
        ({"photometric": "minisblack", "planarconfig": "separate", "rowsperstrip": 8,
          "compression": "zlib"}, _ramp((3, 70, 90), np.uint16), lambda a: a[0]),
        ({"photometric": "minisblack", "planarconfig": "separate", "tile": (16, 16)},
         _ramp((2, 70, 90), np.float64), lambda a: a[0]),
    ],
    ids=["tiled", "tiled-zlib-float32", "tiled-predictor-bigendian", "strips-zlib",
         "strips-predictor", "rgb-tiled", "rgb-separate-strips", "planar-strips", "planar-tiled"],
)
def test_read_image_windows_by_segment(tmp_path, kwargs, data, band0):
    path = tmp_path / "img.tif"
    tifffile.imwrite(path, data, **kwargs)
    whole = band0(tifffile.imread(path))
    for x0, y0, x1, y1 in _SEGMENT_WINDOWS:
        got = sio.read_image(path, window=(x0, y0, x1, y1))
        _same(got, whole[y0:y1, x0:x1])


def _ngrdi(rgb):
    """Reference (G - R) / (G + R) in float64, 0 where both are 0."""
    r, g = (rgb[..., k].astype(np.float64) for k in (0, 1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(r + g > 0, (g - r) / (r + g), 0.0)


@pytest.mark.parametrize(
    "kwargs, data",
    [
        ({"photometric": "rgb"}, _ramp((70, 90, 3), np.uint8)),
        ({"photometric": "rgb", "byteorder": ">"}, _ramp((70, 90, 3), np.uint16)),
        ({"photometric": "rgb", "tile": (16, 16), "compression": "zlib"},
         _ramp((70, 90, 3), np.uint8)),
        ({"photometric": "rgb", "planarconfig": "separate", "rowsperstrip": 8,
          "compression": "zlib"}, _ramp((3, 70, 90), np.uint16)),
    ],
    ids=["rgb-contig", "rgb-bigendian", "rgb-tiled", "rgb-separate-strips"],
)
def test_read_vegetation_index_of_rgb_windows(tmp_path, kwargs, data):
    """The normalised green-red difference of an RGB image's windows (memory-mapped, by
    segment, whole), against a float64 reference of tifffile's bands."""
    path = tmp_path / "img.tif"
    tifffile.imwrite(path, data, **kwargs)
    bands = tifffile.imread(path)
    if bands.shape[0] == 3:
        bands = np.moveaxis(bands, 0, -1)
    whole = _ngrdi(bands)
    assert np.ptp(whole) > 0.5  # the ramp has green and red pixels
    got = sio.read_vegetation_index(path)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, whole, rtol=LUMA_RTOL, atol=LUMA_RTOL)
    for x0, y0, x1, y1 in _SEGMENT_WINDOWS:
        got = sio.read_vegetation_index(path, window=(x0, y0, x1, y1))
        np.testing.assert_allclose(got, whole[y0:y1, x0:x1], rtol=LUMA_RTOL, atol=LUMA_RTOL)


@pytest.mark.parametrize(
    "kwargs, data",
    [
        ({"photometric": "rgb", "byteorder": ">"}, _ramp((70, 90, 3), np.uint16)),
        ({"photometric": "rgb", "tile": (16, 16), "compression": "zlib"},
         _ramp((70, 90, 3), np.uint8)),
        ({}, _ramp((70, 90), np.uint16)),
    ],
    ids=["rgb-bigendian", "rgb-tiled", "grey"],
)
def test_read_image_and_vegetation_in_one_read_equal_the_two_readers(tmp_path, kwargs, data):
    """One read gives exactly what read_image and read_vegetation_index give apart (None for
    a grey image), over every window."""
    path = tmp_path / "img.tif"
    tifffile.imwrite(path, data, **kwargs)
    for window in [None] + _SEGMENT_WINDOWS:
        image, index = sio.read_image_and_vegetation(path, window=window)
        expected = sio.read_image(path, window=window)
        assert image.dtype == expected.dtype
        np.testing.assert_array_equal(image, expected)
        veg = sio.read_vegetation_index(path, window=window)
        if veg is None:
            assert index is None
        else:
            np.testing.assert_array_equal(index, veg)


def test_read_vegetation_index_is_none_without_colour(tmp_path):
    """A grey image (and a grey image of several planes) has no vegetation index; a window
    outside an RGB image is the caller's error."""
    path = tmp_path / "img.tif"
    tifffile.imwrite(path, _ramp((37, 53), np.uint16))
    assert sio.read_vegetation_index(path) is None
    tifffile.imwrite(path, _ramp((3, 37, 53), np.uint16), photometric="minisblack",
                     planarconfig="separate")
    assert sio.read_vegetation_index(path, window=(0, 0, 10, 10)) is None
    tifffile.imwrite(path, _ramp((37, 53, 3), np.uint8), photometric="rgb")
    with pytest.raises(ValueError, match="not inside"):
        sio.read_vegetation_index(path, window=(0, 0, 60, 10))


def test_read_image_window_decodes_only_its_segments(tmp_path):
    # A tile that the window does not overlap is made undecodable: the whole image can no longer
    # be read, the window still can, so the reader did not decode that tile.
    path = tmp_path / "img.tif"
    data = _ramp((64, 64), np.uint16)
    tifffile.imwrite(path, data, tile=(16, 16), compression="zlib")
    with tifffile.TiffFile(path) as tif:
        page = tif.pages.first
        offset, count = page.dataoffsets[15], page.databytecounts[15]  # the last tile
    raw = bytearray(path.read_bytes())
    raw[offset:offset + count] = b"\xff" * count
    path.write_bytes(bytes(raw))
    with pytest.raises(ImageFormatError, match="cannot decode"):
        sio.read_image(path)
    np.testing.assert_array_equal(sio.read_image(path, window=(2, 3, 40, 45)), data[3:45, 2:40])


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
def test_read_image_window_of_sparse_file(tmp_path):
    # GDAL omits empty blocks with SPARSE_OK (byte count 0); they read as zeros, as GDAL reads them.
    from rasterio.windows import Window

    path = tmp_path / "sparse.tif"
    data = _ramp((70, 90), np.uint16) + 1
    with rasterio.open(path, "w", driver="GTiff", width=90, height=70, count=1, dtype="uint16",
                       tiled=True, blockxsize=32, blockysize=32, sparse_ok=True,
                       compress="deflate") as ds:
        ds.write(data[:32, :32], 1, window=Window(0, 0, 32, 32))
    with rasterio.open(path) as ds:
        expected = ds.read(1)
    assert expected[40:, 40:].max() == 0  # the file is sparse there
    np.testing.assert_array_equal(sio.read_image(path, window=(20, 25, 80, 60)),
                                  expected[25:60, 20:80])


def test_read_image_window_of_real_image(pleiades_pair):
    path = pleiades_pair / "img_01.tif"
    full = tifffile.imread(path)
    part = sio.read_image(path, window=(100, 200, 300, 250))
    np.testing.assert_array_equal(part, full[200:250, 100:300])
    # A plain in-memory copy, not a view of a memory map that would keep the file open.
    assert type(part) is np.ndarray and part.base is None


def test_read_image_bad_window(tmp_path):
    path = tmp_path / "img.tif"
    tifffile.imwrite(path, np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match="window"):
        sio.read_image(path, window=(0, 0, 11, 5))


def test_read_image_missing_and_folder(tmp_path):
    with pytest.raises(ImageFormatError, match="no such file") as exc:
        sio.read_image(tmp_path / "nope.tif")
    assert str(tmp_path / "nope.tif") in str(exc.value)
    with pytest.raises(ImageFormatError, match="folder"):
        sio.read_image(tmp_path)


def test_read_image_not_a_tiff(tmp_path):
    path = tmp_path / "img.tif"
    path.write_text("LINE_OFF: 12\n")
    with pytest.raises(ImageFormatError, match="not a readable TIFF") as exc:
        sio.read_image(path)
    assert exc.value.path == str(path)
    empty = tmp_path / "empty.tif"
    empty.write_bytes(b"")
    with pytest.raises(ImageFormatError, match="empty.tif"):
        sio.read_image(empty)


@pytest.mark.parametrize("name, head, what", [
    ("img.jp2", b"\x00\x00\x00\x0cjP  \r\n\x87\n" + b"\x00" * 20, "JPEG 2000 \\(JP2\\)"),
    ("img.j2k", b"\xff\x4f\xff\x51" + b"\x00" * 20, "JPEG 2000 codestream"),
    ("img.ntf", b"NITF02.10" + b"\x00" * 20, "NITF"),
])
def test_read_image_names_other_satellite_formats(tmp_path, name, head, what):
    path = tmp_path / name
    path.write_bytes(head)
    with pytest.raises(ImageFormatError, match=what + ".*gdal_translate -of GTiff " + name) as exc:
        sio.read_image(path)
    assert exc.value.path == str(path)


def test_read_image_truncated_pixel_data(tmp_path):
    whole = tmp_path / "whole.tif"
    tifffile.imwrite(whole, _ramp((64, 64), np.uint16))
    data = whole.read_bytes()
    cut = tmp_path / "cut.tif"
    cut.write_bytes(data[: len(data) - 1000])
    with pytest.raises(ImageFormatError, match="truncated") as exc:
        sio.read_image(cut)
    assert "cut.tif" in str(exc.value)


def test_read_image_truncated_before_directory(tmp_path, pleiades_pair):
    # The Pleiades crop keeps its image directory at the end: cutting it loses the directory.
    data = (pleiades_pair / "img_01.tif").read_bytes()
    cut = tmp_path / "cut.tif"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageFormatError, match="cut.tif"):
        sio.read_image(cut)


@pytest.mark.parametrize(
    "data, match",
    [(np.zeros((8, 16), bool), "1-bit"), (np.zeros((8, 16), np.complex64), "complex")],
    ids=["bilevel", "complex"],
)
def test_read_image_unsupported_layout(tmp_path, data, match):
    path = tmp_path / "img.tif"
    tifffile.imwrite(path, data)
    with pytest.raises(ImageFormatError, match=match):
        sio.read_image(path)


@pytest.mark.filterwarnings("ignore::rasterio.errors.NotGeoreferencedWarning")
@pytest.mark.parametrize("compress", ["deflate", "lzw"])
def test_read_image_compressed_by_gdal(tmp_path, compress):
    # GDAL (through rasterio) writes the file; tifffile decodes deflate itself, while LZW needs the
    # optional imagecodecs package: without it the error must say so.
    path = tmp_path / f"{compress}.tif"
    data = _ramp((40, 60), np.uint16)
    with rasterio.open(path, "w", driver="GTiff", width=60, height=40, count=1, dtype="uint16",
                       compress=compress, tiled=False) as ds:
        ds.write(data, 1)
    try:
        import imagecodecs  # noqa: F401
        has_codecs = True
    except ImportError:
        has_codecs = False
    if compress == "deflate" or has_codecs:
        np.testing.assert_array_equal(sio.read_image(path), data)
        np.testing.assert_array_equal(sio.read_image(path, window=(3, 4, 50, 30)), data[4:30, 3:50])
    else:
        with pytest.raises(ImageFormatError, match="LZW.*imagecodecs") as exc:
            sio.read_image(path)
        assert exc.value.path == str(path)


# -- tonemap -----------------------------------------------------------------------------------
def test_tonemap_matches_reference():
    rng = np.random.default_rng(0)
    img = rng.gamma(2.0, 300.0, (64, 80)).astype(np.uint16)
    img[0, :5] = 65535  # saturated pixels must not stretch the scale
    lo, hi = np.percentile(img.astype(np.float64), [2.0, 98.0])
    expected = np.clip((img - lo) / (hi - lo), 0.0, 1.0) ** (1.0 / 2.2)
    got = sio.tonemap(img, low_percentile=2.0, high_percentile=98.0)
    assert got.dtype == np.float32 and got.shape == img.shape
    np.testing.assert_allclose(got, expected, atol=TONEMAP_TOL)
    assert got.min() == 0.0 and got.max() == 1.0


def test_tonemap_gamma_midpoint():
    img = np.array([[0.0, 50.0, 100.0]])
    got = sio.tonemap(img, low_percentile=0.0, high_percentile=100.0, gamma=0.5)
    np.testing.assert_allclose(got, [[0.0, math.sqrt(0.5), 1.0]], atol=TONEMAP_TOL)


@pytest.mark.parametrize(
    "img",
    [np.full((5, 7), 123.0), np.full((5, 7), np.nan), np.zeros((0, 3))],
    ids=["constant", "all-nan", "empty"],
)
def test_tonemap_degenerate_is_zeros(img):
    got = sio.tonemap(img)
    assert got.shape == img.shape and got.dtype == np.float32
    assert not np.isnan(got).any() and (got == 0.0).all()


def test_tonemap_nan_pixels_become_zero():
    img = np.arange(20, dtype=np.float64).reshape(4, 5)
    img[1, 1] = np.nan
    img[2, 2] = np.inf
    got = sio.tonemap(img)
    assert np.isfinite(got).all() and got[1, 1] == 0.0 and got[2, 2] == 0.0
    assert 0.0 <= got.min() and got.max() <= 1.0


@pytest.mark.parametrize("kwargs", [{"low_percentile": 60.0, "high_percentile": 40.0},
                                    {"high_percentile": 101.0}, {"gamma": 0.0}])
def test_tonemap_rejects_bad_parameters(kwargs):
    with pytest.raises(OptionsError):
        sio.tonemap(np.zeros((3, 3)), **kwargs)


# -- GeoTIFF -----------------------------------------------------------------------------------
def test_write_geotiff_read_by_rasterio_utm(tmp_path):
    path = tmp_path / "dsm.tif"
    data = np.linspace(2000.0, 2500.0, 7 * 9).reshape(7, 9)
    data[3, 4] = np.nan
    geotiff.write_geotiff(path, data, epsg=32740, x_min=359746.25, y_max=7651923.5, resolution=0.5)
    with rasterio.open(path) as ds:
        assert ds.crs.to_epsg() == 32740
        t = ds.transform
        assert (t.a, t.b, t.c, t.d, t.e, t.f) == (0.5, 0.0, 359746.25, 0.0, -0.5, 7651923.5)
        assert ds.dtypes == ("float32",)
        assert math.isnan(ds.nodata)
        band = ds.read(1)
        mask = ds.read_masks(1)
    np.testing.assert_array_equal(band, data.astype(np.float32))
    assert mask[3, 4] == 0 and (mask > 0).sum() == data.size - 1
    assert sorted(os.listdir(tmp_path)) == ["dsm.tif"]  # no temporary left behind


def test_write_geotiff_integer_geographic(tmp_path):
    path = tmp_path / "dem.tif"
    data = _ramp((6, 5), np.int16) - 100
    data[0, 0] = -32768
    geotiff.write_geotiff(path, data, epsg=4326, x_min=55.5, y_max=-21.0, resolution=1 / 3600,
                      nodata=-32768, dtype=np.int16)
    with rasterio.open(path) as ds:
        assert ds.crs.to_epsg() == 4326
        assert ds.transform.a == 1 / 3600 and ds.transform.e == -1 / 3600
        assert (ds.transform.c, ds.transform.f) == (55.5, -21.0)
        assert ds.nodata == -32768 and ds.dtypes == ("int16",)
        np.testing.assert_array_equal(ds.read(1), data)
    back, info = geotiff.read_geotiff(path)
    np.testing.assert_array_equal(back, data)
    assert info == geotiff.GeoInfo(epsg=4326, x_min=55.5, y_max=-21.0, resolution=1 / 3600, nodata=-32768.0)


@pytest.mark.parametrize(
    "kwargs, match",
    [({"epsg": 1}, "epsg"), ({"resolution": 0.0}, "resolution"),
     ({"resolution": float("nan")}, "resolution"), ({"dtype": np.int16}, "nan"),
     ({"dtype": np.uint8, "nodata": -1}, "not representable")],
)
def test_write_geotiff_rejects_bad_arguments(tmp_path, kwargs, match):
    args = dict(epsg=32631, x_min=0.0, y_max=0.0, resolution=1.0)
    args.update(kwargs)
    with pytest.raises(OptionsError, match=match):
        geotiff.write_geotiff(tmp_path / "x.tif", np.zeros((2, 2)), **args)
    assert os.listdir(tmp_path) == []


def test_read_geotiff_inverts_write(tmp_path):
    path = tmp_path / "dsm.tif"
    data = np.arange(12, dtype=np.float32).reshape(3, 4)
    geotiff.write_geotiff(path, data, epsg=32631, x_min=448000.0, y_max=5411000.0, resolution=2.0, nodata=-9999.0)
    back, info = geotiff.read_geotiff(path)
    np.testing.assert_array_equal(back, data)
    assert (info.epsg, info.x_min, info.y_max, info.resolution, info.nodata) == (
        32631, 448000.0, 5411000.0, 2.0, -9999.0)
    # Pixel centres agree with rasterio's (row, col) -> centre coordinates.
    with rasterio.open(path) as ds:
        rx, ry = ds.xy([0, 2, 1], [0, 3, 2])
    x, y = info.pixel_to_xy(col=[0, 3, 2], row=[0, 2, 1])
    np.testing.assert_array_equal(x, rx)
    np.testing.assert_array_equal(y, ry)
    col, row = info.xy_to_pixel(x=x, y=y)
    np.testing.assert_array_equal(col, [0, 3, 2])
    np.testing.assert_array_equal(row, [0, 2, 1])


def test_read_geotiff_real_dsm_matches_rasterio(pleiades_pair):
    path = pleiades_pair / "s2p_dsm.tif"
    data, info = geotiff.read_geotiff(path)
    with rasterio.open(path) as ds:
        assert info.epsg == ds.crs.to_epsg()
        assert (info.x_min, info.y_max, info.resolution) == (ds.transform.c, ds.transform.f, ds.transform.a)
        assert math.isnan(info.nodata) and math.isnan(ds.nodata)
        np.testing.assert_array_equal(data, ds.read(1))


def _geokeys(model, raster, code_key, code):
    return (1, 1, 0, 3, 1024, 0, 1, model, 1025, 0, 1, raster, code_key, 0, 1, code)


def test_read_geotiff_pixel_is_point_and_offset_tiepoint(tmp_path):
    # A tie point at raster (2, 3) of a PixelIsPoint file: GDAL shifts to the corner by half a cell.
    path = tmp_path / "pt.tif"
    tifffile.imwrite(path, np.zeros((6, 8), np.float32), metadata=None, extratags=[
        (33550, "d", 3, (30.0, 30.0, 0.0), True),
        (33922, "d", 6, (2.0, 3.0, 0.0, 500060.0, 4000000.0, 0.0), True),
        (34735, "H", 16, _geokeys(1, 2, 3072, 32633), True),
    ])
    _, info = geotiff.read_geotiff(path)
    with rasterio.open(path) as ds:
        assert (info.x_min, info.y_max, info.resolution, info.epsg) == (
            ds.transform.c, ds.transform.f, ds.transform.a, ds.crs.to_epsg())
    assert info.nodata is None


def test_read_geotiff_errors(tmp_path):
    plain = tmp_path / "plain.tif"
    tifffile.imwrite(plain, np.zeros((4, 4), np.float32))
    with pytest.raises(ImageFormatError, match="not a GeoTIFF") as exc:
        geotiff.read_geotiff(plain)
    assert "plain.tif" in str(exc.value)
    user = tmp_path / "user.tif"
    tifffile.imwrite(user, np.zeros((4, 4), np.float32), metadata=None, extratags=[
        (33550, "d", 3, (1.0, 1.0, 0.0), True),
        (33922, "d", 6, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0), True),
        (34735, "H", 16, _geokeys(1, 1, 3072, 32767), True),
    ])
    with pytest.raises(ImageFormatError, match="user-defined"):
        geotiff.read_geotiff(user)
    rotated = tmp_path / "rot.tif"
    tifffile.imwrite(rotated, np.zeros((4, 4), np.float32), metadata=None, extratags=[
        (34264, "d", 16, (1.0, 0.5, 0, 10.0, 0.5, -1.0, 0, 20.0, 0, 0, 0, 0, 0, 0, 0, 1), True),
        (34735, "H", 16, _geokeys(1, 1, 3072, 32631), True),
    ])
    with pytest.raises(ImageFormatError, match="rotated"):
        geotiff.read_geotiff(rotated)


def test_write_tiff_with_rpc_tag_read_by_rasterio(tmp_path, pleiades_pair):
    from satsweep.geometry.rpc import RPCModel
    from satsweep.geometry.rpc_formats import rpc_tiff_extratag

    rpc = RPCModel.from_image(pleiades_pair / "img_01.tif").cropped(x0=10, y0=20)
    path = tmp_path / "crop.tif"
    data = _ramp((30, 40), np.uint16)
    geotiff.write_tiff(path, data, extratags=[rpc_tiff_extratag(rpc)])
    with rasterio.open(path) as ds:
        np.testing.assert_array_equal(ds.read(1), data)
        assert ds.rpcs.samp_off == rpc.col_offset and ds.rpcs.line_off == rpc.row_offset
        np.testing.assert_array_equal(ds.rpcs.line_num_coeff, rpc.row_num)
    assert sorted(os.listdir(tmp_path)) == ["crop.tif"]


# -- atomic outputs ----------------------------------------------------------------------------
def test_atomic_output_renames_on_success(tmp_path):
    target = tmp_path / "out.tif"
    with atomic.atomic_output(target) as tmp:
        assert os.path.dirname(tmp) == str(tmp_path) and tmp.endswith(".tif") and tmp != str(target)
        with open(tmp, "w") as f:
            f.write("new")
        assert not target.exists()
    assert target.read_text() == "new"
    assert os.listdir(tmp_path) == ["out.tif"]


def test_atomic_output_keeps_old_file_on_error(tmp_path):
    target = tmp_path / "out.tif"
    target.write_text("old")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic.atomic_output(target) as tmp:
            with open(tmp, "w") as f:
                f.write("half")
            raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert os.listdir(tmp_path) == ["out.tif"]


def test_write_geotiff_failure_leaves_nothing(tmp_path):
    target = tmp_path / "dsm.tif"
    with pytest.raises(ValueError, match="2D"):
        geotiff.write_geotiff(target, np.zeros((2, 3, 4)), epsg=32631, x_min=0.0, y_max=0.0, resolution=1.0)
    assert os.listdir(tmp_path) == []


def test_atomic_output_missing_folder(tmp_path):
    with pytest.raises(OptionsError, match="does not exist"):
        with atomic.atomic_output(tmp_path / "no" / "out.tif"):
            pass


def test_non_atomic_write_goes_straight_to_the_target(tmp_path):
    target = tmp_path / "plain.tif"
    geotiff.write_tiff(target, np.ones((3, 3), np.uint8), atomic=False)
    np.testing.assert_array_equal(tifffile.imread(target), np.ones((3, 3), np.uint8))
    assert os.listdir(tmp_path) == ["plain.tif"]


@pytest.mark.parametrize("n_bytes", [2, 4, 6, 12])
def test_read_image_cut_inside_the_header(tmp_path, n_bytes, capsys):
    whole = tmp_path / "whole.tif"
    tifffile.imwrite(whole, _ramp((16, 16), np.uint16))
    cut = tmp_path / "cut.tif"
    cut.write_bytes(whole.read_bytes()[:n_bytes])
    with pytest.raises(ImageFormatError, match="cut.tif"):
        sio.read_image(cut)
    # reported once, by the error: no tifffile log line besides it
    assert "tifffile" not in capsys.readouterr().err
