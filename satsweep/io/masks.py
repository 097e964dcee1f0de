"""Per-image masks of the pixels to leave out (clouds, a delivery's margins, water): GDAL's.

A mask is a raster of the image's own size in which 0 marks a pixel to leave out and any other
value a pixel of data: GDAL's mask band, which QGIS, rasterio (``dataset.read_masks``) and
``gdal_translate -mask`` read and write. satsweep finds an image's mask where GDAL does:

- beside the image, as ``<image file name>.msk`` (GDAL's external mask: ``img.tif.msk``);
- inside the image, as a page whose NewSubfileType is 4 (a transparency mask) of the image's
  size (GDAL's internal mask, ``GDAL_TIFF_INTERNAL_MASK=YES``, the default of GDAL 3);
- with ``--mask-dir DIR``, as ``DIR/<image file name>.msk`` (masks made apart from the
  delivery: a cloud detector's, hand-drawn ones), in place of the two above for the images
  that have one there.

Masked pixels are no data for every stage, as the no-data value and the zero fill of a delivery's
margins are (``satsweep.io.views.validity_mask``): no tie points there, no heights matched on
them, a view with too little left is left out with a warning naming it.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Sequence

import numpy as np

from satsweep.errors import ImageFormatError, InputError

# GDAL's name of an image's external mask: the image's file name with this added.
MASK_SUFFIX = ".msk"
# NewSubfileType of a transparency mask (TIFF 6.0's FILETYPE_MASK): GDAL's internal masks.
_SUBFILE_MASK = 4


@dataclasses.dataclass(frozen=True)
class MaskFile:
    """Where an image's mask lies: a TIFF file and the page of it that holds the mask."""

    path: str  # the mask's file: the image itself for an internal mask
    page: int  # the page (image file directory) of that file holding the mask
    internal: bool  # whether the mask lies inside the image (GDAL's internal mask)

    def describe(self) -> str:
        """For the report and logs: the mask's file, or that it lies inside the image."""
        return f"{self.path} (internal mask)" if self.internal else self.path

    def read(self, window: Sequence[int] | None = None) -> np.ndarray:
        """Whether each pixel of ``window`` = (x0, y0, x1, y1), ends excluded (None: all),
        holds data (bool: the mask's value is not 0). ImageFormatError naming the mask."""
        from satsweep.io.images import _open_tiff, _read_segments, _window_slices

        with _open_tiff(self.path) as (tif, _):
            page = tif.pages[self.page]
            rows, cols = _window_slices(window, int(page.imagewidth), int(page.imagelength))
            try:
                values = _read_segments(tif, page, rows, cols)
            except Exception as exc:  # a codec or a truncated segment: the mask's problem
                raise ImageFormatError(self.path, f"cannot decode the mask ({exc})") from None
        return values != 0


def _mask_layout_problem(page, shape: tuple[int, int]) -> str | None:
    """Why ``page`` cannot be an image's mask of ``shape`` (rows, columns), or None."""
    size = (int(page.imagelength), int(page.imagewidth))
    if size != tuple(shape):
        return (f"the mask is {size[1]}x{size[0]} pixels but its image {shape[1]}x{shape[0]}: "
                "a mask has its image's size")
    if page.axes not in ("YX", "YXS", "SYX"):  # (of several bands, the first is read)
        return f"a mask is a 2-D raster, this one has axes {page.axes} (shape {page.shape})"
    if page.dtype is None or page.dtype.kind not in "bui":
        return f"a mask holds integers (0 = no data), this one {page.dtype}"
    return None


def _internal_mask(image: str, shape: tuple[int, int]) -> MaskFile | None:
    """The image's internal mask (its page of NewSubfileType 4 of the image's size), or None."""
    from satsweep.io.images import _open_tiff

    with _open_tiff(image) as (tif, _):
        for index, page in enumerate(tif.pages):
            if index == 0:
                continue
            if int(getattr(page, "subfiletype", 0)) != _SUBFILE_MASK:
                continue
            if (int(page.imagelength), int(page.imagewidth)) != tuple(shape):
                continue  # an overview's mask
            problem = _mask_layout_problem(page, shape)
            if problem is not None:
                raise ImageFormatError(image, f"internal mask: {problem}")
            return MaskFile(path=image, page=index, internal=True)
    return None


def _external_mask(path: str, image: str, shape: tuple[int, int]) -> MaskFile:
    """The mask in the file ``path`` (its first page), checked against its image's size."""
    from satsweep.io.images import _open_tiff

    with _open_tiff(path) as (_, page):
        problem = _mask_layout_problem(page, shape)
    if problem is not None:
        raise ImageFormatError(path, f"{problem} ({os.path.basename(image)})")
    return MaskFile(path=path, page=0, internal=False)


def _sidecar(folder: str, image: str, names: dict[str, str] | None = None) -> str | None:
    """``folder/<image file name>.msk`` (the suffix in either case, as GDAL looks for it), or
    None. ``names``: the folder's file names by their lower case, when already listed."""
    wanted = os.path.basename(image) + MASK_SUFFIX
    if names is None:
        for name in (wanted, os.path.basename(image) + MASK_SUFFIX.upper()):
            candidate = os.path.join(folder, name)
            if os.path.isfile(candidate):
                return candidate
        return None
    hit = names.get(wanted.lower())
    return None if hit is None else os.path.join(folder, hit)


def find_mask(image: str | os.PathLike, shape: tuple[int, int], *,
              mask_file: str | os.PathLike | None = None) -> MaskFile | None:
    """The mask of ``image`` (of ``shape`` = (rows, columns)): ``mask_file`` when given, else
    GDAL's external mask beside it, else its internal mask, else None. ImageFormatError naming
    the mask when it is not one of the image's size."""
    image = os.fspath(image)
    if mask_file is not None:
        return _external_mask(os.fspath(mask_file), image, shape)
    beside = _sidecar(os.path.dirname(image), image)
    if beside is not None:
        return _external_mask(beside, image, shape)
    from satsweep.io.products import tiled_product

    if tiled_product(image) is not None:
        return None  # a tiled product's scene: no internal mask (its tiles' are not read)
    return _internal_mask(image, shape)


def mask_files_in(mask_dir: str | os.PathLike, images: Sequence[str | os.PathLike]
                  ) -> list[str | None]:
    """Each image's mask in the folder ``mask_dir`` (``<image file name>.msk``, matched
    case-insensitively), None for an image without one there: a mask is only needed where
    there are clouds. InputError naming the folder when it cannot be read or holds a mask for
    none of the images (a wrong folder would otherwise mask nothing without a word)."""
    folder = os.fspath(mask_dir)
    try:
        names = {n.lower(): n for n in os.listdir(folder)}
    except OSError as exc:
        raise InputError(folder, f"cannot read the mask folder ({exc.strerror or exc})") from None
    out = [_sidecar(folder, os.fspath(image), names) for image in images]
    if images and all(m is None for m in out):
        example = os.path.basename(os.fspath(images[0])) + MASK_SUFFIX
        raise InputError(folder, f"the mask folder holds a mask for none of the {len(out)} "
                                 f"images (named after each image, as {example})")
    return out
