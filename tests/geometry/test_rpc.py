"""Tests of satsweep.geometry.rpc against independent references.

Oracles: rpcm (its projection, its iterative localization and its file readers), GDAL through
rasterio (its reading of TIFF tag 50844 and of ``_RPC.TXT`` / ``.RPB`` / ``.aux.xml`` sidecars),
and exact identities (round trips, crop offsets).
"""

from __future__ import annotations

import json
import pickle
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import rasterio
import rpcm
import tifffile

from satsweep.errors import ImageFormatError, LocalizationError, RPCError
from satsweep.geometry.rpc import TIFF_TAG_RPC, RPCModel
from satsweep.geometry.rpc_formats import rpc_tiff_extratag, write_rpc_txt

# Pleiades pair: ground near 2340 m above the ellipsoid (data README); +-100 m covers its relief.
GROUND_ALT = 2340.0
ALTS = (GROUND_ALT - 100.0, GROUND_ALT, GROUND_ALT + 100.0)
# Agreement of our projection with rpcm's: both evaluate the same float64 rational functions in a
# different order; rounding is ~1e-11 px at 2e4-pixel offsets, the requirement is 1e-6 px.
PROJ_VS_RPCM_PX = 1e-6
# Same, relative to the size of the projected coordinate, for the vendor files whose test grid
# (the +-1 normalised ground cube) projects up to 4e5 px away (SkySat has 1-degree scales):
# float64 rounding of a 20-term sum is a few 1e-16 relative; 1e-12 leaves a wide margin.
PROJ_VS_RPCM_REL = 1e-12
# Localization stops once the reprojection is within tol_px (1e-6 px by default): the round trip
# must meet that exactly (the brief asks for 1e-4 px; this is the stricter promise of the API).
ROUND_TRIP_PX = 1e-6
# rpcm's localization stops at 1e-9 px and ours at 1e-6 px: at 0.5 m/px the two solutions differ by
# < 1e-6 m, i.e. ~1e-11 degree; 1e-10 degree (1 cm) allows for the Jacobian's conditioning.
LOC_VS_RPCM_DEG = 1e-10
# rpcm's localization stops at 1e-9 in normalised image units, 5e-7 px at these 512-px scales.
RPCM_LOC_PX = 1e-6
# cropped(): the shifted offset is added instead of subtracted afterwards, a different rounding of
# values up to 4e4 px (ulp 7e-12 px).
CROP_PX = 1e-9

# One point alone vs inside a batch: BLAS may sum the 20 terms in another order (1 ulp, ~2e-12 px).
BATCH_PX = 1e-9

RPC_FILES = ("rpc_IKONOS.txt", "rpc_PLANET_L1A.txt", "rpc_PLANET_L1B.txt", "rpc_PLEIADES.xml",
             "rpc_SPOT6.xml", "rpc_WV2.xml", "rpc_WV3.xml", "skysat_RPC.TXT")


def _pixel_grid(width: int, height: int, n: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid of pixel positions from the outer corner to the opposite outer corner."""
    cols, rows = np.meshgrid(np.linspace(-0.5, width - 0.5, n), np.linspace(-0.5, height - 0.5, n))
    return cols.ravel(), rows.ravel()


def _rpcm_from_ours(m: RPCModel) -> rpcm.RPCModel:
    """rpcm's model built from GDAL-style strings of our numbers (repr is exact)."""
    d = {"LINE_OFF": repr(m.row_offset), "SAMP_OFF": repr(m.col_offset),
         "LAT_OFF": repr(m.lat_offset), "LONG_OFF": repr(m.lon_offset),
         "HEIGHT_OFF": repr(m.alt_offset), "LINE_SCALE": repr(m.row_scale),
         "SAMP_SCALE": repr(m.col_scale), "LAT_SCALE": repr(m.lat_scale),
         "LONG_SCALE": repr(m.lon_scale), "HEIGHT_SCALE": repr(m.alt_scale)}
    for key, v in (("LINE_NUM_COEFF", m.row_num), ("LINE_DEN_COEFF", m.row_den),
                   ("SAMP_NUM_COEFF", m.col_num), ("SAMP_DEN_COEFF", m.col_den)):
        d[key] = " ".join(repr(float(x)) for x in v)
    return rpcm.RPCModel(d)


def _ground_cube(m: RPCModel, n: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """lon/lat/alt on the n^3 grid of the normalised cube [-1, 1]^3 around the offsets."""
    u = np.linspace(-1.0, 1.0, n)
    a, b, c = (g.ravel() for g in np.meshgrid(u, u, u, indexing="ij"))
    return (m.lon_offset + m.lon_scale * a, m.lat_offset + m.lat_scale * b,
            m.alt_offset + m.alt_scale * c)


def _gdal_rpc(path: Path) -> rpcm.RPCModel:
    """The RPC that GDAL (through rasterio) finds for an image, as an rpcm model."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path) as src:
            tags = src.tags(ns="RPC")
    assert tags, f"GDAL found no RPC for {path}"
    return rpcm.RPCModel(tags)


def _assert_same_projection_as(ours: RPCModel, ref: rpcm.RPCModel, tol_px: float) -> None:
    lon, lat, alt = _ground_cube(ours)
    c, r = ours.projection(lon=lon, lat=lat, alt=alt)
    rc, rr = ref.projection(lon, lat, alt)
    np.testing.assert_allclose(c, rc, rtol=0, atol=tol_px)
    np.testing.assert_allclose(r, rr, rtol=0, atol=tol_px)


@pytest.fixture
def pleiades_models(pleiades_pair):
    """(ours, rpcm's from GDAL's reading of the tag, width, height) for both real images."""
    out = []
    for name in ("img_01.tif", "img_02.tif"):
        path = pleiades_pair / name
        with tifffile.TiffFile(path) as tif:
            height, width = tif.pages.first.shape
        out.append((RPCModel.from_image(path), rpcm.rpc_from_geotiff(str(path)), width, height))
    return out


@pytest.fixture
def wv2(shared_data) -> RPCModel:
    return RPCModel.from_file(shared_data / "rpc_files" / "rpc_WV2.xml")


# -- real Pleiades crops ------------------------------------------------------------------------
def test_pleiades_projection_matches_rpcm(pleiades_models):
    for ours, ref, width, height in pleiades_models:
        cols, rows = _pixel_grid(width, height)
        for alt in ALTS:
            # Ground points from rpcm's own localization: independent of our code.
            lon, lat = ref.localization(cols, rows, alt)
            c, r = ours.projection(lon=lon, lat=lat, alt=alt)
            rc, rr = ref.projection(lon, lat, alt)
            assert np.abs(c - rc).max() < PROJ_VS_RPCM_PX
            assert np.abs(r - rr).max() < PROJ_VS_RPCM_PX
            # The crop was folded into the polynomials: the grid lands back on the crop.
            assert np.abs(c - cols).max() < RPCM_LOC_PX and np.abs(r - rows).max() < RPCM_LOC_PX


def test_pleiades_localization_round_trip_and_matches_rpcm(pleiades_models):
    for ours, ref, width, height in pleiades_models:
        cols, rows = _pixel_grid(width, height)
        alts = np.linspace(ALTS[0], ALTS[-1], 5)[:, None]  # broadcasts against the grid
        lon, lat = ours.localization(col=cols, row=rows, alt=alts)
        assert lon.shape == (5, cols.size)
        c, r = ours.projection(lon=lon, lat=lat, alt=alts)
        assert np.hypot(c - cols, r - rows).max() <= ROUND_TRIP_PX
        for k, alt in enumerate(alts[:, 0]):
            rlon, rlat = ref.localization(cols, rows, alt)
            assert np.abs(lon[k] - rlon).max() < LOC_VS_RPCM_DEG
            assert np.abs(lat[k] - rlat).max() < LOC_VS_RPCM_DEG


def test_pleiades_tag_read_like_gdal(pleiades_pair):
    # GDAL (rasterio) reads tag 50844 independently of tifffile and of our tag order.
    path = pleiades_pair / "img_02.tif"
    ours = RPCModel.from_image(path)
    _assert_same_projection_as(ours, _gdal_rpc(path), PROJ_VS_RPCM_PX)
    assert ours.source == str(path)


def test_footprint_is_localization_of_the_outer_corners(pleiades_models):
    ours, ref, width, height = pleiades_models[0]
    lon, lat = ours.footprint(width=width, height=height, alt=GROUND_ALT)
    rlon, rlat = ref.localization([-0.5, width - 0.5, width - 0.5, -0.5],
                                  [-0.5, -0.5, height - 0.5, height - 0.5], GROUND_ALT)
    np.testing.assert_allclose(lon, rlon, rtol=0, atol=LOC_VS_RPCM_DEG)
    np.testing.assert_allclose(lat, rlat, rtol=0, atol=LOC_VS_RPCM_DEG)


# -- vendor files -------------------------------------------------------------------------------
@pytest.mark.parametrize("name", RPC_FILES)
def test_rpc_file_parses_like_rpcm(shared_data, name):
    path = shared_data / "rpc_files" / name
    ours = RPCModel.from_file(path)
    ref = rpcm.rpc_from_rpc_file(str(path))
    # Same decimal strings through float(): the numbers must be identical (for DIMAP both apply
    # the 1-based pixel convention to LINE_OFF/SAMP_OFF).
    for attr in ("row_offset", "col_offset", "lat_offset", "lon_offset", "alt_offset",
                 "row_scale", "col_scale", "lat_scale", "lon_scale", "alt_scale"):
        assert getattr(ours, attr) == getattr(ref, attr), attr
    for attr in ("row_num", "row_den", "col_num", "col_den"):
        np.testing.assert_array_equal(getattr(ours, attr), getattr(ref, attr), err_msg=attr)
    lon, lat, alt = _ground_cube(ours)
    c, r = ours.projection(lon=lon, lat=lat, alt=alt)
    rc, rr = ref.projection(lon, lat, alt)
    # relative to the largest coordinate of the grid: rounding scales with the terms' size,
    # not with the (possibly near-zero) result
    np.testing.assert_allclose(c, rc, rtol=0, atol=PROJ_VS_RPCM_REL * np.abs(rc).max())
    np.testing.assert_allclose(r, rr, rtol=0, atol=PROJ_VS_RPCM_REL * np.abs(rr).max())


@pytest.mark.parametrize("name", RPC_FILES)
def test_rpc_file_localization_round_trip(shared_data, name):
    ours = RPCModel.from_file(shared_data / "rpc_files" / name)
    u = np.linspace(-1.0, 1.0, 5)
    a, b, h = (g.ravel() for g in np.meshgrid(u, u, u, indexing="ij"))
    cols = ours.col_offset + ours.col_scale * a
    rows = ours.row_offset + ours.row_scale * b
    alts = ours.alt_offset + ours.alt_scale * h
    lon, lat = ours.localization(col=cols, row=rows, alt=alts)
    c, r = ours.projection(lon=lon, lat=lat, alt=alts)
    assert np.hypot(c - cols, r - rows).max() <= ROUND_TRIP_PX


def test_dimap_neo_offsets_are_zero_based_like_rpcm(shared_data, tmp_path):
    # A Pleiades Neo file (no sample in shared data): the Pleiades file restructured with the
    # PNEO element names that rpcm reads. rpcm does not subtract 1 for PNEO.
    text = (shared_data / "rpc_files" / "rpc_PLEIADES.xml").read_text()
    direct = re.search(r"<Direct_Model>.*</Direct_Model>", text, re.S).group(0)
    direct_neo = (direct.replace("Direct_Model>", "ImagetoGround_Values>")
                  .replace("SAMP_", "LON_").replace("LINE_", "LAT_"))
    text = (text.replace(direct, direct_neo).replace("PHR_SENSOR", "PNEO_SENSOR")
            .replace("Inverse_Model>", "GroundtoImage_Values>"))
    path = tmp_path / "RPC_PNEO.XML"
    path.write_text(text)
    ours = RPCModel.from_file(path)
    ref = rpcm.RPCModel(rpcm.rpc_file_readers.read_rpc_xml(text))
    assert (ours.row_offset, ours.col_offset) == (ref.row_offset, ref.col_offset)
    phr = RPCModel.from_file(shared_data / "rpc_files" / "rpc_PLEIADES.xml")
    assert ours.row_offset == phr.row_offset + 1.0
    _assert_same_projection_as(ours, ref, PROJ_VS_RPCM_PX)


# -- round trips --------------------------------------------------------------------------------
def test_tag_values_round_trip(wv2):
    values = wv2.to_tag_values()
    assert values.shape == (92,) and values.dtype == np.float64
    back = RPCModel.from_tag_values(values, source="x")
    assert back == wv2
    lon, lat, alt = _ground_cube(wv2)
    for a, b in zip(back.projection(lon=lon, lat=lat, alt=alt),
                    wv2.projection(lon=lon, lat=lat, alt=alt)):
        np.testing.assert_array_equal(a, b)


def test_dict_round_trip_through_json(wv2):
    back = RPCModel.from_dict(json.loads(json.dumps(wv2.to_dict())))
    assert back == wv2 and back.source == wv2.source
    np.testing.assert_array_equal(back.to_tag_values(), wv2.to_tag_values())
    assert pickle.loads(pickle.dumps(wv2)) == wv2


def test_rpc_txt_round_trip_and_gdal_reads_it(wv2, tmp_path):
    img = tmp_path / "scene.tif"
    tifffile.imwrite(img, np.zeros((16, 16), np.uint16))
    txt = tmp_path / "scene_RPC.TXT"
    write_rpc_txt(txt, wv2)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # temp renamed
    back = RPCModel.from_file(txt)
    np.testing.assert_array_equal(back.to_tag_values(), wv2.to_tag_values())
    # The file follows GDAL's _RPC.TXT layout: GDAL finds it beside the image and reads it.
    _assert_same_projection_as(wv2, _gdal_rpc(img), PROJ_VS_RPCM_PX)
    # and so does from_image, via the sidecar (the TIFF has no tag).
    assert RPCModel.from_image(img) == wv2


def test_tiff_tag_written_with_tifffile_reads_back(wv2, tmp_path):
    img = tmp_path / "tagged.tif"
    tifffile.imwrite(img, np.arange(24 * 32, dtype=np.uint16).reshape(24, 32),
                     extratags=[rpc_tiff_extratag(wv2)])
    assert rpc_tiff_extratag(wv2)[:3] == (TIFF_TAG_RPC, "d", 92)
    back = RPCModel.from_image(img)
    assert back == wv2 and back.source == str(img)
    assert RPCModel.from_file(img) == wv2  # from_file accepts a TIFF too
    _assert_same_projection_as(wv2, _gdal_rpc(img), PROJ_VS_RPCM_PX)  # GDAL agrees on the order


def test_rpb_sidecar_read_like_gdal(wv2, tmp_path):
    img = tmp_path / "scene.tif"
    tifffile.imwrite(img, np.zeros((16, 16), np.uint16))

    def block(name, v):
        return f"\t{name} = (\n" + ",\n".join(f"\t\t\t{x:+.15E}" for x in v) + ");\n"

    scal = {"errBias": wv2.err_bias, "errRand": wv2.err_rand, "lineOffset": wv2.row_offset,
            "sampOffset": wv2.col_offset, "latOffset": wv2.lat_offset,
            "longOffset": wv2.lon_offset, "heightOffset": wv2.alt_offset,
            "lineScale": wv2.row_scale, "sampScale": wv2.col_scale, "latScale": wv2.lat_scale,
            "longScale": wv2.lon_scale, "heightScale": wv2.alt_scale}
    text = ('satId = "WV02";\nbandId = "P";\nSpecId = "RPC00B";\nBEGIN_GROUP = IMAGE\n'
            + "".join(f"\t{k} = {v!r};\n" for k, v in scal.items())
            + block("lineNumCoef", wv2.row_num) + block("lineDenCoef", wv2.row_den)
            + block("sampNumCoef", wv2.col_num) + block("sampDenCoef", wv2.col_den)
            + "END_GROUP = IMAGE\nEND;\n")
    (tmp_path / "scene.RPB").write_text(text)
    ours = RPCModel.from_image(img)
    assert ours.source == str(tmp_path / "scene.RPB")
    _assert_same_projection_as(ours, _gdal_rpc(img), PROJ_VS_RPCM_PX)
    _assert_same_projection_as(ours, _rpcm_from_ours(wv2), PROJ_VS_RPCM_PX)
    assert ours.err_bias == wv2.err_bias


def test_aux_xml_sidecar_read_like_gdal(shared_data, tmp_path):
    ref = rpcm.rpc_from_rpc_file(str(shared_data / "rpc_files" / "rpc_WV3.xml"))
    img = tmp_path / "scene.tif"
    tifffile.imwrite(img, np.zeros((16, 16), np.uint16))
    items = "".join(f'    <MDI key="{k}">{v}</MDI>\n' for k, v in ref.to_geotiff_dict().items())
    (tmp_path / "scene.tif.aux.xml").write_text(
        f'<PAMDataset>\n  <Metadata domain="RPC">\n{items}  </Metadata>\n</PAMDataset>\n')
    ours = RPCModel.from_image(img)
    _assert_same_projection_as(ours, _gdal_rpc(img), PROJ_VS_RPCM_PX)
    assert ours.err_bias == -1.0  # not in this file: GDAL's "unknown"


@pytest.mark.parametrize("vendor,sidecar", [("rpc_WV2.xml", "SCENE.XML"),
                                            ("rpc_PLEIADES.xml", "Scene.xml"),
                                            ("rpc_IKONOS.txt", "SCENE_rpc.txt")])
def test_vendor_sidecar_found_case_insensitively(shared_data, tmp_path, vendor, sidecar):
    img = tmp_path / "scene.TIF"
    tifffile.imwrite(img, np.zeros((16, 16), np.uint16))
    shutil.copy(shared_data / "rpc_files" / vendor, tmp_path / sidecar)
    assert RPCModel.from_image(img) == RPCModel.from_file(shared_data / "rpc_files" / vendor)


def test_unrelated_xml_beside_image_is_passed_over(wv2, tmp_path):
    img = tmp_path / "scene.tif"
    tifffile.imwrite(img, np.zeros((16, 16), np.uint16))
    (tmp_path / "scene.xml").write_text("<catalog><item/></catalog>")
    with pytest.raises(RPCError, match="no RPC found") as exc:
        RPCModel.from_image(img)
    assert "scene.xml" in str(exc.value) and str(img) in str(exc.value)
    write_rpc_txt(tmp_path / "scene_RPC.TXT", wv2)  # a real sidecar is then found
    assert RPCModel.from_image(img) == wv2


# An Airbus DIMAP delivery in tiles (names as Airbus writes them): 2 x 2 tiles of 16384 rows
# and 20480 columns (sizes that differ, so that a row / column mix-up shows), no overlap.
DIMAP_PRODUCT = "PHR1B_P_201306290657283_SEN_001"
DIMAP_TILE_ROWS, DIMAP_TILE_COLS = 16384, 20480


def _dimap_delivery(folder: Path, shared_data: Path, tiles, *, listed=None,
                    overlap: int = 0) -> None:
    """IMG_<product>_RiCj.TIF for each (i, j) in ``tiles`` (no RPC of their own), the real
    Pleiades RPC file as RPC_<product>.XML and a DIM_<product>.XML that lists ``listed``
    (default: the tiles) with its regular tiling."""
    for r, c in tiles:
        tifffile.imwrite(folder / f"IMG_{DIMAP_PRODUCT}_R{r}C{c}.TIF",
                         np.zeros((16, 16), np.uint16))
    shutil.copy(shared_data / "rpc_files" / "rpc_PLEIADES.xml", folder / f"RPC_{DIMAP_PRODUCT}.XML")
    files = "".join(f'<Data_File tile_R="{r}" tile_C="{c}"><DATA_FILE_PATH '
                    f'href="IMG_{DIMAP_PRODUCT}_R{r}C{c}.TIF"/></Data_File>'
                    for r, c in (tiles if listed is None else listed))
    (folder / f"DIM_{DIMAP_PRODUCT}.XML").write_text(
        "<?xml version='1.0'?><Dimap_Document><Metadata_Identification><METADATA_PROFILE>"
        "PHR_SENSOR</METADATA_PROFILE></Metadata_Identification><Raster_Data><Data_Access>"
        f"<Data_Files>{files}</Data_Files></Data_Access><Raster_Dimensions><NROWS>30000</NROWS>"
        "<NCOLS>40000</NCOLS><Tile_Set><Regular_Tiling>"
        f'<NTILES_SIZE nrows="{DIMAP_TILE_ROWS}" ncols="{DIMAP_TILE_COLS}"/>'
        f"<OVERLAP_ROW>{overlap}</OVERLAP_ROW><OVERLAP_COL>0</OVERLAP_COL></Regular_Tiling>"
        "</Tile_Set></Raster_Dimensions></Raster_Data></Dimap_Document>")


def test_dimap_tiles_find_the_product_rpc_placed_like_gdal(shared_data, tmp_path):
    tiles = [(1, 1), (1, 2), (2, 1), (2, 2)]
    _dimap_delivery(tmp_path, shared_data, tiles)
    scene = RPCModel.from_file(tmp_path / f"RPC_{DIMAP_PRODUCT}.XML")
    for r, c in tiles:
        img = tmp_path / f"IMG_{DIMAP_PRODUCT}_R{r}C{c}.TIF"
        ours = RPCModel.from_image(img)
        _assert_same_projection_as(ours, _gdal_rpc(img), PROJ_VS_RPCM_PX)  # GDAL's Pleiades reader
        assert ours.col_offset == scene.col_offset - (c - 1) * DIMAP_TILE_COLS
        assert ours.row_offset == scene.row_offset - (r - 1) * DIMAP_TILE_ROWS
    # A scene in one file (IMG_<product>.TIF) takes the product's RPC as it is.
    tifffile.imwrite(tmp_path / f"IMG_{DIMAP_PRODUCT}.TIF", np.zeros((16, 16), np.uint16))
    assert RPCModel.from_image(tmp_path / f"IMG_{DIMAP_PRODUCT}.TIF") == scene


@pytest.mark.parametrize("case,message", [
    ("no DIM", r"DIM_\*\.XML, which is not beside it"),
    ("not listed", r"it does not list the tile"),
    ("overlap", r"tiles that overlap"),
])
def test_a_dimap_tile_of_unknown_place_is_an_error(shared_data, tmp_path, case, message):
    _dimap_delivery(tmp_path, shared_data, [(1, 1), (1, 2)],
                    listed=[(1, 1)] if case == "not listed" else None,
                    overlap=8 if case == "overlap" else 0)
    if case == "no DIM":
        (tmp_path / f"DIM_{DIMAP_PRODUCT}.XML").unlink()
    img = tmp_path / f"IMG_{DIMAP_PRODUCT}_R1C2.TIF"
    with pytest.raises(RPCError, match=message) as exc:
        RPCModel.from_image(img)
    assert str(img) in str(exc.value) and f"RPC_{DIMAP_PRODUCT}.XML" in str(exc.value)
    # The first tile starts where the scene does: its RPC needs no place.
    assert RPCModel.from_image(tmp_path / f"IMG_{DIMAP_PRODUCT}_R1C1.TIF") == RPCModel.from_file(
        tmp_path / f"RPC_{DIMAP_PRODUCT}.XML")


def test_the_dimap_rpc_name_is_among_those_looked_for(tmp_path):
    img = tmp_path / f"IMG_{DIMAP_PRODUCT}_R1C1.TIF"
    tifffile.imwrite(img, np.zeros((16, 16), np.uint16))
    with pytest.raises(RPCError, match=f"RPC_{DIMAP_PRODUCT.upper()}.XML"):
        RPCModel.from_image(img)


# -- crops --------------------------------------------------------------------------------------
def test_cropped_shifts_projection_exactly(pleiades_models):
    ours, _, width, height = pleiades_models[1]
    x0, y0 = 137, 411.25
    crop = ours.cropped(x0=x0, y0=y0)
    cols, rows = _pixel_grid(width, height)
    lon, lat = ours.localization(col=cols, row=rows, alt=GROUND_ALT)
    c, r = ours.projection(lon=lon, lat=lat, alt=GROUND_ALT)
    cc, cr = crop.projection(lon=lon, lat=lat, alt=GROUND_ALT)
    assert np.abs(cc - (c - x0)).max() < CROP_PX
    assert np.abs(cr - (r - y0)).max() < CROP_PX
    # localization in crop pixels lands on the same ground points
    clon, clat = crop.localization(col=cols - x0, row=rows - y0, alt=GROUND_ALT)
    assert np.abs(clon - lon).max() < LOC_VS_RPCM_DEG
    assert np.abs(clat - lat).max() < LOC_VS_RPCM_DEG
    assert ours.cropped(x0=0, y0=0) == ours


# -- API behaviour ------------------------------------------------------------------------------
def test_projection_broadcasts_and_matches_pointwise(wv2):
    lon = wv2.lon_offset + np.linspace(-0.02, 0.02, 4)[None, :]
    lat = wv2.lat_offset + np.linspace(-0.02, 0.02, 3)[:, None]
    c, r = wv2.projection(lon=lon, lat=lat, alt=100.0)
    assert c.shape == r.shape == (3, 4)
    ref = _rpcm_from_ours(wv2)
    for i in range(3):
        for j in range(4):
            rc, rr = ref.projection(float(lon[0, j]), float(lat[i, 0]), 100.0)
            assert abs(c[i, j] - rc) < PROJ_VS_RPCM_PX and abs(r[i, j] - rr) < PROJ_VS_RPCM_PX
    cs, rs = wv2.projection(lon=float(lon[0, 1]), lat=float(lat[2, 0]), alt=100.0)
    assert np.ndim(cs) == 0 and isinstance(cs, float)
    assert abs(cs - c[2, 1]) < BATCH_PX and abs(rs - r[2, 1]) < BATCH_PX


def test_model_is_immutable(wv2):
    with pytest.raises(AttributeError):
        wv2.col_offset = 0.0
    with pytest.raises(ValueError):
        wv2.row_num[0] = 0.0


def test_constructor_rejects_bad_coefficients(wv2):
    kw = wv2.to_dict()
    kw["col_den"] = kw["col_den"][:19]
    with pytest.raises(RPCError, match="col_den has 19 coefficients"):
        RPCModel(**kw)
    kw = wv2.to_dict()
    kw["lat_scale"] = 0.0
    with pytest.raises(RPCError, match="lat_scale is zero"):
        RPCModel(**kw)


def test_from_dict_rejects_unknown_and_missing_keys(wv2):
    d = wv2.to_dict()
    with pytest.raises(RPCError, match="unknown RPC dict key"):
        RPCModel.from_dict({**d, "bogus": 1})
    del d["alt_scale"]
    with pytest.raises(RPCError, match="alt_scale"):
        RPCModel.from_dict(d)


def test_from_tag_values_rejects_wrong_count(wv2):
    with pytest.raises(RPCError, match="91 values, expected 92") as exc:
        RPCModel.from_tag_values(wv2.to_tag_values()[:91], source="tag.tif")
    assert "tag.tif" in str(exc.value)


# -- bad input ----------------------------------------------------------------------------------
def test_tiff_without_any_rpc(tmp_path):
    img = tmp_path / "bare.tif"
    tifffile.imwrite(img, np.zeros((8, 8), np.uint16))
    with pytest.raises(RPCError) as exc:
        RPCModel.from_image(img)
    msg = str(exc.value)
    assert str(img) in msg and "50844" in msg and "sidecar" in msg


def test_truncated_tiff(wv2, tmp_path):
    good = tmp_path / "good.tif"
    tifffile.imwrite(good, np.zeros((64, 64), np.uint16), extratags=[rpc_tiff_extratag(wv2)])
    data = good.read_bytes()
    for n in (3, 12, len(data) // 2, len(data) - 1):
        bad = tmp_path / f"cut{n}.tif"
        bad.write_bytes(data[:n])
        with pytest.raises(ImageFormatError, match="truncated") as exc:
            RPCModel.from_image(bad)
        assert str(bad) in str(exc.value)


def test_non_tiff_image(tmp_path):
    bad = tmp_path / "photo.tif"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    with pytest.raises(ImageFormatError, match="not a TIFF") as exc:
        RPCModel.from_image(bad)
    assert str(bad) in str(exc.value)
    with pytest.raises(ImageFormatError, match="cannot read image"):
        RPCModel.from_image(tmp_path / "absent.tif")


def _skysat_lines(shared_data) -> list[str]:
    return (shared_data / "rpc_files" / "skysat_RPC.TXT").read_text().splitlines()


def test_rpc_text_with_a_missing_key(shared_data, tmp_path):
    bad = tmp_path / "bad_RPC.TXT"
    bad.write_text("\n".join(l for l in _skysat_lines(shared_data)
                             if not l.startswith("SAMP_SCALE")) + "\n")
    with pytest.raises(RPCError, match="missing RPC key.*SAMP_SCALE") as exc:
        RPCModel.from_file(bad)
    assert str(bad) in str(exc.value)
    bad.write_text("\n".join(l for l in _skysat_lines(shared_data)
                             if not l.startswith("LINE_DEN_COEFF_7:")) + "\n")
    with pytest.raises(RPCError, match="LINE_DEN_COEFF_7"):
        RPCModel.from_file(bad)


def test_rpc_text_with_a_non_numeric_value(shared_data, tmp_path):
    bad = tmp_path / "bad_RPC.TXT"
    lines = [("LAT_OFF: twenty-five" if l.startswith("LAT_OFF") else l)
             for l in _skysat_lines(shared_data)]
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(RPCError, match="LAT_OFF = 'twenty-five' is not a number") as exc:
        RPCModel.from_file(bad)
    assert str(bad) in str(exc.value)


def test_xml_with_a_missing_key_and_unknown_formats(shared_data, tmp_path):
    text = (shared_data / "rpc_files" / "rpc_WV2.xml").read_text()
    bad = tmp_path / "bad.xml"
    bad.write_text(re.sub(r"<HEIGHTSCALE>.*?</HEIGHTSCALE>", "", text))
    with pytest.raises(RPCError, match="missing RPC key.*HEIGHT_SCALE"):
        RPCModel.from_file(bad)
    bad.write_text(text[: len(text) // 2])
    with pytest.raises(RPCError, match="malformed XML"):
        RPCModel.from_file(bad)
    other = tmp_path / "notes.txt"
    other.write_text("hello: world\n")
    with pytest.raises(RPCError, match="unknown RPC format") as exc:
        RPCModel.from_file(other)
    assert str(other) in str(exc.value)
    with pytest.raises(RPCError, match="cannot read RPC file"):
        RPCModel.from_file(tmp_path / "absent_RPC.TXT")


# -- localization failures ----------------------------------------------------------------------
def test_localization_of_non_finite_input_raises(wv2):
    with pytest.raises(LocalizationError, match="not finite"):
        wv2.localization(col=[10.0, np.nan], row=[5.0, 5.0], alt=100.0)
    with pytest.raises(LocalizationError, match="not finite"):
        wv2.localization(col=10.0, row=5.0, alt=np.inf)


def test_localization_of_degenerate_model_raises(wv2):
    kw = wv2.to_dict()
    kw["col_num"] = [0.5] + [0.0] * 19  # the column no longer depends on the ground
    kw["col_den"] = [1.0] + [0.0] * 19
    flat = RPCModel(**kw)
    with pytest.raises(LocalizationError, match="singular Jacobian"):
        flat.localization(col=wv2.col_offset, row=wv2.row_offset, alt=wv2.alt_offset)


def test_localization_that_runs_out_of_iterations_raises(wv2):
    with pytest.raises(LocalizationError, match="did not converge.*after 1 iterations"):
        wv2.localization(col=0.0, row=0.0, alt=0.0, max_iter=1)


# Central differences with h = 1e-4 (normalised units) of a cubic rational: truncation error
# ~h^2 * third derivative ~ 1e-8 of the pixel scale (~1e4 px) -> ~1e-4 px per unit; rounding
# 1e-12 px / 1e-4 -> 1e-8. Jacobian entries are ~1e4 px per unit, so 1e-6 relative is strict.
JACOBIAN_REL = 1e-6


def test_analytic_jacobian_matches_finite_differences(shared_data):
    # The Newton solver's Jacobian (internal) against differences of the public projection.
    for name in ("rpc_WV3.xml", "rpc_PLEIADES.xml", "rpc_PLANET_L1A.txt"):
        m = RPCModel.from_file(shared_data / "rpc_files" / name)
        rng = np.random.default_rng(7)
        x, y, h = rng.uniform(-0.9, 0.9, (3, 50))
        zeros = np.zeros(50)
        _, _, a, b, c, d = m._residual_and_jacobian(x, y, h, zeros, zeros)
        step = 1e-4

        def proj(xx, yy):
            return m.projection(lon=m.lon_offset + m.lon_scale * xx,
                                lat=m.lat_offset + m.lat_scale * yy,
                                alt=m.alt_offset + m.alt_scale * h)

        (cxp, rxp), (cxm, rxm) = proj(x + step, y), proj(x - step, y)
        (cyp, ryp), (cym, rym) = proj(x, y + step), proj(x, y - step)
        for analytic, numeric in ((a, (cxp - cxm) / (2 * step)), (b, (cyp - cym) / (2 * step)),
                                  (c, (rxp - rxm) / (2 * step)), (d, (ryp - rym) / (2 * step))):
            scale = np.abs(np.stack([a, b, c, d])).max()
            np.testing.assert_allclose(analytic, numeric, rtol=0, atol=JACOBIAN_REL * scale)


def test_an_all_zero_denominator_is_an_error_naming_the_file(tmp_path):
    """Such an RPC would divide by zero in every projection (numpy warnings, NaN pixels)."""
    from satsweep.errors import RPCError
    from satsweep.geometry.rpc_formats import write_rpc_txt

    good = RPCModel(row_num=[0.0, 1.0] + [0.0] * 18, row_den=[1.0] + [0.0] * 19,
                    col_num=[0.0, 0.0, 1.0] + [0.0] * 17, col_den=[1.0] + [0.0] * 19,
                    row_offset=500.0, col_offset=500.0, lat_offset=45.0, lon_offset=5.0,
                    alt_offset=100.0, row_scale=500.0, col_scale=500.0, lat_scale=0.01,
                    lon_scale=0.01, alt_scale=100.0)
    path = tmp_path / "bad_RPC.TXT"
    write_rpc_txt(path, good)
    text = path.read_text()
    text = "\n".join(ln if not ln.startswith("LINE_DEN_COEFF") else
                     ln.split(":")[0] + ": 0.0" for ln in text.splitlines())
    path.write_text(text + "\n")
    with pytest.raises(RPCError, match=r"bad_RPC.TXT: row_den is all zeros"):
        RPCModel.from_file(path)
