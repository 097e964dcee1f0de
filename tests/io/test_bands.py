"""Rasters on disk read and written by windows, and the streamed GeoTIFFs made from them, checked
against numpy and against independent readers (tifffile, rasterio/GDAL)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from satsweep.io.bands import RawBand, read_npy_window
from satsweep.io.cog import overview_shapes, write_cog


def test_raw_band_windows_match_numpy(tmp_path):
    rng = np.random.default_rng(0)
    truth = np.full((37, 53), np.nan, np.float32)
    band = RawBand.create(tmp_path / "b.raw", truth.shape, np.float32, np.nan)
    for _ in range(20):
        r0, c0 = rng.integers(0, 30), rng.integers(0, 45)
        block = rng.normal(size=(rng.integers(1, 8), rng.integers(1, 9))).astype(np.float32)
        block = block[:truth.shape[0] - r0, :truth.shape[1] - c0]
        band.write(int(r0), int(c0), block)
        truth[r0:r0 + block.shape[0], c0:c0 + block.shape[1]] = block
    np.testing.assert_array_equal(band.read(0, 37, 0, 53), truth)
    np.testing.assert_array_equal(band.read(5, 17, 3, 40), truth[5:17, 3:40])
    with pytest.raises(ValueError, match="outside the band"):
        band.read(0, 38, 0, 53)


def test_unwritten_cells_read_as_the_fill_value(tmp_path):
    band = RawBand.create(tmp_path / "m.raw", (4, 5), np.uint8, 255)
    band.write(1, 1, np.zeros((2, 2), np.uint8))  # zeros written are not "unwritten"
    expected = np.full((4, 5), 255, np.uint8)
    expected[1:3, 1:3] = 0
    np.testing.assert_array_equal(band.read(0, 4, 0, 5), expected)


def test_npy_window_reads_only_the_window(tmp_path):
    a = np.arange(12 * 17, dtype=np.float64).reshape(12, 17)
    np.save(tmp_path / "a.npy", a)
    np.testing.assert_array_equal(read_npy_window(tmp_path / "a.npy", 3, 9, 2, 15), a[3:9, 2:15])


def _nanmean_2x2(a: np.ndarray) -> np.ndarray:
    """Independent reference of an "average" overview: per 2 x 2 block, the mean of its finite
    cells (NaN where none), odd sides padded with NaN."""
    h, w = a.shape
    out = np.full((-(-h // 2), -(-w // 2)), np.nan)
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            block = a[2 * i:2 * i + 2, 2 * j:2 * j + 2].astype(np.float64)
            finite = block[np.isfinite(block)]
            if finite.size:
                out[i, j] = finite.mean()
    return out.astype(np.float32)


def test_streamed_geotiff_is_tiled_compressed_with_overviews_for_gdal(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    import tifffile

    rng = np.random.default_rng(1)
    a = rng.normal(100.0, 5.0, (150, 230)).astype(np.float32)
    a[rng.random(a.shape) < 0.1] = np.nan
    band = RawBand.create(tmp_path / "dsm.raw", a.shape, np.float32, np.nan)
    band.write(0, 0, a)
    path = tmp_path / "dsm.tif"
    write_cog(path, band, epsg=32631, x_min=450000.0, y_max=5400000.0, resolution=0.5,
              nodata=math.nan, description="height", units="m",
              items={"VERTICAL_REFERENCE": "WGS84 ellipsoid"}, tile=64)
    np.testing.assert_array_equal(tifffile.imread(path, key=0), a)
    with tifffile.TiffFile(path) as tif:
        assert tif.pages[0].predictor == 3 and tif.pages[0].compression == 8
    with rasterio.open(path) as src:
        assert src.crs.to_epsg() == 32631 and src.transform.a == 0.5
        assert (src.transform.c, src.transform.f) == (450000.0, 5400000.0)
        assert src.block_shapes == [(64, 64)] and src.compression.name == "deflate"
        assert math.isnan(src.nodata) and src.units == ("m",) and src.descriptions == ("height",)
        assert src.tags()["VERTICAL_REFERENCE"] == "WGS84 ellipsoid"
        assert src.overviews(1) == [2, 4]  # halved until one 64 px tile: 75x115, 38x58
        assert overview_shapes(a.shape, 64) == [(75, 115), (38, 58)]
        first = src.read(1, out_shape=(75, 115))  # GDAL reads the first overview
        np.testing.assert_allclose(first, _nanmean_2x2(a), rtol=1e-6, equal_nan=True)
        np.testing.assert_array_equal(src.read(1), a)
