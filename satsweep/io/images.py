"""Reading satellite images (TIFF) with tifffile, and tonemapping them.

- ``read_image``: the first band of a TIFF as a 2D array in its stored dtype, or an RGB image's
  luminance (optionally only a window of it: an uncompressed file is memory-mapped, a tiled or
  stripped one has only the segments under the window decoded).
- ``tonemap``: a robust percentile clip and gamma, to about [0, 1].

GeoTIFFs (DSMs, DEMs) are read and written by :mod:`satsweep.io.geotiff`.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import struct
from typing import Iterator, Sequence

import numpy as np

from satsweep.errors import ImageFormatError, OptionsError

# Default tone-mapping percentiles: robust to a few saturated or dead pixels.
DEFAULT_LOW_PERCENTILE = 1.0
DEFAULT_HIGH_PERCENTILE = 99.0


# -- reading -----------------------------------------------------------------------------------
# What tifffile raises on files that are not TIFFs or are cut short (struct.error for a file cut
# inside its header, for instance): each becomes an ImageFormatError naming the file.
_TIFF_READ_ERRORS = (ValueError, OSError, EOFError, IndexError, KeyError, struct.error,
                     TypeError, OverflowError, ZeroDivisionError)


@contextlib.contextmanager
def quiet_tifffile() -> Iterator[None]:
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
    """Open a TIFF and yield (TiffFile, first page); every failure to read it, in here or in the
    caller's block, is an ImageFormatError naming the file (tifffile's own log lines are
    silenced meanwhile)."""
    import tifffile

    path = os.fspath(path)
    if not os.path.exists(path):
        raise ImageFormatError(path, "no such file")
    if os.path.isdir(path):
        raise ImageFormatError(path, "is a folder, not an image")
    try:
        with quiet_tifffile():
            tif = tifffile.TiffFile(path)
    except _TIFF_READ_ERRORS as exc:
        raise ImageFormatError(path, _not_a_tiff(path, exc)) from None
    with tif, quiet_tifffile():
        try:
            pages = tif.pages
            page = pages.first if len(pages) else None
        except _TIFF_READ_ERRORS as exc:
            raise ImageFormatError(path, f"corrupt TIFF image directory ({exc})") from None
        if page is None:
            raise ImageFormatError(
                path, f"truncated or empty TIFF: no image directory within its {tif.filehandle.size} bytes"
            )
        try:
            yield tif, page
        except _TIFF_READ_ERRORS as exc:
            # A tag read lazily (the size, a GeoTIFF key) holding the wrong type or count: the
            # file is corrupt, whatever the caller was reading.
            raise ImageFormatError(path, f"corrupt TIFF tags ({type(exc).__name__}: "
                                         f"{str(exc)[:200]})") from None


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


# Luminance of an RGB image (ITU-R BT.601 weights of red, green and blue, as OpenCV's and
# COLMAP's grey conversions): pansharpened colour deliveries are matched on all three bands,
# not on their red band alone.
LUMA_WEIGHTS = (0.299, 0.587, 0.114)


def _is_rgb(page) -> bool:
    """Whether the page is an RGB image (photometric RGB, 3 samples or more: alpha is ignored)."""
    return int(page.photometric) == 2 and int(page.samplesperpixel) >= 3


def luminance(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) red, green, blue samples -> float32 luminance (LUMA_WEIGHTS); a grey sample
    (R = G = B, a fill value among them) keeps its value exactly."""
    r, g, b = (rgb[..., k].astype(np.float32) for k in range(3))
    y = LUMA_WEIGHTS[0] * r + LUMA_WEIGHTS[1] * g + LUMA_WEIGHTS[2] * b
    return np.where((r == g) & (g == b), r, y).astype(np.float32)


def _grey(data: np.ndarray, axes: str, rows: slice, cols: slice, rgb: bool) -> np.ndarray:
    """The window ``rows``, ``cols`` of the page's pixels ``data``: the first band, or the
    luminance of an RGB image (see read_image)."""
    if rgb:
        return luminance(_colour(data, axes, rows, cols))
    if axes == "YXS":
        return np.array(data[rows, cols, 0])
    if axes == "SYX":
        return np.array(data[0, rows, cols])
    return np.array(data[rows, cols])


def _colour(data: np.ndarray, axes: str, rows: slice, cols: slice) -> np.ndarray:
    """The window ``rows``, ``cols`` of an RGB page's pixels ``data`` as (H, W, 3) red, green,
    blue."""
    if axes == "SYX":
        return np.stack([data[k, rows, cols] for k in range(3)], axis=-1)
    return np.array(data[rows, cols, :3])


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


def _read_segments(tif, page, rows: slice, cols: slice, colour: bool = False) -> np.ndarray:
    """The window of the first band (native byte order), or of an RGB image's luminance,
    decoding only the tiles or strips that it overlaps: a small AOI of a large compressed or
    tiled scene reads a small part of the file.

    Segments are numbered row by row over the page's grid of tiles (or strips), band after band
    when the bands are stored separately (planar configuration 2); a segment with no bytes (a
    sparse file's empty block) reads as zeros, as GDAL and tifffile read it.
    """
    seg_rows, seg_cols = _segment_shape(page)
    across = -(-int(page.imagewidth) // seg_cols)
    per_band = across * -(-int(page.imagelength) // seg_rows)
    rgb = _is_rgb(page)
    separate = page.axes == "SYX"
    bands = 3 if rgb else 1
    out = np.zeros((rows.stop - rows.start, cols.stop - cols.start, bands),
                   page.dtype.newbyteorder("="))
    fh = tif.filehandle
    decode = page.decode
    for ty in range(rows.start // seg_rows, (rows.stop - 1) // seg_rows + 1):
        for tx in range(cols.start // seg_cols, (cols.stop - 1) // seg_cols + 1):
            y0, x0 = ty * seg_rows, tx * seg_cols
            for band in range(bands if separate else 1):
                index = band * per_band + ty * across + tx
                if not page.databytecounts[index]:
                    continue
                fh.seek(page.dataoffsets[index])
                data = fh.read(page.databytecounts[index])
                segment, _, _ = decode(data, index, jpegtables=page.jpegtables)
                # The overlap of the segment and the window, in image coordinates.
                r0, r1 = max(y0, rows.start), min(y0 + segment.shape[1], rows.stop)
                c0, c1 = max(x0, cols.start), min(x0 + segment.shape[2], cols.stop)
                part = segment[0, r0 - y0:r1 - y0, c0 - x0:c1 - x0]
                target = out[r0 - rows.start:r1 - rows.start, c0 - cols.start:c1 - cols.start]
                if separate:
                    target[..., band] = part[..., 0]
                else:
                    target[...] = part[..., :bands]
    if colour and rgb:
        return out
    return luminance(out) if rgb else out[..., 0]


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


def image_nodata(path: str | os.PathLike) -> float | None:
    """The no-data value a TIFF declares (GDAL's tag 42113), or None (of a tiled product's DIM
    or TIL file, the value its tiles share: ``satsweep.io.products``)."""
    from satsweep.io.geotiff import TAG_GDAL_NODATA, _parse_nodata
    from satsweep.io.products import tiled_product

    path = os.fspath(path)
    product = tiled_product(path)
    if product is not None:  # a tiled product: its tiles' value, which they must share
        values = {repr(v): v for v in (image_nodata(t.path) for t in product.tiles)}
        if len(values) > 1:
            raise ImageFormatError(path, f"{product.kind}: its tiles declare different no-data "
                                         f"values ({', '.join(sorted(values))})")
        return next(iter(values.values()))
    with _open_tiff(path) as (_, page):
        tag = page.tags.get(TAG_GDAL_NODATA)
        return _parse_nodata(path, tag.value if tag is not None else None)


def image_shape(path: str | os.PathLike) -> tuple[int, int]:
    """(height, width) of the first band of a TIFF, read from its header only (of a tiled
    product's DIM or TIL file, its scene: ``satsweep.io.products``)."""
    from satsweep.io.products import tiled_product

    path = os.fspath(path)
    product = tiled_product(path)
    if product is not None:
        return product.shape
    with _open_tiff(path) as (_, page):
        _check_layout(path, page)
        return int(page.imagelength), int(page.imagewidth)


def read_image(path: str | os.PathLike, *, window: Sequence[int] | None = None) -> np.ndarray:
    """Read the first band of a TIFF as a 2D array in its stored dtype (native byte order); of an
    RGB image (photometric RGB), its luminance ``0.299 R + 0.587 G + 0.114 B`` as float32
    (LUMA_WEIGHTS; grey pixels, R = G = B, keep their value exactly).

    ``window = (x0, y0, x1, y1)`` (pixel indices, ends excluded) reads only that part; an
    uncompressed contiguous file is then memory-mapped so that only the window is read.
    Raises ImageFormatError naming the file when it is missing, not a TIFF, truncated, or of an
    unsupported layout (volumes, 1-bit, complex samples) or compression.
    """
    return _read_checked(path, window, colour=False)[0]


def _read_checked(path: str | os.PathLike, window: Sequence[int] | None, *,
                  colour: bool, rgb_only: bool = False) -> tuple[np.ndarray | None, bool]:
    """(the window's pixels in native byte order, whether the image is RGB): ``read_image``'s
    pixels, or with ``colour`` an RGB image's (H, W, 3) bands instead of their luminance; with
    ``rgb_only``, (None, False) for an image of one band, nothing decoded. A tiled product's
    DIM or TIL file reads the tiles under the window (``satsweep.io.products``)."""
    from satsweep.io.products import tiled_product

    path = os.fspath(path)
    product = tiled_product(path)
    if product is not None:
        return product.read(window, colour=colour, rgb_only=rgb_only)
    with _open_tiff(path) as (tif, page):
        _check_layout(path, page)
        size = int(page.imagewidth), int(page.imagelength)
        rgb = _is_rgb(page)
        if rgb_only and not rgb:
            return None, False
        if not _window_inside(window, *size):
            out = None  # the caller's error, raised below (not the file's)
        else:
            out = _read_window(path, tif, page, window, *_window_slices(window, *size),
                               colour=colour)
    if out is None:
        raise ValueError(f"window {window} is not inside the {size[0]}x{size[1]} image")
    return out.astype(out.dtype.newbyteorder("="), copy=False), rgb


def read_image_and_vegetation(path: str | os.PathLike, *, window: Sequence[int] | None = None
                              ) -> tuple[np.ndarray, np.ndarray | None]:
    """(``read_image``, ``read_vegetation_index``) of one window from one read: an RGB image's
    bands are decoded once and give both; an image of one band gives (its pixels, None)."""
    out, rgb = _read_checked(path, window, colour=True)
    if not rgb:
        return out, None
    return luminance(out), vegetation_index(out)


# A pixel shows vegetation (leaves, and grass) from this index on: the threshold of the crowns'
# rule (satsweep.products.fusion.green_crown_tops, measured there), of the report's
# vegetation share per view, and the lower end of the canopy threshold of the leaf state from
# colour (satsweep.dense.similarity.leaf_state_from_vegetation).
VEGETATION_INDEX_MIN = 0.1


# The vegetation index of RGB deliveries: the normalised green-red difference (G - R) / (G + R)
# (Tucker 1979), which needs no near-infrared band: leaves are greener than they are red, soil,
# asphalt, roofs and shadows about as red as green. 0 where both bands are 0.
def vegetation_index(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) red, green, blue samples -> float32 (G - R) / (G + R), in [-1, 1]."""
    r, g = (rgb[..., k].astype(np.float32) for k in (0, 1))
    total = r + g
    return np.where(total > 0, (g - r) / np.where(total > 0, total, 1.0), 0.0).astype(np.float32)


def read_vegetation_index(path: str | os.PathLike, *, window: Sequence[int] | None = None
                          ) -> np.ndarray | None:
    """The ``vegetation_index`` of an RGB image (photometric RGB) over ``window`` (as
    ``read_image``'s), float32; None for an image of one band (panchromatic, a grey TIFF), which
    has no colour to tell leaves by. ImageFormatError naming the file as ``read_image``."""
    out, rgb = _read_checked(path, window, colour=True, rgb_only=True)
    return vegetation_index(out) if rgb else None


def _window_inside(window, width: int, height: int) -> bool:
    if window is None:
        return True
    x0, y0, x1, y1 = (int(v) for v in window)
    return 0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height


def _read_window(path: str, tif, page, window, rows: slice, cols: slice,
                 colour: bool = False) -> np.ndarray:
    """The pixels of ``rows``, ``cols`` of the first band, or of an RGB image's luminance (see
    ``read_image``); with ``colour``, an RGB image's (H, W, 3) bands instead."""
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
        rgb = _is_rgb(page)
        take = _colour if colour and rgb else functools.partial(_grey, rgb=rgb)
        if mappable:
            data = np.memmap(path, dtype=dtype, mode="r", offset=page.dataoffsets[0], shape=page.shape)
            out = take(data, page.axes, rows, cols)
            del data
        elif window is not None and _segmented(page):
            out = _read_segments(tif, page, rows, cols, colour=colour)
        else:
            out = take(page.asarray(), page.axes, rows, cols)
    except Exception as exc:  # noqa: BLE001 - any decoder failure on this file is a format error
        raise ImageFormatError(path, _decode_problem(page, exc)) from None
    return out


def tonemap(
    image: np.ndarray,
    *,
    low_percentile: float = DEFAULT_LOW_PERCENTILE,
    high_percentile: float = DEFAULT_HIGH_PERCENTILE,
    gamma: float = 1.0 / 2.2,
    valid: np.ndarray | None = None,
) -> np.ndarray:
    """Map an image to float32 in [0, 1] for display: clip at robust percentiles, scale, gamma.

    ``out = clip((v - p_low) / (p_high - p_low), 0, 1) ** gamma`` with the percentiles taken over
    the finite pixels (and only those of the ``valid`` mask when given: no-data fill values do
    not stretch the range). A constant image (or one without finite pixels) maps to zeros;
    non-finite pixels map to 0 and the pixels outside ``valid`` to the median of the others, so
    the result never holds NaN and no-data areas are flat (no edges to match inside them).
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
    if valid is not None:
        finite &= np.asarray(valid, bool)
    out = np.zeros(a.shape, dtype=np.float32)
    if not finite.any():
        return out
    lo, hi = np.percentile(a[finite], [low_percentile, high_percentile])
    if not hi > lo:
        return out
    t = np.clip((np.where(finite, a, lo) - lo) / (hi - lo), 0.0, 1.0) ** gamma
    out[...] = t
    if valid is not None and not finite.all():
        out[~finite] = np.float32(np.median(out[finite]))
    return out
