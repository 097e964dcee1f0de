"""The sun's position (satsweep.geometry.sun) against a published reference."""

from __future__ import annotations

import datetime as dt

from satsweep.geometry.sun import solar_position

# NOAA's general (low-precision) formulas against NREL's SPA, which is good to 0.0003 degree:
# their series for the declination and the equation of time leave a few tenths of a degree.
LOW_PRECISION_DEG = 0.3


def test_solar_position_on_nrels_spa_example():
    """Reda & Andreas (2004), NREL's Solar Position Algorithm, worked example: 2003-10-17
    12:30:30 local time (UTC-7) at 39.742476 N, 105.1786 W: topocentric zenith 50.11162 deg
    (with refraction, about 0.02 deg there), azimuth 194.34024 deg from north."""
    when = dt.datetime(2003, 10, 17, 12, 30, 30, tzinfo=dt.timezone(dt.timedelta(hours=-7)))
    elevation, azimuth = solar_position(lon=-105.1786, lat=39.742476, when=when)
    assert abs(elevation - (90.0 - 50.11162)) < LOW_PRECISION_DEG
    assert abs(azimuth - 194.34024) < LOW_PRECISION_DEG
