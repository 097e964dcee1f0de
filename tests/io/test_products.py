"""A DIMAP product given by its DIM file: the scene over its tiles, as GDAL's DIMAP driver
mosaics it (rasterio as the oracle), the product's RPC, its metadata, and its errors."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
import tifffile

from satsweep.errors import ImageFormatError, RPCError
from satsweep.geometry.rpc import RPCModel
from satsweep.geometry.rpc_formats import write_rpc_txt
from satsweep.io.images import image_shape, read_image, read_image_and_vegetation
from satsweep.io.sources import open_source
from tests.geometry.test_rpc import PROJ_VS_RPCM_PX, _assert_same_projection_as, _gdal_rpc

PRODUCT = "PHR1B_P_201306290657283_SEN_001"
# A scene of 50 x 70 pixels in tiles of 32 rows and 40 columns (sizes that differ, so that a
# row / column mix-up shows): 2 x 2 tiles, the last row and column of tiles cut short.
ROWS, COLS, TILE_ROWS, TILE_COLS = 50, 70, 32, 40
TILES = [(1, 1), (1, 2), (2, 1), (2, 2)]


def _dim_xml(*, rows: int, cols: int, tile_rows: int, tile_cols: int, listed, rpc_href: str | None,
             fmt: str = "image/tiff", extra: str = "") -> str:
    files = "".join(f'<Data_File tile_R="{r}" tile_C="{c}"><DATA_FILE_PATH '
                    f'href="IMG_{PRODUCT}_R{r}C{c}.TIF"/></Data_File>' for r, c in listed)
    rpc = ("" if rpc_href is None else
           "<Geoposition><Geoposition_Models><Rational_Function_Model><Component><COMPONENT_TITLE>"
           f'SENSOR Rational Function Model</COMPONENT_TITLE><COMPONENT_PATH href="{rpc_href}"/>'
           "</Component></Rational_Function_Model></Geoposition_Models></Geoposition>")
    return ("<?xml version='1.0'?><Dimap_Document><Metadata_Identification><METADATA_FORMAT "
            'version="2.0">DIMAP</METADATA_FORMAT><METADATA_PROFILE>PHR_SENSOR</METADATA_PROFILE>'
            f"</Metadata_Identification>{extra}{rpc}<Raster_Data><Data_Access><DATA_FILE_FORMAT>"
            f"{fmt}</DATA_FILE_FORMAT><Data_Files>{files}</Data_Files></Data_Access>"
            f"<Raster_Dimensions><NROWS>{rows}</NROWS><NCOLS>{cols}</NCOLS><NBANDS>1</NBANDS>"
            f'<Tile_Set><Regular_Tiling><NTILES_SIZE nrows="{tile_rows}" ncols="{tile_cols}"/>'
            "<OVERLAP_ROW>0</OVERLAP_ROW><OVERLAP_COL>0</OVERLAP_COL></Regular_Tiling></Tile_Set>"
            "</Raster_Dimensions></Raster_Data></Dimap_Document>")


def _delivery(folder: Path, scene: np.ndarray, *, tile_rows: int = TILE_ROWS,
              tile_cols: int = TILE_COLS, listed=None, rpc_href: str | None = None,
              **kw) -> Path:
    """The tiles of ``scene`` (IMG_<product>_RiCj.TIF) and their DIM_<product>.XML."""
    rows, cols = scene.shape[:2]
    tiles = [(r + 1, c + 1) for r in range(-(-rows // tile_rows))
             for c in range(-(-cols // tile_cols))]
    for r, c in tiles:
        part = scene[(r - 1) * tile_rows:r * tile_rows, (c - 1) * tile_cols:c * tile_cols]
        tifffile.imwrite(folder / f"IMG_{PRODUCT}_R{r}C{c}.TIF", part,
                         photometric="rgb" if part.ndim == 3 else None)
    dim = folder / f"DIM_{PRODUCT}.XML"
    dim.write_text(_dim_xml(rows=rows, cols=cols, tile_rows=tile_rows, tile_cols=tile_cols,
                            listed=tiles if listed is None else listed, rpc_href=rpc_href, **kw))
    return dim


@pytest.fixture
def scene() -> np.ndarray:
    return np.random.default_rng(5).integers(0, 4096, (ROWS, COLS)).astype(np.uint16)


def _gdal_read(path: Path, window=None, driver: str = "DIMAP") -> np.ndarray:
    """GDAL's reading (rasterio) of the product file ``path`` by its ``driver``."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path) as src:
            assert src.driver == driver
            if window is None:
                return src.read(1)
            x0, y0, x1, y1 = window
            return src.read(1, window=((y0, y1), (x0, x1)))


@pytest.mark.parametrize("window", [None, (0, 0, 70, 50), (30, 20, 55, 45), (39, 31, 41, 33),
                                    (40, 32, 70, 50), (5, 3, 12, 9)])
def test_a_dim_file_reads_as_gdal_mosaics_its_tiles(tmp_path, scene, window):
    dim = _delivery(tmp_path, scene)
    assert image_shape(dim) == (ROWS, COLS)
    ours = read_image(dim, window=window)
    assert ours.dtype == np.uint16
    np.testing.assert_array_equal(ours, _gdal_read(dim, window))


def test_a_dim_file_takes_the_product_rpc_of_its_scene(shared_data, tmp_path, scene):
    dim = _delivery(tmp_path, scene)
    shutil.copy(shared_data / "rpc_files" / "rpc_PLEIADES.xml", tmp_path / f"RPC_{PRODUCT}.XML")
    ours = RPCModel.from_image(dim)
    # The scene starts where its first tile does: GDAL's RPC of that tile is the scene's.
    _assert_same_projection_as(ours, _gdal_rpc(tmp_path / f"IMG_{PRODUCT}_R1C1.TIF"),
                               PROJ_VS_RPCM_PX)
    # The file the DIM names comes first (any format RPCModel.from_file reads).
    write_rpc_txt(tmp_path / "named_RPC.TXT", ours.cropped(x0=3, y0=4))
    named = RPCModel.from_image(_delivery(tmp_path, scene, rpc_href="named_RPC.TXT"))
    assert named.col_offset == pytest.approx(ours.col_offset - 3)
    assert named.row_offset == pytest.approx(ours.row_offset - 4)


def test_an_rgb_product_reads_its_colour_across_tiles(tmp_path):
    rgb = np.random.default_rng(6).integers(0, 256, (ROWS, COLS, 3)).astype(np.uint8)
    dim = _delivery(tmp_path, rgb)
    whole = tmp_path / "whole.tif"
    tifffile.imwrite(whole, rgb, photometric="rgb")
    for window in (None, (30, 20, 55, 45)):
        grey, green = read_image_and_vegetation(dim, window=window)
        ref_grey, ref_green = read_image_and_vegetation(whole, window=window)
        np.testing.assert_array_equal(grey, ref_grey)
        np.testing.assert_array_equal(green, ref_green)


def test_a_dim_file_opens_as_one_source_with_its_metadata(shared_data, tmp_path, scene):
    strip = ("<Dataset_Sources><Source_Identification><Strip_Source><MISSION>PHR</MISSION>"
             "<MISSION_INDEX>1B</MISSION_INDEX><IMAGING_DATE>2013-06-29</IMAGING_DATE>"
             "<IMAGING_TIME>06:57:28.3Z</IMAGING_TIME></Strip_Source></Source_Identification>"
             "</Dataset_Sources>")
    dim = _delivery(tmp_path, scene, extra=strip)
    shutil.copy(shared_data / "rpc_files" / "rpc_PLEIADES.xml", tmp_path / f"RPC_{PRODUCT}.XML")
    source = open_source(dim)
    assert source.shape == (ROWS, COLS) and source.mask is None and source.nodata is None
    assert source.acquisition.acquisition_time_utc.startswith("2013-06-29T06:57:28")
    np.testing.assert_array_equal(source.read((10, 10, 60, 40)), scene[10:40, 10:60])


def test_the_pleiades_crop_as_a_tiled_product_is_the_same_view(pleiades_pair, tmp_path):
    """A real crop cut into 3 x 2 tiles of 400 x 600 pixels: the same pixels and the same RPC as
    the crop itself, so every stage sees the same view."""
    crop = pleiades_pair / "img_01.tif"
    pixels = read_image(crop)
    write_rpc_txt(tmp_path / f"RPC_{PRODUCT}.TXT", RPCModel.from_image(crop))
    dim = _delivery(tmp_path, pixels, tile_rows=600, tile_cols=400, rpc_href=f"RPC_{PRODUCT}.TXT")
    ours, ref = open_source(dim), open_source(crop)
    assert ours.shape == ref.shape and len(list(tmp_path.glob("IMG_*.TIF"))) == 6
    for window in (None, (350, 550, 450, 650), (0, 599, 1024, 601)):
        np.testing.assert_array_equal(ours.read(window), ref.read(window))
    cols, rows = np.meshgrid(np.linspace(0, 1023, 5), np.linspace(0, 1023, 5))
    lon, lat = ref.rpc.localization(col=cols, row=rows, alt=2340.0)
    for model in (ours.rpc, ref.rpc):
        c, r = model.projection(lon=lon, lat=lat, alt=2340.0)
        np.testing.assert_allclose(c, cols, atol=PROJ_VS_RPCM_PX * 10)
        np.testing.assert_allclose(r, rows, atol=PROJ_VS_RPCM_PX * 10)


@pytest.mark.parametrize("case,message", [
    ("tile missing", r"its tile IMG_.*_R2C2\.TIF is not there"),
    ("tile size", r"its tile IMG_.*_R1C2\.TIF is 40x32 pixels; at R1C2 .* it should be 30x32"),
    ("not listed", r"leave part of the 70x50 scene uncovered \(no tile R2C1\)"),
    ("jp2", r"tiles are JPEG 2000 .*gdal_translate -of GTiff DIM_"),
    ("pixel types", r"tiles differ in pixel type"),
    ("not xml", r"DIMAP product: cannot read its XML"),
])
def test_a_product_that_is_not_one_image_is_an_error_naming_its_dim_file(tmp_path, scene, case,
                                                                       message):
    listed = [(1, 1), (1, 2), (2, 2)] if case == "not listed" else None
    dim = _delivery(tmp_path, scene, listed=listed,
                    fmt="image/jp2" if case == "jp2" else "image/tiff")
    if case == "tile missing":
        (tmp_path / f"IMG_{PRODUCT}_R2C2.TIF").unlink()
    elif case == "tile size":
        tifffile.imwrite(tmp_path / f"IMG_{PRODUCT}_R1C2.TIF", np.zeros((32, 40), np.uint16))
    elif case == "pixel types":
        tifffile.imwrite(tmp_path / f"IMG_{PRODUCT}_R2C1.TIF", np.zeros((18, 40), np.uint8))
    elif case == "not xml":
        dim.write_text(dim.read_text()[:200])
    with pytest.raises(ImageFormatError, match=message) as exc:
        open_source(dim)
    assert str(exc.value).startswith(f"{dim}: DIMAP product: ")


def test_a_product_without_its_rpc_is_an_rpc_error(tmp_path, scene):
    dim = _delivery(tmp_path, scene)
    with pytest.raises(RPCError,
                       match=rf"no RPC: the DIMAP product's RPC file \(RPC_{PRODUCT}\.XML"):
        RPCModel.from_image(dim)


def test_other_xml_is_not_taken_for_a_product(tmp_path):
    other = tmp_path / "scene.xml"
    other.write_text("<catalog><item/></catalog>")
    with pytest.raises(ImageFormatError, match="not a readable TIFF"):
        image_shape(other)


# -- Maxar tiled products (.TIL) ------------------------------------------------------------------
TIL_STEM = "16FEB12345678-P1BS-500123456010_01_P001"
# (ULColOffset, ULRowOffset, LRColOffset, LRRowOffset) of each tile, inclusive: the second
# overlaps the first over columns 30..39 (GDAL's TIL driver: the later tile wins there).
TIL_TILES = [(0, 0, 39, 31), (30, 0, 69, 31), (0, 32, 69, 49)]


def _til_product(folder: Path, scene: np.ndarray, tiles=TIL_TILES, *, imd: bool = True,
                 sizes=None) -> Path:
    """X.TIL over the tiles of ``scene`` at ``tiles``, and X.IMD with its size and a date."""
    from satsweep.synth.multidate import imd_text

    groups = []
    for k, (x0, y0, x1, y1) in enumerate(tiles, start=1):
        name = f"{TIL_STEM}_R{k}C1-500123456010_01_P001.TIF"
        part = scene[y0:y1 + 1, x0:x1 + 1] if sizes is None else np.zeros(sizes[k - 1], scene.dtype)
        tifffile.imwrite(folder / name, part)
        groups.append(f"BEGIN_GROUP = TILE_{k}\n\tfilename = \"{name}\";\n\tULColOffset = {x0};\n"
                      f"\tULRowOffset = {y0};\n\tURColOffset = {x1};\n\tURRowOffset = {y0};\n"
                      f"\tLRColOffset = {x1};\n\tLRRowOffset = {y1};\n\tLLColOffset = {x0};\n"
                      f"\tLLRowOffset = {y1};\nEND_GROUP = TILE_{k}\n")
    til = folder / f"{TIL_STEM}.TIL"
    til.write_text('bandId = "P";\n' + f"numTiles = {len(tiles)};\ntileSizeX = 40;\n"
                   "tileSizeY = 32;\ntileOverlap = 0;\n" + "".join(groups) + "END;\n")
    if imd:
        (folder / f"{TIL_STEM}.IMD").write_text(imd_text(
            date_time="2016-02-12T16:12:34Z", rows=scene.shape[0], cols=scene.shape[1],
            sun_azimuth_deg=151.2, sun_elevation_deg=38.4, sat_azimuth_deg=20.0,
            sat_elevation_deg=70.0, off_nadir_deg=18.0, in_track_deg=5.0, cross_track_deg=-17.0,
            gsd_m=0.31, catalog_id="104001001234AB00", satellite="WV03"))
    return til


@pytest.mark.parametrize("window", [None, (25, 20, 50, 40), (35, 0, 45, 10), (0, 31, 70, 33)])
def test_a_til_file_reads_as_gdal_mosaics_its_tiles(tmp_path, scene, window):
    scene = scene.copy()
    scene[0:32, 30:40] += 1  # the overlap differs between the first two tiles' copies
    til = _til_product(tmp_path, scene)
    tifffile.imwrite(tmp_path / f"{TIL_STEM}_R1C1-500123456010_01_P001.TIF",
                     scene[0:32, 0:40] - np.pad(np.ones((32, 10), np.uint16), ((0, 0), (30, 0))))
    assert image_shape(til) == (ROWS, COLS)
    ours = read_image(til, window=window)
    gdal = _gdal_read(til, window, driver="TIL")
    np.testing.assert_array_equal(ours, gdal)
    x0, y0, x1, y1 = window or (0, 0, COLS, ROWS)
    np.testing.assert_array_equal(ours, scene[y0:y1, x0:x1])  # the later tile's copy


def test_a_til_file_takes_its_rpb_and_its_imd(pleiades_pair, tmp_path, scene):
    til = _til_product(tmp_path, scene)
    with pytest.raises(RPCError, match=rf"no RPC: the Maxar tiled product's RPC file "
                                       rf"\({TIL_STEM}\.RPB\) is not beside it"):
        RPCModel.from_image(til)
    # An RPB as GDAL writes it, of a real RPC.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(pleiades_pair / "img_01.tif") as src:
            rpcs = src.rpcs
        with rasterio.open(tmp_path / "x.tif", "w", driver="GTiff", width=8, height=8, count=1,
                           dtype="uint16", rpcs=rpcs, RPB="YES") as dst:
            dst.write(np.zeros((1, 8, 8), np.uint16))
    shutil.move(tmp_path / "x.RPB", tmp_path / f"{TIL_STEM}.RPB")
    source = open_source(til)
    _assert_same_projection_as(source.rpc, _gdal_rpc(til), PROJ_VS_RPCM_PX)
    assert source.acquisition.acquisition_time_utc.startswith("2016-02-12T16:12:34")
    assert source.acquisition.sun_elevation_deg == pytest.approx(38.4)
    assert source.acquisition.satellite == "WV03"


@pytest.mark.parametrize("case,message", [
    ("no imd", rf"the scene's size is in its {TIL_STEM}\.IMD .*which is not beside it"),
    ("outside", r"TILE_2 .*columns 30\.\.75, rows 0\.\.31 are not inside the 70x50 scene"),
    ("gap", r"leave part of the 70x50 scene uncovered \(column 0, row 32\)"),
    ("size", r"its tile .*_R3C1-.*\.TIF is 70x10 pixels; from column 0, row 32 to column 69, "
             r"row 49 \(TILE_3\) it should be 70x18"),
])
def test_a_til_product_that_is_not_one_image_is_an_error_naming_it(tmp_path, scene, case, message):
    tiles = {"outside": [(0, 0, 39, 31), (30, 0, 75, 31), (0, 32, 69, 49)],
             "gap": TIL_TILES[:2]}.get(case, TIL_TILES)
    sizes = [(32, 40), (32, 40), (10, 70)] if case == "size" else None
    til = _til_product(tmp_path, scene, tiles, imd=case != "no imd", sizes=sizes)
    with pytest.raises(ImageFormatError, match=message) as exc:
        open_source(til)
    assert str(exc.value).startswith(f"{til}: Maxar tiled product: ")
