"""Loading the user's images for the pipeline: read, find the AOI in each, crop, shift the RPC.

A ``View`` is one image cropped to the part that sees the AOI box between the altitude range's
bounds (plus a margin), with the RPC of the crop (``rpc.cropped``) and the crop offset. Only the
window is read from disk when the TIFF is uncompressed and contiguous, so full satellite scenes
can be given directly.

Pixel convention: (0, 0) is the centre of the first pixel; a crop box ``(x0, y0, x1, y1)`` holds
the pixels ``x0 <= col < x1``, ``y0 <= row < y1`` (ends excluded, as Python slices).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from satsweep.errors import AOIError, OptionsError
from satsweep.geometry.altitude import AltitudeRange
from satsweep.geometry.aoi import AOI

if TYPE_CHECKING:  # pragma: no cover
    from satsweep.geometry.rpc import RPCModel
    from satsweep.io.sources import ImageSource

log = logging.getLogger(__name__)

# Pixels added around the AOI footprint: room for matching windows, for RPC bias (typically a few
# pixels for Pleiades/WorldView) and for sub-pixel interpolation at the crop edges.
DEFAULT_MARGIN_PX = 32


@dataclasses.dataclass(frozen=True, eq=False)
class View:
    """One image cropped to the AOI, with the RPC of the crop.

    ``image`` is the raw crop (uint8/uint16 kept as stored, other pixel types as float32);
    ``rpc`` projects ground points into crop pixels; ``(x0, y0)`` is the crop's top-left pixel in
    the original image, so crop pixel (c, r) is original pixel (c + x0, r + y0).
    """

    path: str  # the image file
    image: np.ndarray  # cropped raw pixels, 2D
    rpc: "RPCModel"  # RPC of the crop (projects ground points to crop pixels)
    x0: int  # column of the crop's first pixel in the original image
    y0: int  # row of the crop's first pixel in the original image
    valid: np.ndarray | None = None  # bool mask of the pixels that hold data (None: all do);
    # see validity_mask, and the image's own mask (satsweep.io.masks)
    vegetation: np.ndarray | None = None  # float32 vegetation index of the crop's pixels
    # (satsweep.io.images.vegetation_index; None: an image without colour, or not read)

    @property
    def height(self) -> int:
        """Crop height in pixels."""
        return int(self.image.shape[0])

    @property
    def width(self) -> int:
        """Crop width in pixels."""
        return int(self.image.shape[1])

    @property
    def name(self) -> str:
        """The image's file name without folders, for logs and reports."""
        return os.path.basename(self.path)


# An image that sees less of the AOI's footprint than this gets a warning. A sliver of a pixel
# past the image's edge is not worth one: a 17-view 0.3 m synthetic stack's views warned that
# they saw "only about 100%" (99.7%).
PARTIAL_AOI_WARN_FRACTION = 0.995


def projected_aoi_box(project: Callable[..., tuple], aoi: AOI,
                      alt_range: AltitudeRange) -> tuple[float, float, float, float]:
    """(col_min, row_min, col_max, row_max) of the AOI box's edges at both altitude bounds (a
    vertical projects to a segment, so these bound the whole cube), projected by
    ``project(lon=, lat=, alt=) -> (col, row)`` (an RPC's ``projection``, or a camera's)."""
    lon, lat = aoi.boundary()
    alt = np.array([alt_range.min, alt_range.max], dtype=np.float64)
    col, row = project(lon=lon[None, :], lat=lat[None, :], alt=alt[:, None])
    col, row = np.asarray(col, np.float64), np.asarray(row, np.float64)
    if not (np.isfinite(col).all() and np.isfinite(row).all()):
        raise AOIError(f"the RPC projects the AOI {aoi} to non-finite pixel coordinates")
    return float(col.min()), float(row.min()), float(col.max()), float(row.max())


def aoi_footprint(
    rpc: Any,
    aoi: AOI,
    alt_range: AltitudeRange,
    image_shape: Sequence[int],
    *,
    margin_px: int = 0,
    path: str | os.PathLike | None = None,
    warn_partial: bool = True,
) -> tuple[int, int, int, int]:
    """Pixel box ``(x0, y0, x1, y1)`` (ends excluded) of the image that sees the AOI.

    Projects the AOI box's edges (its 4 corners and points between them) at the lowest and the
    highest altitude, takes the bounding box of every pixel whose centre it touches, widens it by
    ``margin_px`` and clips it to the image of shape ``(height, width)``. Raises AOIError (naming
    ``path`` when given) when the box misses the image. Logs a warning when the image sees only
    part of the AOI (unless ``warn_partial`` is False).
    """
    if int(margin_px) != margin_px or margin_px < 0:
        raise OptionsError(f"margin_px = {margin_px!r}: must be an integer >= 0")
    height, width = int(image_shape[0]), int(image_shape[1])
    where = f"{os.fspath(path)}: " if path is not None else ""
    c0, r0, c1, r1 = projected_aoi_box(rpc.projection, aoi, alt_range)
    # Pixel centres are integers: pixels floor(c0) .. ceil(c1) cover [c0, c1].
    bx0, by0 = int(np.floor(c0)) - int(margin_px), int(np.floor(r0)) - int(margin_px)
    bx1, by1 = int(np.ceil(c1)) + 1 + int(margin_px), int(np.ceil(r1)) + 1 + int(margin_px)
    x0, y0, x1, y1 = max(bx0, 0), max(by0, 0), min(bx1, width), min(by1, height)
    if x0 >= x1 or y0 >= y1:
        raise AOIError(
            f"{where}the image ({width}x{height} pixels) does not see the AOI {aoi} at "
            f"{alt_range}: it projects to columns {c0:.0f}..{c1:.0f}, rows {r0:.0f}..{r1:.0f}"
        )
    # Coverage of the AOI itself (without the margin) by the image.
    inner = (max(c0, -0.5), max(r0, -0.5), min(c1, width - 0.5), min(r1, height - 0.5))
    area = max(c1 - c0, 1e-9) * max(r1 - r0, 1e-9)
    seen = max(inner[2] - inner[0], 0.0) * max(inner[3] - inner[1], 0.0) / area
    if seen < PARTIAL_AOI_WARN_FRACTION and warn_partial:
        log.warning("%sthe image sees only about %.0f%% of the AOI footprint", where, 100.0 * seen)
    return x0, y0, x1, y1


# Zeros connected to the crop's border in runs of at least this many pixels are a delivery's
# fill (its margins outside the scene), not dark ground: real 11-14 bit imagery has no such runs.
MIN_ZERO_RUN_PX = 64


def validity_mask(image: np.ndarray, nodata: float | None = None) -> np.ndarray | None:
    """The pixels of an image that hold data, or None when all do. Not data: NaN, the file's
    no-data value, and runs of exact zeros of at least ``MIN_ZERO_RUN_PX`` pixels connected to
    the border (the usual fill of a delivery's margins)."""
    import cv2

    a = np.asarray(image)
    bad = ~np.isfinite(a) if a.dtype.kind == "f" else np.zeros(a.shape, bool)
    if nodata is not None and np.isfinite(nodata):
        bad |= a == nodata
    zero = (a == 0).astype(np.uint8)
    if zero.any():
        n, labels, stats, _ = cv2.connectedComponentsWithStats(zero, connectivity=8)
        border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        big = np.zeros(n, bool)
        big[border] = stats[border, cv2.CC_STAT_AREA] >= MIN_ZERO_RUN_PX
        big[0] = False  # the non-zero pixels
        bad |= big[labels]
    return None if not bad.any() else ~bad


def _pixels(image: np.ndarray) -> np.ndarray:
    """Keep uint8/uint16 pixels as stored; convert any other type to float32."""
    if image.dtype in (np.uint8, np.uint16, np.float32):
        return image
    return image.astype(np.float32)


def crop_to_aoi(
    image: np.ndarray,
    rpc: Any,
    aoi: AOI,
    alt_range: AltitudeRange,
    *,
    margin_px: int = DEFAULT_MARGIN_PX,
    path: str | os.PathLike | None = None,
) -> View:
    """Crop an image already in memory to the AOI footprint (see ``aoi_footprint``)."""
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f"crop_to_aoi needs a 2D image, got shape {image.shape}")
    x0, y0, x1, y1 = aoi_footprint(rpc, aoi, alt_range, image.shape, margin_px=margin_px, path=path)
    crop = np.array(image[y0:y1, x0:x1])
    return View(
        path=os.fspath(path) if path is not None else "<memory>",
        image=_pixels(crop), rpc=rpc.cropped(x0=x0, y0=y0), x0=x0, y0=y0,
    )


def load_views(
    images: Sequence[str | os.PathLike | "ImageSource"],
    aoi: AOI,
    alt_range: AltitudeRange,
    *,
    margin_px: int = DEFAULT_MARGIN_PX,
    warn_partial: bool = True,
    vegetation: bool = False,
) -> list[View]:
    """Each image's window that sees the AOI cube, with the RPC of the crop; one View per image,
    in order. ``images`` are paths or ``ImageSource`` objects (``satsweep.io.sources``: then no
    header or RPC is read again). With ``vegetation``, each colour image's crop also gives its
    vegetation index (``View.vegetation``).

    Raises InputError for fewer than two images or an image given twice, ImageFormatError /
    RPCError naming a bad image or RPC, AOIError naming an image that does not see the AOI.
    """
    from satsweep.io.sources import open_sources

    views = []
    for source in open_sources(images):
        x0, y0, x1, y1 = source.footprint(aoi, alt_range, margin_px=margin_px,
                                          warn_partial=warn_partial)
        if vegetation:
            crop, index = source.read_with_vegetation((x0, y0, x1, y1))
        else:
            crop, index = source.read((x0, y0, x1, y1)), None
        valid = validity_mask(crop, source.nodata)
        masked = source.read_mask((x0, y0, x1, y1))
        if masked is not None:
            log.info("%s: its mask %s leaves out %.1f%% of the crop", source.path,
                     source.mask.describe(), 100.0 * (1.0 - float(np.mean(masked))))
            valid = masked if valid is None else valid & masked
            valid = None if valid.all() else valid
        views.append(View(path=source.path, image=_pixels(crop),
                          rpc=source.rpc.cropped(x0=x0, y0=y0), x0=x0, y0=y0,
                          valid=valid, vegetation=index))
        log.info("%s: crop x=%d..%d, y=%d..%d of %dx%d", source.path, x0, x1, y0, y1,
                 source.shape[1], source.shape[0])
    return views
