"""Acquisition metadata of an image: when it was taken and from where the sun and the satellite
saw the ground, read from whatever the delivery holds.

``read_acquisition_metadata(image)`` returns an ``AcquisitionMetadata`` (date-time in UTC, sun
azimuth and elevation, satellite azimuth and elevation, off-nadir angle, satellite id, cloud
cover, and which file gave each), or None when nothing is found. Absent metadata is normal:
crops often carry only their RPC. A value that is present but unreadable (a number or date that
does not parse, an angle out of range, a malformed sidecar) never raises: it is left out and
described in ``warnings`` (``"FILE: problem"``), for the run report.

Where it looks, in this order; a field takes the value of the first source that has it, and a
later source that disagrees adds a warning naming both files (its value is not used):

1. The image's own ``GDAL_METADATA`` TIFF tag (42112): ``<GDALMetadata><Item name="..."
   domain="IMAGERY">``, GDAL's IMAGERY domain keys ``ACQUISITIONDATETIME`` (GDAL writes
   ``YYYY-MM-DD HH:MM:SS``, UTC; ISO-8601 is read too), ``SATELLITEID``, ``CLOUDCOVER`` (percent,
   999 = not available), and ``SUN_AZIMUTH`` / ``SUN_ELEVATION`` items. Items of the IMAGERY
   domain win over items without a domain; band items (with a ``sample`` attribute) are not
   read. Where those keys are missing, the items GDAL copies from a NITF delivery into a GeoTIFF
   converted from it: ``NITF_IDATIM`` (``CCYYMMDDhhmmss``, UTC; else the STDIDC TRE's
   ``NITF_STDIDC_ACQUISITION_DATE``) and ``NITF_USE00A_SUN_AZ`` /
   ``NITF_USE00A_SUN_EL``. The image's own tag comes first for the reason its RPC tag does
   (``RPCModel.from_image``): it cannot be separated from the pixels, a sidecar can.
2. GDAL's PAM sidecar ``IMAGE.tif.aux.xml``: ``<Metadata domain="IMAGERY"><MDI key="...">``,
   the same keys.
3. Maxar/DigitalGlobe ``STEM.IMD`` beside the image (``key = value;`` lines in ``BEGIN_GROUP =
   IMAGE_1 ... END_GROUP = IMAGE_1``, keys read case-insensitively, those of the IMAGE_1 group
   before the top level's): ``firstLineTime``, ``satId``, ``meanSunAz``, ``meanSunEl``,
   ``meanSatAz``, ``meanSatEl``, ``meanOffNadirViewAngle``, ``cloudCover`` (a fraction; negative
   = not available).
4. ``STEM.XML`` beside the image: a Maxar/DigitalGlobe ``<isd><IMD><IMAGE>`` (the same names in
   capitals: ``FIRSTLINETIME``, ``MEANSUNAZ`` ...), or an Airbus DIMAP v2 document (below).
5. Airbus DIMAP v2 ``DIM_*.XML`` (Pleiades, SPOT 6/7) in the image's folder, only when it really
   describes this image: GDAL's naming rule (image ``IMG_X.*`` or ``IMG_X_RiCj.*`` -> ``DIM_X.XML``)
   or its ``Raster_Data/.../Data_File/DATA_FILE_PATH href`` names a file with the image's stem
   (the same name, any extension: a JPEG 2000 converted to GeoTIFF keeps its stem). A DIMAP file
   that names other images is never used. Read: ``Dataset_Sources/Source_Identification/
   Strip_Source`` (``MISSION`` + ``MISSION_INDEX``, e.g. ``PHR 1B``; ``IMAGING_DATE`` +
   ``IMAGING_TIME``) and the ``Geometric_Data/Use_Area/Located_Geometric_Values`` of
   ``LOCATION_TYPE`` ``Center`` (else the first): its ``TIME`` (preferred to the strip's time: it
   is the image centre's), ``Solar_Incidences/SUN_AZIMUTH``, ``SUN_ELEVATION``, and
   ``Acquisition_Angles/VIEWING_ANGLE`` (the angle at the satellite between nadir and the line of
   sight: the off-nadir angle) and ``INCIDENCE_ANGLE`` (the angle at the ground between the
   vertical and the line of sight: the satellite elevation is 90 minus it). DIMAP's
   ``AZIMUTH_ANGLE`` is the scene orientation, not the satellite azimuth, so no satellite azimuth
   is reported from DIMAP. DIMAP RPC files (``RPC_*.XML``) hold no date or angle.

Sidecars are matched case-insensitively (``IMG.tif`` finds ``img.IMD``). The TIFF ``DateTime`` tag
(306) is not read: TIFF 6.0 defines it as the file's creation time, which in a delivery or a
crop is when it was processed or cut, not when it was acquired, and reporting it as an
acquisition date would mislead.

Conventions: times are UTC (every format above states UTC; a time without a zone is taken as
UTC, one with an offset is converted), reported as ISO-8601 ``YYYY-MM-DDTHH:MM:SS[.ffffff]Z``
(sub-microsecond digits are dropped). Angles are degrees; azimuths clockwise from north in
[0, 360), elevations above the horizon; the satellite angles are those of the line of sight from
the ground to the satellite (Maxar's ``meanSatAz`` / ``meanSatEl``).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import os
import re
from pathlib import Path
from typing import Any, Callable, Iterable
from xml.etree import ElementTree

# TIFF tag holding GDAL's metadata items as XML.
TAG_GDAL_METADATA = 42112

# Two sources that give one value are said to agree within these; beyond them the report warns.
# GDAL's IMAGERY domain keeps whole seconds (it truncates the vendor's fraction), so one time
# copied by GDAL may be up to 1 s earlier than the vendor's.
TIME_AGREEMENT_S = 1.0
# Vendors round their mean angles to 0.1 degree (Maxar IMD/XML): two copies of a value agree
# far better; a larger difference is a different value.
ANGLE_AGREEMENT_DEG = 0.1
# GDAL writes the cloud cover as a whole percent (it truncates Maxar's fraction x 100).
CLOUD_AGREEMENT_PERCENT = 1.0

# GDAL's IMAGERY-domain value meaning "cloud cover not available".
GDAL_CLOUDCOVER_NA = 999.0

# The fields of AcquisitionMetadata that hold values, in report order.
FIELDS = (
    "acquisition_time_utc",
    "satellite",
    "sun_azimuth_deg",
    "sun_elevation_deg",
    "satellite_azimuth_deg",
    "satellite_elevation_deg",
    "off_nadir_deg",
    "cloud_cover_percent",
)


@dataclasses.dataclass(frozen=True)
class AcquisitionMetadata:
    """What is known of one image's acquisition; None where the delivery does not say."""

    acquisition_time_utc: str | None = None  # ISO-8601 UTC, e.g. 2019-06-01T10:31:12Z
    satellite: str | None = None  # satellite / sensor id as the vendor writes it (WV02, PHR 1B)
    sun_azimuth_deg: float | None = None  # clockwise from north, [0, 360)
    sun_elevation_deg: float | None = None  # above the horizon, [-90, 90]
    satellite_azimuth_deg: float | None = None  # of the satellite seen from the ground, [0, 360)
    satellite_elevation_deg: float | None = None  # of the satellite seen from the ground, [0, 90]
    off_nadir_deg: float | None = None  # at the satellite, between nadir and the line of sight
    cloud_cover_percent: float | None = None  # of the image, [0, 100]
    sources: tuple[tuple[str, str], ...] = ()  # (field, where its value was read), for each field set
    warnings: tuple[str, ...] = ()  # "FILE: problem" for each value present but not usable

    @property
    def acquisition_datetime(self) -> _dt.datetime | None:
        """The acquisition time as a timezone-aware UTC datetime, or None."""
        if self.acquisition_time_utc is None:
            return None
        return _dt.datetime.fromisoformat(self.acquisition_time_utc.replace("Z", "+00:00"))

    def source_of(self, field: str) -> str | None:
        """Where ``field``'s value was read (a file, and the part of it), or None."""
        return dict(self.sources).get(field)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: every field (None as null), ``sources`` as {field: where}, ``warnings``."""
        out: dict[str, Any] = {name: getattr(self, name) for name in FIELDS}
        out["sources"] = dict(self.sources)
        out["warnings"] = list(self.warnings)
        return out


# -- values --------------------------------------------------------------------------------------
_TIME = re.compile(
    r"^(\d{4})-(\d{2})-(\d{2})[T ](\d{2}):(\d{2}):(\d{2})(?:[.,](\d+))?\s*(Z|[+-]\d{2}:?\d{2})?$",
    re.IGNORECASE,
)


def with_computed_sun(meta: AcquisitionMetadata | None, *, lon: float,
                      lat: float) -> AcquisitionMetadata | None:
    """``meta`` with the sun angles it lacks computed from its date-time at (``lon``, ``lat``)
    (:func:`satsweep.geometry.sun.solar_position`; its sources say so), when it has a date-time;
    otherwise ``meta`` as it is. Crops converted from NITF may keep the image's date and lose
    the USE00A TRE that holds the sun's angles."""
    if meta is None or meta.acquisition_datetime is None or (
            meta.sun_azimuth_deg is not None and meta.sun_elevation_deg is not None):
        return meta
    from satsweep.geometry.sun import solar_position  # noqa: PLC0415

    elevation, azimuth = solar_position(lon=lon, lat=lat, when=meta.acquisition_datetime)
    where = f"computed from the acquisition time at ({lon:.5f}, {lat:.5f})"
    values: dict[str, float] = {}
    if meta.sun_azimuth_deg is None:
        values["sun_azimuth_deg"] = round(azimuth, 2)
    if meta.sun_elevation_deg is None:
        values["sun_elevation_deg"] = round(elevation, 2)
    return dataclasses.replace(meta, **values,
                               sources=meta.sources + tuple((k, where) for k in values))


def parse_utc_time(text: str) -> _dt.datetime:
    """A date-time as written by the formats above -> an aware UTC datetime; ValueError if not.

    ``YYYY-MM-DD[T ]HH:MM:SS[.fraction][Z|+HH:MM]``; no zone means UTC; the fraction is cut to
    microseconds.
    """
    m = _TIME.match(text.strip())
    if m is None:
        raise ValueError(f"{text!r} is not a date-time YYYY-MM-DDTHH:MM:SS[.f][Z]")
    year, month, day, hour, minute, second = (int(g) for g in m.groups()[:6])
    micro = int((m.group(7) or "0")[:6].ljust(6, "0"))
    zone = m.group(8)
    offset = _dt.timedelta(0)
    if zone and zone.upper() != "Z":
        sign = -1 if zone[0] == "-" else 1
        digits = zone[1:].replace(":", "")
        offset = sign * _dt.timedelta(hours=int(digits[:2]), minutes=int(digits[2:]))
    try:
        local = _dt.datetime(year, month, day, hour, minute, second, micro,
                             tzinfo=_dt.timezone(offset))
    except ValueError as exc:
        raise ValueError(f"{text!r} is not a valid date-time ({exc})") from None
    return local.astimezone(_dt.timezone.utc)


def _iso(when: _dt.datetime) -> str:
    return when.isoformat(timespec="microseconds" if when.microsecond else "seconds").replace("+00:00", "Z")


def _number(text: str) -> float:
    value = float(text.strip().strip('"'))
    if not math.isfinite(value):
        raise ValueError
    return value


def _azimuth(value: float) -> float | str:
    return value % 360.0  # any finite azimuth is an angle: brought into [0, 360)


def _range(lo: float, hi: float) -> Callable[[float], float | str]:
    def check(value: float) -> float | str:
        return value if lo <= value <= hi else f"is outside [{lo:g}, {hi:g}] degrees"
    return check


_ANGLE_CHECKS: dict[str, Callable[[float], float | str]] = {
    "sun_azimuth_deg": _azimuth,
    "satellite_azimuth_deg": _azimuth,
    "sun_elevation_deg": _range(-90.0, 90.0),
    "satellite_elevation_deg": _range(0.0, 90.0),
    "off_nadir_deg": _range(0.0, 90.0),
}


class _Source:
    """The values read from one source, with the problems met."""

    def __init__(self, where: str, file: str):
        self.where = where  # shown in ``sources``: the file and the part of it
        self.file = file  # named in warnings
        self.values: dict[str, Any] = {}
        self.warnings: list[str] = []

    def warn(self, problem: str) -> None:
        self.warnings.append(f"{self.file}: {problem}")

    def time(self, key: str, text: str | None) -> None:
        if text is None or not text.strip():
            return
        try:
            self.values.setdefault("acquisition_time_utc", _iso(parse_utc_time(text.strip().strip('"'))))
        except ValueError as exc:
            self.warn(f"{key}: {exc}")

    def text(self, field: str, text: str | None) -> None:
        value = (text or "").strip().strip('"').strip()
        if value:
            self.values.setdefault(field, value)

    def _number(self, key: str, text: str | None) -> float | None:
        """The number in ``text``; None (with a warning when it is not a number) otherwise."""
        if text is None or not text.strip():
            return None
        try:
            return _number(text)
        except ValueError:
            self.warn(f"{key} = {text.strip()!r} is not a number")
            return None

    def angle(self, field: str, key: str, text: str | None, *, transform=None) -> None:
        if field in self.values or (value := self._number(key, text)) is None:
            return
        if transform is not None:
            value = transform(value)
        checked = _ANGLE_CHECKS[field](value)
        if isinstance(checked, str):
            self.warn(f"{key} = {text.strip()} {checked}")
        else:
            self.values[field] = checked

    def cloud(self, key: str, text: str | None, *, fraction: bool) -> None:
        """Cloud cover: a fraction (Maxar, negative = n/a) or a percent (GDAL, 999 = n/a)."""
        if "cloud_cover_percent" in self.values or (value := self._number(key, text)) is None:
            return
        if (fraction and value < 0.0) or (not fraction and value == GDAL_CLOUDCOVER_NA):
            return  # the format's "not available"
        percent = 100.0 * value if fraction else value
        if 0.0 <= percent <= 100.0:
            self.values["cloud_cover_percent"] = percent
        else:
            self.warn(f"{key} = {text.strip()} is not a cloud cover "
                      f"({'a fraction in [0, 1]' if fraction else 'a percent in [0, 100] or 999'})")


# -- GDAL metadata (TIFF tag, PAM) ---------------------------------------------------------------
def _nitf_idatim(text: str | None) -> str | None:
    """NITF 2.1's image date-time ``CCYYMMDDhhmmss`` (UTC) as ISO-8601; other texts as they are
    (the time parser then says what is wrong); None for an empty one."""
    value = (text or "").strip()
    if re.fullmatch(r"\d{14}", value):
        return (f"{value[0:4]}-{value[4:6]}-{value[6:8]}T{value[8:10]}:{value[10:12]}:"
                f"{value[12:14]}Z")
    return value or None


def _gdal_items(source: _Source, items: dict[str, str]) -> None:
    """GDAL's IMAGERY keys (upper-cased) -> values; then the NITF items that GDAL copies into a
    GeoTIFF converted from a NITF delivery (WorldView's, the IARPA and DFC2019 stacks):
    ``NITF_IDATIM`` (image date-time; else the STDIDC TRE's ``NITF_STDIDC_ACQUISITION_DATE``,
    also ``CCYYMMDDhhmmss``) and the USE00A TRE's ``NITF_USE00A_SUN_AZ`` /
    ``NITF_USE00A_SUN_EL``, where the IMAGERY keys do not say."""
    source.time("ACQUISITIONDATETIME", items.get("ACQUISITIONDATETIME"))
    source.text("satellite", items.get("SATELLITEID"))
    source.angle("sun_azimuth_deg", "SUN_AZIMUTH", items.get("SUN_AZIMUTH"))
    source.angle("sun_elevation_deg", "SUN_ELEVATION", items.get("SUN_ELEVATION"))
    source.cloud("CLOUDCOVER", items.get("CLOUDCOVER"), fraction=False)
    source.time("NITF_IDATIM", _nitf_idatim(items.get("NITF_IDATIM")))
    source.time("NITF_STDIDC_ACQUISITION_DATE",
                _nitf_idatim(items.get("NITF_STDIDC_ACQUISITION_DATE")))
    source.angle("sun_azimuth_deg", "NITF_USE00A_SUN_AZ", items.get("NITF_USE00A_SUN_AZ"))
    source.angle("sun_elevation_deg", "NITF_USE00A_SUN_EL", items.get("NITF_USE00A_SUN_EL"))


def _parse_xml(source: _Source, data: bytes | str) -> ElementTree.Element | None:
    try:
        root = ElementTree.fromstring(data)
    except ElementTree.ParseError as exc:
        source.warn(f"malformed XML ({exc})")
        return None
    for el in root.iter():  # drop namespaces: the paths below are plain
        if isinstance(el.tag, str) and "}" in el.tag:
            el.tag = el.tag.rsplit("}", 1)[1]
    return root


def _read_tiff_tag(image: Path) -> _Source | None:
    """The image's GDAL_METADATA tag; None when it has none. ImageFormatError for a bad image."""
    from satsweep.io.images import _open_tiff  # noqa: PLC0415

    with _open_tiff(image) as (_, page):
        tag = page.tags.get(TAG_GDAL_METADATA)
        value = None if tag is None else tag.value
    if value is None:
        return None
    if isinstance(value, bytes):
        value = value.decode("utf-8", errors="replace")
    source = _Source(f"{image} (TIFF tag {TAG_GDAL_METADATA} GDAL_METADATA)",
                     f"{image} (TIFF tag {TAG_GDAL_METADATA} GDAL_METADATA)")
    root = _parse_xml(source, str(value).strip().strip("\x00"))
    if root is None:
        return source
    imagery: dict[str, str] = {}
    default: dict[str, str] = {}
    for item in root.iter("Item"):
        if item.get("sample") is not None:  # a band's item, not the dataset's
            continue
        domain = (item.get("domain") or "").upper()
        name = (item.get("name") or "").upper()
        if domain == "IMAGERY":
            imagery.setdefault(name, item.text or "")
        elif domain == "":
            default.setdefault(name, item.text or "")
    _gdal_items(source, {**default, **imagery})
    return source


def _read_pam(path: Path) -> _Source:
    source = _Source(f"{path} (GDAL PAM)", str(path))
    data = _read_bytes(source, path)
    root = None if data is None else _parse_xml(source, data)
    if root is None:
        return source
    imagery: dict[str, str] = {}
    default: dict[str, str] = {}
    for md in root.findall("Metadata"):  # the dataset's, not those of PAMRasterBand
        domain = (md.get("domain") or "").upper()
        target = imagery if domain == "IMAGERY" else default if domain == "" else None
        if target is None:
            continue
        for mdi in md.iter("MDI"):
            target.setdefault((mdi.get("key") or "").upper(), mdi.text or "")
    _gdal_items(source, {**default, **imagery})
    return source


# -- Maxar / DigitalGlobe ----------------------------------------------------------------------
def _maxar_keys(source: _Source, get: Callable[[str], str | None], what: str) -> None:
    """The IMD keys (lower-cased names: IMD and XML spell them differently)."""
    def first(*names: str) -> tuple[str, str | None]:
        for name in names:
            value = get(name)
            if value is not None:
                return name, value
        return names[0], None

    key, value = first("firstlinetime")
    source.time(f"{what}{key}", value)
    key, value = first("satid")
    source.text("satellite", value)
    for field, names in (("sun_azimuth_deg", ("meansunaz", "sunaz")),
                         ("sun_elevation_deg", ("meansunel", "sunel")),
                         ("satellite_azimuth_deg", ("meansataz", "sataz")),
                         ("satellite_elevation_deg", ("meansatel", "satel")),
                         ("off_nadir_deg", ("meanoffnadirviewangle", "offnadirviewangle"))):
        key, value = first(*names)
        source.angle(field, f"{what}{key}", value)
    key, value = first("cloudcover")
    source.cloud(f"{what}{key}", value, fraction=True)


def parse_imd(text: str) -> dict[str, dict[str, str]]:
    """Maxar ``.IMD`` text -> {group name (lower case, "" for the top level): {key (lower
    case): raw value}}. Values lose their ``;`` and surrounding quotes; a value in parentheses
    may span lines. Nested groups are keyed by the innermost name."""
    groups: dict[str, dict[str, str]] = {"": {}}
    stack: list[str] = []
    pending = ""
    for line in text.splitlines():
        statement = (pending + " " + line).strip() if pending else line.strip()
        if not statement:
            continue
        if statement.count("(") > statement.count(")"):  # a list continues on the next line
            pending = statement
            continue
        pending = ""
        key, sep, value = statement.partition("=")
        key = key.strip().lower()
        value = value.strip().rstrip(";").strip()
        if not sep:
            if key.rstrip(";") == "end":
                break
            continue
        if key == "begin_group":
            stack.append(value.lower())
            groups.setdefault(value.lower(), {})
        elif key == "end_group":
            if stack:
                stack.pop()
        else:
            groups[stack[-1] if stack else ""].setdefault(key, value.strip('"'))
    return groups


def _read_imd(path: Path) -> _Source:
    source = _Source(str(path), str(path))
    data = _read_bytes(source, path)
    if data is None:
        return source
    if b"\x00" in data[:4096]:
        source.warn("binary file, not a Maxar .IMD text")
        return source
    groups = parse_imd(data.decode("utf-8", errors="replace"))
    image_groups = sorted(g for g in groups if re.fullmatch(r"image_\d+", g))
    image = groups.get("image_1") or (groups[image_groups[0]] if image_groups else {})
    top = groups[""]
    _maxar_keys(source, lambda k: image.get(k, top.get(k)), "")
    return source


def _read_maxar_xml(source: _Source, root: ElementTree.Element) -> None:
    image = root.find("IMD/IMAGE")
    if image is None:
        return  # an RPC-only XML: nothing to say about the acquisition
    children = {}
    for child in image:
        if isinstance(child.tag, str):
            children.setdefault(child.tag.lower(), child.text)
    _maxar_keys(source, children.get, "IMD/IMAGE/")


# -- Airbus DIMAP v2 -----------------------------------------------------------------------------
def _read_dimap(source: _Source, root: ElementTree.Element) -> None:
    strip = root.find("Dataset_Sources/Source_Identification/Strip_Source")
    located = root.findall("Geometric_Data/Use_Area/Located_Geometric_Values")
    centre = next((g for g in located if (g.findtext("LOCATION_TYPE") or "").strip().lower() == "center"),
                  located[0] if located else None)
    if centre is not None and centre.findtext("TIME"):
        source.time("Located_Geometric_Values/TIME", centre.findtext("TIME"))
    if strip is not None:
        mission = (strip.findtext("MISSION") or "").strip()
        index = (strip.findtext("MISSION_INDEX") or "").strip()
        source.text("satellite", " ".join(v for v in (mission, index) if v))
        date = (strip.findtext("IMAGING_DATE") or "").strip()
        clock = (strip.findtext("IMAGING_TIME") or "").strip()
        if date and clock:
            source.time("Strip_Source/IMAGING_DATE + IMAGING_TIME", f"{date}T{clock}")
        elif date and "acquisition_time_utc" not in source.values:
            source.warn("Strip_Source/IMAGING_DATE without IMAGING_TIME: no date-time reported")
    if centre is not None:
        sun = centre.find("Solar_Incidences")
        if sun is not None:
            source.angle("sun_azimuth_deg", "Solar_Incidences/SUN_AZIMUTH", sun.findtext("SUN_AZIMUTH"))
            source.angle("sun_elevation_deg", "Solar_Incidences/SUN_ELEVATION", sun.findtext("SUN_ELEVATION"))
        view = centre.find("Acquisition_Angles")
        if view is not None:
            source.angle("off_nadir_deg", "Acquisition_Angles/VIEWING_ANGLE", view.findtext("VIEWING_ANGLE"))
            source.angle("satellite_elevation_deg", "Acquisition_Angles/INCIDENCE_ANGLE",
                         view.findtext("INCIDENCE_ANGLE"), transform=lambda v: 90.0 - v)


def _dimap_file_stems(root: ElementTree.Element) -> set[str]:
    """Stems (lower case) of the raster files a DIMAP document lists."""
    stems = set()
    for el in root.iter("DATA_FILE_PATH"):
        href = (el.get("href") or el.text or "").strip()
        if href:
            stems.add(Path(href.replace("\\", "/").rsplit("/", 1)[-1]).stem.lower())
    return stems


def _dimap_named_by_rule(image: Path) -> list[str]:
    """GDAL's rule: IMG_X.* or IMG_X_RiCj.* is described by DIM_X.XML (lower-case names)."""
    from satsweep.geometry.rpc_formats import dimap_names  # noqa: PLC0415

    return dimap_names(image, "dim")


# -- files -------------------------------------------------------------------------------------
def _read_bytes(source: _Source, path: Path) -> bytes | None:
    try:
        return path.read_bytes()
    except OSError as exc:
        source.warn(f"cannot read ({exc.strerror or exc})")
        return None


def _read_xml_sidecar(path: Path, *, image: Path | None = None) -> tuple[_Source, ElementTree.Element | None]:
    """A same-stem XML or a DIM file: Maxar isd or DIMAP. With ``image``, a DIMAP document is
    read only if it lists the image (the caller has no naming rule for it)."""
    source = _Source(str(path), str(path))
    data = _read_bytes(source, path)
    root = None if data is None else _parse_xml(source, data)
    if root is None:
        return source, None
    if root.tag == "isd":
        _read_maxar_xml(source, root)
    elif root.tag == "Dimap_Document":
        if image is None or image.stem.lower() in _dimap_file_stems(root):
            _read_dimap(source, root)
    return source, root


def _listing(image: Path) -> tuple[dict[str, Path], str | None]:
    """{lower-case name: path} of the files beside the image, or a warning."""
    try:
        return {p.name.lower(): p for p in image.parent.iterdir() if p.is_file()}, None
    except OSError as exc:
        return {}, f"{image.parent}: cannot list the image folder for metadata sidecars ({exc.strerror or exc})"


def _sources(image: Path) -> Iterable[_Source]:
    from satsweep.io.products import tiled_product  # noqa: PLC0415

    product = tiled_product(image)
    if product is not None:  # a DIM file: itself; a TIL file: the IMD beside it
        if image.suffix.lower() != ".til":
            yield _read_xml_sidecar(image)[0]
            return
        names, _ = _listing(image)
        imd = names.get(f"{image.stem.lower()}.imd")
        if imd is not None:
            yield _read_imd(imd)
        return
    tag = _read_tiff_tag(image)
    if tag is not None:
        yield tag
    names, problem = _listing(image)
    if problem is not None:
        failed = _Source(str(image.parent), str(image.parent))
        failed.warnings.append(problem)
        yield failed
        return
    stem = image.stem.lower()
    used: set[Path] = set()
    pam = names.get(f"{image.name.lower()}.aux.xml")
    if pam is not None:
        yield _read_pam(pam)
    imd = names.get(f"{stem}.imd")
    if imd is not None:
        yield _read_imd(imd)
    xml = names.get(f"{stem}.xml")
    if xml is not None:
        used.add(xml)
        yield _read_xml_sidecar(xml)[0]
    by_rule = [names[n] for n in _dimap_named_by_rule(image) if n in names and names[n] not in used]
    for path in by_rule:
        used.add(path)
        yield _read_xml_sidecar(path)[0]
    if by_rule:
        return
    # Any other DIM_*.XML is used only if it lists this image among its raster files.
    for name in sorted(n for n in names if n.startswith("dim_") and n.endswith(".xml")):
        path = names[name]
        if path in used:
            continue
        source, root = _read_xml_sidecar(path, image=image)
        if root is None:
            source.warnings = [f"{w}; cannot tell whether it describes {image.name}" for w in source.warnings]
        if source.values or source.warnings:
            yield source


def _agree(field: str, a: Any, b: Any) -> bool:
    if field == "acquisition_time_utc":
        ta, tb = parse_utc_time(a), parse_utc_time(b)
        return abs((ta - tb).total_seconds()) <= TIME_AGREEMENT_S
    if field == "satellite":
        def norm(s):
            return re.sub(r"[^0-9A-Z]", "", str(s).upper())
        return norm(a) == norm(b)
    if field == "cloud_cover_percent":
        return abs(a - b) <= CLOUD_AGREEMENT_PERCENT
    d = abs(a - b)
    if field.endswith("azimuth_deg"):
        d = min(d, 360.0 - d)
    return d <= ANGLE_AGREEMENT_DEG


def read_acquisition_metadata(image_path: str | os.PathLike) -> AcquisitionMetadata | None:
    """The acquisition metadata of a TIFF image, from its tags and the sidecars beside it.

    Returns None when no source holds any of it (the usual case for crops). Problems with the
    metadata (unparsable values, malformed sidecars, sources that disagree) are in ``warnings``;
    only an image that is missing or not a readable TIFF raises (ImageFormatError), as reading
    its pixels would. See the module docstring for the sources, their order and conventions.
    """
    image = Path(image_path)
    values: dict[str, Any] = {}
    where: dict[str, str] = {}
    warnings: list[str] = []
    for source in _sources(image):
        warnings.extend(source.warnings)
        for field in FIELDS:
            if field not in source.values:
                continue
            value = source.values[field]
            if field not in values:
                values[field] = value
                where[field] = source.where
            elif not _agree(field, values[field], value):
                warnings.append(f"{source.file}: {field} {value!r} differs from {values[field]!r} "
                                f"given by {where[field]}, which is reported")
    if not values and not warnings:
        return None
    return AcquisitionMetadata(**values, sources=tuple((f, where[f]) for f in FIELDS if f in where),
                               warnings=tuple(warnings))
