"""RPC file formats: readers of every delivery format, and writers (``_RPC.TXT``, the TIFF tag).

``RPCModel.from_file`` and ``RPCModel.from_image`` (``satsweep.geometry.rpc``) call these; the
format is detected from the content, not the file name.

* TIFF tag 50844 (``RPCCoefficientTag``, 92 doubles: ERR_BIAS, ERR_RAND, LINE_OFF, SAMP_OFF,
  LAT_OFF, LONG_OFF, HEIGHT_OFF, LINE_SCALE, SAMP_SCALE, LAT_SCALE, LONG_SCALE, HEIGHT_SCALE, then
  20 LINE_NUM, 20 LINE_DEN, 20 SAMP_NUM, 20 SAMP_DEN coefficients).
* ``KEY: value`` text: GDAL ``_RPC.TXT`` and Ikonos/Planet/SkySat text (values may carry units,
  e.g. ``+005124.00 pixels``; coefficients as ``LINE_NUM_COEFF_1`` ... ``_20`` or all 20 on one
  ``LINE_NUM_COEFF`` line).
* ``.RPB`` (DigitalGlobe/GDAL ``lineOffset = ...;`` and ``lineNumCoef = ( ..., ... );``).
* DigitalGlobe/Maxar XML (``<isd><RPB><IMAGE>...``).
* Airbus DIMAP v2 RPC XML (Pleiades ``PHR_SENSOR``, SPOT 6/7 ``S6_SENSOR``/``S7_SENSOR``: the
  ``Inverse_Model`` is used and, as these products count pixels from (1, 1), one is subtracted from
  LINE_OFF and SAMP_OFF; Pleiades Neo ``PNEO_SENSOR``: ``GroundtoImage_Values``, 0-based). This is
  what rpcm does. The direct (image-to-ground) DIMAP model is not used: localization is iterative.
* GDAL PAM ``.aux.xml`` with a ``<Metadata domain="RPC">`` block.

``dimap_rpc_by_rule`` finds a DIMAP delivery's RPC by GDAL's naming rule (``IMG_X_RiCj.TIF`` ->
``RPC_X.XML``, the tile placed in the scene by ``DIM_X.XML``).

Formats that do not give ERR_BIAS / ERR_RAND get -1 (GDAL's "unknown").
"""

from __future__ import annotations

import math
import os
import re
import struct
import tempfile
from pathlib import Path
from typing import Any, Mapping, NamedTuple, Sequence
from xml.etree import ElementTree

import numpy as np

from satsweep.errors import ImageFormatError, RPCError
from satsweep.geometry.rpc import (
    _OPTIONAL_KEYS,
    _POLYS,
    _SCALARS,
    _UNKNOWN_ERR,
    N_TAG_VALUES,
    N_TERMS,
    TIFF_TAG_RPC,
    RPCModel,
)

# RPB / DigitalGlobe XML names (upper-cased) -> GDAL keys.
_DG_NAMES: dict[str, str] = {
    "ERRBIAS": "ERR_BIAS",
    "ERRRAND": "ERR_RAND",
    "LINEOFFSET": "LINE_OFF",
    "SAMPOFFSET": "SAMP_OFF",
    "LATOFFSET": "LAT_OFF",
    "LONGOFFSET": "LONG_OFF",
    "HEIGHTOFFSET": "HEIGHT_OFF",
    "LINESCALE": "LINE_SCALE",
    "SAMPSCALE": "SAMP_SCALE",
    "LATSCALE": "LAT_SCALE",
    "LONGSCALE": "LONG_SCALE",
    "HEIGHTSCALE": "HEIGHT_SCALE",
    "LINENUMCOEF": "LINE_NUM_COEFF",
    "LINEDENCOEF": "LINE_DEN_COEFF",
    "SAMPNUMCOEF": "SAMP_NUM_COEFF",
    "SAMPDENCOEF": "SAMP_DEN_COEFF",
}

# DIMAP profiles: (element holding the ground-to-image model, pixel (1, 1) is the first pixel).
_DIMAP_PROFILES: dict[str, tuple[str, bool]] = {
    "PHR_SENSOR": ("Inverse_Model", True),
    "S6_SENSOR": ("Inverse_Model", True),
    "S7_SENSOR": ("Inverse_Model", True),
    "PNEO_SENSOR": ("GroundtoImage_Values", False),
}

_TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


# ---------------------------------------------------------------------------------------------
# Writers
# ---------------------------------------------------------------------------------------------
def _rpc_txt_text(rpc: RPCModel) -> str:
    """GDAL ``_RPC.TXT`` content; ``repr`` of a float round-trips it exactly."""
    lines = [f"{key}: {getattr(rpc, name)!r}" for key, name in _SCALARS]
    for key, name in _POLYS:
        lines += [f"{key}_{i + 1}: {float(c)!r}" for i, c in enumerate(getattr(rpc, name))]
    return "\n".join(lines) + "\n"


def write_rpc_txt(path: str | os.PathLike, rpc: RPCModel) -> None:
    """Write ``rpc`` as a GDAL-style ``_RPC.TXT`` (``KEY: value`` lines), atomically.

    The text goes to a temporary file in the same folder, which is then renamed over ``path``;
    nothing half-written is left behind on failure. Values are written exactly (shortest repr).
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="ascii", newline="\n") as f:
            f.write(_rpc_txt_text(rpc))
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def rpc_tiff_extratag(rpc: RPCModel) -> tuple:
    """``(50844, 'd', 92, values, True)``: the RPC tag for ``tifffile.imwrite(extratags=[...])``."""
    return (TIFF_TAG_RPC, "d", N_TAG_VALUES, tuple(float(v) for v in rpc.to_tag_values()), True)


# ---------------------------------------------------------------------------------------------
# Readers
# ---------------------------------------------------------------------------------------------
class _NotAnRPC(RPCError):
    """The file is readable but in no RPC format known here (an RPCError for callers)."""


def _model_from_fields(path: str | os.PathLike | None, fields: Mapping[str, Any]) -> RPCModel:
    """Build a model from GDAL-keyed fields (floats and 20-vectors); RPCError for missing keys."""
    required = [k for k, _ in _SCALARS if k not in _OPTIONAL_KEYS] + [k for k, _ in _POLYS]
    missing = [k for k in required if k not in fields]
    if missing:
        shown = ", ".join(missing[:6]) + (f" and {len(missing) - 6} more" if len(missing) > 6 else "")
        raise RPCError(path, f"missing RPC key(s) {shown}")
    kw: dict[str, Any] = {name: fields.get(key, _UNKNOWN_ERR) for key, name in _SCALARS}
    kw.update({name: fields[key] for key, name in _POLYS})
    return RPCModel(**kw, source=path)


def _number(path: Path, key: str, text: str | None) -> float:
    """One float from ``text`` (the first token; units after it are ignored)."""
    tokens = (text or "").split()
    if not tokens:
        raise RPCError(path, f"{key} has no value")
    try:
        v = float(tokens[0])
    except ValueError:
        raise RPCError(path, f"{key} = {tokens[0]!r} is not a number") from None
    if not math.isfinite(v):
        raise RPCError(path, f"{key} = {tokens[0]!r} is not a finite number")
    return v


def _numbers(path: Path, key: str, tokens: Sequence[str]) -> np.ndarray:
    """The 20 coefficients ``key`` from ``tokens``."""
    if len(tokens) != N_TERMS:
        raise RPCError(path, f"{key} has {len(tokens)} values, expected {N_TERMS}")
    return np.array([_number(path, f"{key}_{i + 1}", t) for i, t in enumerate(tokens)])


def _parse_rpc_bytes(path: Path, data: bytes) -> RPCModel:
    """Dispatch on content: XML, RPB or ``KEY: value`` text."""
    head = data.lstrip(b"\xef\xbb\xbf \t\r\n")
    if head.startswith(b"<"):
        return _read_xml(path, data)
    if b"\x00" in data[:4096]:
        raise _NotAnRPC(path, "binary file in no RPC format known here")
    text = data.decode("utf-8", errors="replace")
    if re.search(r"^\s*linenumcoef\s*=", text, re.IGNORECASE | re.MULTILINE):
        return _read_rpb(path, text)
    if re.search(r"^\s*LINE_NUM_COEFF", text, re.IGNORECASE | re.MULTILINE):
        return _read_key_value_text(path, text)
    raise _NotAnRPC(path, "unknown RPC format (expected GDAL _RPC.TXT or Ikonos text, .RPB, "
                          "DigitalGlobe XML, DIMAP XML or GDAL .aux.xml)")


def _read_key_value_text(path: Path, text: str) -> RPCModel:
    """GDAL ``_RPC.TXT`` / Ikonos ``KEY: value [unit]`` lines."""
    raw: dict[str, str] = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if not sep:
            continue
        key = re.sub(r"[^A-Z0-9_]", "", key.upper())
        value = value.strip()
        if key in raw and raw[key] != value:
            raise RPCError(path, f"{key} is given twice with different values")
        raw[key] = value
    fields: dict[str, Any] = {}
    for key, _ in _SCALARS:
        if key in raw:
            fields[key] = _number(path, key, raw[key])
    for key, _ in _POLYS:
        if key in raw:  # all 20 values on one line (GDAL metadata style)
            fields[key] = _numbers(path, key, raw[key].split())
        elif any(f"{key}_{i}" in raw for i in range(1, N_TERMS + 1)):
            absent = [f"{key}_{i}" for i in range(1, N_TERMS + 1) if f"{key}_{i}" not in raw]
            if absent:
                raise RPCError(path, f"missing RPC key(s) {', '.join(absent[:6])}")
            fields[key] = np.array([_number(path, f"{key}_{i}", raw[f"{key}_{i}"])
                                    for i in range(1, N_TERMS + 1)])
    return _model_from_fields(path, fields)


def _read_rpb(path: Path, text: str) -> RPCModel:
    """DigitalGlobe/GDAL ``.RPB``: ``name = value;`` and ``name = ( v1, ..., v20 );``."""
    fields: dict[str, Any] = {}
    for m in re.finditer(r"(\w+)\s*=\s*(\([^)]*\)|[^;=()]*);", text):
        key = _DG_NAMES.get(m.group(1).upper())
        if key is None:
            continue
        value = m.group(2).strip()
        if key.endswith("_COEFF"):
            tokens = [t.strip() for t in value.strip("()").split(",")]
            fields[key] = _numbers(path, m.group(1), tokens)
        else:
            fields[key] = _number(path, m.group(1), value.strip('"'))
    return _model_from_fields(path, fields)


def _local(tag: str) -> str:
    """An XML tag without its namespace."""
    return tag.rsplit("}", 1)[-1]


def _without_namespaces(root: ElementTree.Element) -> ElementTree.Element:
    """``root`` with every tag's namespace dropped (in place), so that paths below are plain."""
    for el in root.iter():
        if isinstance(el.tag, str):
            el.tag = _local(el.tag)
    return root


def _read_xml(path: Path, data: bytes) -> RPCModel:
    """Dispatch XML: DIMAP, DigitalGlobe ``isd`` or GDAL PAM."""
    try:
        root = _without_namespaces(ElementTree.fromstring(data))
    except ElementTree.ParseError as exc:
        raise RPCError(path, f"malformed XML ({exc})") from None
    if root.tag == "Dimap_Document":
        return _read_dimap(path, root)
    image = root.find("RPB/IMAGE") if root.tag == "isd" else None
    if image is not None:
        return _read_dg_xml(path, image)
    for md in root.iter("Metadata"):
        if md.get("domain") == "RPC":
            return _read_pam(path, md)
    raise _NotAnRPC(path, f"XML root <{root.tag}> holds no RPC known here (expected DIMAP "
                          "Dimap_Document, DigitalGlobe isd/RPB or GDAL PAM RPC metadata)")


def _read_dg_xml(path: Path, image: ElementTree.Element) -> RPCModel:
    """DigitalGlobe/Maxar ``<isd><RPB><IMAGE>``: scalars as elements, coefficient lists."""
    fields: dict[str, Any] = {}
    for name, key in _DG_NAMES.items():
        if key.endswith("_COEFF"):
            elems = image.findall(f"{name}List/{name}")
            if elems:
                tokens = " ".join(e.text or "" for e in elems).split()
                fields[key] = _numbers(path, name, tokens)
        else:
            el = image.find(name)
            if el is not None:
                fields[key] = _number(path, name, el.text)
    return _model_from_fields(path, fields)


def _read_dimap(path: Path, root: ElementTree.Element) -> RPCModel:
    """Airbus DIMAP v2 RPC (Pleiades, SPOT 6/7, Pleiades Neo): ground-to-image model."""
    profile = (root.findtext("Metadata_Identification/METADATA_PROFILE") or "").strip()
    if profile not in _DIMAP_PROFILES:
        raise _NotAnRPC(path, f"DIMAP profile {profile or '(none)'!r} is not supported "
                              f"(supported: {', '.join(_DIMAP_PROFILES)})")
    model_name, one_based = _DIMAP_PROFILES[profile]
    rfm = root.find("Rational_Function_Model/Global_RFM")
    model = rfm.find(model_name) if rfm is not None else None
    validity = rfm.find("RFM_Validity") if rfm is not None else None
    if model is None or validity is None:
        raise RPCError(path, f"DIMAP {profile} lacks Rational_Function_Model/Global_RFM/"
                             f"{model_name} or RFM_Validity")
    fields: dict[str, Any] = {}
    for key, _ in _POLYS:
        texts = [model.findtext(f"{key}_{i}") for i in range(1, N_TERMS + 1)]
        absent = [f"{key}_{i}" for i, t in enumerate(texts, 1) if t is None]
        if len(absent) == N_TERMS:
            continue
        if absent:
            raise RPCError(path, f"missing RPC key(s) {', '.join(absent[:6])}")
        fields[key] = np.array([_number(path, f"{key}_{i}", t) for i, t in enumerate(texts, 1)])
    for key, _ in _SCALARS:
        text = validity.findtext(key)
        if text is not None:
            fields[key] = _number(path, key, text)
    if one_based:  # these products count pixels from (1, 1)
        for key in ("LINE_OFF", "SAMP_OFF"):
            if key in fields:
                fields[key] -= 1.0
    return _model_from_fields(path, fields)


# Airbus DIMAP deliveries name their files after the product: a scene's image IMG_X.*, or its
# tiles IMG_X_RiCj.* (R rows, C columns of tiles, counted from 1), beside DIM_X.XML and RPC_X.XML.
_DIMAP_TILE = re.compile(r"(.+)_r(\d+)c(\d+)")


def dimap_names(image: Path, prefix: str) -> list[str]:
    """GDAL's naming rule for Airbus DIMAP deliveries (Pleiades, SPOT 6/7, Pleiades Neo): the
    lower-case names of the ``prefix`` file ("dim" or "rpc") of the image IMG_X.* or of a tile
    of it IMG_X_RiCj.*, in the order GDAL looks for them (``prefix_X_RiCj.xml``, then
    ``prefix_X.xml``); none for an image not named IMG_*."""
    stem = image.stem.lower()
    if not stem.startswith("img_") or len(stem) <= 4:
        return []
    rest = stem[4:]
    names = [f"{prefix}_{rest}.xml"]
    tiled = _DIMAP_TILE.fullmatch(rest)
    if tiled:
        names.append(f"{prefix}_{tiled.group(1)}.xml")
    return names


class DimapTiling(NamedTuple):
    """What a DIM file (namespaces dropped) says of its raster files' places, as written (the
    fields GDAL reads): ``files``, (href, tile_R, tile_C) of each ``Data_File`` (the href
    stripped, "" when there is none; tile_R / tile_C None when absent); ``tiled``, whether
    ``Raster_Dimensions/Tile_Set/Regular_Tiling`` is given; ``size``, its ``NTILES_SIZE``'s
    (nrows, ncols) attributes (None without one); ``overlap``, its OVERLAP_ROW / OVERLAP_COL
    ("0" when absent)."""

    files: tuple[tuple[str, str | None, str | None], ...]
    tiled: bool
    size: tuple[str | None, str | None] | None
    overlap: tuple[str, str]


def dimap_tiling(root: ElementTree.Element) -> DimapTiling:
    """The ``DimapTiling`` of a DIM file's root (``_without_namespaces``)."""
    files = []
    for data_file in (root.findall("Raster_Data/Data_Access/Data_Files/Data_File")
                      or root.iter("Data_File")):
        path = data_file.find("DATA_FILE_PATH")
        href = "" if path is None else (path.get("href") or path.text or "").strip()
        files.append((href, data_file.get("tile_R"), data_file.get("tile_C")))
    tiling = root.find("Raster_Data/Raster_Dimensions/Tile_Set/Regular_Tiling")
    size = None if tiling is None else tiling.find("NTILES_SIZE")
    overlap = tuple("0" if tiling is None else (tiling.findtext(k) or "0").strip()
                    for k in ("OVERLAP_ROW", "OVERLAP_COL"))
    return DimapTiling(files=tuple(files), tiled=tiling is not None,
                       size=None if size is None else (size.get("nrows"), size.get("ncols")),
                       overlap=overlap)


def dimap_rpc_by_rule(image: Path, names: Mapping[str, Path]) -> RPCModel | None:
    """The RPC of a DIMAP delivery's image or tile (``dimap_names``), from the folder listing
    ``names`` ({lower-case name: path}); None when there is no such RPC file.

    The product's RPC models the whole scene. A tile IMG_X_RiCj after the first starts at
    ((j - 1) tile columns, (i - 1) tile rows) of it, which DIM_X.XML's regular tiling gives
    (``Raster_Dimensions/Tile_Set/Regular_Tiling/NTILES_SIZE`` and the ``Data_File`` that lists
    the tile, as GDAL reads them): the model returned is cropped there. RPCError naming the image
    when that place is not known (no DIM file, the tile not listed, overlapping tiles)."""
    rpc_path = next((names[n] for n in dimap_names(image, "rpc") if n in names), None)
    if rpc_path is None:
        return None
    model = RPCModel.from_file(rpc_path)
    tiled = _DIMAP_TILE.fullmatch(image.stem.lower()[4:])
    if tiled is None or (int(tiled.group(2)), int(tiled.group(3))) == (1, 1):
        return model
    x0, y0 = _dimap_tile_origin(image, rpc_path, names)
    return model.cropped(x0=x0, y0=y0)


def _dimap_tile_origin(image: Path, rpc_path: Path, names: Mapping[str, Path]) -> tuple[int, int]:
    """(column, row) of a DIMAP tile's first pixel in its product's scene (see above)."""
    where = f"{rpc_path.name} models the whole scene, and the place of tile {image.name} in it"
    dim = next((names[n] for n in dimap_names(image, "dim") if n in names), None)
    if dim is None:
        raise RPCError(image, f"{where} is in the product's DIM_*.XML, which is not beside it")
    try:
        root = _without_namespaces(ElementTree.fromstring(dim.read_bytes()))
    except (OSError, ElementTree.ParseError) as exc:
        raise RPCError(image, f"{where} is in {dim.name}, which cannot be read ({exc})") from None
    layout = dimap_tiling(root)
    tile = next((t for t in layout.files
                 if t[0].replace("\\", "/").rsplit("/", 1)[-1].lower() == image.name.lower()),
                None)
    if tile is None or layout.size is None:
        why = ("it does not list the tile" if tile is None
               else "it has no Regular_Tiling/NTILES_SIZE")
        raise RPCError(image, f"{where} is not in {dim.name} ({why})")
    try:
        r, c = int(tile[1] or ""), int(tile[2] or "")
        nrows, ncols = (int(v or "") for v in layout.size)
        overlap = [int(v) for v in layout.overlap]
    except ValueError:
        raise RPCError(image, f"{where}: {dim.name} gives the tile's tile_R / tile_C or the tiles' "
                              "NTILES_SIZE nrows / ncols not as whole numbers") from None
    if any(overlap):
        raise RPCError(image, f"{where}: {dim.name} gives tiles that overlap (OVERLAP_ROW / "
                              f"OVERLAP_COL {overlap[0]} / {overlap[1]}), which satsweep does "
                              "not place")
    return (c - 1) * ncols, (r - 1) * nrows


def _read_pam(path: Path, metadata: ElementTree.Element) -> RPCModel:
    """GDAL PAM ``<Metadata domain="RPC"><MDI key="...">`` (coefficients space-separated)."""
    raw = {(mdi.get("key") or "").upper(): (mdi.text or "") for mdi in metadata.iter("MDI")}
    fields: dict[str, Any] = {}
    for key, _ in _SCALARS:
        if key in raw:
            fields[key] = _number(path, key, raw[key])
    for key, _ in _POLYS:
        if key in raw:
            fields[key] = _numbers(path, key, raw[key].split())
    return _model_from_fields(path, fields)


def _read_tiff_rpc_tag(path: Path) -> np.ndarray | None:
    """The 92 values of tag 50844 of the first page of a TIFF, or None when it has no such tag.

    Raises ImageFormatError for a missing file, a non-TIFF file or a truncated TIFF (pixel data
    extending past the end of the file), and RPCError for a tag of the wrong size or type.
    """
    import tifffile

    from satsweep.io.images import quiet_tifffile

    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            magic = f.read(4)
    except OSError as exc:
        raise ImageFormatError(path, f"cannot read image ({exc.strerror or exc})") from None
    if len(magic) < 4:
        raise ImageFormatError(path, f"truncated image ({size} bytes, not even a TIFF header)")
    if magic not in _TIFF_MAGICS:
        raise ImageFormatError(path, f"not a TIFF file (starts with {magic!r})")
    try:
        with quiet_tifffile(), tifffile.TiffFile(path) as tif:
            if not tif.pages:
                raise ImageFormatError(path, "truncated or corrupt TIFF (no image directory)")
            page = tif.pages[0]
            ends = [o + c for o, c in zip(page.dataoffsets, page.databytecounts)]
            tag = page.tags.get(TIFF_TAG_RPC)
            value = None if tag is None else tag.value
            dtype = None if tag is None else tag.dtype
    except (tifffile.TiffFileError, ValueError, OSError, struct.error, IndexError,
            KeyError) as exc:
        raise ImageFormatError(path, f"truncated or corrupt TIFF ({exc})") from None
    if ends and max(ends) > size:
        raise ImageFormatError(path, f"truncated TIFF: pixel data runs to byte {max(ends)} "
                                     f"but the file has {size} bytes")
    if value is None:
        return None
    if int(dtype) not in (11, 12):  # FLOAT, DOUBLE
        raise RPCError(path, f"TIFF tag {TIFF_TAG_RPC} has type {int(dtype)}, expected DOUBLE")
    values = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if values.size != N_TAG_VALUES:
        raise RPCError(path, f"TIFF tag {TIFF_TAG_RPC} holds {values.size} values, "
                             f"expected {N_TAG_VALUES}")
    return values
