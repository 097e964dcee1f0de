"""Acquisition metadata: TIFF GDAL_METADATA tags, GDAL PAM, Maxar .IMD / .XML and Airbus DIMAP
sidecars, written here with known values, and the real Maxar XML deliveries in ../shared/data."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math
import re
import shutil

import numpy as np
import pytest

from satsweep.errors import ImageFormatError
from satsweep.io.geotiff import write_tiff
from satsweep.io.metadata import (
    TAG_GDAL_METADATA,
    AcquisitionMetadata,
    parse_utc_time,
    read_acquisition_metadata,
)

# The values the synthetic scenes write (issue 26): both forms carry them.
SYNTH_IMD = """satId = "SYNTH";
firstLineTime = 2019-06-01T10:31:12.000000Z;
BEGIN_GROUP = IMAGE_1
\tmeanSunAz = 135.2;
\tmeanSunEl = 61.0;
\tmeanSatAz = 30.1;
\tmeanSatEl = 72.3;
\tmeanOffNadirViewAngle = 17.7;
END_GROUP = IMAGE_1
END;
"""
SYNTH_TAG = ('<GDALMetadata><Item name="ACQUISITIONDATETIME" domain="IMAGERY">2019-06-01T10:31:12Z</Item>'
             '<Item name="SUN_AZIMUTH" domain="IMAGERY">135.2</Item><Item name="SUN_ELEVATION" '
             'domain="IMAGERY">61.0</Item><Item name="SATELLITEID" domain="IMAGERY">SYNTH</Item></GDALMetadata>')
SYNTH_TIME = "2019-06-01T10:31:12Z"


def _tiff(path, gdal_metadata: str | None = None, extratags=()):
    tags = list(extratags)
    if gdal_metadata is not None:
        tags.append((TAG_GDAL_METADATA, "s", 0, gdal_metadata, True))
    write_tiff(path, np.zeros((4, 5), np.uint16), extratags=tags)
    return path


def _items(**items) -> str:
    body = "".join(f'<Item name="{k}" domain="IMAGERY">{v}</Item>' for k, v in items.items())
    return f"<GDALMetadata>{body}</GDALMetadata>"


# -- the synthetic scenes' two forms ---------------------------------------------------------
def test_synthetic_imd_sidecar(tmp_path):
    image = _tiff(tmp_path / "view_0.tif")
    (tmp_path / "view_0.IMD").write_text(SYNTH_IMD)
    meta = read_acquisition_metadata(image)
    assert meta.acquisition_time_utc == SYNTH_TIME
    assert meta.acquisition_datetime == dt.datetime(2019, 6, 1, 10, 31, 12, tzinfo=dt.timezone.utc)
    assert meta.satellite == "SYNTH"
    assert (meta.sun_azimuth_deg, meta.sun_elevation_deg) == (135.2, 61.0)
    assert (meta.satellite_azimuth_deg, meta.satellite_elevation_deg, meta.off_nadir_deg) == (30.1, 72.3, 17.7)
    assert meta.cloud_cover_percent is None and meta.warnings == ()
    assert meta.source_of("sun_azimuth_deg") == str(tmp_path / "view_0.IMD")


def test_imd_keys_inside_the_image_group_win_over_the_top_level(tmp_path):
    # Real IMDs put satId and firstLineTime inside IMAGE_1; the group's values come first.
    text = SYNTH_IMD.replace("\tmeanSunAz", '\tsatId = "WV03";\n\tfirstLineTime = 2020-01-02T03:04:05.5Z;\n\tmeanSunAz')
    image = _tiff(tmp_path / "a.tif")
    (tmp_path / "a.IMD").write_text(text)
    meta = read_acquisition_metadata(image)
    assert meta.satellite == "WV03" and meta.acquisition_time_utc == "2020-01-02T03:04:05.500000Z"


def test_synthetic_gdal_metadata_tag(tmp_path):
    meta = read_acquisition_metadata(_tiff(tmp_path / "v.tif", SYNTH_TAG))
    assert meta.acquisition_time_utc == SYNTH_TIME and meta.satellite == "SYNTH"
    assert (meta.sun_azimuth_deg, meta.sun_elevation_deg) == (135.2, 61.0)
    assert meta.satellite_azimuth_deg is None and meta.off_nadir_deg is None
    assert "GDAL_METADATA" in meta.source_of("acquisition_time_utc") and meta.warnings == ()


def test_nitf_items_of_a_geotiff_converted_from_nitf(tmp_path):
    """gdal_translate of a WorldView NITF copies its default-domain items into the GeoTIFF's
    GDAL_METADATA tag (no domain): the image date-time NITF_IDATIM (CCYYMMDDhhmmss, UTC) and the
    USE00A TRE's sun angles. They give the date and sun where no IMAGERY key does; an IMAGERY
    key, when present, wins; a malformed NITF_IDATIM is a warning naming the key."""
    nitf = ('<GDALMetadata><Item name="NITF_IDATIM">20150219160412</Item>'
            '<Item name="NITF_USE00A_SUN_AZ">153.7</Item><Item name="NITF_USE00A_SUN_EL">38.9</Item>'
            '<Item name="NITF_IID2">15FEB19160412-P1BS-500648062030_01_P001</Item></GDALMetadata>')
    meta = read_acquisition_metadata(_tiff(tmp_path / "n.tif", nitf))
    assert meta.acquisition_time_utc == "2015-02-19T16:04:12Z"
    assert (meta.sun_azimuth_deg, meta.sun_elevation_deg) == (153.7, 38.9)
    assert meta.warnings == ()
    both = nitf.replace("</GDALMetadata>", '<Item name="SUN_AZIMUTH" domain="IMAGERY">150.0</Item>'
                        "</GDALMetadata>")
    assert read_acquisition_metadata(_tiff(tmp_path / "b.tif", both)).sun_azimuth_deg == 150.0
    bad = nitf.replace("20150219160412", "2015021916")
    meta = read_acquisition_metadata(_tiff(tmp_path / "bad.tif", bad))
    assert meta.acquisition_time_utc is None
    assert any("NITF_IDATIM" in w for w in meta.warnings), meta.warnings
    # without NITF_IDATIM, the STDIDC TRE's acquisition date (as the Sat-NeRF tools read the
    # DFC2019 crops); with both, the image subheader's
    stdidc = nitf.replace('name="NITF_IDATIM">20150219160412',
                          'name="NITF_STDIDC_ACQUISITION_DATE">20150219160413')
    meta = read_acquisition_metadata(_tiff(tmp_path / "s.tif", stdidc))
    assert meta.acquisition_time_utc == "2015-02-19T16:04:13Z" and meta.warnings == ()
    both = nitf.replace("</GDALMetadata>", '<Item name="NITF_STDIDC_ACQUISITION_DATE">'
                        "20150219160413</Item></GDALMetadata>")
    meta = read_acquisition_metadata(_tiff(tmp_path / "i.tif", both))
    assert meta.acquisition_time_utc == "2015-02-19T16:04:12Z"


def test_tag_and_sidecar_together_merge_field_by_field(tmp_path):
    image = _tiff(tmp_path / "v.tif", SYNTH_TAG)
    (tmp_path / "V.imd").write_text(SYNTH_IMD)  # stems match case-insensitively
    meta = read_acquisition_metadata(image)
    assert meta.warnings == ()  # they agree
    assert "GDAL_METADATA" in meta.source_of("sun_azimuth_deg")  # the image's own tag comes first
    assert meta.source_of("off_nadir_deg") == str(tmp_path / "V.imd")  # only the IMD has it
    assert meta.off_nadir_deg == 17.7
    d = meta.to_dict()
    assert json.loads(json.dumps(d)) == d
    assert d["sun_elevation_deg"] == 61.0 and d["cloud_cover_percent"] is None
    assert set(d["sources"]) == {"acquisition_time_utc", "satellite", "sun_azimuth_deg", "sun_elevation_deg",
                                 "satellite_azimuth_deg", "satellite_elevation_deg", "off_nadir_deg"}


def test_disagreeing_sources_keep_the_tag_and_warn(tmp_path):
    # GDAL's own date format, truncated to the second, agrees with the IMD's fraction.
    image = _tiff(tmp_path / "v.tif", _items(ACQUISITIONDATETIME="2019-06-01 10:31:12", SUN_AZIMUTH="135.2",
                                              SATELLITEID="SYNTH"))
    (tmp_path / "v.IMD").write_text(SYNTH_IMD.replace("12.000000Z", "12.973685Z").replace("135.2", "140.0"))
    meta = read_acquisition_metadata(image)
    assert meta.acquisition_time_utc == SYNTH_TIME and meta.sun_azimuth_deg == 135.2
    assert len(meta.warnings) == 1
    w = meta.warnings[0]
    assert w.startswith(str(tmp_path / "v.IMD")) and "sun_azimuth_deg" in w and "140.0" in w and "GDAL_METADATA" in w


def test_imagery_domain_wins_and_band_items_are_ignored(tmp_path):
    xml = ('<GDALMetadata><Item name="SUN_AZIMUTH">10</Item><Item name="SUN_AZIMUTH" domain="IMAGERY">20</Item>'
           '<Item name="SUN_ELEVATION" sample="0">33</Item><Item name="SUN_ELEVATION">44</Item>'
           '<Item name="CLOUDCOVER" domain="IMAGERY">999</Item><Item name="SATELLITEID">X1</Item></GDALMetadata>')
    meta = read_acquisition_metadata(_tiff(tmp_path / "v.tif", xml))
    assert meta.sun_azimuth_deg == 20.0 and meta.sun_elevation_deg == 44.0
    assert meta.cloud_cover_percent is None  # 999: GDAL's "not available"
    assert meta.satellite == "X1"


def test_gdal_pam_sidecar(tmp_path):
    image = _tiff(tmp_path / "v.tif")
    (tmp_path / "v.tif.aux.xml").write_text(
        '<PAMDataset><Metadata domain="IMAGERY"><MDI key="ACQUISITIONDATETIME">2015-09-30 10:56:56</MDI>'
        '<MDI key="CLOUDCOVER">12</MDI></Metadata><PAMRasterBand band="1"><Metadata>'
        '<MDI key="SUN_AZIMUTH">1</MDI></Metadata></PAMRasterBand></PAMDataset>')
    meta = read_acquisition_metadata(image)
    assert meta.acquisition_time_utc == "2015-09-30T10:56:56Z" and meta.cloud_cover_percent == 12.0
    assert meta.sun_azimuth_deg is None  # a band's item


# -- absent metadata ---------------------------------------------------------------------------
def test_absent_metadata_is_none(tmp_path):
    assert read_acquisition_metadata(_tiff(tmp_path / "plain.tif")) is None
    # Unrelated GDAL items, sidecars of other stems, and the TIFF DateTime tag (the file's
    # creation time, not the acquisition) say nothing.
    image = _tiff(tmp_path / "b.tif", '<GDALMetadata><Item name="AREA_OR_POINT">Area</Item></GDALMetadata>',
                  extratags=[(306, "s", 0, "2024:05:06 07:08:09", True)])
    (tmp_path / "other.IMD").write_text(SYNTH_IMD)
    assert read_acquisition_metadata(image) is None


def test_missing_image_is_an_image_error(tmp_path):
    with pytest.raises(ImageFormatError, match="nope.tif"):
        read_acquisition_metadata(tmp_path / "nope.tif")


def test_pleiades_crops_carry_no_acquisition_metadata(pleiades_pair):
    for name in ("img_01.tif", "img_02.tif"):  # their GDAL_METADATA tag holds only a GML coverage
        assert read_acquisition_metadata(pleiades_pair / name) is None


# -- malformed metadata: warnings, never exceptions --------------------------------------------
def test_unparsable_values_are_warnings_naming_the_file_and_key(tmp_path):
    image = _tiff(tmp_path / "v.tif")
    text = (SYNTH_IMD.replace("61.0", "sixty").replace("2019-06-01T10", "2019-13-01T10")
            .replace("17.7", "97.7"))
    (tmp_path / "v.IMD").write_text(text)
    meta = read_acquisition_metadata(image)
    assert meta.sun_azimuth_deg == 135.2 and meta.satellite == "SYNTH"  # the rest is read
    assert meta.sun_elevation_deg is None and meta.acquisition_time_utc is None and meta.off_nadir_deg is None
    imd = str(tmp_path / "v.IMD")
    assert len(meta.warnings) == 3 and all(w.startswith(imd + ": ") for w in meta.warnings)
    joined = " | ".join(meta.warnings)
    assert "meansunel = 'sixty' is not a number" in joined
    assert "firstlinetime" in joined and "2019-13-01" in joined
    assert "meanoffnadirviewangle = 97.7 is outside [0, 90]" in joined


def test_malformed_files_are_warnings(tmp_path):
    image = _tiff(tmp_path / "v.tif", "<GDALMetadata><Item name='X'>")
    (tmp_path / "v.XML").write_text("<isd><IMD>")
    meta = read_acquisition_metadata(image)
    assert all(v is None for v in (meta.acquisition_time_utc, meta.satellite, meta.sun_azimuth_deg))
    assert len(meta.warnings) == 2
    assert "GDAL_METADATA" in meta.warnings[0] and "malformed XML" in meta.warnings[0]
    assert meta.warnings[1].startswith(str(tmp_path / "v.XML") + ": malformed XML")
    assert meta.to_dict()["warnings"] == list(meta.warnings)


def test_utc_time_formats():
    utc = dt.timezone.utc
    assert parse_utc_time("2019-06-01T12:31:12+02:00") == dt.datetime(2019, 6, 1, 10, 31, 12, tzinfo=utc)
    assert parse_utc_time("2019-06-01 10:31:12") == dt.datetime(2019, 6, 1, 10, 31, 12, tzinfo=utc)
    assert parse_utc_time("2013-06-29T06:37:18.123456789Z").microsecond == 123456
    for bad in ("2019-06-01", "yesterday", "2019-02-30T00:00:00Z"):
        with pytest.raises(ValueError):
            parse_utc_time(bad)


# -- real Maxar / DigitalGlobe XML deliveries ---------------------------------------------------
def _tag(text: str, name: str) -> str:
    """The first <NAME>value</NAME> of the file's IMD/IMAGE block, read with a plain regex."""
    block = re.search(r"<IMD>.*?<IMAGE>(.*?)</IMAGE>", text, re.S).group(1)
    return re.search(rf"<{name}>(.*?)</{name}>", block).group(1)


@pytest.mark.parametrize("name", ["rpc_WV2.xml", "rpc_WV3.xml"])
def test_real_maxar_xml_sidecar(shared_data, tmp_path, name):
    src = shared_data / "rpc_files" / name
    if not src.is_file():
        pytest.skip(f"{src} is absent")
    shutil.copy(src, tmp_path / "scene.XML")
    meta = read_acquisition_metadata(_tiff(tmp_path / "scene.tif"))
    text = src.read_text()
    assert meta.acquisition_time_utc == _tag(text, "FIRSTLINETIME")  # already ISO-8601 with Z
    assert meta.satellite == _tag(text, "SATID")
    for field, key in (("sun_azimuth_deg", "MEANSUNAZ"), ("sun_elevation_deg", "MEANSUNEL"),
                       ("satellite_azimuth_deg", "MEANSATAZ"), ("satellite_elevation_deg", "MEANSATEL"),
                       ("off_nadir_deg", "MEANOFFNADIRVIEWANGLE")):
        assert getattr(meta, field) == float(_tag(text, key)), field
    assert meta.cloud_cover_percent == 100.0 * float(_tag(text, "CLOUDCOVER"))
    assert meta.warnings == () and meta.source_of("satellite") == str(tmp_path / "scene.XML")
    if name == "rpc_WV2.xml":  # the file's own values, as a reader sees them
        assert (meta.acquisition_time_utc, meta.satellite) == ("2015-09-30T10:56:56.973685Z", "WV02")
        assert (meta.sun_azimuth_deg, meta.sun_elevation_deg) == (162.1, 40.3)


@pytest.mark.parametrize("name", ["rpc_PLEIADES.xml", "rpc_SPOT6.xml"])
def test_dimap_rpc_files_carry_no_dates(shared_data, tmp_path, name):
    src = shared_data / "rpc_files" / name
    if not src.is_file():
        pytest.skip(f"{src} is absent")
    assert not re.search(r"DATE|TIME|SUN_", src.read_text())
    shutil.copy(src, tmp_path / "scene.XML")
    assert read_acquisition_metadata(_tiff(tmp_path / "scene.tif")) is None


# -- Airbus DIMAP v2 ----------------------------------------------------------------------------
def _dimap(files: list[str], *, centre: bool = True) -> str:
    """A DIMAP v2 document; the Center values differ from the corners' so that the choice shows."""
    def located(kind, time, sun_az, sun_el, view, incidence):
        return (f"<Located_Geometric_Values><LOCATION_TYPE>{kind}</LOCATION_TYPE><TIME>{time}</TIME>"
                f"<Acquisition_Angles><AZIMUTH_ANGLE>179.9</AZIMUTH_ANGLE><VIEWING_ANGLE>{view}</VIEWING_ANGLE>"
                f"<INCIDENCE_ANGLE>{incidence}</INCIDENCE_ANGLE></Acquisition_Angles><Solar_Incidences>"
                f"<SUN_AZIMUTH>{sun_az}</SUN_AZIMUTH><SUN_ELEVATION>{sun_el}</SUN_ELEVATION></Solar_Incidences>"
                "</Located_Geometric_Values>")
    geo = located("Top Center", "2013-06-29T06:37:16.5Z", 30.1, 45.0, 8.0, 8.9)
    if centre:
        geo += located("Center", "2013-06-29T06:37:18.123456789Z", 30.5, 45.25, 8.2, 9.1)
    geo += located("Bottom Center", "2013-06-29T06:37:20.5Z", 30.9, 45.5, 8.4, 9.3)
    data = "".join(f'<Data_File><DATA_FILE_PATH href="{f}"/></Data_File>' for f in files)
    return ("<?xml version='1.0'?><Dimap_Document><Metadata_Identification><METADATA_PROFILE>PHR_SENSOR"
            "</METADATA_PROFILE></Metadata_Identification><Dataset_Sources><Source_Identification>"
            "<Strip_Source><MISSION>PHR</MISSION><MISSION_INDEX>1B</MISSION_INDEX>"
            "<IMAGING_DATE>2013-06-29</IMAGING_DATE><IMAGING_TIME>06:37:14.4</IMAGING_TIME></Strip_Source>"
            "</Source_Identification></Dataset_Sources><Raster_Data><Data_Access><Data_Files>"
            f"{data}</Data_Files></Data_Access></Raster_Data><Geometric_Data><Use_Area>{geo}</Use_Area>"
            "</Geometric_Data></Dimap_Document>")


def test_dimap_that_lists_the_image(tmp_path):
    image = _tiff(tmp_path / "img_a.tif")
    (tmp_path / "DIM_product.XML").write_text(_dimap(["IMG_A.JP2", "IMG_B.JP2"]))  # converted JP2: same stem
    meta = read_acquisition_metadata(image)
    assert meta.acquisition_time_utc == "2013-06-29T06:37:18.123456Z"  # the Center's, cut to microseconds
    assert meta.satellite == "PHR 1B"
    assert (meta.sun_azimuth_deg, meta.sun_elevation_deg, meta.off_nadir_deg) == (30.5, 45.25, 8.2)
    assert math.isclose(meta.satellite_elevation_deg, 90.0 - 9.1, abs_tol=1e-12)
    assert meta.satellite_azimuth_deg is None  # AZIMUTH_ANGLE is the scene orientation
    assert meta.source_of("satellite") == str(tmp_path / "DIM_product.XML") and meta.warnings == ()


def test_dimap_of_another_image_is_not_attributed(tmp_path):
    image = _tiff(tmp_path / "img_c.tif")
    (tmp_path / "DIM_product.XML").write_text(_dimap(["IMG_A.JP2", "IMG_B.JP2"]))
    (tmp_path / "img_a.tif").write_bytes(image.read_bytes())
    assert read_acquisition_metadata(image) is None
    assert read_acquisition_metadata(tmp_path / "img_a.tif").satellite == "PHR 1B"


def test_dimap_naming_rule_and_strip_time(tmp_path):
    # GDAL's rule: IMG_X_R1C1 is described by DIM_X.XML, whatever the tiles it lists.
    image = _tiff(tmp_path / "IMG_PHR1B_P_001_R1C1.tif")
    (tmp_path / "DIM_PHR1B_P_001.XML").write_text(_dimap(["IMG_PHR1B_P_001_R2C1.JP2"], centre=False))
    meta = read_acquisition_metadata(image)
    assert meta.satellite == "PHR 1B"
    # No Center: the first located values, whose time wins over the strip's.
    assert meta.acquisition_time_utc == "2013-06-29T06:37:16.500000Z" and meta.sun_azimuth_deg == 30.1
    (tmp_path / "DIM_PHR1B_P_001.XML").write_text(
        _dimap([], centre=False).replace("<TIME>2013-06-29T06:37:16.5Z</TIME>", ""))
    assert read_acquisition_metadata(image).acquisition_time_utc == "2013-06-29T06:37:14.400000Z"


def test_malformed_dimap_in_the_folder_is_a_warning(tmp_path):
    image = _tiff(tmp_path / "img_a.tif")
    (tmp_path / "DIM_broken.XML").write_text("<Dimap_Document><Raster_Data>")
    meta = read_acquisition_metadata(image)
    assert isinstance(meta, AcquisitionMetadata) and meta.satellite is None
    assert len(meta.warnings) == 1 and "DIM_broken.XML: malformed XML" in meta.warnings[0]
    assert "cannot tell whether it describes img_a.tif" in meta.warnings[0]


def test_sun_computed_from_the_date_where_the_metadata_lack_it():
    """A date-time without sun angles (a crop that lost its USE00A TRE): both computed at the
    place given, and the sources say so; a given angle is kept; no date-time, nothing."""
    from satsweep.geometry.sun import solar_position
    from satsweep.io.metadata import AcquisitionMetadata, with_computed_sun

    dated = AcquisitionMetadata(acquisition_time_utc="2015-02-19T16:04:12Z",
                                sources=(("acquisition_time_utc", "v.tif: GDAL_METADATA"),))
    meta = with_computed_sun(dated, lon=-81.66, lat=30.33)
    el, az = solar_position(lon=-81.66, lat=30.33, when=dated.acquisition_datetime)
    assert (meta.sun_elevation_deg, meta.sun_azimuth_deg) == (round(el, 2), round(az, 2))
    assert 30.0 < meta.sun_elevation_deg < 50.0 and 120.0 < meta.sun_azimuth_deg < 180.0  # winter morning
    assert "computed from the acquisition time" in meta.source_of("sun_azimuth_deg")
    assert meta.source_of("acquisition_time_utc") == "v.tif: GDAL_METADATA"
    half = dataclasses.replace(dated, sun_azimuth_deg=150.0)
    meta = with_computed_sun(half, lon=-81.66, lat=30.33)
    assert meta.sun_azimuth_deg == 150.0 and meta.sun_elevation_deg == round(el, 2)
    assert meta.source_of("sun_azimuth_deg") is None
    undated = AcquisitionMetadata(satellite="WV03")
    assert with_computed_sun(undated, lon=0.0, lat=0.0) is undated
    assert with_computed_sun(None, lon=0.0, lat=0.0) is None
