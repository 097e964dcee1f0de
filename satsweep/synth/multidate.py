"""Multi-date synthetic scenes: views grouped into acquisitions on different dates.

A real stack of satellite images of one place (say 19 WorldView-3 crops over 13 months) is hard
for stereo because everything but the buildings changes between dates: the sun (shading and
cast shadows), the trees (leaf-on, autumn, leaf-off), the grass, the parked cars, the
radiometry; and because the viewing geometry is spread all around (incidences up to about 30
degrees) with pointing errors of metres. ``SynthOptions(acquisitions=N)`` makes
``satsweep.synth.scene.generate_scene`` render such a stack; this module plans it and draws what
changes with the date. The truth surface (and ``truth_dsm.tif``) never changes.

Plan (``plan_acquisitions``, deterministic in the options):

* **Acquisitions**: N passes of 1 to 3 views each (``views_per_acquisition`` or drawn), on N
  distinct days drawn within ``date_span_days`` of ``start_date``, at a local mean solar time
  between LOCAL_TIME_H (a sun-synchronous descending orbit crosses at about 10:30), sorted by
  date. Views of one pass are PASS_STEP_S seconds apart.
* **Sun**: the sun's elevation and azimuth at the scene centre at the acquisition's time
  (``solar_position``, NOAA's low-precision formulas, about 0.1 degree), rounded to 0.1 degree
  (the value rendered and written). Days whose sun stays below ``min_sun_elevation_deg`` are not
  drawn.
* **Viewing geometry**: each pass has its own orbit heading (``orbit_azimuth_deg`` +-
  HEADING_SPREAD_DEG) and its own cross-track offset; the views of a pass look forward and backward
  along the track (in-track stereo, PASS_BH between consecutive views), so that azimuths come all
  around and incidences up to ``max_off_nadir_deg``. Explicit ``off_nadir_deg``/``azimuth_deg``
  replace the drawn angles, and every pass then flies along ``orbit_azimuth_deg`` (the views are
  as the options give them, as on a single-date scene).
* **Radiometry** per view: ``DN = gain * DN_MAX * (x / DN_MAX) ** gamma + offset + noise``, where
  ``x = radiance * DN_PER_RADIANCE`` is the single-date scene's noise-free DN; gain, offset and
  gamma are drawn per acquisition (illumination, haze: a haze lowers the gain and raises the
  offset) and vary slightly between the views of one pass.

What changes with the date, on a copy of the surface (``acquisition_surface``):

* **Materials**: roofs and facades are far from Lambertian (metal sheets, membranes, glass), so
  their brightness changes with the sun's direction: each building's roof and facades get a
  factor of their own per date (log-normal, MATERIAL_LOG_SIGMA).
* **Vegetation**: a share EVERGREEN_SHARE of the trees keeps its leaves; the others follow the
  season of the date (``leaf_state``: leaf-on in summer, brighter crowns in spring and autumn,
  leaf-off in winter, when only a share ``leaf_density`` of a crown's cells keeps its branches and
  the others show what lies beneath, and let the sun through). The leaves' fine texture is drawn
  again on every date.
* **Ground**: grass and soil get a brightness factor and a fine texture of their own per date
  (mown, dry or wet patches) as strong as the grass's own fine texture; its coarse texture
  stays.
* **Transients**: cars, vans and trucks parked along the kerbs and driving in the lanes, and
  market stalls on the plazas, drawn again on every date. They are rendered (with their shadows)
  but are not in the truth, as with a lidar truth surveyed on another day.

Which of these change is ``date_effects`` (any of DATE_EFFECTS); the others stay as on a
single-date scene (the sun without "sun" is the options' ``sun_elevation_deg`` and
``sun_azimuth_deg`` on every date).

Acquisition metadata (``write_imd``, ``gdal_metadata_xml``): a DigitalGlobe/Maxar-style ``.IMD``
sidecar beside each view and the TIFF tag GDAL_METADATA (42112), with the date-time, the sun's
and the satellite's angles, as satsweep reads them.

Every draw comes from the scene's seed and its own stream number: the same options give the
same plan and the same surfaces.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from satsweep.geometry.sun import solar_position
from satsweep.io.atomic import atomic_output
from satsweep.synth.town import (
    GROUND,
    PLAZA,
    ROAD,
    ROOF,
    ROOF_BOX,
    ROOF_GABLE,
    STALL,
    VEHICLE,
    SurfaceGrid,
    fractal_noise,
)

# What may change between dates (SynthOptions.date_effects).
DATE_EFFECTS = ("sun", "materials", "vegetation", "ground", "transients", "radiometry")

# Local mean solar time of the overpasses (hours): sun-synchronous satellites such as
# WorldView-3 cross the equator descending at about 10:30; off-nadir passes come a little earlier
# or later.
LOCAL_TIME_H = (10.0, 11.25)
# Seconds between consecutive views of one pass (in-track stereo, about a minute).
PASS_STEP_S = 60
# Base-to-height ratio between consecutive views of one pass, and the largest |tan| of the
# along-track look of a pass's middle (its views look forward and backward around it).
PASS_BH = (0.12, 0.30)
PASS_ALONG_CENTRE = 0.15
# Smallest drawn off-nadir angle (degrees): real acquisitions are never exactly at nadir.
MIN_DRAWN_OFF_NADIR_DEG = 3.0
# Spread of the orbit heading between passes (degrees, +-): the ground track's heading varies
# a little with the latitude of the scene within the image strip.
HEADING_SPREAD_DEG = 3.0
# Satellite id written in the metadata.
SATELLITE_ID = "SYNTH"

# Radiometry: per acquisition, gain, offset (DN) and gamma drawn uniformly in these ranges; the
# views of one pass differ from their acquisition by +-VIEW_GAIN_SPREAD (relative) in gain and
# +-VIEW_OFFSET_SPREAD_DN in offset. A gain up to 1.1 keeps the brightest roofs (3600 DN at gain
# 1) mostly below the 12-bit ceiling, as real images keep theirs.
GAIN_RANGE = (0.75, 1.1)
OFFSET_RANGE_DN = (20.0, 200.0)
GAMMA_RANGE = (0.85, 1.15)
VIEW_GAIN_SPREAD = 0.03
VIEW_OFFSET_SPREAD_DN = 10.0

# Vegetation. Share of evergreen trees (they keep their leaves all year).
EVERGREEN_SHARE = 0.25
# Leaf state of the deciduous trees through the year (northern hemisphere day of year; the
# southern hemisphere is half a year off): leaf-off before LEAF_OUT[0] and after LEAF_FALL[1],
# leaves growing over LEAF_OUT, full over the summer, falling over LEAF_FALL.
LEAF_OUT = (95, 140)
LEAF_FALL = (285, 320)
# Share of a leafless crown's cells that keep branches (the others show what lies beneath).
LEAFLESS_DENSITY = 0.35
# Brightness of the leaves relative to summer: fresh leaves in spring, yellowing ones in autumn.
SPRING_LEAF_FACTOR = 1.15
AUTUMN_LEAF_FACTOR = 1.3
# Albedo of bare branches (panchromatic) and the amplitude of their texture.
BRANCH_ALBEDO = 0.14
BRANCH_TEXTURE = 0.03
# How green the deciduous leaves are in autumn, against 1 in spring and summer and 0 for bare
# branches (``town.greenness``: the colour of the 8-bit RGB deliveries).
AUTUMN_LEAFINESS = 0.3
# Amplitude of the leaves' texture drawn again on each date (the leaves move, the crown's
# self-shadowing follows the sun), as large as the crown's own fine texture (0.035).
LEAF_TEXTURE_CHANGE = 0.035
# Size of the holes of a leafless crown (m): clusters of cells, not single cells.
CROWN_HOLE_SCALE_M = 0.75

# Ground: per date brightness factor of grass and soil, and the amplitude of the date's own
# texture at the scales of the grass's fine texture (2, 1 and 0.5 m: mown, trodden, dry or wet
# patches), as large as that fine texture (0.03); its coarse texture (3-24 m, 0.045) stays.
GROUND_FACTOR_RANGE = (0.85, 1.15)
GROUND_CHANGE_AMPLITUDE = 0.03
GROUND_CHANGE_SCALES_M = (2.0, 1.0, 0.5)
# Materials: the brightness of a roof or a facade depends on the sun's direction (metal sheets,
# membranes and glass are far from Lambertian), so each building's roof and facades get a factor
# of their own per date, log-normal with this spread, clipped to MATERIAL_FACTOR_RANGE.
MATERIAL_LOG_SIGMA = 0.15
MATERIAL_FACTOR_RANGE = (0.7, 1.4)

# Vehicles. Per date, the share of the kerb slots (PARK_SPACING_M apart) holding a parked
# vehicle, and the chance of a moving one per DRIVE_SPACING_M of each lane.
PARK_OCCUPANCY = (0.25, 0.65)
PARK_SPACING_M = (5.6, 6.8)
DRIVE_CHANCE = (0.03, 0.10)
DRIVE_SPACING_M = 12.0
# Distance of the parking lane's centre from the kerb (m).
PARK_LANE_FROM_KERB_M = 1.15
# Kinds of vehicle: (share, length range, width range, height range) in metres; cars also have
# a cabin (the body is CAR_BODY_M high, the roof over the cabin the drawn height).
VEHICLES = (
    ("car", 0.85, (4.0, 4.9), (1.7, 1.9), (1.4, 1.6)),
    ("van", 0.11, (4.8, 6.0), (1.9, 2.1), (1.9, 2.4)),
    ("truck", 0.04, (8.0, 12.0), (2.4, 2.6), (3.0, 3.6)),
)
CAR_BODY_M = (0.65, 0.85)
# Vehicle paints in panchromatic albedo: (share, range): white, black, silver/grey, colours.
PAINTS = ((0.25, (0.55, 0.75)), (0.25, (0.03, 0.07)), (0.30, (0.25, 0.45)), (0.20, (0.10, 0.25)))
WINDSHIELD_ALBEDO = 0.05
# Market stalls on plazas: the chance of a market day, and the plaza area per stall (m^2).
MARKET_CHANCE = 0.5
PLAZA_M2_PER_STALL = 120.0
STALL_SIDE_M = (2.5, 3.5)
STALL_HEIGHT_M = (2.2, 2.8)
STALL_ALBEDO = (0.55, 0.8)

# Random streams (numbers after the seed) of the plan and of each date's changes.
_STREAM_SPLIT = 13
_STREAM_DATES = 10
_STREAM_PASSES = 12
_STREAM_RADIOMETRY = 9
_STREAM_VEGETATION = 7000
_STREAM_GROUND = 8000
_STREAM_TRANSIENTS = 9000
_STREAM_EVERGREEN = 14
_STREAM_MATERIALS = 10000


def iso_utc(when: dt.datetime) -> str:
    """``2019-06-01T10:31:12Z`` (whole seconds, UTC)."""
    return when.strftime("%Y-%m-%dT%H:%M:%SZ")


def parse_iso_utc(text: str) -> dt.datetime:
    """Inverse of ``iso_utc`` (naive datetime in UTC)."""
    return dt.datetime.strptime(text, "%Y-%m-%dT%H:%M:%SZ")


def leaf_state(doy: int, lat: float) -> tuple[float, float]:
    """(share of a deciduous crown's cells keeping leaves or branches, leaf brightness factor)
    on day of year ``doy`` at latitude ``lat`` (the southern hemisphere half a year off).

    Leaf-off: LEAFLESS_DENSITY and the branches' own albedo (factor 0 means "branches"); leaves
    growing: density rising to 1, brightness SPRING_LEAF_FACTOR; summer: 1, 1; falling: density
    falling, brightness AUTUMN_LEAF_FACTOR.
    """
    d = (doy + 182) % 365 if lat < 0 else doy
    if LEAF_OUT[0] <= d < LEAF_OUT[1]:
        f = (d - LEAF_OUT[0]) / (LEAF_OUT[1] - LEAF_OUT[0])
        return LEAFLESS_DENSITY + (1.0 - LEAFLESS_DENSITY) * f, SPRING_LEAF_FACTOR
    if LEAF_OUT[1] <= d < LEAF_FALL[0]:
        return 1.0, 1.0
    if LEAF_FALL[0] <= d < LEAF_FALL[1]:
        f = (d - LEAF_FALL[0]) / (LEAF_FALL[1] - LEAF_FALL[0])
        return 1.0 - (1.0 - LEAFLESS_DENSITY) * f, AUTUMN_LEAF_FACTOR
    return LEAFLESS_DENSITY, 0.0


# ---------------------------------------------------------------------------------------------
# The plan
# ---------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Acquisition:
    """One acquisition (a pass on one date) of a multi-date scene."""

    index: int
    date_time: str  # UTC time of its first view, ISO (``2019-06-01T10:31:12Z``)
    sun_elevation_deg: float  # rendered sun, rounded to 0.1 degree
    sun_azimuth_deg: float  # clockwise from north
    orbit_azimuth_deg: float  # heading of the satellite's motion
    views: tuple[int, ...]  # the scene's views taken on this pass, in time order
    leaf_density: float  # share of the deciduous crowns' cells that keep leaves or branches
    leaf_factor: float  # brightness of the leaves relative to summer (0: leafless branches)
    ground_factor: float  # brightness of grass and soil relative to the truth surface's
    transients: tuple[dict, ...] = ()  # filled when rendered: the vehicles and stalls drawn

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["views"] = list(self.views)
        d["transients"] = [dict(t) for t in self.transients]
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Acquisition":
        return cls(index=int(d["index"]), date_time=str(d["date_time"]),
                   sun_elevation_deg=float(d["sun_elevation_deg"]), sun_azimuth_deg=float(d["sun_azimuth_deg"]),
                   orbit_azimuth_deg=float(d["orbit_azimuth_deg"]), views=tuple(int(v) for v in d["views"]),
                   leaf_density=float(d["leaf_density"]), leaf_factor=float(d["leaf_factor"]),
                   ground_factor=float(d["ground_factor"]),
                   transients=tuple(dict(t) for t in d["transients"]))


@dataclasses.dataclass(frozen=True)
class ViewPlan:
    """What a multi-date scene's view is: its acquisition, time, geometry and radiometry."""

    acquisition: int
    date_time: str  # UTC time of the view (its first line), ISO
    off_nadir_deg: float
    azimuth_deg: float  # satellite azimuth seen from the scene centre
    orbit_azimuth_deg: float  # heading of the pass
    gain: float  # DN = gain * DN_MAX * (x / DN_MAX) ** gamma + offset_dn + noise
    offset_dn: float
    gamma: float


@dataclasses.dataclass(frozen=True)
class MultiDatePlan:
    acquisitions: tuple[Acquisition, ...]
    views: tuple[ViewPlan, ...]


def split_views(rng: np.random.Generator, n_views: int, n_acq: int) -> tuple[int, ...]:
    """Views per acquisition: each 1..3, summing to n_views (requires n_acq <= n_views <= 3 n_acq)."""
    counts = np.ones(n_acq, np.int64)
    for _ in range(n_views - n_acq):
        room = np.nonzero(counts < 3)[0]
        counts[rng.choice(room)] += 1
    return tuple(int(c) for c in counts)


def _draw_days(options, rng: np.random.Generator) -> list[tuple[dt.date, float, dt.datetime]]:
    """(local date, local mean solar hour, UTC time) of each acquisition, sorted, with the sun high enough."""
    from satsweep.errors import OptionsError

    lon, lat = options.location
    start = dt.date.fromisoformat(options.start_date)
    lo_h, hi_h = LOCAL_TIME_H

    def utc(day: dt.date, hour: float) -> dt.datetime:
        when = dt.datetime.combine(day, dt.time()) + dt.timedelta(hours=hour - lon / 15.0)
        return when.replace(microsecond=0) + dt.timedelta(seconds=round(when.microsecond * 1e-6))

    # Days on which the latest overpass time sees the sun high enough (elevation rises towards
    # noon over the whole window, so any such day has a valid time).
    days = [start + dt.timedelta(days=k) for k in range(options.date_span_days)]
    usable = [d for d in days
              if solar_position(lon=lon, lat=lat, when=utc(d, hi_h))[0] >= options.min_sun_elevation_deg]
    if len(usable) < options.acquisitions:
        raise OptionsError(
            f"SynthOptions.min_sun_elevation_deg = {options.min_sun_elevation_deg!r}: only {len(usable)} "
            f"day(s) of the {options.date_span_days} from {options.start_date} see the sun that high at "
            f"latitude {lat:g} by {hi_h:g} h local time, {options.acquisitions} acquisitions need one each")
    pick = sorted(rng.choice(len(usable), size=options.acquisitions, replace=False).tolist())
    out = []
    for k in pick:
        day = usable[k]
        for _ in range(100):
            hour = round(float(rng.uniform(lo_h, hi_h)) * 3600.0) / 3600.0
            if solar_position(lon=lon, lat=lat, when=utc(day, hour))[0] >= options.min_sun_elevation_deg:
                break
        else:  # the latest time is valid by construction of `usable`
            hour = hi_h
        out.append((day, hour, utc(day, hour)))
    return out


def _draw_pass(rng: np.random.Generator, n: int, heading_deg: float, max_off_nadir_deg: float
               ) -> list[tuple[float, float]]:
    """(off-nadir, satellite azimuth) in degrees of the n views of one pass, in time order.

    The satellite flies along ``heading``; seen from the target it is at tan-angles (x across
    the track, to the right of the motion; y along it, negative before it passes): the views of
    a pass share x and look forward, then (for 2-3 views) down and backward.
    """
    t_max = math.tan(math.radians(max_off_nadir_deg))
    t_min = math.tan(math.radians(MIN_DRAWN_OFF_NADIR_DEG))
    h = math.radians(heading_deg)
    along = np.array([math.sin(h), math.cos(h)])
    across = np.array([math.cos(h), -math.sin(h)])
    for _ in range(1000):
        step = rng.uniform(*PASS_BH)
        y0 = rng.uniform(-PASS_ALONG_CENTRE, PASS_ALONG_CENTRE)
        ys = y0 + (np.arange(n) - (n - 1) / 2.0) * step
        x = rng.uniform(-t_max, t_max)
        r = np.hypot(x, ys)
        if np.all(r <= t_max) and np.all(r >= t_min):
            break
    else:  # pragma: no cover - the ranges above always leave room
        raise RuntimeError("could not draw a pass within the off-nadir limits")
    out = []
    for y in ys:
        w = x * across + y * along  # horizontal (satellite - target) / height
        out.append((math.degrees(math.atan(float(np.hypot(*w)))),
                    math.degrees(math.atan2(float(w[0]), float(w[1]))) % 360.0))
    return out


def plan_acquisitions(options) -> MultiDatePlan:
    """Dates, sun, passes, view angles and radiometry of a multi-date scene (``options`` a
    SynthOptions with ``acquisitions >= 1``)."""
    n_acq = options.acquisitions
    counts = options.views_per_acquisition or split_views(
        np.random.default_rng([options.seed, _STREAM_SPLIT]), options.n_views, n_acq)
    days = _draw_days(options, np.random.default_rng([options.seed, _STREAM_DATES]))
    lon, lat = options.location
    effects = set(options.date_effects)
    prng = np.random.default_rng([options.seed, _STREAM_PASSES])
    rrng = np.random.default_rng([options.seed, _STREAM_RADIOMETRY])
    acqs, views = [], []
    first = 0
    for a, (m, (day, _hour, when)) in enumerate(zip(counts, days)):
        if "sun" in effects:
            el, az = solar_position(lon=lon, lat=lat, when=when)
            el, az = round(el, 1), round(az, 1) % 360.0
        else:
            el, az = options.sun_elevation_deg, options.sun_azimuth_deg
        heading = (options.orbit_azimuth_deg + prng.uniform(-HEADING_SPREAD_DEG, HEADING_SPREAD_DEG)) % 360.0
        angles = _draw_pass(prng, m, heading, options.max_off_nadir_deg)
        if options.off_nadir_deg:  # explicit views: their angles, and the options' heading
            angles = list(zip(options.off_nadir_deg[first:first + m], options.azimuth_deg[first:first + m]))
            heading = options.orbit_azimuth_deg
        if "vegetation" in effects:
            density, leaf = leaf_state(day.timetuple().tm_yday, lat)
        else:
            density, leaf = 1.0, 1.0
        ground = float(rrng.uniform(*GROUND_FACTOR_RANGE)) if "ground" in effects else 1.0
        if "radiometry" in effects:
            gain0 = rrng.uniform(*GAIN_RANGE)
            offset0 = rrng.uniform(*OFFSET_RANGE_DN)
            gamma0 = rrng.uniform(*GAMMA_RANGE)
        for k, (th, saz) in enumerate(angles):
            if "radiometry" in effects:
                gain = float(gain0 * (1.0 + rrng.uniform(-VIEW_GAIN_SPREAD, VIEW_GAIN_SPREAD)))
                offset = float(offset0 + rrng.uniform(-VIEW_OFFSET_SPREAD_DN, VIEW_OFFSET_SPREAD_DN))
                gamma = float(gamma0)
            else:
                gain, offset, gamma = 1.0, 0.0, 1.0
            views.append(ViewPlan(acquisition=a, date_time=iso_utc(when + dt.timedelta(seconds=PASS_STEP_S * k)),
                                  off_nadir_deg=float(th), azimuth_deg=float(saz), orbit_azimuth_deg=float(heading),
                                  gain=gain, offset_dn=offset, gamma=gamma))
        acqs.append(Acquisition(index=a, date_time=iso_utc(when), sun_elevation_deg=float(el),
                                sun_azimuth_deg=float(az), orbit_azimuth_deg=float(heading),
                                views=tuple(range(first, first + m)), leaf_density=float(density),
                                leaf_factor=float(leaf), ground_factor=ground))
        first += m
    return MultiDatePlan(acquisitions=tuple(acqs), views=tuple(views))


# ---------------------------------------------------------------------------------------------
# Radiometry
# ---------------------------------------------------------------------------------------------
def radiometric_dn(radiance: np.ndarray, *, gain: float, offset_dn: float, gamma: float,
                   dn_per_radiance: float, dn_max: int) -> np.ndarray:
    """Noise-free DN (float64) of a view with the given radiometry (see the module docstring)."""
    x = np.clip(radiance * (dn_per_radiance / dn_max), 0.0, None)
    return gain * dn_max * x ** gamma + offset_dn


# ---------------------------------------------------------------------------------------------
# What changes with the date
# ---------------------------------------------------------------------------------------------
def _copy_grid(grid: SurfaceGrid) -> SurfaceGrid:
    return dataclasses.replace(grid, top=grid.top.copy(), slope_e=grid.slope_e.copy(),
                               slope_n=grid.slope_n.copy(), material=grid.material.copy(),
                               albedo=grid.albedo.copy(), wall_albedo=grid.wall_albedo.copy(),
                               leafiness=None if grid.leafiness is None else grid.leafiness.copy())


def _window(grid: SurfaceGrid, e0: float, n0: float, e1: float, n1: float) -> tuple[slice, slice]:
    """Slices of the cells whose centres lie in [e0, e1) x [n0, n1) (clipped to the grid)."""
    c = grid.cell_m
    ny, nx = grid.top.shape
    i0 = int(np.clip(math.ceil((e0 - grid.e_min) / c - 0.5), 0, nx))
    i1 = int(np.clip(math.ceil((e1 - grid.e_min) / c - 0.5), 0, nx))
    j0 = int(np.clip(math.ceil((n0 - grid.n_min) / c - 0.5), 0, ny))
    j1 = int(np.clip(math.ceil((n1 - grid.n_min) / c - 0.5), 0, ny))
    return slice(j0, j1), slice(i0, i1)


def _tree_of_cells(grid: SurfaceGrid) -> np.ndarray:
    """(K,) index into ``grid.trees`` of each crown cell of ``grid.under_trees`` (the last tree
    drawn whose crown covers the cell, as the crowns were drawn; -1 where none is found)."""
    ut = grid.under_trees
    ids = np.full(grid.top.shape, -1, np.int32)
    ec, nc = grid.cell_centres()
    for t, (x, y, radius, *_rest) in enumerate(grid.trees):
        win = _window(grid, x - radius, y - radius, x + radius, y + radius)
        if win[0].start >= win[0].stop or win[1].start >= win[1].stop:
            continue
        q = (ec[win[1]][None, :] - x) ** 2 + (nc[win[0]][:, None] - y) ** 2
        sub = ids[win]
        sub[q < radius ** 2] = t
    return ids[ut.j, ut.i]


def _change_vegetation(g: SurfaceGrid, truth: SurfaceGrid, acq: Acquisition, seed: int) -> None:
    ut = truth.under_trees
    if ut is None or ut.j.size == 0:
        return
    rng = np.random.default_rng([seed, _STREAM_VEGETATION + acq.index])
    evergreen = np.random.default_rng([seed, _STREAM_EVERGREEN]).uniform(size=len(truth.trees)) < EVERGREEN_SHARE
    tree = _tree_of_cells(truth)
    deciduous = (tree >= 0) & ~evergreen[np.maximum(tree, 0)]
    j, i = ut.j, ut.i
    # The leaves' fine texture of this date.
    c = g.cell_m
    box = (slice(int(j.min()), int(j.max()) + 1), slice(int(i.min()), int(i.max()) + 1))
    shape = (box[0].stop - box[0].start, box[1].stop - box[1].start)
    jj, ii = j - box[0].start, i - box[1].start
    leaves = fractal_noise(rng, shape, (1.0 / c, 0.5 / c))[jj, ii]
    g.albedo[j, i] = np.clip(g.albedo[j, i] + LEAF_TEXTURE_CHANGE * leaves, 0.02, 0.4).astype(np.float32)
    if acq.leaf_factor != 1.0 and acq.leaf_factor > 0.0:
        g.albedo[j[deciduous], i[deciduous]] = np.clip(
            g.albedo[j[deciduous], i[deciduous]] * acq.leaf_factor, 0.02, 0.4).astype(np.float32)
    if g.leafiness is None:
        g.leafiness = np.ones(g.top.shape, np.float32)
    if acq.leaf_factor == AUTUMN_LEAF_FACTOR:  # the deciduous leaves turning
        g.leafiness[j[deciduous], i[deciduous]] = AUTUMN_LEAFINESS
    if acq.leaf_density < 1.0 and np.any(deciduous):
        holes = fractal_noise(rng, shape, (CROWN_HOLE_SCALE_M / c, 0.5 * CROWN_HOLE_SCALE_M / c))[jj, ii]
        limit = np.quantile(holes[deciduous], 1.0 - acq.leaf_density)
        hole = deciduous & (holes < limit)
        h = np.nonzero(hole)[0]
        g.top[j[h], i[h]] = ut.top[h]
        g.slope_e[j[h], i[h]] = ut.slope_e[h]
        g.slope_n[j[h], i[h]] = ut.slope_n[h]
        g.material[j[h], i[h]] = ut.material[h]
        g.albedo[j[h], i[h]] = ut.albedo[h]
        g.wall_albedo[j[h], i[h]] = ut.wall_albedo[h]
        if acq.leaf_factor == 0.0:  # bare branches on the cells that remain
            b = np.nonzero(deciduous & ~hole)[0]
            g.albedo[j[b], i[b]] = np.clip(BRANCH_ALBEDO + BRANCH_TEXTURE * leaves[b], 0.02, 0.4).astype(np.float32)
            g.wall_albedo[j[b], i[b]] = g.albedo[j[b], i[b]]
            g.leafiness[j[b], i[b]] = 0.0


def _change_materials(g: SurfaceGrid, truth: SurfaceGrid, acq: Acquisition, seed: int) -> None:
    rng = np.random.default_rng([seed, _STREAM_MATERIALS + acq.index])
    lo, hi = MATERIAL_FACTOR_RANGE
    for b in truth.buildings:
        roof, facade = np.clip(np.exp(rng.normal(0.0, MATERIAL_LOG_SIGMA, 2)), lo, hi)
        win = _window(g, b.e0, b.n0, b.e1, b.n1)
        m = g.material[win]
        built = (m == ROOF) | (m == ROOF_GABLE) | (m == ROOF_BOX)
        g.albedo[win] = np.where(built, np.clip(g.albedo[win] * roof, 0.02, 0.95), g.albedo[win])
        g.wall_albedo[win] = np.where(built, np.clip(g.wall_albedo[win] * facade, 0.02, 0.95), g.wall_albedo[win])


def _change_ground(g: SurfaceGrid, acq: Acquisition, seed: int) -> None:
    rng = np.random.default_rng([seed, _STREAM_GROUND + acq.index])
    c = g.cell_m
    change = fractal_noise(rng, g.top.shape, tuple(s / c for s in GROUND_CHANGE_SCALES_M))
    grass = g.material == GROUND
    alb = acq.ground_factor * g.albedo[grass] + GROUND_CHANGE_AMPLITUDE * change[grass]
    g.albedo[grass] = np.clip(alb, 0.04, 0.5).astype(np.float32)


def _paint(rng: np.random.Generator) -> float:
    r = rng.uniform()
    acc = 0.0
    for share, (lo, hi) in PAINTS:
        acc += share
        if r < acc:
            return float(rng.uniform(lo, hi))
    return float(rng.uniform(*PAINTS[-1][1]))


def _put_box(g: SurfaceGrid, win, top: float, albedo, wall_albedo: float, material: int) -> None:
    g.top[win] = top
    g.slope_e[win] = 0.0
    g.slope_n[win] = 0.0
    g.material[win] = material
    g.albedo[win] = albedo
    g.wall_albedo[win] = wall_albedo


def _mm(v: float) -> float:
    """Round to the millimetre (or 1e-3 albedo): transients are recorded so, and drawn as recorded."""
    return round(float(v), 3)


def _vehicle(g: SurfaceGrid, rng: np.random.Generator, centre: tuple[float, float], along_n: bool,
             out: list) -> None:
    """Draw a vehicle of a random kind centred on ``centre`` (ENU m), its length along north
    (``along_n``) or east, if its whole footprint is free road."""
    r = rng.uniform()
    acc = 0.0
    for kind, share, length_r, width_r, height_r in VEHICLES:
        acc += share
        if r < acc:
            break
    length, width, height = _mm(rng.uniform(*length_r)), _mm(rng.uniform(*width_r)), _mm(rng.uniform(*height_r))
    paint = _mm(_paint(rng))
    forward = rng.uniform() < 0.5
    x, y = centre
    hl, hw = (width / 2, length / 2) if along_n else (length / 2, width / 2)
    e0, n0, e1, n1 = _mm(x - hl), _mm(y - hw), _mm(x + hl), _mm(y + hw)
    win = _window(g, e0, n0, e1, n1)
    if win[0].start >= win[0].stop or win[1].start >= win[1].stop or not np.all(g.material[win] == ROAD):
        return
    base = float(np.max(g.top[win]))
    if kind != "car":
        _put_box(g, win, base + height, paint, 0.9 * paint, VEHICLE)
    else:
        body = rng.uniform(*CAR_BODY_M)
        _put_box(g, win, base + body, paint, 0.9 * paint, VEHICLE)
        # The cabin: from 25% to 80% of the length (towards the back), 0.2 m in from the sides,
        # its windshield and rear window dark.
        s0, s1 = (0.25, 0.80) if forward else (0.20, 0.75)
        if along_n:
            cab = _window(g, e0 + 0.2, n0 + s0 * length, e1 - 0.2, n0 + s1 * length)
        else:
            cab = _window(g, e0 + s0 * length, n0 + 0.2, e0 + s1 * length, n1 - 0.2)
        if cab[0].start < cab[0].stop and cab[1].start < cab[1].stop:
            _put_box(g, cab, base + height, paint, WINDSHIELD_ALBEDO, VEHICLE)
            ends = g.albedo[cab]
            if along_n:
                ends[:2, :] = WINDSHIELD_ALBEDO
                ends[-2:, :] = WINDSHIELD_ALBEDO
            else:
                ends[:, :2] = WINDSHIELD_ALBEDO
                ends[:, -2:] = WINDSHIELD_ALBEDO
    out.append({"kind": str(kind), "e0": e0, "n0": n0, "e1": e1, "n1": n1, "top_u": base + height,
                "height_m": height, "albedo": paint})


def _place_transients(g: SurfaceGrid, truth: SurfaceGrid, acq: Acquisition, seed: int) -> list[dict]:
    rng = np.random.default_rng([seed, _STREAM_TRANSIENTS + acq.index])
    out: list[dict] = []
    occupancy = rng.uniform(*PARK_OCCUPANCY)
    drive = rng.uniform(*DRIVE_CHANCE)
    roads_e, widths_e, roads_n, widths_n = truth.roads
    for along_n, centres, widths, lo, hi in ((True, roads_e, widths_e, g.n_min, g.n_max),
                                             (False, roads_n, widths_n, g.e_min, g.e_max)):
        for c, w in zip(centres, widths):
            for side in (-1.0, 1.0):
                park = c + side * (w / 2 - PARK_LANE_FROM_KERB_M)
                lane = c + side * w / 4
                s = lo + rng.uniform(0.0, PARK_SPACING_M[1])
                while s < hi:
                    if rng.uniform() < occupancy:
                        _vehicle(g, rng, (park, s) if along_n else (s, park), along_n, out)
                    s += rng.uniform(*PARK_SPACING_M)
                s = lo + rng.uniform(0.0, DRIVE_SPACING_M)
                while s < hi:
                    if rng.uniform() < drive:
                        _vehicle(g, rng, (lane, s) if along_n else (s, lane), along_n, out)
                    s += DRIVE_SPACING_M
    # Market stalls on the plazas.
    plaza_j, plaza_i = np.nonzero(g.material == PLAZA)
    if plaza_j.size and rng.uniform() < MARKET_CHANCE:
        area = plaza_j.size * g.cell_m ** 2
        ec, nc = g.cell_centres()
        for _ in range(int(area / PLAZA_M2_PER_STALL)):
            k = int(rng.integers(plaza_j.size))
            half = _mm(rng.uniform(*STALL_SIDE_M)) / 2
            x, y = ec[plaza_i[k]], nc[plaza_j[k]]
            e0, n0, e1, n1 = _mm(x - half), _mm(y - half), _mm(x + half), _mm(y + half)
            win = _window(g, e0, n0, e1, n1)
            if win[0].start >= win[0].stop or win[1].start >= win[1].stop or not np.all(g.material[win] == PLAZA):
                continue
            height = _mm(rng.uniform(*STALL_HEIGHT_M))
            albedo = _mm(rng.uniform(*STALL_ALBEDO))
            top = float(np.max(g.top[win])) + height
            _put_box(g, win, top, albedo, 0.8 * albedo, STALL)
            out.append({"kind": "stall", "e0": e0, "n0": n0, "e1": e1, "n1": n1, "top_u": top,
                        "height_m": height, "albedo": albedo})
    for t in out:  # the top as recorded (mm), not as drawn (float64 sums): tests allow for it
        t["top_u"] = _mm(t["top_u"])
    return out


def acquisition_surface(truth: SurfaceGrid, acq: Acquisition, *, seed: int,
                        effects: Sequence[str]) -> tuple[SurfaceGrid, list[dict]]:
    """The surface as it looks on ``acq``'s date: a copy of the truth surface with this date's
    materials, vegetation, ground and transients (those of ``effects``), and the transients
    drawn (dicts: kind, footprint e0, n0, e1, n1 and top height top_u in ENU metres, height_m
    above the road, albedo; mm-rounded). The truth is not changed."""
    g = _copy_grid(truth)
    if "materials" in effects:
        _change_materials(g, truth, acq, seed)
    if "vegetation" in effects:
        _change_vegetation(g, truth, acq, seed)
    if "ground" in effects:
        _change_ground(g, acq, seed)
    transients = _place_transients(g, truth, acq, seed) if "transients" in effects else []
    return g, transients


# ---------------------------------------------------------------------------------------------
# Metadata
# ---------------------------------------------------------------------------------------------
TAG_GDAL_METADATA = 42112


def gdal_metadata_xml(*, date_time: str, sun_azimuth_deg: float, sun_elevation_deg: float,
                      satellite: str = SATELLITE_ID) -> str:
    """GDAL's ``GDALMetadata`` XML of a view's IMAGERY domain (date-time, sun angles, satellite)."""
    items = (("ACQUISITIONDATETIME", date_time), ("SUN_AZIMUTH", f"{sun_azimuth_deg:.1f}"),
             ("SUN_ELEVATION", f"{sun_elevation_deg:.1f}"), ("SATELLITEID", satellite))
    body = "".join(f'<Item name="{k}" domain="IMAGERY">{v}</Item>' for k, v in items)
    return f"<GDALMetadata>{body}</GDALMetadata>"


def gdal_metadata_extratag(xml: str) -> tuple:
    """The GDAL_METADATA tag for ``tifffile.imwrite(extratags=[...])``."""
    return (TAG_GDAL_METADATA, "s", 0, xml, True)


def imd_text(*, date_time: str, rows: int, cols: int, sun_azimuth_deg: float, sun_elevation_deg: float,
             sat_azimuth_deg: float, sat_elevation_deg: float, off_nadir_deg: float, in_track_deg: float,
             cross_track_deg: float, gsd_m: float, catalog_id: str, satellite: str = SATELLITE_ID) -> str:
    """A DigitalGlobe/Maxar-style ``.IMD`` (``key = value;`` lines, ``BEGIN_GROUP``/``END_GROUP``)
    with the view's time, size, sun and satellite angles in group IMAGE_1."""
    when = parse_iso_utc(date_time)
    first_line = when.strftime("%Y-%m-%dT%H:%M:%S.000000Z")
    lines = [
        'version = "28.4";',
        f"generationTime = {(when + dt.timedelta(days=1)).strftime('%Y-%m-%dT%H:%M:%S.000000Z')};",
        f'productOrderId = "{catalog_id}_P001";',
        f'productCatalogId = "{catalog_id}";',
        'imageDescriptor = "ORStandard2A";',
        'bandId = "P";',
        'panSharpenAlgorithm = "None";',
        f"numRows = {rows};",
        f"numColumns = {cols};",
        'productLevel = "LV1B";',
        'productType = "Basic";',
        "numberOfLooks = 1;",
        'radiometricLevel = "Corrected";',
        "bitsPerPixel = 16;",
        'compressionType = "None";',
        "BEGIN_GROUP = IMAGE_1",
        f'\tsatId = "{satellite}";',
        f'\tCatId = "{catalog_id}";',
        '\tSCANDIRECTION = "Forward";',
        f"\tfirstLineTime = {first_line};",
        f"\tmeanCollectedGSD = {gsd_m:.3f};",
        f"\tmeanSunAz = {sun_azimuth_deg:.1f};",
        f"\tmeanSunEl = {sun_elevation_deg:.1f};",
        f"\tmeanSatAz = {sat_azimuth_deg:.1f};",
        f"\tmeanSatEl = {sat_elevation_deg:.1f};",
        f"\tmeanInTrackViewAngle = {in_track_deg:.1f};",
        f"\tmeanCrossTrackViewAngle = {cross_track_deg:.1f};",
        f"\tmeanOffNadirViewAngle = {off_nadir_deg:.1f};",
        "\tcloudCover = 0.000;",
        "END_GROUP = IMAGE_1",
        "END;",
    ]
    return "\n".join(lines) + "\n"


def write_imd(path: str | os.PathLike, text: str) -> None:
    """Write an ``.IMD`` file atomically."""
    with atomic_output(Path(path)) as tmp:
        Path(tmp).write_text(text, encoding="ascii")


def track_angles(camera) -> tuple[float, float]:
    """(in-track, cross-track) view angles in degrees of a pushbroom camera's view of the scene
    centre: the angles of the line of sight from the vertical, in the plane along the track and
    across it (positive: the satellite ahead of / right of the target)."""
    col, row = camera.project(e=0.0, n=0.0, u=0.0)
    w = camera.position(row=row)
    v = np.asarray(camera.velocity)
    across = np.array([v[1], -v[0], 0.0])
    return (math.degrees(math.atan2(float(w @ v), float(w[2]))),
            math.degrees(math.atan2(float(w @ across), float(w[2]))))
