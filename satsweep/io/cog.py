"""GeoTIFFs users can stream: tiled, compressed, with internal overviews, written from a band on
disk window by window.

``write_cog`` writes a ``RawBand`` (``satsweep.io.bands``) as a tiled GeoTIFF (``TILE_PX``
square tiles, deflate with the floating-point predictor for float bands and the horizontal one
for integers) followed by its overviews, each half the size of the one before, as
reduced-resolution pages (NewSubfileType 1) down to one tile: the layout GDAL, rasterio and QGIS
read as internal overviews, so a viewer or ``gdal_translate -outsize`` only decodes what it
shows, and an HTTP range reader only fetches the tiles it needs. Neither the band nor an
overview is ever held whole: the tiles are read from disk row of tiles by row of tiles, and each
overview is made from the one before it into a temporary band.

The georeferencing is that of ``satsweep.io.geotiff.write_geotiff`` (ModelPixelScale,
ModelTiepoint, GeoKeyDirectory, GDAL_NODATA); GDAL's metadata tag (42112) carries the band's
description and unit and the dataset's items (e.g. the vertical reference of heights).

The pages' IFDs are written before their tiles, page after page (tifffile's layout), not all at
the start of the file as GDAL's COG driver arranges them: readers get every tile and overview
from their offsets just the same, with one more range request per page.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Iterator, Literal, Mapping
from xml.sax.saxutils import escape

import numpy as np

from satsweep.io.bands import RawBand

# Side (pixels) of the square tiles of every page.
TILE_PX = 256
# GDAL's metadata tag.
TAG_GDAL_METADATA = 42112
# Side, in tiles, of the blocks read from a band at once when its overview is made (bounds the
# memory whatever the band's size: 2048 x 2048 cells).
_OVERVIEW_BLOCK_TILES = 4


def overview_shapes(shape: tuple[int, int], tile: int = TILE_PX) -> list[tuple[int, int]]:
    """The shapes of the overviews of a raster of ``shape``: halved (rounded up) until the
    raster fits in one tile."""
    out = []
    h, w = shape
    while max(h, w) > tile:
        h, w = -(-h // 2), -(-w // 2)
        out.append((h, w))
    return out


def _gdal_metadata(description: str | None, units: str | None,
                   items: Mapping[str, str] | None) -> str | None:
    parts = [f'<Item name="{escape(k)}">{escape(str(v))}</Item>' for k, v in (items or {}).items()]
    if description:
        parts.append(f'<Item name="DESCRIPTION" sample="0" role="description">'
                     f'{escape(description)}</Item>')
    if units:
        parts.append(f'<Item name="" sample="0" role="unittype">{escape(units)}</Item>')
    return f"<GDALMetadata>{''.join(parts)}</GDALMetadata>" if parts else None


def _halve(block: np.ndarray, fill, resampling: str) -> np.ndarray:
    """2 x 2 reduction of ``block`` (odd sides padded with ``fill``): the mean of the cells that
    are not ``fill`` (NaN-aware) for "average", the top-left cell for "nearest"."""
    h, w = block.shape
    if resampling == "nearest":
        return block[0::2, 0::2].copy()
    padded = np.full((h + h % 2, w + w % 2), fill, block.dtype)
    padded[:h, :w] = block
    nan_fill = isinstance(fill, (float, np.floating)) and math.isnan(fill)
    total = np.zeros((padded.shape[0] // 2, padded.shape[1] // 2))
    count = np.zeros(total.shape, np.int8)
    for dy in (0, 1):
        for dx in (0, 1):
            quarter = padded[dy::2, dx::2]
            valid = np.isfinite(quarter) if nan_fill else quarter != fill
            total += np.where(valid, quarter, 0.0)
            count += valid
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), fill)
    return mean.astype(block.dtype)


def _overview(src: RawBand, path: Path, resampling: str, tile: int) -> RawBand:
    """The 2 x 2 reduction of ``src`` into a new band at ``path``, made by square blocks (of an
    even side, so that every block halves on its own)."""
    h, w = src.shape
    dst = RawBand.create(path, (-(-h // 2), -(-w // 2)), src.dtype, src.fill)
    step = 2 * tile * _OVERVIEW_BLOCK_TILES
    for r0 in range(0, h, step):
        for c0 in range(0, w, step):
            block = src.read(r0, min(r0 + step, h), c0, min(c0 + step, w))
            dst.write(r0 // 2, c0 // 2, _halve(block, src.fill, resampling))
    return dst


def _tiles(band: RawBand, tile: int) -> Iterator[np.ndarray]:
    """The band's tiles in row-major order, edge tiles padded with the band's fill value."""
    h, w = band.shape
    for r0 in range(0, h, tile):
        rows = band.read(r0, min(r0 + tile, h), 0, w)
        for c0 in range(0, w, tile):
            out = np.full((tile, tile), band.fill, band.dtype)
            piece = rows[:, c0:c0 + tile]
            out[:piece.shape[0], :piece.shape[1]] = piece
            yield out


def write_cog(path: str | os.PathLike, band: RawBand, *, epsg: int, x_min: float, y_max: float,
              resolution: float, nodata: float | int | None,
              resampling: Literal["average", "nearest"] = "average",
              description: str | None = None, units: str | None = None,
              items: Mapping[str, str] | None = None, tile: int = TILE_PX,
              work_dir: str | os.PathLike | None = None) -> None:
    """Write ``band`` as a tiled, deflate-compressed GeoTIFF with internal overviews at
    ``path`` (see the module docstring). ``x_min``/``y_max``: the outer corner of the top-left
    cell; ``nodata``: the GDAL_NODATA value (None: none); ``resampling``: how overviews reduce
    2 x 2 cells ("average" ignores nodata; "nearest" for masks and counts). The overviews' bands
    are made in ``work_dir`` (default: beside ``path``) and removed after."""
    import tifffile

    from satsweep.io.geotiff import georeference_tags

    path = Path(path)
    work = Path(work_dir) if work_dir is not None else path.parent
    tags = georeference_tags(epsg=epsg, x_min=x_min, y_max=y_max, resolution=resolution,
                             nodata=nodata, dtype=band.dtype)
    xml = _gdal_metadata(description, units, items)
    if xml is not None:
        tags.append((TAG_GDAL_METADATA, "s", 0, xml, True))
    predictor = 3 if band.dtype.kind == "f" else 2
    common = dict(dtype=band.dtype, tile=(tile, tile), compression="zlib", predictor=predictor,
                  photometric="minisblack", metadata=None)
    overviews: list[RawBand] = []
    try:
        with tifffile.TiffWriter(path, bigtiff=band.nbytes > 2**31) as tif:
            tif.write(_tiles(band, tile), shape=band.shape, extratags=tags, **common)
            level = band
            for k, _ in enumerate(overview_shapes(band.shape, tile)):
                level = _overview(level, work / f".{path.stem}.overview{k + 1}.raw", resampling,
                                  tile)
                overviews.append(level)
                tif.write(_tiles(level, tile), shape=level.shape, subfiletype=1, **common)
                if len(overviews) > 1:  # only the last level is needed for the next one
                    overviews[-2].remove()
    finally:
        for level in overviews:
            level.remove()
