"""An Airbus DIMAP product given by its DIM file: the scene as one image over its tiles.

GDAL opens a Pleiades, SPOT 6/7 or Pleiades Neo delivery's ``DIM_X.XML`` as one raster: the
GeoTIFF tiles it lists (``IMG_X_R1C1.TIF``, ``IMG_X_R1C2.TIF``, ...) side by side, with the
product's RPC (``RPC_X.XML``), which models the whole scene. CARS and S2P users pass that file
as the image. satsweep reads it the same way (``dimap_product``): the readers of
``satsweep.io.images`` read a window of the scene from the tiles under it, ``RPCModel.from_image``
takes the product's RPC, and the acquisition metadata comes from the DIM file itself.

The tiles' places are ``Raster_Data/Raster_Dimensions/Tile_Set/Regular_Tiling``'s tile size
and each ``Data_File``'s ``tile_R`` / ``tile_C``, as GDAL reads them; a product of one file
has no tiling. Every problem with the product (a tile missing, of the wrong size or format,
tiles that overlap or leave a gap, JPEG 2000 tiles) is an ImageFormatError naming the DIM file.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import Sequence
from xml.etree import ElementTree

import numpy as np

from satsweep.errors import ImageFormatError

# Bytes of a file read to tell a DIMAP document from other XML before parsing it all.
_HEAD_BYTES = 4096


@dataclasses.dataclass(frozen=True)
class DimapTile:
    """One file of a DIMAP product and its place in the scene."""

    path: str  # the tile's GeoTIFF
    x0: int  # column of its first pixel in the scene
    y0: int  # row of its first pixel in the scene
    width: int
    height: int


@dataclasses.dataclass(frozen=True)
class DimapProduct:
    """A DIMAP product's scene: its size, its tiles, its RPC file."""

    path: str  # the DIM file
    shape: tuple[int, int]  # (rows, columns) of the scene
    tiles: tuple[DimapTile, ...]  # row by row, covering the scene once
    rpc_path: str | None  # the product's RPC file, None when there is none beside it

    @property
    def rpc_names(self) -> str:
        """The RPC file(s) looked for, for an error saying there is none."""
        return f"RPC_{Path(self.path).stem[4:]}.XML" if _dim_stem(self.path) else "RPC_*.XML"

    def pieces(self, window: Sequence[int]) -> list[tuple[DimapTile, tuple[int, int, int, int],
                                                          tuple[slice, slice]]]:
        """For ``window`` = (x0, y0, x1, y1) of the scene (ends excluded): each tile under it,
        the window in the tile's pixels and where that part goes in the window's array."""
        x0, y0, x1, y1 = (int(v) for v in window)
        out = []
        for t in self.tiles:
            a0, b0 = max(x0, t.x0), max(y0, t.y0)
            a1, b1 = min(x1, t.x0 + t.width), min(y1, t.y0 + t.height)
            if a0 < a1 and b0 < b1:
                out.append((t, (a0 - t.x0, b0 - t.y0, a1 - t.x0, b1 - t.y0),
                            (slice(b0 - y0, b1 - y0), slice(a0 - x0, a1 - x0))))
        return out

    def read(self, window: Sequence[int] | None, *, colour: bool, rgb_only: bool = False
             ) -> tuple[np.ndarray | None, bool]:
        """``satsweep.io.images._read_checked`` of the scene: (the window's pixels, whether the
        tiles are RGB), read from the tiles under the window."""
        from satsweep.io.images import _read_checked, _window_inside

        rows, cols = self.shape
        if not _window_inside(window, cols, rows):
            raise ValueError(f"window {window} is not inside the {cols}x{rows} image")
        window = (0, 0, cols, rows) if window is None else tuple(int(v) for v in window)
        out, rgb = None, False
        for tile, part, (rs, cs) in self.pieces(window):
            piece, rgb = _read_checked(tile.path, part, colour=colour, rgb_only=rgb_only)
            if piece is None:  # rgb_only, and the tiles are of one band
                return None, False
            if out is None:
                out = np.zeros((window[3] - window[1], window[2] - window[0]) + piece.shape[2:],
                               piece.dtype)
            out[rs, cs] = piece
        return out, rgb


def _dim_stem(path: str) -> bool:
    return Path(path).stem.lower().startswith("dim_") and len(Path(path).stem) > 4


def dimap_product(path: str | os.PathLike) -> DimapProduct | None:
    """The DIMAP product whose DIM file is ``path``, or None when ``path`` is not an XML file
    holding a ``Dimap_Document`` (any image satsweep reads otherwise). Read once per file
    version (cached on its size and modification time). ImageFormatError naming the DIM file
    for a product that cannot be read as one image."""
    path = os.fspath(path)
    if not path.lower().endswith(".xml"):
        return None
    try:
        stat = os.stat(path)
        with open(path, "rb") as fh:
            head = fh.read(_HEAD_BYTES)
    except OSError:
        return None  # the TIFF readers report a missing file
    if b"Dimap_Document" not in head:
        return None
    return _read_product(os.path.abspath(path), stat.st_size, stat.st_mtime_ns, path)


@functools.lru_cache(maxsize=32)
def _read_product(abspath: str, size: int, mtime_ns: int, given: str) -> DimapProduct:
    from satsweep.geometry.rpc_formats import _without_namespaces

    def bad(problem: str) -> ImageFormatError:
        return ImageFormatError(given, f"DIMAP product: {problem}")

    try:
        root = _without_namespaces(ElementTree.fromstring(Path(abspath).read_bytes()))
    except (OSError, ElementTree.ParseError) as exc:
        raise bad(f"cannot read its XML ({exc})") from None
    if root.tag != "Dimap_Document":
        raise bad(f"the XML root is <{root.tag}>, not <Dimap_Document>")
    folder = os.path.dirname(abspath)
    dims = root.find("Raster_Data/Raster_Dimensions")
    try:
        rows, cols = (int((dims.findtext(k) or "").strip()) for k in ("NROWS", "NCOLS"))
    except (AttributeError, ValueError):
        raise bad("no whole NROWS / NCOLS in Raster_Data/Raster_Dimensions") from None
    fmt = (root.findtext("Raster_Data/Data_Access/DATA_FILE_FORMAT") or "").strip().lower()
    name = os.path.basename(given)
    if "jp2" in fmt or "jpeg2000" in fmt:
        raise bad(f"its tiles are JPEG 2000 ({fmt}), not GeoTIFF: satsweep reads TIFF images; "
                  f"convert the product with gdal_translate -of GTiff {name} OUT.tif (GDAL "
                  "mosaics the tiles and carries the RPC into the GeoTIFF)")
    files = (root.findall("Raster_Data/Data_Access/Data_Files/Data_File")
             or list(root.iter("Data_File")))
    if not files:
        raise bad("it lists no Data_File")
    tiling = dims.find("Tile_Set/Regular_Tiling")
    if tiling is None:
        if len(files) != 1:
            raise bad(f"it lists {len(files)} files but no Regular_Tiling to place them")
        size_r, size_c = rows, cols
    else:
        size = tiling.find("NTILES_SIZE")
        try:
            size_r, size_c = int(size.get("nrows", "")), int(size.get("ncols", ""))
            overlap = [int((tiling.findtext(k) or "0").strip())
                       for k in ("OVERLAP_ROW", "OVERLAP_COL")]
        except (AttributeError, ValueError):
            raise bad("no whole NTILES_SIZE nrows / ncols in its Regular_Tiling") from None
        if any(overlap):
            raise bad(f"its tiles overlap (OVERLAP_ROW / OVERLAP_COL {overlap[0]} / {overlap[1]}), "
                      "which satsweep does not mosaic")
        if size_r <= 0 or size_c <= 0:
            raise bad(f"NTILES_SIZE {size_c}x{size_r} is empty")
    from satsweep.io.images import _check_layout, _is_rgb, _open_tiff

    tiles, seen, kinds = [], set(), {}
    for data_file in files:
        href_el = data_file.find("DATA_FILE_PATH")
        href = "" if href_el is None else (href_el.get("href") or href_el.text or "").strip()
        if not href:
            raise bad("a Data_File has no DATA_FILE_PATH href")
        try:
            r, c = int(data_file.get("tile_R", "1")), int(data_file.get("tile_C", "1"))
        except ValueError:
            raise bad(f"{href}: tile_R / tile_C are not whole numbers") from None
        y0, x0 = (r - 1) * size_r, (c - 1) * size_c
        if r < 1 or c < 1 or y0 >= rows or x0 >= cols or (r, c) in seen:
            raise bad(f"{href}: tile R{r}C{c} is outside the {cols}x{rows} scene or listed twice")
        seen.add((r, c))
        tile_path = os.path.join(folder, *href.replace("\\", "/").split("/"))
        want = (min(size_r, rows - y0), min(size_c, cols - x0))
        if not os.path.isfile(tile_path):
            raise bad(f"its tile {href} is not there ({tile_path})")
        try:
            with _open_tiff(tile_path) as (_, page):
                _check_layout(tile_path, page)
                got = (int(page.imagelength), int(page.imagewidth))
                kinds[href] = f"{page.dtype}{' RGB' if _is_rgb(page) else ''}"
        except ImageFormatError as exc:
            raise bad(f"its tile {href}: {exc.problem}") from None
        if len(set(kinds.values())) > 1:
            raise bad("its tiles differ in pixel type or bands ("
                      + ", ".join(f"{k}: {v}" for k, v in kinds.items()) + ")")
        if tuple(got) != want:
            raise bad(f"its tile {href} is {got[1]}x{got[0]} pixels; at R{r}C{c} of a "
                      f"{cols}x{rows} scene in tiles of {size_c}x{size_r} it should be "
                      f"{want[1]}x{want[0]}")
        tiles.append(DimapTile(path=tile_path, x0=x0, y0=y0, width=want[1], height=want[0]))
    covered = sum(t.width * t.height for t in tiles)
    if covered != rows * cols:
        missing = [f"R{r + 1}C{c + 1}" for r in range(-(-rows // size_r))
                   for c in range(-(-cols // size_c)) if (r + 1, c + 1) not in seen]
        raise bad(f"its tiles leave part of the {cols}x{rows} scene uncovered (no tile "
                  f"{', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''})")
    tiles.sort(key=lambda t: (t.y0, t.x0))
    return DimapProduct(path=given, shape=(rows, cols), tiles=tuple(tiles),
                        rpc_path=_rpc_file(root, folder, abspath))


def _rpc_file(root: ElementTree.Element, folder: str, dim: str) -> str | None:
    """The product's RPC file: the one the DIM file names (its Rational_Function_Model
    component), else RPC_X.XML beside DIM_X.XML (GDAL's rule); None when neither is there."""
    candidates = []
    for comp in root.iter("Component"):
        href = comp.find("COMPONENT_PATH")
        href = "" if href is None else (href.get("href") or href.text or "").strip()
        title = (comp.findtext("COMPONENT_TITLE") or "") + (comp.findtext("COMPONENT_TYPE") or "")
        if href and ("rpc" in href.lower().rsplit("/", 1)[-1] or "rational" in title.lower()):
            candidates.append(os.path.join(folder, *href.replace("\\", "/").split("/")))
    if _dim_stem(dim):
        stem = Path(dim).stem[4:]
        try:
            names = {n.lower(): n for n in os.listdir(folder)}
        except OSError:
            names = {}
        hit = names.get(f"rpc_{stem.lower()}.xml")
        if hit is not None:
            candidates.append(os.path.join(folder, hit))
    return next((c for c in candidates if os.path.isfile(c)), None)
