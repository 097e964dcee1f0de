"""A tiled product given by its product file: the scene as one image over its tiles.

GDAL opens two kinds of delivery of a scene in several GeoTIFF tiles as one raster, and CARS
and S2P users pass that file as the image:

- an Airbus DIMAP product (Pleiades, SPOT 6/7, Pleiades Neo) by its ``DIM_X.XML``: the tiles
  ``IMG_X_R1C1.TIF``, ``IMG_X_R1C2.TIF``, ... it lists, placed by
  ``Raster_Data/Raster_Dimensions/Tile_Set/Regular_Tiling``'s tile size and each
  ``Data_File``'s ``tile_R`` / ``tile_C`` (a product of one file has no tiling), with the
  product's RPC (the file its Rational_Function_Model names, else ``RPC_X.XML``);
- a Maxar (DigitalGlobe) product by its ``X.TIL``: the tiles of its ``TILE_n`` groups, each
  placed by its ``ULColOffset`` / ``ULRowOffset`` .. ``LRColOffset`` / ``LRRowOffset``
  (inclusive), in a scene of the ``numRows`` x ``numColumns`` of ``X.IMD`` beside it, with the
  RPC of ``X.RPB`` (GDAL's TIL driver; a later tile over an earlier one wins, as there).

satsweep reads them the same way (``tiled_product``): the readers of ``satsweep.io.images``
read a window of the scene from the tiles under it, ``RPCModel.from_image`` takes the product's
RPC, and the acquisition metadata come from the DIM file, or the IMD. Every problem with the
product (a tile missing, of the wrong size, pixel type or format, tiles that leave a gap, JPEG
2000 tiles) is an ImageFormatError naming the product file.
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
class ProductTile:
    """One file of a DIMAP product and its place in the scene."""

    path: str  # the tile's GeoTIFF
    x0: int  # column of its first pixel in the scene
    y0: int  # row of its first pixel in the scene
    width: int
    height: int


@dataclasses.dataclass(frozen=True)
class TiledProduct:
    """A tiled product's scene: its size, its tiles, its RPC file."""

    path: str  # the product file (DIM_X.XML, X.TIL), as given
    kind: str  # "DIMAP product", "Maxar tiled product": for messages
    shape: tuple[int, int]  # (rows, columns) of the scene
    tiles: tuple[ProductTile, ...]  # in reading order (a later tile over an earlier one wins)
    folder: str  # the product file's folder
    rpc_candidates: tuple[str, ...]  # where its RPC may be, relative to ``folder``, in order
    rpc_names: str  # the RPC file(s) looked for, for an error saying there is none

    @property
    def rpc_path(self) -> str | None:
        """The product's RPC file: the first of ``rpc_candidates`` there (by its name in any
        case), None when there is none (looked for each time: the product is cached)."""
        names = _listing(self.folder)
        for href in self.rpc_candidates:
            exact = _in_folder(self.folder, href)
            if os.path.isfile(exact):
                return exact
            hit = names.get(href.lower())
            if hit is not None and os.path.isfile(os.path.join(self.folder, hit)):
                return os.path.join(self.folder, hit)
        return None

    def pieces(self, window: Sequence[int]) -> list[tuple[ProductTile, tuple[int, int, int, int],
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



def tiled_product(path: str | os.PathLike) -> TiledProduct | None:
    """The tiled product whose product file is ``path`` (a DIMAP ``DIM_X.XML``, a Maxar
    ``X.TIL``), or None for any other file (an image satsweep reads as it is). Read once per
    file version (cached on its size and modification time). ImageFormatError naming the
    product file for a product that cannot be read as one image."""
    path = os.fspath(path)
    suffix = os.path.splitext(path)[1].lower()
    if suffix not in (".xml", ".til"):
        return None
    try:
        stat = os.stat(path)
        with open(path, "rb") as fh:
            head = fh.read(_HEAD_BYTES)
    except OSError:
        return None  # the TIFF readers report a missing file
    if suffix == ".xml" and b"Dimap_Document" not in head:
        return None
    return _read_product(os.path.abspath(path), stat.st_size, stat.st_mtime_ns, path)


@functools.lru_cache(maxsize=32)
def _read_product(abspath: str, size: int, mtime_ns: int, given: str) -> TiledProduct:
    if abspath.lower().endswith(".til"):
        return _read_til(abspath, given)
    return _read_dimap(abspath, given)


def _problem(given: str, kind: str):
    def bad(problem: str) -> ImageFormatError:
        return ImageFormatError(given, f"{kind}: {problem}")
    return bad


def _in_folder(folder: str, href: str) -> str:
    """A file the product names (relative to its folder, either slash)."""
    return os.path.join(folder, *href.replace("\\", "/").split("/"))


def _listing(folder: str) -> dict[str, str]:
    try:
        return {n.lower(): n for n in os.listdir(folder)}
    except OSError:
        return {}


def _tile(bad, href: str, tile_path: str, x0: int, y0: int, want: tuple[int, int],
          kinds: dict[str, str], where: str) -> ProductTile:
    """One tile, checked: there, a TIFF of a supported layout, of ``want`` = (rows, columns),
    of the other tiles' pixel type and bands (``kinds``, filled in)."""
    from satsweep.io.images import _check_layout, _is_rgb, _open_tiff

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
    if got != tuple(want):
        raise bad(f"its tile {href} is {got[1]}x{got[0]} pixels; {where} it should be "
                  f"{want[1]}x{want[0]}")
    return ProductTile(path=tile_path, x0=x0, y0=y0, width=want[1], height=want[0])


def _uncovered(tiles: list[ProductTile], rows: int, cols: int) -> tuple[int, int] | None:
    """A pixel (column, row) of the scene that no tile covers, or None."""
    xs = sorted({0, cols, *(t.x0 for t in tiles), *(t.x0 + t.width for t in tiles)})
    ys = sorted({0, rows, *(t.y0 for t in tiles), *(t.y0 + t.height for t in tiles)})
    for y in (v for v in ys if v < rows):
        for x in (v for v in xs if v < cols):
            if not any(t.x0 <= x < t.x0 + t.width and t.y0 <= y < t.y0 + t.height for t in tiles):
                return x, y
    return None


def _not_jp2(bad, what: str, name: str) -> None:
    if any(k in what.lower() for k in ("jp2", "jpeg2000", "jpeg 2000", ".j2k")):
        raise bad(f"its tiles are JPEG 2000 ({what}), not GeoTIFF: satsweep reads TIFF images; "
                  f"convert the product with gdal_translate -of GTiff {name} OUT.tif (GDAL "
                  "mosaics the tiles and carries the RPC into the GeoTIFF)")


# -- Airbus DIMAP ---------------------------------------------------------------------------------
def _read_dimap(abspath: str, given: str) -> TiledProduct:
    from satsweep.geometry.rpc_formats import _without_namespaces, dimap_tiling

    bad = _problem(given, "DIMAP product")
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
    _not_jp2(bad, (root.findtext("Raster_Data/Data_Access/DATA_FILE_FORMAT") or "").strip(),
             os.path.basename(given))
    layout = dimap_tiling(root)
    files = layout.files
    if not files:
        raise bad("it lists no Data_File")
    if not layout.tiled:
        if len(files) != 1:
            raise bad(f"it lists {len(files)} files but no Regular_Tiling to place them")
        size_r, size_c = rows, cols
    else:
        try:
            size_r, size_c = (int(v or "") for v in layout.size or (None, None))
            overlap = [int(v) for v in layout.overlap]
        except ValueError:
            raise bad("no whole NTILES_SIZE nrows / ncols in its Regular_Tiling") from None
        if any(overlap):
            raise bad(f"its tiles overlap (OVERLAP_ROW / OVERLAP_COL {overlap[0]} / {overlap[1]}), "
                      "which satsweep does not mosaic")
        if size_r <= 0 or size_c <= 0:
            raise bad(f"NTILES_SIZE {size_c}x{size_r} is empty")
    tiles, seen, kinds = [], set(), {}
    for href, tile_r, tile_c in files:
        if not href:
            raise bad("a Data_File has no DATA_FILE_PATH href")
        try:
            r, c = (int("1" if v is None else v) for v in (tile_r, tile_c))
        except ValueError:
            raise bad(f"{href}: tile_R / tile_C are not whole numbers") from None
        y0, x0 = (r - 1) * size_r, (c - 1) * size_c
        if r < 1 or c < 1 or y0 >= rows or x0 >= cols or (r, c) in seen:
            raise bad(f"{href}: tile R{r}C{c} is outside the {cols}x{rows} scene or listed twice")
        seen.add((r, c))
        tiles.append(_tile(bad, href, _in_folder(folder, href), x0, y0,
                           (min(size_r, rows - y0), min(size_c, cols - x0)), kinds,
                           f"at R{r}C{c} of a {cols}x{rows} scene in tiles of {size_c}x{size_r}"))
    if _uncovered(tiles, rows, cols) is not None:
        missing = [f"R{r + 1}C{c + 1}" for r in range(-(-rows // size_r))
                   for c in range(-(-cols // size_c)) if (r + 1, c + 1) not in seen]
        raise bad(f"its tiles leave part of the {cols}x{rows} scene uncovered (no tile "
                  f"{', '.join(missing[:4])}{' ...' if len(missing) > 4 else ''})")
    tiles.sort(key=lambda t: (t.y0, t.x0))
    stem = Path(abspath).stem
    rule = f"RPC_{stem[4:]}.XML" if stem.lower().startswith("dim_") and len(stem) > 4 else None
    return TiledProduct(path=given, kind="DIMAP product", shape=(rows, cols), tiles=tuple(tiles),
                        folder=folder, rpc_candidates=_dimap_rpc_files(root, rule),
                        rpc_names=rule or "RPC_*.XML")


def _dimap_rpc_files(root: ElementTree.Element, rule: str | None) -> tuple[str, ...]:
    """Where a DIMAP product's RPC may be: the file the DIM file names (its
    Rational_Function_Model component), then ``rule`` (RPC_X.XML beside DIM_X.XML: GDAL's)."""
    candidates = []
    for comp in root.iter("Component"):
        href = comp.find("COMPONENT_PATH")
        href = "" if href is None else (href.get("href") or href.text or "").strip()
        title = (comp.findtext("COMPONENT_TITLE") or "") + (comp.findtext("COMPONENT_TYPE") or "")
        if href and ("rpc" in href.lower().rsplit("/", 1)[-1] or "rational" in title.lower()):
            candidates.append(href)
    return tuple(candidates) + ((rule,) if rule else ())


# -- Maxar .TIL -----------------------------------------------------------------------------------
def _read_til(abspath: str, given: str) -> TiledProduct:
    from satsweep.io.metadata import parse_imd

    bad = _problem(given, "Maxar tiled product")
    try:
        data = Path(abspath).read_bytes()
    except OSError as exc:
        raise bad(f"cannot read it ({exc.strerror or exc})") from None
    if b"\x00" in data[:_HEAD_BYTES]:
        raise bad("a binary file, not a .TIL text")
    groups = parse_imd(data.decode("utf-8", errors="replace"))
    folder, stem = os.path.dirname(abspath), Path(abspath).stem
    names = _listing(folder)
    imd = names.get(f"{stem.lower()}.imd")
    if imd is None:
        raise bad(f"the scene's size is in its {stem}.IMD (numRows, numColumns), which is not "
                  "beside it")
    try:
        top = parse_imd(Path(folder, imd).read_text(encoding="utf-8", errors="replace"))[""]
        rows, cols = int(top["numrows"]), int(top["numcolumns"])
    except (OSError, KeyError, ValueError):
        raise bad(f"{imd} gives no whole numRows / numColumns") from None
    try:
        count = int(groups[""].get("numtiles", ""))
    except ValueError:
        raise bad("no whole numTiles") from None
    tiles, kinds = [], {}
    for k in range(1, count + 1):
        group = groups.get(f"tile_{k}")
        href = (group or {}).get("filename", "")
        if not href:
            raise bad(f"no TILE_{k} group with a filename (numTiles = {count})")
        _not_jp2(bad, href, os.path.basename(given))
        try:
            x0, y0, x1, y1 = (int(group[key]) for key in
                              ("ulcoloffset", "ulrowoffset", "lrcoloffset", "lrrowoffset"))
        except (KeyError, ValueError):
            raise bad(f"TILE_{k}: no whole ULColOffset / ULRowOffset / LRColOffset / "
                      "LRRowOffset") from None
        if not (0 <= x0 <= x1 < cols and 0 <= y0 <= y1 < rows):
            raise bad(f"TILE_{k} ({href}): columns {x0}..{x1}, rows {y0}..{y1} are not inside "
                      f"the {cols}x{rows} scene of {imd}")
        tiles.append(_tile(bad, href, _in_folder(folder, href), x0, y0,
                           (y1 - y0 + 1, x1 - x0 + 1), kinds,
                           f"from column {x0}, row {y0} to column {x1}, row {y1} (TILE_{k})"))
    if not tiles:
        raise bad("it lists no tile (numTiles = 0)")
    gap = _uncovered(tiles, rows, cols)
    if gap is not None:
        raise bad(f"its tiles leave part of the {cols}x{rows} scene uncovered (column {gap[0]}, "
                  f"row {gap[1]})")
    return TiledProduct(path=given, kind="Maxar tiled product", shape=(rows, cols),
                        tiles=tuple(tiles), folder=folder, rpc_candidates=(f"{stem}.RPB",),
                        rpc_names=f"{stem}.RPB")
