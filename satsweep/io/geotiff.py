"""North-up GeoTIFFs (DSMs, DEMs) with the GeoTIFF tags and GDAL's nodata tag, in EPSG
coordinate reference systems; and plain TIFFs with extra tags.

Georeferencing convention: ``x_min``/``y_max`` are the outer corner of the top-left pixel
(GeoTIFF PixelIsArea, GDAL's geotransform origin); the centre of pixel (col, row), with (0, 0)
the centre of the first pixel, is ``(x_min + (col + 0.5) * rx, y_max - (row + 0.5) * ry)``.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Sequence

import numpy as np

from satsweep.errors import ImageFormatError, OptionsError
from satsweep.io.atomic import _maybe_atomic
from satsweep.io.images import _open_tiff, read_image

# TIFF / GeoTIFF tag codes.
TAG_MODEL_PIXEL_SCALE = 33550
TAG_MODEL_TIEPOINT = 33922
TAG_MODEL_TRANSFORMATION = 34264
TAG_GEO_KEY_DIRECTORY = 34735
TAG_GDAL_NODATA = 42113

# GeoKey ids and values (GeoTIFF 1.0 / OGC 19-008).
KEY_MODEL_TYPE = 1024  # GTModelTypeGeoKey
KEY_RASTER_TYPE = 1025  # GTRasterTypeGeoKey
KEY_GEOGRAPHIC_TYPE = 2048  # GeographicTypeGeoKey
KEY_GEOG_ANGULAR_UNITS = 2054  # GeogAngularUnitsGeoKey
KEY_PROJECTED_CS_TYPE = 3072  # ProjectedCSTypeGeoKey
KEY_VERTICAL_CS_TYPE = 4096  # VerticalCSTypeGeoKey
MODEL_PROJECTED = 1
MODEL_GEOGRAPHIC = 2
RASTER_PIXEL_IS_AREA = 1
RASTER_PIXEL_IS_POINT = 2
ANGULAR_DEGREE = 9102
USER_DEFINED = 32767


@dataclasses.dataclass(frozen=True)
class GeoInfo:
    """Georeferencing of a north-up raster.

    ``x_min``, ``y_max``: outer corner of the top-left pixel, in CRS units (metres for UTM, degrees
    for EPSG:4326). ``resolution``: pixel width; ``resolution_y``: pixel height (None: square
    pixels, same as ``resolution``). ``vertical_epsg``: the vertical CRS a DEM declares, if any
    (e.g. 5773 for EGM96 geoid heights). ``nodata``: value marking missing cells (NaN allowed), None
    when the file declares none.
    """

    epsg: int  # EPSG code of the horizontal CRS
    x_min: float  # west edge of the raster
    y_max: float  # north edge of the raster
    resolution: float  # pixel width (> 0)
    nodata: float | None = math.nan  # missing-data marker, None when there is none
    resolution_y: float | None = None  # pixel height (> 0); None: equal to resolution
    vertical_epsg: int | None = None  # VerticalCSTypeGeoKey when the file declares one (DEMs)

    @property
    def pixel_size(self) -> tuple[float, float]:
        """(pixel width, pixel height), both positive, in CRS units."""
        return self.resolution, (self.resolution if self.resolution_y is None else self.resolution_y)

    def pixel_to_xy(self, *, col, row) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates ((0, 0) = centre of the first pixel) -> CRS coordinates."""
        rx, ry = self.pixel_size
        col, row = np.asarray(col, np.float64), np.asarray(row, np.float64)
        return self.x_min + (col + 0.5) * rx, self.y_max - (row + 0.5) * ry

    def xy_to_pixel(self, *, x, y) -> tuple[np.ndarray, np.ndarray]:
        """CRS coordinates -> pixel coordinates ((0, 0) = centre of the first pixel)."""
        rx, ry = self.pixel_size
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        return (x - self.x_min) / rx - 0.5, (self.y_max - y) / ry - 0.5

    def is_nodata(self, values: np.ndarray) -> np.ndarray:
        """Boolean mask of cells that are missing: the nodata value, and NaN in any case."""
        values = np.asarray(values)
        bad = np.isnan(values) if values.dtype.kind == "f" else np.zeros(values.shape, bool)
        if self.nodata is not None and not math.isnan(self.nodata):
            bad |= values == self.nodata
        return bad


# -- GeoTIFF -----------------------------------------------------------------------------------
def _crs_kind(epsg: int) -> str:
    """'projected' or 'geographic' for an EPSG code; OptionsError when pyproj does not know it."""
    import pyproj

    try:
        crs = pyproj.CRS.from_epsg(int(epsg))
    except pyproj.exceptions.CRSError:
        raise OptionsError(f"epsg = {epsg!r}: not a known EPSG coordinate reference system") from None
    if crs.is_projected:
        return "projected"
    if crs.is_geographic:
        return "geographic"
    raise OptionsError(f"epsg = {epsg!r}: neither a projected nor a geographic CRS")


def _geokeys(epsg: int) -> list[int]:
    """GeoKeyDirectoryTag values for a north-up, PixelIsArea raster in ``epsg``."""
    if _crs_kind(epsg) == "projected":
        keys = [(KEY_MODEL_TYPE, MODEL_PROJECTED), (KEY_RASTER_TYPE, RASTER_PIXEL_IS_AREA),
                (KEY_PROJECTED_CS_TYPE, int(epsg))]
    else:
        keys = [(KEY_MODEL_TYPE, MODEL_GEOGRAPHIC), (KEY_RASTER_TYPE, RASTER_PIXEL_IS_AREA),
                (KEY_GEOGRAPHIC_TYPE, int(epsg)), (KEY_GEOG_ANGULAR_UNITS, ANGULAR_DEGREE)]
    values = [1, 1, 0, len(keys)]
    for key, value in sorted(keys):
        values += [key, 0, 1, value]
    return values


def _nodata_text(nodata: float, dtype: np.dtype) -> str:
    """GDAL_NODATA text: 'nan', an integer for integer pixels, else the shortest exact decimal."""
    if math.isnan(nodata):
        if dtype.kind != "f":
            raise OptionsError(f"nodata = nan is impossible for {dtype} pixels: give a numeric nodata")
        return "nan"
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        if nodata != int(nodata) or not info.min <= nodata <= info.max:
            raise OptionsError(f"nodata = {nodata!r} is not representable in {dtype} pixels")
        return str(int(nodata))
    return repr(float(nodata))


def write_geotiff(
    path: str | os.PathLike,
    array: np.ndarray,
    *,
    epsg: int,
    x_min: float,
    y_max: float,
    resolution: float,
    nodata: float | None = math.nan,
    atomic: bool = True,
    dtype: np.dtype | type = np.float32,
) -> None:
    """Write a 2D array as a north-up GeoTIFF (float32 unless ``dtype`` says otherwise).

    ``x_min``, ``y_max``: outer corner of the top-left pixel in the CRS ``epsg`` (projected, e.g.
    UTM, or geographic); ``resolution``: square pixel size in CRS units. Tags: ModelPixelScale,
    ModelTiepoint, GeoKeyDirectory (PixelIsArea) and GDAL_NODATA (omitted when nodata is None).
    Written to a temporary name and renamed unless ``atomic`` is False.
    """
    import tifffile

    array = np.asarray(array)
    if array.ndim != 2 or 0 in array.shape:
        raise ValueError(f"write_geotiff needs a non-empty 2D array, got shape {array.shape}")
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise OptionsError(f"resolution = {resolution!r}: must be finite and > 0")
    if not (math.isfinite(x_min) and math.isfinite(y_max)):
        raise OptionsError(f"GeoTIFF origin ({x_min!r}, {y_max!r}) must be finite")
    dtype = np.dtype(dtype)
    tags = georeference_tags(epsg=epsg, x_min=x_min, y_max=y_max, resolution=resolution,
                             nodata=nodata, dtype=dtype)
    with _maybe_atomic(path, atomic) as target:
        tifffile.imwrite(
            target, np.ascontiguousarray(array, dtype=dtype), photometric="minisblack",
            metadata=None, extratags=tags,
        )


def georeference_tags(*, epsg: int, x_min: float, y_max: float, resolution: float,
                      nodata: float | None, dtype) -> list[tuple]:
    """tifffile extratags of a north-up raster: ModelPixelScale, ModelTiepoint (the outer corner
    of the top-left pixel), GeoKeyDirectory (PixelIsArea) and GDAL_NODATA (none when ``nodata``
    is None)."""
    geokeys = tuple(_geokeys(epsg))
    tags = [
        (TAG_MODEL_PIXEL_SCALE, "d", 3, (float(resolution), float(resolution), 0.0), True),
        (TAG_MODEL_TIEPOINT, "d", 6, (0.0, 0.0, 0.0, float(x_min), float(y_max), 0.0), True),
        (TAG_GEO_KEY_DIRECTORY, "H", len(geokeys), geokeys, True),
    ]
    if nodata is not None:
        tags.append((TAG_GDAL_NODATA, "s", 0, _nodata_text(float(nodata), np.dtype(dtype)), True))
    return tags


def write_tiff(
    path: str | os.PathLike,
    array: np.ndarray,
    *,
    extratags: Sequence[tuple] = (),
    atomic: bool = True,
) -> None:
    """Write an array as a plain TIFF (2D grey, or HxWx3/4 colour) with optional extra tags.

    ``extratags`` are tifffile extratags ``(code, dtype, count, value, writeonce)``, e.g. the RPC
    tag of ``satsweep.rpc.rpc_tiff_extratag``. Written to a temporary name and renamed unless
    ``atomic`` is False.
    """
    import tifffile

    array = np.ascontiguousarray(array)
    if array.ndim == 2:
        photometric = "minisblack"
    elif array.ndim == 3 and array.shape[2] in (3, 4):
        photometric = "rgb"
    else:
        raise ValueError(f"write_tiff needs a 2D or HxWx3/4 array, got shape {array.shape}")
    with _maybe_atomic(path, atomic) as target:
        tifffile.imwrite(target, array, photometric=photometric, metadata=None, extratags=list(extratags))


def _geokey_values(path: str, directory: Sequence[int]) -> dict[int, int]:
    """Inline (SHORT) values of a GeoKeyDirectoryTag, keyed by GeoKey id."""
    d = [int(v) for v in directory]
    if len(d) < 4 or len(d) < 4 + 4 * d[3]:
        raise ImageFormatError(path, "malformed GeoKeyDirectoryTag")
    keys = {}
    for i in range(d[3]):
        key, location, count, value = d[4 + 4 * i: 8 + 4 * i]
        if location == 0 and count == 1:
            keys[key] = value
    return keys


def _parse_nodata(path: str, text) -> float | None:
    if text is None:
        return None
    if isinstance(text, bytes):
        text = text.decode("ascii", "replace")
    text = str(text).strip().strip("\x00").strip()
    try:
        return float(text)
    except ValueError:
        raise ImageFormatError(path, f"GDAL_NODATA tag {text!r} is not a number") from None


def read_geotiff(path: str | os.PathLike) -> tuple[np.ndarray, GeoInfo]:
    """Read the first band of a north-up GeoTIFF and its georeferencing (``read_geotiff_info``).
    The array keeps its stored dtype."""
    info = read_geotiff_info(path)
    return read_image(path), info


def read_geotiff_info(path: str | os.PathLike) -> GeoInfo:
    """The georeferencing of a north-up GeoTIFF, from its header only.

    Supports EPSG projected CRSs (ProjectedCSTypeGeoKey) and geographic ones (GeographicTypeGeoKey,
    e.g. EPSG:4326 DEMs with degree pixels), PixelIsArea and PixelIsPoint (GDAL's half-pixel shift),
    tie points at any raster position, and axis-aligned ModelTransformation tags. Raises
    ImageFormatError naming the file for missing or unsupported georeferencing (rotated
    rasters, user-defined CRSs).
    """
    path = os.fspath(path)
    with _open_tiff(path) as (_, page):
        tags = page.tags
        if TAG_GEO_KEY_DIRECTORY not in tags:
            raise ImageFormatError(path, "not a GeoTIFF: no GeoKeyDirectoryTag (34735)")
        keys = _geokey_values(path, tags[TAG_GEO_KEY_DIRECTORY].value)
        nodata = _parse_nodata(path, tags[TAG_GDAL_NODATA].value if TAG_GDAL_NODATA in tags else None)
        scale = tags[TAG_MODEL_PIXEL_SCALE].value if TAG_MODEL_PIXEL_SCALE in tags else None
        tie = tags[TAG_MODEL_TIEPOINT].value if TAG_MODEL_TIEPOINT in tags else None
        matrix = tags[TAG_MODEL_TRANSFORMATION].value if TAG_MODEL_TRANSFORMATION in tags else None
    model = keys.get(KEY_MODEL_TYPE)
    if model == MODEL_PROJECTED:
        epsg = keys.get(KEY_PROJECTED_CS_TYPE)
    elif model == MODEL_GEOGRAPHIC:
        epsg = keys.get(KEY_GEOGRAPHIC_TYPE)
    else:
        raise ImageFormatError(
            path, f"unsupported GeoTIFF model type {model} (need projected or geographic)"
        )
    if epsg is None or epsg == USER_DEFINED:
        raise ImageFormatError(
            path,
            "user-defined or missing CRS code: reproject it to an EPSG CRS "
            "(e.g. gdalwarp -t_srs EPSG:4326)",
        )
    if scale is not None and tie is not None and len(scale) >= 2 and len(tie) >= 6:
        rx, ry = float(scale[0]), float(scale[1])
        i, j, x, y = float(tie[0]), float(tie[1]), float(tie[3]), float(tie[4])
        x_min, y_max = x - i * rx, y + j * ry
    elif matrix is not None and len(matrix) == 16:
        m = [float(v) for v in matrix]
        if m[1] != 0.0 or m[4] != 0.0:
            raise ImageFormatError(
                path, "rotated or sheared raster (ModelTransformationTag) is not supported"
            )
        rx, ry, x_min, y_max = m[0], -m[5], m[3], m[7]
    else:
        raise ImageFormatError(path, "no ModelPixelScale + ModelTiepoint (or ModelTransformation) tags")
    if not (rx > 0.0 and ry > 0.0 and all(map(math.isfinite, (rx, ry, x_min, y_max)))):
        raise ImageFormatError(path, f"unsupported pixel size ({rx}, {-ry}): need a north-up raster")
    if keys.get(KEY_RASTER_TYPE) == RASTER_PIXEL_IS_POINT:
        # The tie point is the centre of its pixel: move to the outer corner, as GDAL does.
        x_min, y_max = x_min - 0.5 * rx, y_max + 0.5 * ry
    vertical = keys.get(KEY_VERTICAL_CS_TYPE)
    return GeoInfo(
        epsg=int(epsg), x_min=x_min, y_max=y_max, resolution=rx, nodata=nodata,
        resolution_y=None if ry == rx else ry,
        vertical_epsg=None if vertical is None else int(vertical),
    )
