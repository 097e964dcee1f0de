"""Image and GeoTIFF input/output with tifffile, and atomic output files.

- ``read_image``: the first band of a TIFF as a 2D array in its stored dtype (optionally only a
  window of it, read without decoding the rest when the file is uncompressed and contiguous).
- ``read_geotiff`` / ``write_geotiff``: north-up GeoTIFFs (DSMs, DEMs) with the three GeoTIFF tags
  and GDAL's nodata tag, in EPSG coordinate reference systems.
- ``write_tiff``: a plain TIFF with extra tags (e.g. a uint16 crop carrying its RPC tag).
- ``atomic_output``: every file is written under a temporary name in the destination folder and
  renamed on success, so a failed run never leaves a half-written output.

Georeferencing convention: ``x_min``/``y_max`` are the outer corner of the top-left pixel
(GeoTIFF PixelIsArea, GDAL's geotransform origin); the centre of pixel (col, row), with (0, 0)
the centre of the first pixel, is ``(x_min + (col + 0.5) * rx, y_max - (row + 0.5) * ry)``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import secrets
import struct
from typing import Iterator, Sequence

import numpy as np

from .errors import ImageFormatError, OptionsError

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

# Default tone-mapping percentiles: robust to a few saturated or dead pixels.
DEFAULT_LOW_PERCENTILE = 1.0
DEFAULT_HIGH_PERCENTILE = 99.0


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


# -- atomic outputs ----------------------------------------------------------------------------
def check_output_dir(path: str | os.PathLike, *, overwrite: bool) -> None:
    """Refuse an output folder that is a file, or a non-empty folder without ``overwrite``.

    Called before anything is computed, so that a refused run writes nothing."""
    from .errors import OutputExistsError

    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isdir(path):
        raise OptionsError(f"--out {path}: exists and is not a folder")
    if os.path.isdir(path) and os.listdir(path) and not overwrite:
        raise OutputExistsError(f"--out {path}: folder is not empty (pass --overwrite to write into it)")


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary path beside ``path``; rename it to ``path`` on success, remove it on error.

    The temporary name keeps the extension (``.NAME.RANDOM.tmp.tif``) and lives in the same folder,
    so the final ``os.replace`` is atomic on POSIX file systems.
    """
    path = os.fspath(path)
    folder, name = os.path.split(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise OptionsError(f"{path}: output folder {folder} does not exist")
    stem, ext = os.path.splitext(name)
    tmp = os.path.join(folder, f".{stem}.{secrets.token_hex(6)}.tmp{ext}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


@contextlib.contextmanager
def _maybe_atomic(path: str | os.PathLike, atomic: bool) -> Iterator[str]:
    if atomic:
        with atomic_output(path) as tmp:
            yield tmp
    else:
        yield os.fspath(path)


# -- reading -----------------------------------------------------------------------------------
# What tifffile raises on files that are not TIFFs or are cut short (struct.error for a file cut
# inside its header, for instance): each becomes an ImageFormatError naming the file.
_TIFF_READ_ERRORS = (ValueError, OSError, EOFError, IndexError, KeyError, struct.error)


@contextlib.contextmanager
def _quiet_tifffile() -> Iterator[None]:
    """Silence tifffile's own log lines while opening a file: a corrupt file is reported once, by
    the ImageFormatError that names it, not also by a library log line above it."""
    logger = logging.getLogger("tifffile")
    previous = logger.disabled
    logger.disabled = True
    try:
        yield
    finally:
        logger.disabled = previous


# Leading bytes of the other formats satellite images are delivered in, which GDAL converts to
# GeoTIFF with their RPCs (a conversion keeps the pixel grid the RPCs refer to).
_OTHER_FORMATS = (
    (b"\x00\x00\x00\x0cjP  \r\n\x87\n", "a JPEG 2000 (JP2) image"),
    (b"\xff\x4f\xff\x51", "a JPEG 2000 codestream (J2K)"),
    (b"NITF", "an NITF image"),
    (b"NSIF", "an NSIF (NITF) image"),
)


def _not_a_tiff(path: str, exc: Exception) -> str:
    """Why ``path`` cannot be opened as a TIFF, naming the format it is if a known one."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(12)
    except OSError:
        head = b""
    for magic, what in _OTHER_FORMATS:
        if head.startswith(magic):
            return (f"{what}, not a TIFF: satsweep reads TIFF images; convert it with "
                    f"gdal_translate -of GTiff {os.path.basename(path)} OUT.tif (GDAL carries "
                    "its RPCs into the GeoTIFF's RPC tag or an .RPB file beside it, which "
                    "satsweep reads)")
    return f"not a readable TIFF file ({exc})"


@contextlib.contextmanager
def _open_tiff(path: str | os.PathLike):
    """Open a TIFF and yield (TiffFile, first page); every failure is an ImageFormatError."""
    import tifffile

    path = os.fspath(path)
    if not os.path.exists(path):
        raise ImageFormatError(path, "no such file")
    if os.path.isdir(path):
        raise ImageFormatError(path, "is a folder, not an image")
    try:
        with _quiet_tifffile():
            tif = tifffile.TiffFile(path)
    except _TIFF_READ_ERRORS as exc:
        raise ImageFormatError(path, _not_a_tiff(path, exc)) from None
    with tif:
        try:
            with _quiet_tifffile():
                pages = tif.pages
                page = pages.first if len(pages) else None
        except _TIFF_READ_ERRORS as exc:
            raise ImageFormatError(path, f"corrupt TIFF image directory ({exc})") from None
        if page is None:
            raise ImageFormatError(
                path, f"truncated or empty TIFF: no image directory within its {tif.filehandle.size} bytes"
            )
        yield tif, page


def _check_layout(path: str, page) -> None:
    """Raise ImageFormatError unless the page holds a supported 2D (multi-band) raster."""
    if page.axes not in ("YX", "YXS", "SYX"):
        raise ImageFormatError(path, f"unsupported TIFF layout: axes {page.axes} shape {page.shape}")
    kind = page.dtype.kind if page.dtype is not None else "?"
    if kind not in "uif" or page.dtype.itemsize > 8:
        what = "1-bit" if kind == "b" else str(page.dtype)
        raise ImageFormatError(path, f"unsupported pixel type {what} (need integer or float samples)")
    size = page.parent.filehandle.size
    ends = [o + c for o, c in zip(page.dataoffsets, page.databytecounts) if c > 0]
    if ends and max(ends) > size:
        raise ImageFormatError(
            path, f"truncated: pixel data runs to byte {max(ends)} but the file has {size} bytes"
        )


def _first_band(data: np.ndarray, axes: str) -> np.ndarray:
    if axes == "YXS":
        return data[..., 0]
    if axes == "SYX":
        return data[0]
    return data


def _segment_shape(page) -> tuple[int, int]:
    """(rows, columns) of a page's tiles, or of its strips (whole rows)."""
    height = int(page.imagelength)
    if page.is_tiled:
        return int(page.tilelength), int(page.tilewidth)
    rows = int(page.rowsperstrip or height)
    return min(rows, height), int(page.imagewidth)


def _segmented(page) -> bool:
    """Whether a window of the page can be read segment by segment: tiles, or several strips,
    in a layout that ``_read_segments`` places (2-D, bits in the usual order)."""
    if int(page.imagedepth) != 1 or int(page.fillorder) != 1:
        return False
    seg_rows, _ = _segment_shape(page)
    return bool(page.is_tiled) or seg_rows < int(page.imagelength)


def _read_segments(tif, page, rows: slice, cols: slice) -> np.ndarray:
    """The first band's window (native byte order), decoding only the tiles or strips that it
    overlaps: a small AOI of a large compressed or tiled scene reads a small part of the file.

    Segments are numbered row by row over the page's grid of tiles (or strips), the first band's
    segments first when the bands are stored separately (planar configuration 2); a segment with
    no bytes (a sparse file's empty block) reads as zeros, as GDAL and tifffile read it.
    """
    seg_rows, seg_cols = _segment_shape(page)
    across = -(-int(page.imagewidth) // seg_cols)
    out = np.zeros((rows.stop - rows.start, cols.stop - cols.start),
                   page.dtype.newbyteorder("="))
    fh = tif.filehandle
    decode = page.decode
    for ty in range(rows.start // seg_rows, (rows.stop - 1) // seg_rows + 1):
        for tx in range(cols.start // seg_cols, (cols.stop - 1) // seg_cols + 1):
            index = ty * across + tx
            if not page.databytecounts[index]:
                continue
            fh.seek(page.dataoffsets[index])
            data = fh.read(page.databytecounts[index])
            segment, _, _ = decode(data, index, jpegtables=page.jpegtables)
            y0, x0 = ty * seg_rows, tx * seg_cols
            # The overlap of the segment and the window, in image coordinates.
            r0, r1 = max(y0, rows.start), min(y0 + segment.shape[1], rows.stop)
            c0, c1 = max(x0, cols.start), min(x0 + segment.shape[2], cols.stop)
            out[r0 - rows.start:r1 - rows.start, c0 - cols.start:c1 - cols.start] = \
                segment[0, r0 - y0:r1 - y0, c0 - x0:c1 - x0, 0]
    return out


def _window_slices(window, width: int, height: int) -> tuple[slice, slice]:
    if window is None:
        return slice(0, height), slice(0, width)
    x0, y0, x1, y1 = (int(v) for v in window)
    if not (0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height):
        raise ValueError(f"window {window} is not inside the {width}x{height} image")
    return slice(y0, y1), slice(x0, x1)


def _decode_problem(page, exc: Exception) -> str:
    """One-line reason why tifffile could not decode a page, with the usual remedy."""
    compression = getattr(page.compression, "name", str(page.compression))
    if isinstance(exc, ImportError) or "imagecodecs" in str(exc):
        return (
            f"cannot decode {compression} compressed pixels without the 'imagecodecs' package "
            "(pip install imagecodecs, or rewrite it uncompressed: gdal_translate -co COMPRESS=NONE)"
        )
    return f"cannot decode the pixel data ({compression} compression: {type(exc).__name__}: {exc})"


def image_shape(path: str | os.PathLike) -> tuple[int, int]:
    """(height, width) of the first band of a TIFF, read from its header only."""
    path = os.fspath(path)
    with _open_tiff(path) as (_, page):
        _check_layout(path, page)
        return int(page.imagelength), int(page.imagewidth)


def read_image(path: str | os.PathLike, *, window: Sequence[int] | None = None) -> np.ndarray:
    """Read the first band of a TIFF as a 2D array in its stored dtype (native byte order).

    ``window = (x0, y0, x1, y1)`` (pixel indices, ends excluded) reads only that part; an
    uncompressed contiguous file is then memory-mapped so that only the window is read.
    Raises ImageFormatError naming the file when it is missing, not a TIFF, truncated, or of an
    unsupported layout (volumes, 1-bit, complex samples) or compression.
    """
    path = os.fspath(path)
    with _open_tiff(path) as (tif, page):
        _check_layout(path, page)
        rows, cols = _window_slices(window, int(page.imagewidth), int(page.imagelength))
        dtype = page.dtype.newbyteorder(tif.byteorder)
        mappable = (
            window is not None
            and page.is_contiguous
            and int(page.compression) == 1
            and int(page.predictor) == 1
            and int(page.fillorder) == 1
            and page.bitspersample == 8 * dtype.itemsize
        )
        try:
            if mappable:
                data = np.memmap(path, dtype=dtype, mode="r", offset=page.dataoffsets[0], shape=page.shape)
                out = np.array(_first_band(data, page.axes)[rows, cols])
                del data
            elif window is not None and _segmented(page):
                out = _read_segments(tif, page, rows, cols)
            else:
                out = np.array(_first_band(page.asarray(), page.axes)[rows, cols])
        except Exception as exc:  # noqa: BLE001 - any decoder failure on this file is a format error
            raise ImageFormatError(path, _decode_problem(page, exc)) from None
    return out.astype(out.dtype.newbyteorder("="), copy=False)


def tonemap(
    image: np.ndarray,
    *,
    low_percentile: float = DEFAULT_LOW_PERCENTILE,
    high_percentile: float = DEFAULT_HIGH_PERCENTILE,
    gamma: float = 1.0 / 2.2,
) -> np.ndarray:
    """Map an image to float32 in [0, 1] for display: clip at robust percentiles, scale, gamma.

    ``out = clip((v - p_low) / (p_high - p_low), 0, 1) ** gamma`` with the percentiles taken over
    the finite pixels. A constant image (or one without finite pixels) maps to zeros; non-finite
    pixels map to 0, so the result never holds NaN.
    """
    if not 0.0 <= low_percentile < high_percentile <= 100.0:
        raise OptionsError(
            f"tonemap percentiles low={low_percentile!r}, high={high_percentile!r}: "
            "need 0 <= low < high <= 100"
        )
    if not (math.isfinite(gamma) and gamma > 0.0):
        raise OptionsError(f"tonemap gamma = {gamma!r}: must be finite and > 0")
    a = np.asarray(image, dtype=np.float64)
    finite = np.isfinite(a)
    out = np.zeros(a.shape, dtype=np.float32)
    if not finite.any():
        return out
    lo, hi = np.percentile(a[finite], [low_percentile, high_percentile])
    if not hi > lo:
        return out
    t = np.clip((np.where(finite, a, lo) - lo) / (hi - lo), 0.0, 1.0) ** gamma
    out[...] = t
    return out


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
    geokeys = tuple(_geokeys(epsg))
    tags = [
        (TAG_MODEL_PIXEL_SCALE, "d", 3, (float(resolution), float(resolution), 0.0), True),
        (TAG_MODEL_TIEPOINT, "d", 6, (0.0, 0.0, 0.0, float(x_min), float(y_max), 0.0), True),
        (TAG_GEO_KEY_DIRECTORY, "H", len(geokeys), geokeys, True),
    ]
    if nodata is not None:
        tags.append((TAG_GDAL_NODATA, "s", 0, _nodata_text(float(nodata), dtype), True))
    with _maybe_atomic(path, atomic) as target:
        tifffile.imwrite(
            target, np.ascontiguousarray(array, dtype=dtype), photometric="minisblack",
            metadata=None, extratags=tags,
        )


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
    """Read the first band of a north-up GeoTIFF and its georeferencing.

    Supports EPSG projected CRSs (ProjectedCSTypeGeoKey) and geographic ones (GeographicTypeGeoKey,
    e.g. EPSG:4326 DEMs with degree pixels), PixelIsArea and PixelIsPoint (GDAL's half-pixel shift),
    tie points at any raster position, and axis-aligned ModelTransformation tags. The array keeps
    its stored dtype. Raises ImageFormatError naming the file for missing or unsupported
    georeferencing (rotated rasters, user-defined CRSs).
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
    array = read_image(path)
    info = GeoInfo(
        epsg=int(epsg), x_min=x_min, y_max=y_max, resolution=rx, nodata=nodata,
        resolution_y=None if ry == rx else ry,
        vertical_epsg=None if vertical is None else int(vertical),
    )
    return array, info
