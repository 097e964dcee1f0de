"""``satsweep synth``: synthetic satellite views of a known surface, with exact ground truth.

``generate_scene(out_dir, SynthOptions(...))`` writes into ``out_dir``:

* ``view_NN.tif``: single-band uint16 (12-bit values) images (``product="rgb8"``: 8-bit RGB,
  as pansharpened deliveries are, see :func:`to_rgb8`) of a seeded town, each seen by a
  linear pushbroom satellite (``satsweep.synth.pushbroom``) from its own off-nadir angle and azimuth,
  rendered by exact ray casting (first surface point along each line of sight) with
  ``supersampling**2`` rays per pixel, Lambertian shading under a sun with cast shadows, and
  Gaussian noise. The RPC is in TIFF tag 50844 and in the sidecar ``view_NN_RPC.TXT``.
* ``truth_dsm.tif``: the true surface as a float32 GeoTIFF on the UTM grid of the scene
  (``dsm_resolution_m`` cells aligned to multiples of the resolution, covering the AOI; each cell
  holds the maximum ellipsoidal altitude of the surface over the cell, taken over a 5x5 grid of
  points that includes the cell centre; nodata NaN).
* ``scene.json``: the AOI (lon/lat box and GeoJSON), the altitude range, each view's file,
  angles, pointing bias and RPC fit residual, the base-to-height ratio of each pair, the
  options, the exact cameras and the building list.

RPC and pointing bias. Each view's RPC is a least-squares fit (``satsweep.synth.rpcfit``) of its
pushbroom camera over the scene's ground cube; its residual is reported (a few 1e-9 px). A view
with pointing bias ``b = (bx, by)`` pixels was rendered with the true camera, but the RPC written
beside it is the fit of the true camera *shifted by -b*: a ground point ``X`` appears in the
image at ``RPC(X) + b``. The first view has no bias; the others draw theirs uniformly in
``[-bias_px, bias_px]^2``. A bundle adjustment should find the corrections ``+b``.

Multi-date scenes (``acquisitions = N >= 1``, ``satsweep.synth.multidate``): the views are
grouped into N acquisitions (passes of 1-3 views) on N dates; each date has its own sun (shading
and cast shadows), trees (leaf-on to leafless), grass, cars and market stalls, radiometry (gain,
offset, gamma per view) and pass geometry (azimuths all around, off-nadir up to
``max_off_nadir_deg``), and ``large_bias_px`` adds pointing errors of tens of pixels to some
views. The truth surface and ``truth_dsm.tif`` are those of the single-date scene of the same
town: the transients and the seasons are in the images only. Beside each view go
``view_NN.IMD`` (DigitalGlobe/Maxar style: date-time, sun and satellite angles) and, in the TIFF,
the GDAL_METADATA tag (date-time, sun angles, satellite), unless ``write_metadata`` is False;
``scene.json`` records each view's acquisition, date-time, sun and satellite angles, radiometry
and bias either way, and each acquisition's date, sun, season and transients.

Every random draw comes from ``seed``: the same options give the same files. The default
options (one date) give the same files as before the multi-date scenes existed.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import math
import os
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from satsweep import __version__
from satsweep.errors import InputError, OptionsError
from satsweep.geometry.aoi import AOI
from satsweep.geometry.geodesy import ENUFrame, utm_to_lonlat
from satsweep.geometry.rpc import RPCModel
from satsweep.geometry.rpc_formats import rpc_tiff_extratag, write_rpc_txt
from satsweep.io.atomic import atomic_output, check_output_dir
from satsweep.io.geotiff import write_geotiff, write_tiff
from satsweep.io.images import LUMA_WEIGHTS
from satsweep.options import Options
from satsweep.products.grid import DSMGrid, dsm_grid_for_aoi
from satsweep.synth.multidate import (
    DATE_EFFECTS,
    Acquisition,
    MultiDatePlan,
    acquisition_surface,
    gdal_metadata_extratag,
    gdal_metadata_xml,
    imd_text,
    plan_acquisitions,
    radiometric_dn,
    track_angles,
    write_imd,
)
from satsweep.synth.pushbroom import PushbroomCamera, base_to_height
from satsweep.synth.rpcfit import RPCFitResidual, cube_grid, fit_rpc, rpc_residual
from satsweep.synth.town import (
    GROUND_RELIEF_M,
    MAX_BUILDING_M,
    RayCaster,
    ShadowMap,
    SurfaceGrid,
    build_surface,
    greenness,
    shade,
    sun_vector,
)
from satsweep.threads import map_in_threads

SCENE_FILE = "scene.json"
TRUTH_DSM_FILE = "truth_dsm.tif"
SCENE_FORMAT = "satsweep-synth-scene"
SCENE_VERSION = 1

# Viewing geometry of the built-in views: (off-nadir angle, satellite azimuth) in degrees. The
# first three give base-to-height ratios 0.20, 0.25 and 0.43 (all pairs within 0.1 .. 0.5).
# Views beyond the table repeat it with the azimuth turned by 37 degrees per round.
DEFAULT_VIEW_ANGLES: tuple[tuple[float, float], ...] = (
    (10.0, 20.0), (4.0, 120.0), (14.0, 200.0), (9.0, 290.0),
    (16.0, 75.0), (7.0, 250.0), (12.0, 160.0), (18.0, 330.0),
)
DEFAULT_AZIMUTH_TURN_DEG = 37.0

# Nominal height range of the surface relative to the scene centre's ground (ENU up, m): ground
# relief, plus the tallest building. Cameras, the surface grid and the RPC cube cover it.
NOMINAL_Z_RANGE = (-GROUND_RELIEF_M - 1.0, GROUND_RELIEF_M + MAX_BUILDING_M + 1.0)
# Extra ground around the views' footprints on the surface grid (m).
WORLD_MARGIN_M = 4.0
# The AOI stays this many pixels inside every image, at every nominal height.
AOI_MARGIN_PX = 4.0
# DN per unit radiance (albedo x irradiance): bright roofs reach about 3000 of 4095 (12 bits).
DN_PER_RADIANCE = 4000.0
DN_MAX = 4095
# Sampling of the RPC fit over the ground cube (lon x lat x alt) and of its check.
RPC_FIT_GRID = (15, 15, 7)
# Largest SynthOptions.rpc_height_scale_m: Planet's and SkySat's RPCs span 2.5-10 km, but a cubic
# fitted over more than a few kilometres of a pushbroom's heights would no longer be exact
# within the scene (the fit's residual, reported per view, is what tells).
RPC_HEIGHT_SCALE_MAX_M = 2000.0
RPC_CHECK_POINTS = 2000
# Sub-samples per DSM cell side for the per-cell maximum (odd: the centre is one of them).
DSM_SUBSAMPLES = 5
# Rays cast at once while rendering (bounds memory to a few hundred MB).
RENDER_CHUNK_RAYS = 1 << 17
# Threads rendering chunks at once (numpy releases the GIL in the ray walk: 1.7x on 2 cores).
RENDER_THREADS = 4

RADIOMETRY_MODEL = (
    "DN = clip(round(gain * DN_MAX * (x / DN_MAX) ** gamma + offset_dn + noise), 0, DN_MAX) with "
    "x = radiance * DN_PER_RADIANCE (the single-date scene's noise-free DN), DN_MAX = 4095"
)
ACQUISITIONS_NOTE = (
    "each acquisition's surface is the truth surface with that date's roof and facade brightness, "
    "trees, grass and transients (vehicles, stalls: footprint and top in ENU metres, height above "
    "the road); the truth DSM has none of them"
)
BIAS_CONVENTION = (
    "image content of ground point X is at RPC(X) + bias_px (col, row): the image was rendered "
    "with the true camera and the RPC is the fit of the true camera shifted by -bias_px"
)


def parse_location(text: str) -> tuple[float, float]:
    """``LON,LAT`` (degrees) as a scene centre for ``SynthOptions.location``; OptionsError
    naming the text otherwise (the ranges are SynthOptions' check)."""
    parts = str(text).split(",")
    try:
        lon, lat = (float(v) for v in parts)
    except ValueError:
        raise OptionsError(f"--location {text}: expected LON,LAT in degrees") from None
    return lon, lat


@dataclasses.dataclass(frozen=True)
class SynthOptions(Options):
    """Options of a synthetic scene. Angles in degrees, lengths in metres, images in pixels."""

    seed: int = 0  # random seed: the same options give the same scene
    n_views: int = 3  # number of views
    size_px: int = 512  # width and height of every view
    gsd_m: float = 0.5  # ground sample distance at the scene centre (horizontal plane)
    bias_px: float = 0.0  # max |pointing bias| per axis; view 0 has none, others uniform draws
    location: tuple[float, float] = (2.3488, 48.8534)  # (lon, lat) of the scene centre
    ground_alt_m: float = 100.0  # height of the ground at the centre above the WGS84 ellipsoid
    orbit_height_m: float = 694000.0  # height of the orbit line above the scene
    orbit_azimuth_deg: float = 192.0  # heading of the satellite's motion (descending orbit); multi-date: the mean
    off_nadir_deg: tuple[float, ...] = ()  # per view; () = built-in DEFAULT_VIEW_ANGLES (multi-date: drawn)
    azimuth_deg: tuple[float, ...] = ()  # satellite azimuth per view; () = built-in (multi-date: drawn)
    sun_elevation_deg: float = 55.0  # sun height above the horizon (multi-date: only without the "sun" effect)
    sun_azimuth_deg: float = 155.0  # sun azimuth, clockwise from north (likewise)
    supersampling: int = 2  # rays per pixel side (2 -> 2x2 rays averaged per pixel)
    noise_dn: float = 6.0  # standard deviation of the Gaussian image noise (DN)
    cell_m: float = 0.25  # cell size of the true surface grid
    dsm_resolution_m: float = 0.5  # cell size of truth_dsm.tif (UTM metres)
    # Multi-date scenes (satsweep.synth.multidate). 0: one date, every view under the same sun,
    # season, cars and radiometry (the scenes of the benchmarks); N >= 1: the views grouped into
    # N acquisitions (passes of 1-3 views) on N different dates, each with its own sun, trees,
    # grass, cars, radiometry and pass geometry (angles drawn unless off_nadir_deg is given).
    acquisitions: int = 0
    views_per_acquisition: tuple[int, ...] = ()  # views of each acquisition (1-3 each, summing to n_views); () = drawn
    start_date: str = "2019-01-01"  # multi-date: first day (ISO) of the period the dates are drawn in
    date_span_days: int = 395  # multi-date: length of that period in days (13 months)
    min_sun_elevation_deg: float = 25.0  # multi-date: days whose sun stays lower at the overpass are not drawn
    max_off_nadir_deg: float = 30.0  # multi-date: largest drawn off-nadir angle (azimuths all around)
    # multi-date: what changes from one date to another (any of multidate.DATE_EFFECTS); the
    # others stay as on a single-date scene
    date_effects: tuple[str, ...] = ("sun", "materials", "vegetation", "ground", "transients", "radiometry")
    large_bias_px: float = 0.0  # largest extra pointing error (px, any direction) of some views, added to bias_px
    large_bias_fraction: float = 0.25  # share of the views after view 0 given a large error (at least one)
    # .IMD sidecar and GDAL_METADATA tag with each view's date, sun and satellite angles: None =
    # in multi-date scenes (single-date scenes have no dates; True is refused there)
    write_metadata: bool | None = None
    # What each view's image is: "dn16", 12-bit digital numbers in a uint16 band (a sensor's
    # radiometry); "rgb8", an 8-bit RGB delivery as pansharpened products are, each image
    # stretched to its own range (satsweep.synth.scene.to_rgb8)
    product: str = "dn16"
    # Half the span of altitudes (m) each view's RPC is fitted over, about the middle of the
    # scene's nominal heights: its HEIGHT_SCALE. Real deliveries' RPCs span a kilometre or more
    # (WorldView-2/3, Pleiades: HEIGHT_SCALE 500 m), so a reconstruction given neither
    # --alt-range nor --dem crops whole views and fits its first cameras over that span; 0: the
    # scene's own heights (ground relief to the tallest roof, about 70 m: the benchmarks' scenes
    # until the forty-ninth session, docs/measurements.md)
    rpc_height_scale_m: float = 0.0

    def check(self) -> None:
        self._require(self.n_views >= 1, "n_views", "need at least one view")
        self._require(self.n_views <= 64, "n_views", "at most 64 views")
        self._require(16 <= self.size_px <= 8192, "size_px", "must lie in 16 .. 8192 pixels")
        self._require(0.05 <= self.gsd_m <= 5.0, "gsd_m", "must lie in 0.05 .. 5 m")
        self._require(math.isfinite(self.bias_px) and 0.0 <= self.bias_px <= 50.0, "bias_px",
                      "must lie in 0 .. 50 pixels")
        lon, lat = self.location
        self._require(math.isfinite(lon) and -180.0 <= lon <= 180.0, "location", "longitude must lie in [-180, 180]")
        self._require(math.isfinite(lat) and -80.0 <= lat <= 84.0, "location",
                      "latitude must lie in [-80, 84] (the UTM range)")
        self._require(math.isfinite(self.ground_alt_m) and -500.0 <= self.ground_alt_m <= 9000.0,
                      "ground_alt_m", "must lie in -500 .. 9000 m")
        self._require(100e3 <= self.orbit_height_m <= 2000e3, "orbit_height_m", "must lie in 100 .. 2000 km")
        self._require(math.isfinite(self.orbit_azimuth_deg), "orbit_azimuth_deg", "must be finite")
        for name in ("off_nadir_deg", "azimuth_deg"):
            value = getattr(self, name)
            self._require(len(value) in (0, self.n_views), name,
                          f"give one angle per view ({self.n_views}) or none for the built-in views")
            self._require(all(math.isfinite(v) for v in value), name, "angles must be finite")
        self._require(len(self.off_nadir_deg) == len(self.azimuth_deg), "azimuth_deg",
                      "give off_nadir_deg and azimuth_deg together")
        self._require(all(0.0 <= v <= 30.0 for v in self.off_nadir_deg), "off_nadir_deg",
                      "off-nadir angles must lie in 0 .. 30 degrees")
        self._require(5.0 <= self.sun_elevation_deg <= 90.0, "sun_elevation_deg", "must lie in 5 .. 90 degrees")
        self._require(math.isfinite(self.sun_azimuth_deg), "sun_azimuth_deg", "must be finite")
        self._require(2 <= self.supersampling <= 8, "supersampling", "must lie in 2 .. 8 (rays per pixel side)")
        self._require(math.isfinite(self.noise_dn) and 0.0 <= self.noise_dn <= 500.0, "noise_dn",
                      "must lie in 0 .. 500 DN")
        self._require(0.02 <= self.cell_m <= 0.25, "cell_m", "must lie in 0.02 .. 0.25 m")
        self._require(self.cell_m <= self.gsd_m / 2.0 + 1e-12, "cell_m",
                      f"must be at most half the GSD ({self.gsd_m / 2:g} m)")
        self._require(0.1 <= self.dsm_resolution_m <= 10.0, "dsm_resolution_m", "must lie in 0.1 .. 10 m")
        self._require(math.isfinite(self.rpc_height_scale_m)
                      and 0.0 <= self.rpc_height_scale_m <= RPC_HEIGHT_SCALE_MAX_M,
                      "rpc_height_scale_m", f"must lie in 0 .. {RPC_HEIGHT_SCALE_MAX_M:g} m (0: the "
                      "scene's own heights)")
        self._check_multidate()

    def _check_multidate(self) -> None:
        n = self.acquisitions
        self._require(0 <= n <= 64, "acquisitions", "must lie in 0 .. 64 (0: a single-date scene)")
        if n:
            self._require(n <= self.n_views <= 3 * n, "acquisitions",
                          f"{n} acquisitions of 1 to 3 views need n_views in {n} .. {3 * n} (n_views = {self.n_views})")
        self._require(not self.views_per_acquisition or len(self.views_per_acquisition) == n,
                      "views_per_acquisition", f"give one count per acquisition ({n}) or none")
        self._require(all(1 <= v <= 3 for v in self.views_per_acquisition), "views_per_acquisition",
                      "each acquisition has 1 to 3 views")
        self._require(not self.views_per_acquisition or sum(self.views_per_acquisition) == self.n_views,
                      "views_per_acquisition", f"the counts must add up to n_views ({self.n_views})")
        try:
            dt.date.fromisoformat(self.start_date)
            ok = len(self.start_date) == 10
        except ValueError:
            ok = False
        self._require(ok, "start_date", "expected an ISO date YYYY-MM-DD")
        self._require(1 <= self.date_span_days <= 3660, "date_span_days", "must lie in 1 .. 3660 days")
        self._require(self.date_span_days >= n, "date_span_days",
                      f"each of the {n} acquisitions needs a day of its own")
        self._require(math.isfinite(self.min_sun_elevation_deg) and 5.0 <= self.min_sun_elevation_deg <= 80.0,
                      "min_sun_elevation_deg", "must lie in 5 .. 80 degrees")
        self._require(math.isfinite(self.max_off_nadir_deg) and 5.0 <= self.max_off_nadir_deg <= 40.0,
                      "max_off_nadir_deg", "must lie in 5 .. 40 degrees")
        unknown = sorted(set(self.date_effects) - set(DATE_EFFECTS))
        self._require(not unknown, "date_effects", f"unknown {', '.join(unknown)} (known: {', '.join(DATE_EFFECTS)})")
        self._require(len(set(self.date_effects)) == len(self.date_effects), "date_effects", "names repeated")
        self._require(math.isfinite(self.large_bias_px) and 0.0 <= self.large_bias_px <= 100.0, "large_bias_px",
                      "must lie in 0 .. 100 pixels")
        self._require(math.isfinite(self.large_bias_fraction) and 0.0 < self.large_bias_fraction <= 1.0,
                      "large_bias_fraction", "must lie in (0, 1]")
        self._require(not (self.write_metadata and n == 0), "write_metadata",
                      "single-date scenes have no acquisition dates: set acquisitions >= 1")
        self._require(self.product in PRODUCTS, "product", f"must be one of {', '.join(PRODUCTS)}")

    @property
    def multidate(self) -> bool:
        """Whether the views are grouped into acquisitions on different dates."""
        return self.acquisitions > 0

    def plan(self) -> MultiDatePlan | None:
        """The multi-date plan (dates, sun, passes, radiometry); None for a single-date scene."""
        return plan_acquisitions(self) if self.multidate else None

    def view_geometry(self) -> list[tuple[float, float, float]]:
        """(off-nadir, satellite azimuth, orbit heading) in degrees of every view."""
        plan = self.plan()
        if plan is not None:
            return [(v.off_nadir_deg, v.azimuth_deg, v.orbit_azimuth_deg) for v in plan.views]
        return [(th, az, self.orbit_azimuth_deg) for th, az in self.view_angles()]

    def view_angles(self) -> list[tuple[float, float]]:
        """(off-nadir, azimuth) in degrees of every view."""
        if self.multidate:
            return [(th, az) for th, az, _ in self.view_geometry()]
        if self.off_nadir_deg:
            return list(zip(self.off_nadir_deg, self.azimuth_deg))
        out = []
        for k in range(self.n_views):
            th, az = DEFAULT_VIEW_ANGLES[k % len(DEFAULT_VIEW_ANGLES)]
            turn = DEFAULT_AZIMUTH_TURN_DEG * (k // len(DEFAULT_VIEW_ANGLES))
            out.append((th, (az + turn) % 360.0))
        return out

    def view_biases(self) -> list[tuple[float, float]]:
        """Pointing bias (col, row) in pixels of every view: view 0 none, the others seeded."""
        rng = np.random.default_rng([self.seed, 7])
        draws = rng.uniform(-self.bias_px, self.bias_px, size=(self.n_views, 2))
        draws[0] = 0.0
        if self.large_bias_px > 0.0 and self.n_views > 1:
            # Large errors on a share of the views after view 0: a magnitude between half and
            # all of large_bias_px, in any direction (as one real view was off by 36 px).
            big = np.random.default_rng([self.seed, 8])
            count = max(1, int(round(self.large_bias_fraction * (self.n_views - 1))))
            which = big.choice(np.arange(1, self.n_views), size=count, replace=False)
            size = big.uniform(0.5 * self.large_bias_px, self.large_bias_px, size=count)
            angle = big.uniform(0.0, 2.0 * math.pi, size=count)
            draws[which, 0] += size * np.cos(angle)
            draws[which, 1] += size * np.sin(angle)
        return [(float(a), float(b)) for a, b in draws]

    def scene_dict(self) -> dict:
        """The options as scene.json records them: every field, except that a single-date
        scene leaves out the multi-date fields at their defaults, and every scene ``product``
        at its default (so that its scene.json is the same as before they existed)."""
        d = self.to_dict()
        if self.product == "dn16":
            del d["product"]  # (scenes from before the field existed)
        if not self.multidate:
            for f in dataclasses.fields(self):
                if f.name in MULTIDATE_FIELDS and getattr(self, f.name) == f.default:
                    del d[f.name]
        return d


# The SynthOptions fields that came with the multi-date scenes.
MULTIDATE_FIELDS = ("acquisitions", "views_per_acquisition", "start_date", "date_span_days",
                    "min_sun_elevation_deg", "max_off_nadir_deg", "date_effects", "large_bias_px",
                    "large_bias_fraction", "write_metadata")


# ---------------------------------------------------------------------------------------------
# Scene design: frame, cameras, surface extent, AOI
# ---------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class SceneDesign:
    """Everything about a scene that follows from its options before the surface is drawn."""

    frame: ENUFrame  # ENU frame at the scene centre (ground altitude)
    cameras: tuple[PushbroomCamera, ...]  # exact cameras (ENU)
    world: tuple[float, float, float, float]  # surface grid extent (e_min, n_min, e_max, n_max), m
    aoi_half_m: float  # the AOI is the ENU square [-a, a]^2 (its lon/lat box)
    z_range: tuple[float, float]  # nominal surface heights (ENU up, m) the cameras must cover


def design_scene(options: SynthOptions) -> SceneDesign:
    """Cameras, surface grid extent and AOI of a scene (deterministic in the options)."""
    lon, lat = options.location
    frame = ENUFrame(float(lon), float(lat), float(options.ground_alt_m))
    cams = tuple(
        PushbroomCamera.from_angles(
            off_nadir_deg=th, azimuth_deg=az, orbit_azimuth_deg=heading,
            orbit_height_m=options.orbit_height_m, gsd_m=options.gsd_m,
            width=options.size_px, height=options.size_px,
        )
        for th, az, heading in options.view_geometry()
    )
    z_lo, z_hi = NOMINAL_Z_RANGE
    w = options.size_px
    corners_c = np.array([-0.5, w - 0.5, w - 0.5, -0.5])
    corners_r = np.array([-0.5, -0.5, w - 0.5, w - 0.5])
    pts = [np.stack(cam.ground_point(col=corners_c, row=corners_r, u=z), axis=1)
           for cam in cams for z in (z_lo, z_hi)]
    pts = np.concatenate(pts)
    c = options.cell_m
    e_min = math.floor((pts[:, 0].min() - WORLD_MARGIN_M) / c) * c
    n_min = math.floor((pts[:, 1].min() - WORLD_MARGIN_M) / c) * c
    e_max = math.ceil((pts[:, 0].max() + WORLD_MARGIN_M) / c) * c
    n_max = math.ceil((pts[:, 1].max() + WORLD_MARGIN_M) / c) * c
    if options.multidate or options.large_bias_px > 0.0:
        # The AOI must also lie inside each image where its RPC (the camera shifted by the
        # pointing error) puts it, as real crops leave room for their pointing errors.
        margins = [AOI_MARGIN_PX + max(abs(bx), abs(by)) for bx, by in options.view_biases()]
    else:
        margins = None
    aoi_half = _aoi_half_size(cams, z_range=(z_lo, z_hi), size_px=w, margins_px=margins)
    if aoi_half < 4.0 * options.gsd_m:
        raise OptionsError(
            f"SynthOptions.size_px = {w}: too small for the views' relief displacement "
            f"(the area seen by every view is {2 * aoi_half:.1f} m wide); use a larger size or "
            "smaller off-nadir angles"
        )
    return SceneDesign(frame=frame, cameras=cams, world=(e_min, n_min, e_max, n_max),
                       aoi_half_m=aoi_half, z_range=(z_lo, z_hi))


def _aoi_half_size(cams: Sequence[PushbroomCamera], *, z_range: tuple[float, float], size_px: int,
                   margins_px: Sequence[float] | None = None) -> float:
    """Largest a such that the square [-a, a]^2 at every height in z_range is inside every view,
    AOI_MARGIN_PX (or each view's ``margins_px``) from its edges."""
    zs = np.array([z_range[0], 0.5 * (z_range[0] + z_range[1]), z_range[1]])

    def fits(a: float) -> bool:
        t = np.linspace(-a, a, 9)
        edge_e = np.concatenate([t, t, np.full(9, -a), np.full(9, a)])
        edge_n = np.concatenate([np.full(9, -a), np.full(9, a), t, t])
        e = np.repeat(edge_e[None], zs.size, 0)
        n = np.repeat(edge_n[None], zs.size, 0)
        u = np.repeat(zs[:, None], edge_e.size, 1)
        for k, cam in enumerate(cams):
            col, row = cam.project(e=e, n=n, u=u)
            margin = AOI_MARGIN_PX if margins_px is None else margins_px[k]
            lo, hi = margin, size_px - 1 - margin
            if not (np.all((col >= lo) & (col <= hi)) and np.all((row >= lo) & (row <= hi))):
                return False
        return True

    lo, hi = 0.0, 0.5 * size_px * max(c.line_step_m for c in cams) * 2.0
    if not fits(lo):
        return 0.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if fits(mid) else (lo, mid)
    return lo


def _aoi_box(frame: ENUFrame, half: float) -> AOI:
    """Lon/lat box of the ENU square [-half, half]^2 at the frame's altitude (edges sampled)."""
    t = np.linspace(-half, half, 9)
    e = np.concatenate([t, t, np.full(9, -half), np.full(9, half)])
    n = np.concatenate([np.full(9, -half), np.full(9, half), t, t])
    lon, lat, _ = frame.to_geodetic(e=e, n=n, u=np.zeros_like(e))
    return AOI(float(lon.min()), float(lat.min()), float(lon.max()), float(lat.max()))


# ---------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------
def render_radiance(grid: SurfaceGrid, shadows: ShadowMap, camera: PushbroomCamera, *,
                    supersampling: int, rows: tuple[int, int] | None = None) -> np.ndarray:
    """Noise-free radiance image (float64, albedo units) of ``camera`` over rows [r0, r1).

    Each pixel averages ``supersampling**2`` rays through a regular sub-grid of the pixel
    (offsets ``(k + 0.5) / s - 0.5``); each ray shows the first surface point along it.
    """
    return render_radiance_greenness(grid, shadows, camera, supersampling=supersampling, rows=rows)[0]


def render_radiance_greenness(grid: SurfaceGrid, shadows: ShadowMap, camera: PushbroomCamera, *,
                              supersampling: int, rows: tuple[int, int] | None = None
                              ) -> tuple[np.ndarray, np.ndarray]:
    """(radiance, greenness) images of ``camera`` over rows [r0, r1): the radiance as
    ``render_radiance``'s, and each pixel's greenness (``town.greenness`` of its rays, weighted
    by their radiance, 0..1: how green the light it receives is)."""
    s = int(supersampling)
    r0, r1 = (0, camera.height) if rows is None else rows
    off = (np.arange(s) + 0.5) / s - 0.5
    width = camera.width
    rows_per_chunk = max(1, RENDER_CHUNK_RAYS // (width * s * s))
    out = np.empty((r1 - r0, width))
    green = np.empty((r1 - r0, width))
    caster = RayCaster(grid)

    def render_rows(a: int) -> None:
        b = min(a + rows_per_chunk, r1)
        rr = (np.arange(a, b)[:, None] + off[None, :]).reshape(-1)  # sub-rows
        cc = (np.arange(width)[:, None] + off[None, :]).reshape(-1)  # sub-cols
        R, C = np.meshgrid(rr, cc, indexing="ij")
        origin, direction = camera.ray(col=C.ravel(), row=R.ravel())
        hits = caster.cast(origin, direction)
        rad = shade(grid, hits, shadows)
        g = (rad * greenness(grid, hits)).reshape(b - a, s, width, s).mean(axis=(1, 3))
        rad = rad.reshape(b - a, s, width, s).mean(axis=(1, 3))
        out[a - r0:b - r0] = rad
        green[a - r0:b - r0] = np.where(rad > 0.0, g / np.where(rad > 0.0, rad, 1.0), 0.0)

    # Each chunk writes its own rows: the same image whatever the threads' order.
    map_in_threads(render_rows, range(r0, r1, rows_per_chunk), max_threads=RENDER_THREADS,
                   name="render")
    return out, green


def to_dn(radiance: np.ndarray, *, noise_dn: float, rng: np.random.Generator) -> np.ndarray:
    """Radiance -> uint16 digital numbers (12-bit range) with Gaussian noise of ``noise_dn``."""
    dn = radiance * DN_PER_RADIANCE + rng.standard_normal(radiance.shape) * noise_dn
    return np.clip(np.rint(dn), 0, DN_MAX).astype(np.uint16)


def to_dn_radiometric(radiance: np.ndarray, *, gain: float, offset_dn: float, gamma: float, noise_dn: float,
                      rng: np.random.Generator) -> np.ndarray:
    """Radiance -> uint16 DN of a multi-date view: ``RADIOMETRY_MODEL`` plus Gaussian noise."""
    dn = radiometric_dn(radiance, gain=gain, offset_dn=offset_dn, gamma=gamma, dn_per_radiance=DN_PER_RADIANCE,
                        dn_max=DN_MAX)
    dn = dn + rng.standard_normal(radiance.shape) * noise_dn
    return np.clip(np.rint(dn), 0, DN_MAX).astype(np.uint16)


# The image products of SynthOptions.product.
PRODUCTS = ("dn16", "rgb8")
# "rgb8": the quantiles (%) of each view's DN that its stretch maps to 0 and 255 (a dynamic
# range adjustment of its own, as 8-bit deliveries have: one date's is not another's), the
# gamma of the stretch, and each channel's (gain, offset) of the stretched value (a grey scene
# seen through three bands that respond a little differently).
RGB8_CLIP_PERCENT = (0.5, 99.5)
RGB8_GAMMA = 1.6
RGB8_CHANNELS = ((0.97, 0.0), (1.0, 0.0), (0.9, 0.03))
# Vegetation's colour: a pixel of greenness g (``render_radiance_greenness``) and stretched
# value x gets RGB8_GREEN[c] * g * x added to channel c: green up, red and blue down, with a
# sum weighted by the luminance weights (``satsweep.io.images.LUMA_WEIGHTS``) of zero, so that
# the grey image satsweep matches is the grey scene's (to the 8-bit rounding). A crown in leaf
# then has a normalised green-red difference (G - R) / (G + R) of about 0.33, grass 0.17, the
# rest 0.015.
RGB8_GREEN = (-0.35, 0.25, -(LUMA_WEIGHTS[1] * 0.25 - LUMA_WEIGHTS[0] * 0.35) / LUMA_WEIGHTS[2])


def to_rgb8(dn: np.ndarray, greenness: np.ndarray | None = None) -> np.ndarray:
    """A view's digital numbers as an 8-bit RGB delivery (H, W, 3): stretched from its
    RGB8_CLIP_PERCENT quantiles to [0, 1], raised to 1 / RGB8_GAMMA, each channel's response
    applied, vegetation coloured by ``greenness`` (per pixel, 0..1; None: none, see
    RGB8_GREEN), rounded to 8 bits. Shadows keep a few grey levels, as they do in such
    products."""
    lo, hi = np.percentile(dn, RGB8_CLIP_PERCENT)
    x = np.clip((dn.astype(np.float64) - lo) / max(float(hi - lo), 1.0), 0.0, 1.0) ** (1.0 / RGB8_GAMMA)
    rgb = np.stack([gain * x + offset for gain, offset in RGB8_CHANNELS], axis=-1)
    if greenness is not None:
        rgb += (np.asarray(greenness, np.float64) * x)[..., None] * np.asarray(RGB8_GREEN)
    return np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------------------------
# RPC of a view
# ---------------------------------------------------------------------------------------------
def fit_view_rpc(camera: PushbroomCamera, frame: ENUFrame, *, lon_range: tuple[float, float],
                 lat_range: tuple[float, float], alt_range: tuple[float, float],
                 bias_px: tuple[float, float], seed: int) -> tuple[RPCModel, RPCFitResidual, RPCFitResidual]:
    """RPC of ``camera`` shifted by ``-bias_px``, fitted over the ground cube.

    Returns (rpc, residual over the fit grid, residual at random points of the cube).
    """
    def samples(lon, lat, alt):
        e, n, u = frame.from_geodetic(lon=lon, lat=lat, alt=alt)
        col, row = camera.project(e=e, n=n, u=u)
        return col - bias_px[0], row - bias_px[1]

    lon, lat, alt = cube_grid(lon_range=lon_range, lat_range=lat_range, alt_range=alt_range,
                              n_lon=RPC_FIT_GRID[0], n_lat=RPC_FIT_GRID[1], n_alt=RPC_FIT_GRID[2])
    col, row = samples(lon, lat, alt)
    rpc, fit_res = fit_rpc(lon=lon, lat=lat, alt=alt, col=col, row=row)
    rng = np.random.default_rng([seed, 5])
    lo = rng.uniform(*lon_range, RPC_CHECK_POINTS)
    la = rng.uniform(*lat_range, RPC_CHECK_POINTS)
    al = rng.uniform(*alt_range, RPC_CHECK_POINTS)
    col, row = samples(lo, la, al)
    check = rpc_residual(rpc, lon=lo, lat=la, alt=al, col=col, row=row)
    return rpc, fit_res, check


# ---------------------------------------------------------------------------------------------
# Truth DSM
# ---------------------------------------------------------------------------------------------
def surface_altitude(grid: SurfaceGrid, frame: ENUFrame, *, lon, lat,
                     z_range: tuple[float, float] = NOMINAL_Z_RANGE) -> np.ndarray:
    """Ellipsoidal altitude (m) of the surface at (lon, lat) (degrees); NaN off the grid.

    The vertical (ellipsoid normal) through (lon, lat) is a straight line in ENU; its crossing
    with the height field is found by fixed-point steps (exact to float rounding except within
    micrometres of a wall, where either side may be returned).
    """
    lon, lat = np.broadcast_arrays(np.asarray(lon, np.float64), np.asarray(lat, np.float64))
    a_lo, a_hi = frame.alt0 + z_range[0], frame.alt0 + z_range[1]
    lo = np.stack(frame.from_geodetic(lon=lon, lat=lat, alt=np.full(lon.shape, a_lo)), axis=-1)
    hi = np.stack(frame.from_geodetic(lon=lon, lat=lat, alt=np.full(lon.shape, a_hi)), axis=-1)
    s = _vertical_crossing(grid, lo, hi)
    return a_lo + s * (a_hi - a_lo)


def _vertical_crossing(grid: SurfaceGrid, lo: np.ndarray, hi: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Fraction s along the segments lo -> hi (ENU, (..., 3)) where they cross the surface."""
    d = hi - lo
    s = (0.0 - lo[..., 2]) / d[..., 2]
    for _ in range(iterations):
        p = lo + s[..., None] * d
        h = grid.height(e=p[..., 0], n=p[..., 1])
        s = s + (h - p[..., 2]) / d[..., 2]
    return s


def truth_dsm(grid: SurfaceGrid, frame: ENUFrame, dsm: DSMGrid, *,
              z_range: tuple[float, float] = NOMINAL_Z_RANGE) -> np.ndarray:
    """Max surface altitude per DSM cell (float64, row 0 = north), over DSM_SUBSAMPLES^2 points.

    Cell corners go through pyproj exactly; points inside a cell are interpolated bilinearly
    between the corners' ENU coordinates (the UTM -> ENU map is affine to nanometres over a
    cell), at the two altitudes of ``z_range``, and the vertical through each point is
    intersected with the surface.
    """
    res = dsm.resolution
    xs = dsm.x_min + np.arange(dsm.width + 1) * res
    ys = dsm.y_max - np.arange(dsm.height + 1) * res
    X, Y = np.meshgrid(xs, ys)
    lon, lat = utm_to_lonlat(x=X, y=Y, epsg=dsm.epsg)
    a_lo, a_hi = frame.alt0 + z_range[0], frame.alt0 + z_range[1]
    lo = np.stack(frame.from_geodetic(lon=lon, lat=lat, alt=np.full(lon.shape, a_lo)), axis=-1)
    hi = np.stack(frame.from_geodetic(lon=lon, lat=lat, alt=np.full(lon.shape, a_hi)), axis=-1)
    k = DSM_SUBSAMPLES
    f = (np.arange(k) + 0.5) / k
    out = np.full((dsm.height, dsm.width), -np.inf)
    for fy in f:
        for fx in f:
            def interp(c):
                return ((1 - fy) * ((1 - fx) * c[:-1, :-1] + fx * c[:-1, 1:])
                        + fy * ((1 - fx) * c[1:, :-1] + fx * c[1:, 1:]))
            s = _vertical_crossing(grid, interp(lo), interp(hi))
            out = np.fmax(out, a_lo + s * (a_hi - a_lo))
    return out


# ---------------------------------------------------------------------------------------------
# The scene on disk
# ---------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class SceneView:
    """One synthetic view: files, geometry, pointing bias and RPC fit quality."""

    index: int
    image: Path  # the uint16 TIFF (RPC in tag 50844)
    rpc_file: Path  # the _RPC.TXT sidecar
    camera: PushbroomCamera  # exact camera (ENU of the scene frame)
    off_nadir_deg: float
    azimuth_deg: float  # satellite azimuth seen from the scene centre
    bias_px: tuple[float, float]  # (col, row): content of X is at RPC(X) + bias
    rpc_fit_max_px: float  # max RPC residual over the fit grid
    rpc_check_max_px: float  # max RPC residual at random points of the cube
    # Multi-date scenes only (None / identity otherwise):
    acquisition: int | None = None  # index of the view's acquisition in Scene.acquisitions
    date_time: str | None = None  # UTC time of the view (its first line), ISO 8601
    gain: float = 1.0  # radiometry: DN = gain * DN_MAX * (x / DN_MAX) ** gamma + offset_dn + noise
    offset_dn: float = 0.0
    gamma: float = 1.0
    metadata_file: Path | None = None  # the .IMD sidecar, when metadata were written

    def rpc(self) -> RPCModel:
        """The RPC written with the image (tag 50844)."""
        return RPCModel.from_image(self.image)


@dataclasses.dataclass(frozen=True)
class Scene:
    """A synthetic scene written by ``generate_scene`` (or read back by ``Scene.load``)."""

    directory: Path
    options: SynthOptions
    frame: ENUFrame
    aoi: AOI
    aoi_half_m: float  # the AOI is the lon/lat box of the ENU square [-a, a]^2
    alt_range: tuple[float, float]  # lowest and highest surface altitude in the AOI (m)
    world: tuple[float, float, float, float]  # surface grid extent (e_min, n_min, e_max, n_max)
    truth_dsm: Path
    dsm_grid: DSMGrid
    views: tuple[SceneView, ...]
    pairs: tuple[tuple[int, int, float], ...]  # (view a, view b, base-to-height ratio)
    acquisitions: tuple[Acquisition, ...] = ()  # multi-date scenes: dates, sun, season, transients

    @property
    def scene_file(self) -> Path:
        return self.directory / SCENE_FILE

    def acquisition_surface(self, index: int, grid: SurfaceGrid | None = None) -> SurfaceGrid:
        """The surface as acquisition ``index`` of a multi-date scene saw it (rebuilt from the
        seed; identical to the one rendered): the truth with that date's trees, grass and
        transients. ``grid``: the truth surface, when already at hand."""
        if not self.acquisitions:
            raise ValueError("a single-date scene has no acquisitions")
        truth = grid if grid is not None else self.surface()
        acq = self.acquisitions[index]
        surface, _ = acquisition_surface(truth, acq, seed=self.options.seed, effects=self.options.date_effects)
        return surface

    def surface(self) -> SurfaceGrid:
        """The true surface grid (rebuilt from the seed; identical to the one rendered)."""
        e_min, n_min, e_max, n_max = self.world
        return build_surface(seed=self.options.seed, e_min=e_min, n_min=n_min, e_max=e_max,
                             n_max=n_max, cell_m=self.options.cell_m, aoi_half_m=self.aoi_half_m)

    def surface_altitude(self, *, lon, lat, grid: SurfaceGrid | None = None) -> np.ndarray:
        """True surface altitude (m above the ellipsoid) at lon/lat (degrees)."""
        return surface_altitude(grid if grid is not None else self.surface(), self.frame, lon=lon, lat=lat)

    @classmethod
    def load(cls, directory: str | os.PathLike) -> "Scene":
        """Read ``scene.json`` of a scene folder; InputError naming the file when it is bad."""
        directory = Path(directory)
        path = directory / SCENE_FILE
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(path, "no scene file (not a satsweep synth folder?)") from None
        except (OSError, ValueError) as exc:
            raise InputError(path, f"unreadable scene file ({exc})") from None
        if not isinstance(doc, dict) or doc.get("format") != SCENE_FORMAT:
            raise InputError(path, f"not a {SCENE_FORMAT} file")
        if doc.get("version") != SCENE_VERSION:
            raise InputError(path, f"scene version {doc.get('version')!r}, this satsweep reads {SCENE_VERSION}")
        try:
            return _scene_from_doc(directory, doc)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(path, f"malformed scene file ({type(exc).__name__}: {exc})") from None


def _scene_from_doc(directory: Path, doc: dict) -> Scene:
    options = SynthOptions.from_mapping(doc["options"], source=str(directory / SCENE_FILE))
    o = doc["origin"]
    a = doc["aoi"]
    g = doc["truth_dsm"]
    views = tuple(
        SceneView(
            index=k, image=directory / v["image"], rpc_file=directory / v["rpc_file"],
            camera=PushbroomCamera.from_dict(v["camera"]), off_nadir_deg=float(v["off_nadir_deg"]),
            azimuth_deg=float(v["azimuth_deg"]), bias_px=(float(v["bias_px"][0]), float(v["bias_px"][1])),
            rpc_fit_max_px=float(v["rpc_fit"]["max_px"]), rpc_check_max_px=float(v["rpc_check"]["max_px"]),
            **_view_multidate_fields(directory, v),
        )
        for k, v in enumerate(doc["views"])
    )
    return Scene(
        directory=directory, options=options,
        frame=ENUFrame(float(o["lon"]), float(o["lat"]), float(o["alt"])),
        aoi=AOI(a["lon_min"], a["lat_min"], a["lon_max"], a["lat_max"]),
        aoi_half_m=float(doc["aoi_half_m"]),
        alt_range=(float(doc["altitude_range"][0]), float(doc["altitude_range"][1])),
        world=tuple(float(doc["world"][k]) for k in ("e_min", "n_min", "e_max", "n_max")),
        truth_dsm=directory / g["file"],
        dsm_grid=DSMGrid(epsg=int(g["epsg"]), x_min=float(g["x_min"]), y_max=float(g["y_max"]),
                         resolution=float(g["resolution"]), width=int(g["width"]), height=int(g["height"])),
        views=views,
        pairs=tuple((int(p["views"][0]), int(p["views"][1]), float(p["base_to_height"])) for p in doc["pairs"]),
        acquisitions=tuple(Acquisition.from_dict(a) for a in doc.get("acquisitions", ())),
    )


def _view_multidate_fields(directory: Path, v: dict) -> dict:
    """SceneView's multi-date fields from a view's scene.json entry (none on single-date ones)."""
    if "acquisition" not in v:
        return {}
    r = v["radiometry"]
    meta = v["metadata"]
    return {"acquisition": int(v["acquisition"]), "date_time": str(v["date_time"]), "gain": float(r["gain"]),
            "offset_dn": float(r["offset_dn"]), "gamma": float(r["gamma"]),
            "metadata_file": directory / meta["imd"] if meta else None}


def view_name(index: int) -> str:
    return f"view_{index:02d}"


def generate_scene(out_dir: str | os.PathLike, options: SynthOptions | None = None, *,
                   overwrite: bool = False, log: Callable[[str], None] | None = None) -> Scene:
    """Generate a synthetic scene into ``out_dir`` (created if missing) and return it.

    Refuses a non-empty folder (OutputExistsError) unless ``overwrite``; with ``overwrite`` the
    scene's files are replaced and other files are left alone. Every file is written under a
    temporary name and renamed; ``scene.json`` is written last, so a folder with a scene file
    holds a complete scene. ``log``: optional callable receiving progress lines.
    """
    options = options if options is not None else SynthOptions()
    out_dir = Path(out_dir)
    check_output_dir(out_dir, overwrite=overwrite)
    say = log if log is not None else (lambda _msg: None)
    plan = options.plan()
    design = design_scene(options)
    frame = design.frame
    e_min, n_min, e_max, n_max = design.world
    t0 = time.perf_counter()
    grid = build_surface(seed=options.seed, e_min=e_min, n_min=n_min, e_max=e_max, n_max=n_max,
                         cell_m=options.cell_m, aoi_half_m=design.aoi_half_m)
    say(f"surface: {grid.shape[1]}x{grid.shape[0]} cells of {options.cell_m:g} m, "
        f"{len(grid.buildings)} buildings ({time.perf_counter() - t0:.1f} s)")

    aoi = _aoi_box(frame, design.aoi_half_m)
    # The RPC cube: the surface grid's lon/lat box and the nominal altitudes.
    lon_w, lat_w, _ = frame.to_geodetic(e=np.array([e_min, e_max, e_min, e_max]),
                                        n=np.array([n_min, n_min, n_max, n_max]), u=np.zeros(4))
    lon_range = (float(lon_w.min()), float(lon_w.max()))
    lat_range = (float(lat_w.min()), float(lat_w.max()))
    alt_cube = (frame.alt0 + design.z_range[0], frame.alt0 + design.z_range[1])
    if options.rpc_height_scale_m > 0.0:  # as real RPCs, a span of heights about the scene's
        mid = 0.5 * (alt_cube[0] + alt_cube[1])
        alt_cube = (min(alt_cube[0], mid - options.rpc_height_scale_m),
                    max(alt_cube[1], mid + options.rpc_height_scale_m))

    out_dir.mkdir(parents=True, exist_ok=True)
    biases = options.view_biases()
    angles = options.view_angles()
    views_doc: list[dict] = [{} for _ in design.cameras]
    views: list[SceneView | None] = [None] * len(design.cameras)
    write_meta = options.multidate if options.write_metadata is None else options.write_metadata
    # One date (single-date scenes) or one per acquisition: the surface as seen that day, its
    # sun and shadows, and the views taken then.
    if plan is None:
        sun = sun_vector(elevation_deg=options.sun_elevation_deg, azimuth_deg=options.sun_azimuth_deg)
        dates = [(None, grid, ShadowMap(grid, sun), range(len(design.cameras)))]
    else:
        dates = ((acq, None, None, acq.views) for acq in plan.acquisitions)
    acquisitions = []
    for acq, surface, shadows, indices in dates:
        if acq is not None:
            t1 = time.perf_counter()
            surface, transients = acquisition_surface(grid, acq, seed=options.seed, effects=options.date_effects)
            acq = dataclasses.replace(acq, transients=tuple(transients))
            acquisitions.append(acq)
            sun = sun_vector(elevation_deg=acq.sun_elevation_deg, azimuth_deg=acq.sun_azimuth_deg)
            shadows = ShadowMap(surface, sun)
            say(f"acquisition {acq.index}: {acq.date_time}, sun elevation {acq.sun_elevation_deg:g} deg, "
                f"azimuth {acq.sun_azimuth_deg:g} deg, leaves {acq.leaf_density:.2f}, {len(transients)} "
                f"transients ({time.perf_counter() - t1:.1f} s)")
        for k in indices:
            cam, (th, az), bias = design.cameras[k], angles[k], biases[k]
            t1 = time.perf_counter()
            if options.product == "rgb8":  # the colour of vegetation: rgb8 deliveries only
                radiance, green = render_radiance_greenness(surface, shadows, cam,
                                                            supersampling=options.supersampling)
            else:
                radiance = render_radiance(surface, shadows, cam, supersampling=options.supersampling)
            rng = np.random.default_rng([options.seed, 2000 + k])
            if acq is None:
                image = to_dn(radiance, noise_dn=options.noise_dn, rng=rng)
            else:
                vp = plan.views[k]
                image = to_dn_radiometric(radiance, gain=vp.gain, offset_dn=vp.offset_dn, gamma=vp.gamma,
                                          noise_dn=options.noise_dn, rng=rng)
            if options.product == "rgb8":
                image = to_rgb8(image, green)
            rpc, fit_res, check = fit_view_rpc(cam, frame, lon_range=lon_range, lat_range=lat_range,
                                               alt_range=alt_cube, bias_px=bias, seed=options.seed + k)
            name = view_name(k)
            image_path = out_dir / f"{name}.tif"
            rpc_path = out_dir / f"{name}_RPC.TXT"
            incidence, sat_az = cam.viewing_angles()
            tags = [rpc_tiff_extratag(rpc)]
            imd_path = None
            if acq is not None and write_meta:
                imd_path = out_dir / f"{name}.IMD"
                tags.append(gdal_metadata_extratag(gdal_metadata_xml(
                    date_time=vp.date_time, sun_azimuth_deg=acq.sun_azimuth_deg,
                    sun_elevation_deg=acq.sun_elevation_deg)))
            write_tiff(image_path, image, extratags=tags)
            write_rpc_txt(rpc_path, rpc)
            doc = {
                "image": image_path.name, "rpc_file": rpc_path.name, "width": cam.width, "height": cam.height,
                "off_nadir_deg": float(th), "azimuth_deg": float(az), "incidence_deg": incidence,
                "orbit_azimuth_deg": options.orbit_azimuth_deg if acq is None else acq.orbit_azimuth_deg,
                "gsd_m": options.gsd_m, "bias_px": list(bias), "rpc_fit": fit_res.to_dict(),
                "rpc_check": check.to_dict(), "camera": cam.to_dict(),
            }
            view = SceneView(index=k, image=image_path, rpc_file=rpc_path, camera=cam,
                             off_nadir_deg=float(th), azimuth_deg=float(az), bias_px=bias,
                             rpc_fit_max_px=fit_res.max_px, rpc_check_max_px=check.max_px)
            if acq is not None:
                in_track, cross_track = track_angles(cam)
                if imd_path is not None:
                    write_imd(imd_path, imd_text(
                        date_time=vp.date_time, rows=cam.height, cols=cam.width,
                        sun_azimuth_deg=acq.sun_azimuth_deg, sun_elevation_deg=acq.sun_elevation_deg,
                        sat_azimuth_deg=sat_az, sat_elevation_deg=90.0 - incidence, off_nadir_deg=incidence,
                        in_track_deg=in_track, cross_track_deg=cross_track, gsd_m=options.gsd_m,
                        catalog_id=f"SYNTH{options.seed:04d}A{acq.index:02d}V{k:02d}"))
                doc.update({
                    "acquisition": acq.index, "date_time": vp.date_time,
                    "sun_elevation_deg": acq.sun_elevation_deg, "sun_azimuth_deg": acq.sun_azimuth_deg,
                    "satellite_azimuth_deg": sat_az, "satellite_elevation_deg": 90.0 - incidence,
                    "in_track_deg": in_track, "cross_track_deg": cross_track,
                    "radiometry": {"gain": vp.gain, "offset_dn": vp.offset_dn, "gamma": vp.gamma,
                                   "model": RADIOMETRY_MODEL},
                    "metadata": {"imd": imd_path.name, "tiff_tag": "GDAL_METADATA (42112)"} if imd_path else None,
                })
                view = dataclasses.replace(view, acquisition=acq.index, date_time=vp.date_time, gain=vp.gain,
                                           offset_dn=vp.offset_dn, gamma=vp.gamma, metadata_file=imd_path)
            views[k] = view
            views_doc[k] = doc
            say(f"{image_path.name}: off-nadir {th:g} deg, azimuth {az:g} deg, bias ({bias[0]:+.3f}, "
                f"{bias[1]:+.3f}) px, RPC residual {max(fit_res.max_px, check.max_px):.2e} px "
                f"({time.perf_counter() - t1:.1f} s)")

    t1 = time.perf_counter()
    dsm_grid = dsm_grid_for_aoi(aoi, options.dsm_resolution_m)
    dsm = truth_dsm(grid, frame, dsm_grid)
    write_geotiff(out_dir / TRUTH_DSM_FILE, dsm, epsg=dsm_grid.epsg, x_min=dsm_grid.x_min,
                  y_max=dsm_grid.y_max, resolution=dsm_grid.resolution, nodata=math.nan)
    say(f"{TRUTH_DSM_FILE}: {dsm_grid.width}x{dsm_grid.height} cells of {dsm_grid.resolution:g} m, "
        f"EPSG:{dsm_grid.epsg} ({time.perf_counter() - t1:.1f} s)")

    alt_range = _aoi_altitude_range(grid, frame, design.aoi_half_m)
    pairs = [(a, b, base_to_height(design.cameras[a], design.cameras[b]))
             for a in range(len(views)) for b in range(a + 1, len(views))]
    doc = {
        "format": SCENE_FORMAT,
        "version": SCENE_VERSION,
        "generator": f"satsweep {__version__}",
        "options": options.scene_dict(),
        "origin": {"lon": frame.lon0, "lat": frame.lat0, "alt": frame.alt0,
                   "note": "origin of the ENU frame (metres) of the cameras and the surface"},
        "aoi": {"lon_min": aoi.lon_min, "lat_min": aoi.lat_min, "lon_max": aoi.lon_max,
                "lat_max": aoi.lat_max, "geojson": aoi.to_geojson()},
        "aoi_half_m": design.aoi_half_m,
        "altitude_range": list(alt_range),
        "rpc_cube": {"lon": list(lon_range), "lat": list(lat_range), "alt": list(alt_cube)},
        "bias_convention": BIAS_CONVENTION,
    }
    if plan is None:
        doc["sun"] = {"elevation_deg": options.sun_elevation_deg, "azimuth_deg": options.sun_azimuth_deg}
    doc.update({
        "world": {"e_min": e_min, "n_min": n_min, "e_max": e_max, "n_max": n_max, "cell_m": options.cell_m},
        "truth_dsm": {"file": TRUTH_DSM_FILE, "epsg": dsm_grid.epsg, "x_min": dsm_grid.x_min,
                      "y_max": dsm_grid.y_max, "resolution": dsm_grid.resolution,
                      "width": dsm_grid.width, "height": dsm_grid.height,
                      "values": "max ellipsoidal altitude over each cell (5x5 points incl. the centre)"},
        "views": views_doc,
        "pairs": [{"views": [a, b], "base_to_height": r} for a, b, r in pairs],
    })
    if plan is not None:
        doc["acquisitions_note"] = ACQUISITIONS_NOTE
        # The transients (hundreds per date) one a line, not one number a line: placeholders
        # here, replaced in the text below.
        doc["acquisitions"] = [{**a.to_dict(), "transients": f"@@transients{a.index}@@"} for a in acquisitions]
    doc.update({
        "ground": grid.ground.to_dict(),
        "buildings": [b.to_dict() for b in grid.buildings],
    })
    text = json.dumps(doc, indent=1)
    for a in acquisitions:
        rows = ",\n   ".join(json.dumps(t, separators=(",", ":")) for t in a.transients)
        text = text.replace(f'"@@transients{a.index}@@"', f"[\n   {rows}\n  ]" if rows else "[]")
    with atomic_output(out_dir / SCENE_FILE) as tmp:
        Path(tmp).write_text(text + "\n", encoding="utf-8")
    return Scene(
        directory=out_dir, options=options, frame=frame, aoi=aoi, aoi_half_m=design.aoi_half_m,
        alt_range=alt_range, world=design.world, truth_dsm=out_dir / TRUTH_DSM_FILE,
        dsm_grid=dsm_grid, views=tuple(views), pairs=tuple(pairs), acquisitions=tuple(acquisitions),
    )


# Rounding of the reported altitude range, outwards (m): the ENU "up" of the surface grid and
# the ellipsoidal altitude differ by millimetres at the scene's edges (Earth curvature).
ALT_RANGE_ROUNDING_M = 0.01


def _aoi_altitude_range(grid: SurfaceGrid, frame: ENUFrame, half: float) -> tuple[float, float]:
    """(lowest, highest) surface altitude over the AOI square, rounded outwards to centimetres."""
    ec, nc = grid.cell_centres()
    ii = np.nonzero(np.abs(ec) <= half + grid.cell_m)[0]
    jj = np.nonzero(np.abs(nc) <= half + grid.cell_m)[0]
    win = (slice(jj[0], jj[-1] + 1), slice(ii[0], ii[-1] + 1))
    reach = 0.5 * grid.cell_m * (np.abs(grid.slope_e[win]) + np.abs(grid.slope_n[win]))
    lo = float(np.min(grid.top[win] - reach)) + frame.alt0
    hi = float(np.max(grid.top[win] + reach)) + frame.alt0
    r = ALT_RANGE_ROUNDING_M
    return math.floor(lo / r) * r - r, math.ceil(hi / r) * r + r
