"""The user's images, each opened once: its path, RPC and size, with windows read on demand.

A run reads every image's header and RPC once (``open_sources``) and hands the ``ImageSource``
objects to every stage and every tile: the coverage checks, the crops of the views and the
tie points all use them, so an RPC is parsed once per run whatever the number of tiles.
"""

from __future__ import annotations

import dataclasses
import os
from typing import TYPE_CHECKING, Sequence

import numpy as np

from satsweep.errors import AOIError, ImageFormatError, InputError

if TYPE_CHECKING:  # pragma: no cover
    from satsweep.geometry.altitude import AltitudeRange
    from satsweep.geometry.aoi import AOI
    from satsweep.geometry.rpc import RPCModel
    from satsweep.io.masks import MaskFile
    from satsweep.io.metadata import AcquisitionMetadata

# Fewest images stereo needs.
MIN_IMAGES = 2


@dataclasses.dataclass(frozen=True, eq=False)
class ImageSource:
    """One input image: its file, its RPC (of the whole image) and its size."""

    path: str  # the image file, as given
    rpc: "RPCModel"  # projects ground points to pixels of the whole image
    shape: tuple[int, int]  # (rows, columns) of the whole image
    acquisition: "AcquisitionMetadata | None" = None  # date, sun and view angles, when the
    # delivery gives them (satsweep.io.metadata)
    nodata: float | None = None  # the value the file declares for no data (GDAL_NODATA)
    mask: "MaskFile | None" = None  # its mask of pixels to leave out (satsweep.io.masks)

    @property
    def name(self) -> str:
        """The file name without folders, for logs and reports."""
        return os.path.basename(self.path)

    def read(self, window: Sequence[int] | None = None) -> np.ndarray:
        """The pixels of ``window`` = (x0, y0, x1, y1), ends excluded (None: all), as stored."""
        from satsweep.io.images import read_image

        return read_image(self.path, window=window)

    def read_mask(self, window: Sequence[int] | None = None) -> np.ndarray | None:
        """Whether each pixel of ``window`` holds data by the image's mask (bool), or None
        when it has no mask."""
        return None if self.mask is None else self.mask.read(window)

    def read_with_vegetation(self, window: Sequence[int] | None = None
                             ) -> tuple[np.ndarray, np.ndarray | None]:
        """(``read``'s pixels, the vegetation index) of ``window`` from one read
        (``satsweep.io.images.read_image_and_vegetation``); the index is None for an image
        without colour."""
        from satsweep.io.images import read_image_and_vegetation

        return read_image_and_vegetation(self.path, window=window)

    def footprint(self, aoi: "AOI", alt_range: "AltitudeRange", *, margin_px: int = 0,
                  warn_partial: bool = True) -> tuple[int, int, int, int]:
        """The pixel box (x0, y0, x1, y1), ends excluded, that sees the AOI cube, widened by
        ``margin_px`` (``satsweep.io.views.aoi_footprint``); AOIError naming the file when the
        image does not see it."""
        from satsweep.io.views import aoi_footprint

        return aoi_footprint(self.rpc, aoi, alt_range, self.shape, margin_px=margin_px,
                             path=self.path, warn_partial=warn_partial)

    def sees(self, aoi: "AOI", alt_range: "AltitudeRange") -> bool:
        """Whether the footprint of the AOI cube meets the image."""
        try:
            self.footprint(aoi, alt_range, warn_partial=False)
        except AOIError:
            return False
        return True


def open_source(path: str | os.PathLike, *, rpc_file: str | os.PathLike | None = None,
                mask_file: str | os.PathLike | None = None) -> ImageSource:
    """Read an image's header, RPC (tag or sidecar; ``rpc_file`` instead when given, in any
    format ``RPCModel.from_file`` reads), acquisition metadata (when there is some) and find its
    mask (``mask_file`` when given, else GDAL's external or internal one: ``find_mask``);
    ImageFormatError / RPCError naming the file."""
    from satsweep.geometry.rpc import RPCModel
    from satsweep.io.images import image_nodata, image_shape
    from satsweep.io.masks import find_mask
    from satsweep.io.metadata import read_acquisition_metadata

    path = os.fspath(path)
    shape = image_shape(path)
    rpc = RPCModel.from_image(path) if rpc_file is None else RPCModel.from_file(rpc_file)
    return ImageSource(path=path, rpc=rpc, shape=(int(shape[0]), int(shape[1])),
                       acquisition=read_acquisition_metadata(path), nodata=image_nodata(path),
                       mask=find_mask(path, shape, mask_file=mask_file))


def report_names(paths: Sequence[str | os.PathLike]) -> list[str]:
    """How reports and logs name the images ``paths``: each by its file name, or by its path
    (as given) where two share a file name (a/view.tif, b/view.tif)."""
    paths = [os.fspath(p) for p in paths]
    names = [os.path.basename(p) for p in paths]
    return [n if names.count(n) == 1 else p for p, n in zip(paths, names)]


def rpc_files_in(rpc_dir: str | os.PathLike, images: Sequence[str | os.PathLike]) -> list[str]:
    """The RPC of each of ``images`` in the folder ``rpc_dir``: ``<image stem>_RPC.TXT`` (the
    name satsweep's rpc/ outputs and GDAL's sidecars use), matched case-insensitively.
    InputError naming the folder, or the first image that has none there."""
    folder = os.fspath(rpc_dir)
    try:
        names = {n.lower(): n for n in os.listdir(folder)}
    except OSError as exc:
        raise InputError(folder, f"cannot read the RPC folder ({exc.strerror or exc})") from None
    out = []
    for image in images:
        wanted = f"{os.path.splitext(os.path.basename(os.fspath(image)))[0]}_RPC.TXT"
        if wanted.lower() not in names:
            raise InputError(image, f"no {wanted} in the RPC folder {folder}")
        out.append(os.path.join(folder, names[wanted.lower()]))
    return out


def refuse_folders(paths: Sequence[object]) -> None:
    """ImageFormatError naming the first folder among ``paths`` given as images (checked before
    any count: one folder is not "one image"); other items are left alone."""
    for path in paths:
        if isinstance(path, str) and os.path.isdir(path):
            raise ImageFormatError(path, "is a folder, not an image: give the images in it (for "
                                         f"example {os.path.join(path, '*.tif')})")


def refuse_too_few(paths: Sequence[object]) -> None:
    """InputError unless ``paths`` hold at least ``MIN_IMAGES`` images (every entry point's
    rule, after ``refuse_folders``)."""
    if len(paths) < MIN_IMAGES:
        raise InputError(None, f"stereo needs at least {MIN_IMAGES} images, got {len(paths)}")


def open_sources(paths: Sequence[str | os.PathLike | ImageSource], *,
                 rpc_dir: str | os.PathLike | None = None,
                 mask_dir: str | os.PathLike | None = None) -> list[ImageSource]:
    """``open_source`` of every path, in order (sources given as such are kept); with
    ``rpc_dir``, each image's RPC is its file in that folder (``rpc_files_in``: an
    adjustment's RPCs, as satsweep writes to rpc/), not its own; with ``mask_dir``, each
    image's mask is its file in that folder where it has one (``mask_files_in``), and no mask
    where it has none. InputError for fewer than ``MIN_IMAGES`` images, for an image given
    twice, for one whose RPC the folder lacks or for a mask folder that masks none of them."""
    items = [p if isinstance(p, ImageSource) else os.fspath(p) for p in paths]
    refuse_folders(items)
    refuse_too_few(items)
    seen: dict[str, str] = {}
    for item in items:
        path = item.path if isinstance(item, ImageSource) else item
        key = os.path.realpath(path)
        if key in seen:
            raise InputError(path, f"image given twice (also as {seen[key]})")
        seen[key] = path
    files = [None] * len(items)
    masks = [None] * len(items)
    to_open = [k for k, item in enumerate(items) if not isinstance(item, ImageSource)]
    if rpc_dir is not None:
        for k, rpc_file in zip(to_open, rpc_files_in(rpc_dir, [items[k] for k in to_open])):
            files[k] = rpc_file
    if mask_dir is not None:
        from satsweep.io.masks import mask_files_in

        for k, mask_file in zip(to_open, mask_files_in(mask_dir, [items[k] for k in to_open])):
            masks[k] = mask_file
    return [item if isinstance(item, ImageSource)
            else open_source(item, rpc_file=rpc_file, mask_file=mask_file)
            for item, rpc_file, mask_file in zip(items, files, masks)]
