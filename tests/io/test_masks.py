"""Per-image masks (GDAL's external .msk and internal mask pages, a --mask-dir folder): found
where GDAL finds them, read by windows exactly as written, and made no data in the views."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from satsweep.errors import ImageFormatError, InputError
from satsweep.geometry.altitude import AltitudeRange
from satsweep.geometry.aoi import AOI
from satsweep.io.masks import MASK_SUFFIX, find_mask, mask_files_in
from satsweep.io.sources import ImageSource, open_sources
from tests.io.test_views import AffineCamera

SHAPE = (300, 340)  # rows, columns: neither a multiple of the tile size nor square


def _mask_values() -> np.ndarray:
    """0 over a cloud (a disc) and a strip, 255 elsewhere: GDAL's values."""
    yy, xx = np.mgrid[:SHAPE[0], :SHAPE[1]]
    out = np.full(SHAPE, 255, np.uint8)
    out[np.hypot(xx - 200, yy - 120) < 60] = 0
    out[:, :25] = 0
    return out


def _image(path, *, internal: np.ndarray | None = None, tile=None):
    """A 16-bit image of SHAPE (its values: its pixel's index), with ``internal`` as a 1-bit
    mask page of NewSubfileType 4 after it, as GDAL writes an internal mask."""
    pixels = np.arange(SHAPE[0] * SHAPE[1], dtype=np.uint32).reshape(SHAPE) % 60000 + 1
    kw = {} if tile is None else {"tile": tile}
    with tifffile.TiffWriter(path) as tif:
        tif.write(pixels.astype(np.uint16), photometric="minisblack", **kw)
        if internal is not None:
            tif.write(internal != 0, subfiletype=4, photometric=4, compression="deflate", **kw)
    return path


@pytest.mark.parametrize("tile", [None, (64, 64)])
def test_internal_mask_is_found_and_read_by_windows(tmp_path, tile):
    expected = _mask_values() != 0
    image = _image(tmp_path / "img.tif", internal=_mask_values(), tile=tile)
    mask = find_mask(image, SHAPE)
    assert mask is not None and mask.internal and mask.page == 1
    assert np.array_equal(mask.read(), expected)
    assert np.array_equal(mask.read((30, 70, 301, 222)), expected[70:222, 30:301])


def test_external_mask_beside_the_image_wins_over_the_internal_one(tmp_path):
    image = _image(tmp_path / "img.tif", internal=np.full(SHAPE, 255, np.uint8))
    values = _mask_values()
    tifffile.imwrite(str(image) + MASK_SUFFIX, values, compression="deflate")
    mask = find_mask(image, SHAPE)
    assert not mask.internal and mask.path == str(image) + MASK_SUFFIX
    assert np.array_equal(mask.read((0, 0, SHAPE[1], SHAPE[0])), values != 0)


def test_an_image_without_a_mask_has_none(tmp_path):
    assert find_mask(_image(tmp_path / "img.tif"), SHAPE) is None


def test_upper_case_suffix_is_found_as_gdal_finds_it(tmp_path):
    image = _image(tmp_path / "img.tif")
    tifffile.imwrite(str(image) + MASK_SUFFIX.upper(), _mask_values())
    assert find_mask(image, SHAPE).path == str(image) + MASK_SUFFIX.upper()


def test_a_mask_of_another_size_is_an_error_naming_it(tmp_path):
    image = _image(tmp_path / "img.tif")
    tifffile.imwrite(str(image) + MASK_SUFFIX, np.full((SHAPE[0], SHAPE[1] - 1), 255, np.uint8))
    with pytest.raises(ImageFormatError, match=r"img\.tif\.msk: the mask is 339x300 pixels but "
                                               r"its image 340x300"):
        find_mask(image, SHAPE)


def test_a_float_mask_is_an_error_naming_it(tmp_path):
    image = _image(tmp_path / "img.tif")
    tifffile.imwrite(str(image) + MASK_SUFFIX, np.ones(SHAPE, np.float32))
    with pytest.raises(ImageFormatError, match=r"img\.tif\.msk: a mask holds integers"):
        find_mask(image, SHAPE)


def test_mask_folder_gives_each_image_its_mask_or_none(tmp_path, monkeypatch):
    from satsweep.geometry.rpc import RPCModel

    # (The RPCs do not matter here.)
    monkeypatch.setattr(RPCModel, "from_image", classmethod(lambda cls, path: AffineCamera()))
    folder = tmp_path / "masks"
    folder.mkdir()
    images = [_image(tmp_path / f"view_{k}.tif") for k in range(3)]
    tifffile.imwrite(folder / "VIEW_1.TIF.MSK", _mask_values())
    assert mask_files_in(folder, images) == [None, str(folder / "VIEW_1.TIF.MSK"), None]
    sources = open_sources(images, mask_dir=folder)
    assert [s.mask is not None for s in sources] == [False, True, False]
    assert np.array_equal(sources[1].read_mask(), _mask_values() != 0)


def test_a_mask_folder_that_masks_nothing_or_is_missing_is_an_error(tmp_path):
    images = [_image(tmp_path / f"view_{k}.tif") for k in range(2)]
    (tmp_path / "masks").mkdir()
    (tmp_path / "masks" / "view_0.msk").write_bytes(b"")  # the wrong name: no .tif in it
    with pytest.raises(InputError, match=r"masks: the mask folder holds a mask for none of the 2 "
                                         r"images \(named after each image, as view_0\.tif\.msk\)"):
        mask_files_in(tmp_path / "masks", images)
    with pytest.raises(InputError, match="cannot read the mask folder"):
        mask_files_in(tmp_path / "absent", images)


def test_masked_pixels_are_no_data_in_the_views(tmp_path):
    """The view's ``valid`` is the mask's data pixels and the no-data value's, over the crop."""
    from satsweep.io.views import load_views

    values = _mask_values()
    first = _image(tmp_path / "a.tif", internal=values)
    second = _image(tmp_path / "b.tif")
    cam = AffineCamera()
    aoi = AOI(10.0 + 60 / cam.px_per_deg, 20.0 - 250 / cam.px_per_deg,
              10.0 + 290 / cam.px_per_deg, 20.0 - 40 / cam.px_per_deg)
    alt = AltitudeRange(0.0, 40.0)
    sources = [ImageSource(path=str(p), rpc=cam, shape=SHAPE, nodata=1.0,
                           mask=find_mask(p, SHAPE)) for p in (first, second)]
    views = load_views(sources, aoi, alt, margin_px=0)
    x0, y0 = views[0].x0, views[0].y0
    rows, cols = views[0].image.shape
    expected = (values != 0)[y0:y0 + rows, x0:x0 + cols] & (views[0].image != 1)
    assert 0 < expected.mean() < 1
    assert np.array_equal(views[0].valid, expected)
    # The image without a mask: only its no-data value (pixel index 0 holds 1) is left out.
    assert views[1].valid is None or np.array_equal(views[1].valid, views[1].image != 1)


@pytest.mark.parametrize("internal", ["YES", "NO"])
def test_masks_that_gdal_writes_read_as_gdal_reads_them(tmp_path, internal):
    """rasterio (GDAL) as the oracle: a mask written by ``write_mask``, inside the TIFF
    (GDAL_TIFF_INTERNAL_MASK=YES) or beside it (IMAGE.msk), reads as ``read_masks`` reads it."""
    rasterio = pytest.importorskip("rasterio")
    import warnings

    from rasterio.env import Env

    values = _mask_values()
    path = tmp_path / "img.tif"
    profile = dict(driver="GTiff", width=SHAPE[1], height=SHAPE[0], count=1, dtype="uint16",
                   tiled=True, blockxsize=64, blockysize=64, compress="deflate")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with Env(GDAL_TIFF_INTERNAL_MASK=internal):
            with rasterio.open(path, "w", **profile) as out:
                out.write(np.ones(SHAPE, np.uint16), 1)
                out.write_mask(values)
        with rasterio.open(path) as src:
            gdal_reads = src.read_masks(1) != 0
    mask = find_mask(path, SHAPE)
    assert mask.internal == (internal == "YES")
    assert 0 < gdal_reads.mean() < 1
    assert np.array_equal(mask.read(), gdal_reads)
