"""The sun's position seen from a place on the ground at a given time.

Used where an acquisition's metadata give its date-time but not the sun's angles (the date of a
GeoTIFF converted from NITF without its USE00A TRE, say): the similarity of two dates compares
their sun directions (:mod:`satsweep.dense.similarity`). Also used by the synthetic multi-date
scenes (:mod:`satsweep.synth.multidate`) to place their sun.
"""

from __future__ import annotations

import datetime as dt
import math


def solar_position(*, lon: float, lat: float, when: dt.datetime) -> tuple[float, float]:
    """(elevation, azimuth) of the sun in degrees at (lon, lat) at UTC time ``when``.

    NOAA's general solar position formulas (fractional-year series for the declination and the
    equation of time), without refraction: within 0.21 degree of NREL's SPA on its worked example
    (tests/geometry/test_sun.py). Azimuth clockwise from north.
    """
    if when.tzinfo is not None:
        when = when.astimezone(dt.timezone.utc).replace(tzinfo=None)
    doy = when.timetuple().tm_yday
    hours = when.hour + when.minute / 60.0 + (when.second + when.microsecond * 1e-6) / 3600.0
    days_in_year = 366 if (when.year % 4 == 0 and (when.year % 100 != 0 or when.year % 400 == 0)) else 365
    g = 2.0 * math.pi / days_in_year * (doy - 1 + (hours - 12.0) / 24.0)
    eqtime = 229.18 * (0.000075 + 0.001868 * math.cos(g) - 0.032077 * math.sin(g)
                       - 0.014615 * math.cos(2 * g) - 0.040849 * math.sin(2 * g))  # minutes
    decl = (0.006918 - 0.399912 * math.cos(g) + 0.070257 * math.sin(g) - 0.006758 * math.cos(2 * g)
            + 0.000907 * math.sin(2 * g) - 0.002697 * math.cos(3 * g) + 0.00148 * math.sin(3 * g))
    true_solar_min = hours * 60.0 + eqtime + 4.0 * lon
    ha = math.radians(true_solar_min / 4.0 - 180.0)
    phi = math.radians(lat)
    cos_zen = math.sin(phi) * math.sin(decl) + math.cos(phi) * math.cos(decl) * math.cos(ha)
    elevation = 90.0 - math.degrees(math.acos(max(-1.0, min(1.0, cos_zen))))
    azimuth = math.degrees(math.atan2(math.sin(ha), math.cos(ha) * math.sin(phi) - math.tan(decl) * math.cos(phi)))
    return elevation, (azimuth + 180.0) % 360.0
