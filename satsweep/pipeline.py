"""End to end: images + AOI -> DSM, point cloud and report (``satsweep reconstruct``).

Stages (each timed in the report):
  views     read the images and their RPCs, crop each to the AOI cube's footprint, tonemap
  cameras   perspective approximation of every RPC over the AOI (satsweep.camera)
  adjust    bundle adjustment of principal points (satsweep.bundle), per ``reconstruct.adjust``
  skew      shear images so that K has no skew (satsweep.camera.skew_correct_set)
  select    reference views and their sources (satsweep.viewselect)
  sweep     OpenCL plane sweep per reference view (satsweep.sweep), then the MRF (satsweep.mrf)
  dsm       height maps -> cross-check across the reference views (satsweep.dsm) -> points
            over each pixel's footprint (ENU -> UTM) -> per-view rasters -> fusion -> filling
  outputs   dsm.tif, confidence.tif, cloud.ply, dsm.png, cameras.json, config.toml, report.json

An AOI wider or taller than ``[reconstruct] tile_m`` runs every stage from views to the DSM's
fusion tile by tile (``satsweep.tiling``: each tile with its own cameras); the tiles' cores fill
one DSM grid, whose holes are then filled, and the outputs are written once.

Outputs are first written into a hidden staging folder inside DIR and renamed into DIR only
when every stage has succeeded: a failed run leaves what DIR held before untouched.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from .aoi import AOI, AltitudeRange, resolve_altitude_range
from .config import PipelineConfig
from .errors import CameraError, DeviceError, InputError, OptionsError, SatsweepError
from .report import RunReport, to_json

if TYPE_CHECKING:
    from .camera import CameraSet
    from .mrf import MRFOptions
    from .sweep import SweepOptions


@dataclasses.dataclass(frozen=True)
class ReconstructResult:
    out_dir: Path
    dsm_path: Path
    report: dict
    evaluation: dict | None


class OutputFolder:
    """Stage outputs in a hidden folder inside ``out_dir``; move them in place on ``commit``.

    ``out_dir`` may not exist (it is created) or be empty; a non-empty one needs ``overwrite``
    (then only the files this run writes are replaced). ``abort`` removes the staging folder, and
    ``out_dir`` too when this run created it.
    """

    def __init__(self, out_dir: str | os.PathLike, *, overwrite: bool):
        self.out_dir = Path(out_dir)
        self.check(self.out_dir, overwrite=overwrite)
        self.created = not self.out_dir.exists()
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.staging = Path(tempfile.mkdtemp(prefix=".satsweep-partial-", dir=self.out_dir))

    @staticmethod
    def check(out_dir: Path, *, overwrite: bool) -> None:
        """Refuse a path that is a file, or a non-empty folder without ``overwrite``."""
        from .imageio import check_output_dir

        check_output_dir(out_dir, overwrite=overwrite)

    def path(self, name: str) -> Path:
        p = self.staging / name
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def commit(self) -> list[Path]:
        moved = []
        for src in sorted(self.staging.rglob("*")):
            if src.is_file():
                dst = self.out_dir / src.relative_to(self.staging)
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.replace(src, dst)
                moved.append(dst)
        shutil.rmtree(self.staging, ignore_errors=True)
        return moved

    def abort(self) -> None:
        shutil.rmtree(self.staging, ignore_errors=True)
        if self.created:
            shutil.rmtree(self.out_dir, ignore_errors=True)


def enu_height_range(frame, aoi: AOI, alt_range: AltitudeRange) -> tuple[float, float]:
    """ENU ``u`` range spanned by the AOI cube (the AOI box x the altitude range).

    Earth curvature makes a constant altitude sag below u = alt - alt0 away from the origin
    (about 7 mm at 300 m), so the range is taken over the box's corners and edge midpoints."""
    lons = np.array([aoi.lon_min, aoi.lon_max, aoi.lon_min, aoi.lon_max, aoi.center[0]])
    lats = np.array([aoi.lat_min, aoi.lat_min, aoi.lat_max, aoi.lat_max, aoi.center[1]])
    lo = frame.from_geodetic(lon=lons, lat=lats, alt=np.full(5, alt_range.min))[2]
    hi = frame.from_geodetic(lon=lons, lat=lats, alt=np.full(5, alt_range.max))[2]
    return float(np.min(lo)), float(np.max(hi))


def _fill_nan(image: np.ndarray) -> np.ndarray:
    """Skew correction leaves NaN where the sheared image has no source pixel: use 0 there (those
    pixels are in the crop margin, outside the AOI footprint)."""
    out = np.asarray(image, dtype=np.float32)
    return np.where(np.isfinite(out), out, np.float32(0.0)).astype(np.float32)


# Libraries the later stages import (OpenCV: SIFT, the tie points' registration, the coarse
# pass's and the DSM's filters): a background thread imports them while the main thread opens
# the device and reads the images. (reconstruct no longer imports SciPy, whose modules took a
# fresh process about 0.7 s to import.)
PRELOADED_MODULES = ("cv2",)


def _start_preloading() -> threading.Thread:
    """Import PRELOADED_MODULES in a daemon thread; returns the thread (started)."""

    def run():
        for name in PRELOADED_MODULES:
            try:
                importlib.import_module(name)
            except ImportError:  # the stage that needs it imports it again and reports it
                return

    thread = threading.Thread(target=run, name="satsweep-preload", daemon=True)
    thread.start()
    return thread


def reconstruct(images: Sequence[str | os.PathLike], aoi: AOI, out_dir: str | os.PathLike, *,
                alt_range: AltitudeRange | None = None, dem: str | os.PathLike | None = None,
                config: PipelineConfig = PipelineConfig(), overwrite: bool = False,
                truth: str | os.PathLike | None = None, verbose: bool = True,
                command: str = "reconstruct") -> ReconstructResult:
    """Run the whole pipeline; see the module docstring for the stages and outputs."""
    # Everything that can be checked cheaply is checked before anything is written.
    paths = [os.fspath(p) for p in images]
    if len(paths) < 2:
        raise OptionsError(f"need at least two images, got {len(paths)}")
    if truth is not None and not Path(truth).is_file():
        from .errors import InputError

        raise InputError(truth, "truth DSM does not exist")
    out = OutputFolder(out_dir, overwrite=overwrite)
    try:
        result = _reconstruct(paths, aoi, out, alt_range=alt_range, dem=dem, config=config,
                              truth=truth, verbose=verbose, command=command)
    except BaseException:
        out.abort()
        raise
    out.commit()
    return result


def _reconstruct(paths, aoi, out: OutputFolder, *, alt_range, dem, config: PipelineConfig,
                 truth, verbose: bool, command: str) -> ReconstructResult:
    from .device import open_device
    from .dsm import dsm_grid_for_aoi
    from .geo import utm_epsg
    from .ply import PLYWriter
    from .tiling import plan_tiles

    _start_preloading()
    rep = RunReport(command, verbose=verbose)
    rep["settings"] = config.to_dict()
    rep["inputs"] = {"images": paths, "aoi": dataclasses.asdict(aoi), "dem": dem and os.fspath(dem),
                     "truth": truth and os.fspath(truth)}

    device = open_device(config.reconstruct.device)
    rep["device"] = device.info.as_dict()
    rep.log(f"device: {device.info.label}")

    # The DSM grid: the UTM zone of the AOI centre (every tile's, too), cells of --resolution.
    lon_c, lat_c = aoi.center
    grid = dsm_grid_for_aoi(aoi, config.dsm.resolution, epsg=utm_epsg(lon=lon_c, lat=lat_c))
    r = config.reconstruct
    pending = plan_tiles(aoi, grid, tile_m=r.tile_m, overlap_m=r.tile_overlap_m)
    if len(pending) > 1:
        rep.log(f"AOI of {grid.width * grid.resolution:.0f} m x {grid.height * grid.resolution:.0f}"
                f" m: {len(pending)} tiles of at most {r.tile_m:g} m, each with its own cameras")
    # The cloud is written as the areas give it: only one area's points are held at a time.
    cloud = (PLYWriter(out.path("cloud.ply"), with_colors=True,
                       comments=(f"crs EPSG:{grid.epsg}", "generated by satsweep"))
             if r.write_cloud else None)
    try:
        return _reconstruct_tiles(paths, aoi, out, grid, pending, cloud, rep, device,
                                  alt_range=alt_range, dem=dem, config=config, truth=truth)
    except BaseException:
        if cloud is not None:
            cloud.abort()
        raise


def _reconstruct_tiles(paths, aoi, out: OutputFolder, grid, pending, cloud, rep: RunReport,
                       device, *, alt_range, dem, config: PipelineConfig,
                       truth) -> ReconstructResult:
    """The areas of ``pending`` (tiles, cut again where their cameras need it) into the DSM,
    confidence and orthophoto rasters on ``grid`` and the ``cloud`` writer, then the outputs."""
    from .dsm import fill_small_holes
    from .tiling import MIN_TILE_M, can_split, split_tile, sub_grid

    r = config.reconstruct
    names = [Path(p).name for p in paths]
    fused = np.full(grid.shape, np.nan, np.float32)
    conf = np.full(grid.shape, np.nan, np.float32)
    ortho = np.full(grid.shape, np.nan, np.float32) if r.write_ortho else None
    headers: dict = {}  # per image, its RPC and shape, read once for every tile's check
    done, splits, unseen = [], [], []  # done: (tile, its report entry, its cameras)
    shifts: dict[str, list] = {p: [] for p in paths}  # per image, its tiles' own corrections
    deferred = set()  # tiles put back once, for want of matches
    whole = (0, grid.height, 0, grid.width)
    t_start = time.perf_counter()
    while pending:
        tile = pending.pop(0)
        entry = tile.to_dict()
        tile_paths = paths
        if tile.core != whole:
            spent = time.perf_counter() - t_start
            left = (f"; {spent:.0f} s so far, about {spent / len(done) * (len(pending) + 1):.0f} s "
                    "left" if done else "")
            rep.log(f"tile {len(done) + 1}/{len(done) + len(pending) + 1}: cells {tile.core}{left}")
            # Each tile takes the images that see it (a large AOI need not lie in every image).
            tile_paths = _paths_seeing(paths, tile.aoi, alt_range=alt_range, dem=dem,
                                       headers=headers)
            if len(tile_paths) < 2:
                rep.log(f"warning: cells {tile.core} are seen by {len(tile_paths)} image(s): "
                        "left without heights")
                unseen.append({"core_cells": list(tile.core),
                               "images": [Path(p).name for p in tile_paths]})
                continue
        tile_names = [Path(p).name for p in tile_paths]
        split_above = r.tile_max_error_px if can_split(tile, grid, MIN_TILE_M) else 0.0
        # A pointing error is a translation of the whole image: a tile too poor in matches for
        # its own adjustment takes the median of the other tiles' corrections, or waits for them.
        borrowed = ([np.median(np.array(shifts[p]), axis=0).tolist() for p in tile_paths]
                    if all(shifts[p] for p in tile_paths) else None)
        area = _reconstruct_area(tile_paths, tile.aoi, tile.grid, rep.section(entry), device,
                                 alt_range=alt_range, dem=dem, config=config, names=tile_names,
                                 split_above_px=split_above, borrowed_shifts=borrowed,
                                 may_wait=borrowed is None and bool(pending)
                                 and id(tile) not in deferred)
        if area is _LATER:
            deferred.add(id(tile))
            pending.append(tile)
            continue
        if area is _CUT:  # the cameras are too far from the RPCs over this tile: cut it again
            error = max(e["max"] for e in entry["cameras"]["approx_error_px"].values())
            parts = split_tile(tile, aoi, grid, overlap_m=r.tile_overlap_m, min_m=MIN_TILE_M)
            rep.log(f"cameras up to {error:.3f} px from the RPCs over cells {tile.core} (more "
                    f"than tile_max_error_px = {r.tile_max_error_px:g}): {len(parts)} tiles")
            splits.append({"core_cells": list(tile.core), "max_error_px": error,
                           "into": len(parts)})
            pending[:0] = parts
            continue
        rows, cols = tile.core_in_window
        r0, r1, c0, c1 = tile.core
        fused[r0:r1, c0:c1] = area.dsm[rows, cols]
        conf[r0:r1, c0:c1] = area.confidence[rows, cols]
        if ortho is not None:
            ortho[r0:r1, c0:c1] = area.ortho[rows, cols]
        for piece in area.clouds:  # the whole AOI's area kept the grid's points already
            x, y, z, colours = (piece if tile.core == whole
                                else _cloud_in(piece, sub_grid(grid, *tile.core)))
            cloud.append(x, y, z, colors=colours)
        done.append((tile, entry, area.cameras))
        for p, shift in zip(tile_paths, area.shifts or []):
            shifts[p].append(shift)
    if not done:
        raise InputError(None, f"no tile of the AOI is seen by two of the images "
                               f"({', '.join(names)})")
    tiled = len(done) > 1 or bool(unseen)
    rep["tiling"] = {"tile_m": r.tile_m, "overlap_m": r.tile_overlap_m,
                     "max_error_px": r.tile_max_error_px, "tiles": len(done), "splits": splits,
                     "unseen": unseen}
    if tiled:
        if alt_range is not None:  # else each tile's range is in its entry (DEM, tie points)
            rep["altitude_range"] = {"min": alt_range.min, "max": alt_range.max,
                                     "source": "user"}
        rep["aoi_tiles"] = [entry for _, entry, _ in done]
        for k, entry in enumerate(rep["aoi_tiles"]):
            entry["cameras_file"] = f"tiles/tile_{k:02d}/cameras.json"
    else:  # one piece: its figures at the top of the report, as they always were
        for key, value in done[0][1].items():
            if key not in ("core_cells", "window_cells", "level", "aoi"):
                rep[key] = value

    d = config.dsm
    with rep.stage("dsm"):
        filled = 0
        if d.fill_max_hole_cells > 0:
            fused, filled = fill_small_holes(fused, max_hole_cells=d.fill_max_hole_cells,
                                             method=d.fill_method)
        rep["dsm"] = {
            "epsg": grid.epsg, "resolution_m": grid.resolution, "width": grid.width,
            "height": grid.height, "x_min": grid.x_min, "y_max": grid.y_max,
            "filled_fraction": float(np.isfinite(fused).mean()),
            "holes_filled_cells": int(filled),
            **({} if tiled else done[0][1]["dsm"]),  # a tile's own figures are in its entry
        }
    dsm_path, evaluation = _write_outputs(fused, conf, ortho, cloud, grid, rep, out, truth)

    with rep.stage("outputs"):
        from .camera import write_cameras

        if not tiled:
            write_cameras(out.staging, done[0][2])
        for (_, entry, cameras) in (done if tiled else []):
            write_cameras(out.staging / Path(entry["cameras_file"]).parent, cameras)
        out.path("config.toml").write_text(config.to_toml(), encoding="utf-8")
    report = rep.finish()
    out.path("report.json").write_text(rep.to_json() + "\n", encoding="utf-8")
    return ReconstructResult(out_dir=out.out_dir, dsm_path=out.out_dir / dsm_path.name,
                             report=report, evaluation=evaluation)


def _paths_seeing(paths, aoi: AOI, *, alt_range, dem, headers: dict) -> list:
    """The images whose footprint of the AOI cube meets the image: at ``alt_range``, else at
    the DEM's range over the AOI, else at their RPCs' common range (the widest prior).
    ``headers``: path -> (RPC, shape), filled here on first use and kept by the caller."""
    from .aoi import altitude_range_from_rpcs
    from .errors import AOIError
    from .imageio import image_shape
    from .rpc import RPCModel
    from .views import aoi_footprint

    for p in paths:
        if p not in headers:
            headers[p] = (RPCModel.from_image(p), image_shape(p))
    if alt_range is None and dem is None:
        alt = altitude_range_from_rpcs([headers[p][0] for p in paths], warn=False)
    else:
        alt = resolve_altitude_range(alt_range=alt_range, dem=dem, aoi=aoi)
    seeing = []
    for p in paths:
        rpc, shape = headers[p]
        try:
            aoi_footprint(rpc, aoi, alt, shape, path=p)
        except AOIError:
            continue
        seeing.append(p)
    return seeing


@dataclasses.dataclass
class _Area:
    """What one area (the AOI, or one of its tiles) gives: its DSM on its grid before hole
    filling, the confidence raster, the orthophoto, each reference view's cloud, its cameras and
    its own pointing corrections (its figures are in its section of the report)."""

    dsm: np.ndarray
    confidence: np.ndarray
    ortho: np.ndarray | None  # grey level of each cell's highest point (reconstruct.write_ortho)
    clouds: list
    cameras: "CameraSet"
    shifts: list | None  # per view (dcx, dcy) px of its own bundle adjustment; None without one


# _reconstruct_area's answers for an area to be done otherwise: cut in pieces, its cameras being
# too far from the RPCs; or later, its views matching too poorly to be adjusted, once other
# tiles have given their corrections.
_CUT = "cut"
_LATER = "later"


def _cloud_in(cloud, grid) -> tuple:
    """The points of a cloud (x, y, z, colours) whose DSM cell lies in ``grid``."""
    x, y, z, colours = cloud
    i, j = grid.cell_of(x=x, y=y)
    keep = (i >= 0) & (i < grid.height) & (j >= 0) & (j < grid.width)
    return x[keep], y[keep], z[keep], None if colours is None else colours[keep]


def _reconstruct_area(paths, aoi, grid, rep, device, *, alt_range, dem, config: PipelineConfig,
                      names, split_above_px: float = 0.0, borrowed_shifts=None,
                      may_wait: bool = False) -> _Area | str:
    """Every stage from the views to the DSM rasters, for one area (the AOI or one tile of it)
    on its ``grid``, its figures set in ``rep`` (a section of the run's report).

    ``_CUT``, after the cameras stage, when a view's perspective approximation is further than
    ``split_above_px`` (> 0) from its RPC. When the views match too poorly for the bundle
    adjustment: the views' principal points are moved by ``borrowed_shifts`` (per view (dcx,
    dcy), other tiles' corrections) if given, else ``_LATER`` if ``may_wait``, else the
    adjustment is skipped with 2 views under ``adjust = auto`` and the error raised otherwise.
    """
    from . import camera as scam
    from .bundle import adjust_principal_points, shift_principal_points
    from .imageio import tonemap
    from .tiepoints import altitude_range_for_images
    from .views import load_views
    from .viewselect import select_views

    if alt_range is None and dem is None:
        # Neither a range nor a DEM: the RPCs' range (kilometres), narrowed by tie points.
        with rep.stage("altitude"):
            r = config.reconstruct
            alt, rep["altitude_range"] = altitude_range_for_images(
                paths, aoi, config.sparse, quantile=r.tie_altitude_quantile,
                margin_m=r.tie_altitude_margin_m, crop_margin_px=r.crop_margin_px)
        rep.log(f"altitude range {alt.min:.1f}..{alt.max:.1f} m from "
                f"{rep['altitude_range']['tie_points']} tie points (pass --alt-range or --dem to "
                "set it)")
    else:
        alt = resolve_altitude_range(alt_range=alt_range, dem=dem, aoi=aoi)
        rep["altitude_range"] = {"min": alt.min, "max": alt.max,
                                 "source": "user" if alt_range is not None else "dem"}
    with rep.stage("views"):
        views = load_views(paths, aoi, alt, margin_px=config.reconstruct.crop_margin_px)
        images = [tonemap(v.image) for v in views]
        rep["views"] = [{"image": v.path, "crop": [int(v.x0), int(v.y0), int(v.width), int(v.height)]}
                        for v in views]

    with rep.stage("cameras"):
        cameras = scam.build_cameras(views, aoi, alt, config.camera)
        rep["cameras"] = {
            "approx_error_px": {n: v.camera.error.to_dict() for n, v in zip(names, cameras.views)},
            "warnings": list(cameras.warnings),
        }
        for w in cameras.warnings:
            rep.log(f"warning: {w}")
    if split_above_px > 0.0 and max(v.camera.error.max_px for v in cameras.views) > split_above_px:
        return _CUT

    # The kernels the sweep stage will need, built in the background meanwhile.
    device.prebuild(program_forecast(device, cameras, enu_height_range(cameras.frame, aoi, alt),
                                     config))

    mode = config.reconstruct.adjust
    own_shifts = None
    if mode == "off":
        rep["ba"] = {"skipped": "reconstruct.adjust = off"}
    else:
        with rep.stage("adjust"):
            try:
                cameras, ba = adjust_principal_points(cameras, images, config.bundle, config.sparse,
                                                     names=names)
                rep["ba"] = ba.to_dict()
                own_shifts = [list(s) for s in ba.principal_point_shift_px]
            except CameraError as exc:
                if borrowed_shifts is not None:
                    cameras = shift_principal_points(cameras, borrowed_shifts)
                    rep["ba"] = {"skipped": f"not enough matches for the adjustment: {exc}",
                                 "borrowed_principal_point_shift_px": borrowed_shifts}
                    rep.log(f"warning: bundle adjustment of this tile impossible ({exc}); the "
                            "other tiles' pointing corrections are used")
                elif may_wait:
                    rep["ba"] = {"postponed": f"not enough matches for the adjustment: {exc}"}
                    rep.log(f"bundle adjustment of this tile impossible ({exc}): it waits for "
                            "the other tiles' pointing corrections")
                    return _LATER
                elif mode == "on" or len(views) >= 3:
                    raise
                else:
                    rep["ba"] = {"skipped": f"not enough matches for the adjustment: {exc}"}
                    rep.log(f"warning: bundle adjustment skipped: {exc}")

    # The orthophoto's grey levels: the crops' own values (sensor units), the same for every tile
    # (each tile's tonemap stretches its own crop).
    ortho_images = ([np.asarray(v.image, np.float32) for v in views]
                    if config.reconstruct.write_ortho else None)
    if config.reconstruct.skew_correct:
        with rep.stage("skew"):
            unsheared = cameras
            cameras, images = scam.skew_correct_set(cameras, images)
            images = [_fill_nan(im) for im in images]
            if ortho_images is not None:
                _, ortho_images = scam.skew_correct_set(unsheared, ortho_images)

    frame = cameras.frame
    u_range = enu_height_range(frame, aoi, alt)
    with rep.stage("select"):
        selection = select_views([v.camera for v in cameras.views],
                                 mid_height=0.5 * (u_range[0] + u_range[1]),
                                 options=config.views, names=names)
        rep["view_selection"] = selection.to_dict(names)
        for w in selection.warnings:
            rep.log(f"warning: {w}")

    per_view = _sweep_references(device, cameras, images, selection, u_range, config, rep, names,
                                 aoi=aoi, alt_range=alt)
    dsm, confidence, ortho, clouds = _area_rasters(per_view, cameras, images, grid, config, rep,
                                                   ortho_images=ortho_images)
    return _Area(dsm=dsm, confidence=confidence, ortho=ortho, clouds=clouds, cameras=cameras,
                 shifts=own_shifts)

# Smallest interior side (pixels) of an MRF tile (below it, overlaps dominate the work).
MIN_MRF_TILE_PX = 64
# Cost volumes SGM holds on the device at once (sgm_aggregate: pixel-major costs and sums, and
# the input volume while it is converted).
SGM_DEVICE_VOLUMES = 3


def mrf_tile_side(n_planes: int, mrf: MRFOptions, budget_bytes: int,
                  max_alloc_bytes: int) -> int:
    """Interior side (pixels) of the tiles of ``sweep_refine_tiled``.

    ``mrf.tile_px``, reduced so that the cost volume of one tile with its overlap fits
    ``SGM_DEVICE_VOLUMES`` times in the device budget and once in one device allocation.
    DeviceError when even a ``MIN_MRF_TILE_PX`` tile does not fit.
    """
    per_px = 4 * n_planes
    o = mrf.tile_overlap_px
    fit_budget = math.isqrt(max(budget_bytes // (SGM_DEVICE_VOLUMES * per_px), 0)) - 2 * o
    fit_alloc = math.isqrt(max(max_alloc_bytes // per_px, 0)) - 2 * o
    side = min(mrf.tile_px, fit_budget, fit_alloc)
    if side < MIN_MRF_TILE_PX:
        raise DeviceError(f"the MRF's cost volume of a {MIN_MRF_TILE_PX}-pixel tile with its "
                          f"{o}-pixel overlap over {n_planes} planes does not fit the device "
                          f"budget of {budget_bytes / 2**20:.0f} MiB: raise "
                          "sweep.memory_fraction, or lower mrf.tile_overlap_px or the planes")
    return side


def _source_windows(hom: np.ndarray, tile_shape: tuple[int, int],
                    src_shapes: Sequence[tuple[int, int]]) -> list[tuple[int, int, int, int]]:
    """Per source, the window (x0, y0, x1, y1), end exclusive, that a tile's sweep reads.

    ``hom`` (n_planes, n_src, 3, 3) maps tile pixels to source pixels. Where the denominator is
    positive at the tile's corners, a plane maps the tile onto the convex quadrilateral of its
    corners' images, so the box of every plane's corners, with one pixel more for the bilinear
    neighbours, holds every position the sweep samples; clamped to the source, the window keeps
    each position's validity and sampled value (a position outside the source is outside the
    window on the same side, which then ends at the source's edge). A source whose denominator
    is not positive at some corner gets its whole image.
    """
    th, tw = tile_shape
    corners = np.array([[0.0, tw - 1.0, 0.0, tw - 1.0], [0.0, 0.0, th - 1.0, th - 1.0],
                        [1.0, 1.0, 1.0, 1.0]])
    out = []
    for s, (sh, sw) in enumerate(src_shapes):
        mapped = hom[:, s] @ corners  # (n_planes, 3, 4)
        if not (mapped[:, 2] > 0).all():
            out.append((0, 0, sw, sh))
            continue
        u, v = mapped[:, 0] / mapped[:, 2], mapped[:, 1] / mapped[:, 2]
        x0 = min(max(int(math.floor(u.min())) - 1, 0), sw - 1)
        y0 = min(max(int(math.floor(v.min())) - 1, 0), sh - 1)
        x1 = min(max(int(math.ceil(u.max())) + 2, x0 + 1), sw)
        y1 = min(max(int(math.ceil(v.max())) + 2, y0 + 1), sh)
        out.append((x0, y0, x1, y1))
    return out


def mrf_sweep_options(sweep: SweepOptions, mrf: MRFOptions) -> SweepOptions:
    """The sweep options of a sweep whose cost volume ``mrf`` refines: the guided filter radius
    is the method's own (``mrf.sgm_sweep_gf_radius``, ``mrf.gc_sweep_gf_radius``) when that is
    set; otherwise, and without an MRF, ``sweep`` as is."""
    radius = {"sgm": mrf.sgm_sweep_gf_radius, "graphcut": mrf.gc_sweep_gf_radius}.get(mrf.method)
    return sweep if radius is None else sweep.replace(gf_radius=radius)


def mrf_sweep_wants_wta(sweep: SweepOptions, mrf: MRFOptions) -> bool:
    """Whether the sweep under an MRF runs its own winner-take-all: the graph cut starts from it
    (and the left-right check compares it); SGM needs only the volume."""
    return mrf.method != "sgm" or sweep.lr_check


def sweep_refine_tiled(device, ref_image, src_images: Sequence, homographies, heights,
                       sweep: SweepOptions, mrf: MRFOptions, *,
                       progress: Callable[[int, int], None] | None = None):
    """Plane sweep plus MRF refinement of one reference view, tile by tile.

    The reference is cut into tiles of interior side ``mrf_tile_side``; each tile is swept with
    ``mrf.tile_overlap_px`` more pixels on every side (homographies composed with the tile's
    offset), its filtered cost volume refined by ``mrf.method`` (for SGM the volume never leaves
    the device), and its interior kept. So host and device hold one tile's cost volume at a
    time (and, with several tiles, only the windows of the sources that the tile reads), and a
    reference that fits one tile gives exactly the untiled result. The images are
    prefiltered once, whole (the MRF's guide is the reference as given); the left-right check
    (``sweep.lr_check``) runs once on the assembled winner-take-all map, as the untiled sweep
    does. The sweep runs with ``mrf_sweep_options(sweep, mrf)``. With ``sweep.search =
    "coarse_to_fine"`` and SGM, the reference is first swept and refined at half resolution
    (``coarse_plane_index``) and each tile then sweeps plane windows (``satsweep.coarse``).
    ``progress(done, total)`` is called after each tile. Returns (SweepResult with
    n_tiles = the MRF tiles, MRF seconds).
    """
    from .coarse import plane_windows  # noqa: PLC0415
    from .mrf import refine  # noqa: PLC0415
    from .sweep import (PlaneSweep, SweepResult, prefilter, tile_grid,  # noqa: PLC0415
                        visible_at)

    ref = guide = np.ascontiguousarray(ref_image, dtype=np.float32)
    srcs = raw_srcs = [np.ascontiguousarray(s, dtype=np.float32) for s in src_images]
    if sweep.prefilter_sigma_px > 0:
        ref = prefilter(ref, sweep.prefilter_sigma_px)
        srcs = [prefilter(s, sweep.prefilter_sigma_px) for s in srcs]
    hom = np.asarray(homographies, dtype=np.float64)
    hts = np.asarray(heights, dtype=np.float64)
    engine = PlaneSweep(device, mrf_sweep_options(sweep, mrf).replace(lr_check=False,
                                                                      prefilter_sigma_px=0.0))
    h_img, w_img = ref.shape
    # SGM runs on the device: the tile's volume stays there. The graph cut runs on the host.
    on_device = mrf.method == "sgm"
    with_wta = mrf_sweep_wants_wta(sweep, mrf)
    # From the images as given: the coarse pass prefilters its own half-resolution images.
    coarse, seconds = coarse_plane_index(device, guide, raw_srcs, hom, hts, sweep, mrf)
    side = mrf_tile_side(hts.size, mrf, engine.budget_bytes(), device.max_alloc_bytes)
    height = np.full((h_img, w_img), np.nan)
    plane_index = np.zeros((h_img, w_img), np.float32)
    confidence = np.zeros((h_img, w_img), np.float32)
    cost_min = np.zeros((h_img, w_img), np.float32)
    valid = np.zeros((h_img, w_img), bool)
    if with_wta:  # the sweep's winner-take-all map, for the left-right check
        wta_index = np.zeros((h_img, w_img), np.float32)
        wta_valid = np.zeros((h_img, w_img), bool)
    n_tiles, peak, window_planes = 0, 0, 0
    tiles = list(tile_grid(w_img, h_img, side, side, mrf.tile_overlap_px))
    for x0, y0, x1, y1, tx0, ty0, tx1, ty1 in tiles:
        shift = np.array([[1.0, 0.0, tx0], [0.0, 1.0, ty0], [0.0, 0.0, 1.0]])
        tile_hom = hom @ shift
        tile_srcs = srcs
        if len(tiles) > 1:
            # Upload only the part of each source the tile reads, not whole images per tile.
            windows = _source_windows(tile_hom, (ty1 - ty0, tx1 - tx0), [a.shape for a in srcs])
            tile_srcs = [a[wy0:wy1, wx0:wx1] for a, (wx0, wy0, wx1, wy1) in zip(srcs, windows)]
            back = np.array([[[1.0, 0.0, -wx0], [0.0, 1.0, -wy0], [0.0, 0.0, 1.0]]
                             for wx0, wy0, _, _ in windows])
            tile_hom = back[None] @ tile_hom
        planes = None  # this tile's plane windows (coarse-to-fine), else every plane
        if coarse is not None:
            planes = plane_windows(coarse[ty0:ty1, tx0:tx1], hts.size,
                                   block=sweep.window_block_px, halo=sweep.window_halo_px,
                                   margin=sweep.window_margin_planes,
                                   max_fraction=sweep.window_max_fraction)
        r = engine.run(ref[ty0:ty1, tx0:tx1], tile_srcs, tile_hom, hts, keep_volume=True,
                       volume_on_device=on_device, plane_windows=planes,
                       winner_take_all=with_wta)
        window_planes = max(window_planes, hts.size if planes is None else planes.n_planes)
        initial = None if not with_wta else \
            np.clip(np.rint(r.plane_index), 0, hts.size - 1).astype(np.int32)
        try:
            m = refine(device, r.volume, guide[ty0:ty1, tx0:tx1], hts, mrf,
                       cost_scale=float(sweep.census_bits),
                       reject_range_edges=sweep.reject_range_edges, initial_labels=initial,
                       pixel_major=on_device, label_base=r.plane_base,
                       label_count=r.plane_count, label_offset=r.plane_offset)
        finally:
            if on_device:
                r.volume.data.release()
        keep = (slice(y0 - ty0, y1 - ty0), slice(x0 - tx0, x1 - tx0))
        out = (slice(y0, y1), slice(x0, x1))
        # Pixels that no source sees at the chosen plane are invalid.
        seen = visible_at(tile_hom, m.labels, [a.shape for a in tile_srcs])
        valid[out] = m.valid[keep] & seen[keep]
        if with_wta:
            wta_index[out], wta_valid[out] = r.plane_index[keep], r.valid[keep]
        height[out] = m.height[keep]
        plane_index[out] = m.plane_index[keep]
        confidence[out] = m.confidence[keep]
        cost_min[out] = m.cost_min[keep]
        n_tiles += 1
        peak = max(peak, r.peak_device_bytes)
        seconds += m.seconds
        if progress is not None:
            progress(n_tiles, len(tiles))
    if sweep.lr_check:
        valid &= engine.lr_mask(wta_index, wta_valid, ref, srcs, hom, hts)
    height[~valid] = np.nan
    return SweepResult(height=height, plane_index=plane_index, confidence=confidence, valid=valid,
                       cost_min=cost_min, n_tiles=n_tiles, peak_device_bytes=peak,
                       window_planes=window_planes if coarse is not None else None), seconds


def coarse_pass_planes(sweep: SweepOptions, mrf: MRFOptions, shape: tuple[int, int],
                       n_planes: int) -> int:
    """The planes of the coarse pass that ``sweep_refine_tiled`` runs before sweeping a
    reference of ``shape`` over ``n_planes`` planes (every ``sweep.coarse_plane_stride``-th
    plane), or 0 where it runs none: only a coarse-to-fine search under SGM without the
    left-right check has one, and only where the reference gains from it
    (``coarse.worth_a_coarse_pass``)."""
    from .coarse import worth_a_coarse_pass  # noqa: PLC0415

    if sweep.search != "coarse_to_fine" or mrf.method != "sgm" or sweep.lr_check \
            or not worth_a_coarse_pass(shape, n_planes):
        return 0
    return len(range(0, n_planes, sweep.coarse_plane_stride))


def coarse_plane_index(device, ref_image, src_images: Sequence, homographies, heights,
                       sweep: SweepOptions, mrf: MRFOptions) -> tuple[np.ndarray | None, float]:
    """The coarse pass of a coarse-to-fine sweep: the images at half resolution
    (``coarse.downsample2``) swept over every ``sweep.coarse_plane_stride``-th plane and refined
    by ``mrf`` (a full search, tiled as ``sweep_refine_tiled`` tiles), as a map of
    full-resolution plane indices (NaN where invalid) over the reference's pixels. Returns
    (None, 0) where ``coarse_pass_planes`` says there is no coarse pass (another search or MRF,
    or a reference too small or with too few planes to gain); else (map, MRF seconds).
    """
    from .coarse import (downsample2, half_resolution_homographies,  # noqa: PLC0415
                         upsample_index)

    hts = np.asarray(heights, dtype=np.float64)
    shape = np.shape(ref_image)
    if not coarse_pass_planes(sweep, mrf, shape, hts.size):
        return None, 0.0
    stride = sweep.coarse_plane_stride
    planes = slice(0, hts.size, stride)  # coarse_pass_planes counts these
    half, seconds = sweep_refine_tiled(
        device, downsample2(ref_image), [downsample2(s) for s in src_images],
        half_resolution_homographies(np.asarray(homographies)[planes]), hts[planes],
        sweep.replace(search="full"), mrf)
    index = np.where(half.valid, float(stride) * half.plane_index, np.nan)
    return upsample_index(index, shape), seconds


# Pixels of context kept around the AOI's footprint in a reference view (``reference_window``):
# SGM's paths enter the AOI with some history. The sweep stage widens it to the cost filter's
# margin where that is larger (``SweepOptions.tile_margin``: 2 r = 10 px for the
# winner-take-all's radius 5), so that every AOI pixel is filtered over its whole window. The
# rest of the crop margin (``crop_margin_px``, which the sources need) lies outside the AOI at
# every height and is not swept.
REFERENCE_CONTEXT_PX = 8


def reference_window(camera, frame, aoi: AOI, alt_range: AltitudeRange, shape: tuple[int, int],
                     context_px: int = REFERENCE_CONTEXT_PX) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1), end exclusive: the pixels of a reference image of ``shape`` that see the
    AOI cube (the AOI box x the altitude range), through ``camera`` (ENU -> pixels, the image's
    own, skew-corrected where the image is), grown by ``context_px`` and clipped to the image.
    The cube's box is the crop's (``views.projected_aoi_box``), grown by one more pixel for the
    edges' curvature between its samples. A point of the DSM lies inside the AOI, so only these
    pixels can contribute to it."""
    from .errors import AOIError  # noqa: PLC0415
    from .views import projected_aoi_box  # noqa: PLC0415

    P = np.asarray(camera.P, dtype=np.float64)

    def project(*, lon, lat, alt):
        lon, lat, alt = (np.ravel(a) for a in np.broadcast_arrays(lon, lat, alt))
        e, n, u = frame.from_geodetic(lon=lon, lat=lat, alt=alt)
        x = P @ np.stack([e, n, u, np.ones_like(e)])
        x[:, x[2] <= 0] = np.nan  # behind the camera: projected_aoi_box refuses non-finite pixels
        return x[0] / x[2], x[1] / x[2]

    h, w = shape
    try:
        c0, r0, c1, r1 = projected_aoi_box(project, aoi, alt_range)
    except AOIError:
        return 0, 0, w, h  # the cube reaches behind the camera: keep everything
    grow = context_px + 1
    x0 = min(max(int(math.floor(c0)) - grow, 0), w - 1)
    y0 = min(max(int(math.floor(r0)) - grow, 0), h - 1)
    x1 = max(min(int(math.ceil(c1)) + grow + 1, w), x0 + 1)
    y1 = max(min(int(math.ceil(r1)) + grow + 1, h), y0 + 1)
    return x0, y0, x1, y1


def _placed(result, window: tuple[int, int, int, int], shape: tuple[int, int]):
    """The per-pixel maps of a sweep of the reference window ``window``, placed in full-size maps
    of ``shape`` (no height, invalid, zero confidence outside the window)."""
    x0, y0, x1, y1 = window
    height = np.full(shape, np.nan)
    valid = np.zeros(shape, bool)
    confidence = np.zeros(shape, np.float32)
    height[y0:y1, x0:x1] = result.height
    valid[y0:y1, x0:x1] = result.valid
    confidence[y0:y1, x0:x1] = result.confidence
    return height, valid, confidence


def _sweep_references(device, cameras, images, selection, u_range, config: PipelineConfig,
                      rep: RunReport, names, *, aoi: AOI, alt_range: AltitudeRange) -> list[dict]:
    """Sweep every reference view against its sources; MRF refinement per the options.

    Each reference is swept over its ``reference_window`` only (the pixels that see the AOI cube,
    with some context), not over the crop's whole margin; the plane spacing is that of the whole
    image. Without an MRF, the sweep's winner-take-all (its own tiling keeps the cost volume on
    the device). With one, ``sweep_refine_tiled``, timed as the "sweep" stage, whose refinement
    time is then moved to the "mrf" stage and also given in the view's entry with its tile count.
    """
    from .sweep import PlaneSweep, plane_heights, view_homographies

    per_view, sweeps = [], []
    progress = rep.progress("sweep", len(selection.references))
    with_mrf = config.mrf.method != "none"
    swept = mrf_sweep_options(config.sweep, config.mrf)  # the sweep options as run
    for k, r in enumerate(selection.references):
        srcs = list(selection.sources[r])
        ref_proj = cameras.views[r].projection
        src_projs = [cameras.views[s].projection for s in srcs]
        shape = images[r].shape
        window = reference_window(cameras.views[r].camera, cameras.frame, aoi, alt_range, shape,
                                  context_px=max(REFERENCE_CONTEXT_PX, swept.tile_margin))
        x0, y0, x1, y1 = window
        mrf_info = None
        with rep.stage("sweep"):
            heights = plane_heights(ref_proj, src_projs, u_range, config.sweep.step_px,
                                    ref_shape=shape)
            shift = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
            hom = view_homographies(ref_proj, src_projs, heights) @ shift
            ref_image = images[r][y0:y1, x0:x1]  # a view: the sweep makes its own copy
            src_images = [images[s] for s in srcs]
            if with_mrf:
                _check_sgm_labels(heights, config)
                result, seconds = sweep_refine_tiled(
                    device, ref_image, src_images, hom, heights, config.sweep, config.mrf,
                    progress=rep.progress("sweep tiles", 1).callback(names[r]))
            else:
                result = PlaneSweep(device, config.sweep).run(ref_image, src_images, hom, heights)
        if with_mrf:
            rep.move_time("sweep", "mrf", seconds)
            mrf_info = {"method": config.mrf.method, "seconds": seconds,
                        "tiles": int(result.n_tiles),
                        "valid_fraction": float(np.mean(result.valid))}
        progress.update(k + 1, names[r])
        height, valid, confidence = _placed(result, window, shape)
        sweeps.append({
            "reference": names[r], "sources": [names[s] for s in srcs],
            "planes": int(len(heights)),
            "plane_step_m": float(abs(heights[1] - heights[0])) if len(heights) > 1 else None,
            "window": [int(v) for v in window],
            "valid_fraction": float(np.mean(result.valid)), "tiles": int(result.n_tiles),
            "window_planes": result.window_planes,
            "mrf": mrf_info,
        })
        per_view.append({"index": r, "height": height, "valid": valid,
                         "confidence": confidence})
    rep["sweep"] = sweeps
    return per_view


def program_forecast(device, cameras, u_range: tuple[float, float],
                     config: PipelineConfig) -> list:
    """The (source, defines) of the programs that the sweep stage will build, forecast from the
    cameras before adjustment (for ``Device.prebuild``): the view selection and the plane counts
    of those cameras, skew-corrected as the skew stage will do. Adjusting the principal points
    moves every plane's homography by the same translation, which leaves the plane spacing, and
    so the plane count, as it is. A wrong forecast costs only background time. [] where the
    forecast itself fails (the sweep stage then meets the error and reports it)."""
    from .camera import reparametrise, skew_corrected_camera
    from .mrf import SGM_MAX_LABELS, sgm_program_requests
    from .sweep import PlaneSweep, plane_heights
    from .viewselect import select_views

    try:
        cams = [skew_corrected_camera(v.camera)[0] if config.reconstruct.skew_correct else v.camera
                for v in cameras.views]
        projections = [reparametrise(cam, d=v.projection.d, zbar=v.projection.zbar)
                       for cam, v in zip(cams, cameras.views)]
        selection = select_views(cams,
                                 mid_height=0.5 * (u_range[0] + u_range[1]), options=config.views)
        method = config.mrf.method
        if method == "none":
            engine, wta = PlaneSweep(device, config.sweep), True
        else:
            engine = PlaneSweep(device, mrf_sweep_options(config.sweep, config.mrf))
            wta = mrf_sweep_wants_wta(config.sweep, config.mrf)
        requests = []
        for r in selection.references:
            srcs = list(selection.sources[r])
            requests += [q for q in engine.program_requests(len(srcs), wta=wta) if q is not None]
            if method == "sgm":
                shape = (cams[r].height, cams[r].width)
                heights = plane_heights(projections[r], [projections[s] for s in srcs], u_range,
                                        config.sweep.step_px, ref_shape=shape)
                # A coarse-to-fine search's windows are refined by the full search's program
                # (sgm_refine builds SGM for every plane); its coarse pass has its own planes.
                counts = [heights.size]
                n_coarse = coarse_pass_planes(config.sweep, config.mrf, shape, heights.size)
                if n_coarse:
                    counts.append(n_coarse)
                for n in counts:
                    if n <= SGM_MAX_LABELS:
                        requests += sgm_program_requests(device, config.mrf, n)
        return requests
    except SatsweepError:  # raised again, where it belongs, by the stage that meets it
        return []


def _check_sgm_labels(heights: np.ndarray, config: PipelineConfig) -> None:
    """Refuse, before sweeping, an altitude range with more planes than SGM handles."""
    from .mrf import SGM_MAX_LABELS

    if config.mrf.method == "sgm" and heights.size > SGM_MAX_LABELS:
        raise InputError(None, f"the altitude range spans {abs(heights[-1] - heights[0]):.0f} m: "
                               f"{heights.size} planes at [sweep] step_px = "
                               f"{config.sweep.step_px:g}, more than SGM's {SGM_MAX_LABELS}; "
                               "give a tighter --alt-range or --dem, a larger step_px, or "
                               "--mrf none")


def _nanmean_stack(arrays: list[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """Per-cell mean over the arrays that have a value there; NaN where none has one."""
    if not arrays:
        return np.full(shape, np.nan, np.float32)
    stack = np.stack(arrays).astype(np.float64)
    have = np.isfinite(stack)
    n = have.sum(axis=0)
    total = np.where(have, stack, 0.0).sum(axis=0)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan).astype(np.float32)


# Metres added around the pixel centres' box for the ENU -> map fit: the footprint sub-samples
# lie within half a pixel of their centres (well under this at any satellite's ground sampling).
FOOTPRINT_PAD_M = 5.0


def _enu_to_map(frame, epsg: int, points: list[tuple[np.ndarray, ...]]):
    """The ENU -> (UTM, height) map (``dsm.ENUToMap``) fitted over the bounding box of the
    points, widened by ``FOOTPRINT_PAD_M`` for their footprint sub-samples."""
    from .dsm import ENUToMap

    lo, hi = np.zeros(3), np.ones(3)  # any box when there is no point at all
    present = [p for p in points if p[0].size]
    if present:  # the box of every view's points, without concatenating millions of them
        lo = np.array([min(p[k].min() for p in present) for k in range(3)])
        hi = np.array([max(p[k].max() for p in present) for k in range(3)])
        lo[:2] -= FOOTPRINT_PAD_M
        hi[:2] += FOOTPRINT_PAD_M
    return ENUToMap.fit(frame, epsg, e_range=(lo[0], hi[0]), n_range=(lo[1], hi[1]),
                        u_range=(lo[2], hi[2]))


def _area_rasters(per_view, cameras, images, grid, config: PipelineConfig, rep, *,
                  ortho_images=None):
    """The "dsm" stage of one area on its ``grid``: each reference view's height map ->
    cross-check -> points over each pixel's footprint (ENU -> UTM) -> per-view rasters ->
    fusion. Returns (DSM before hole filling, confidence raster, orthophoto of
    ``ortho_images``' values (the views' in the cameras' pixels; None: no orthophoto), one cloud
    (x, y, z, grey colours) per reference view); the stage's figures go to ``rep["dsm"]``."""
    from .dsm import (cross_check_heights, flat_cells, fuse_dsms, height_map_to_enu,
                      map_view_points, match_radiometry, rasterise_max_cells, value_at_highest)

    d = config.dsm
    with rep.stage("dsm"):
        heights = [np.where(pv["valid"], pv["height"], np.nan) for pv in per_view]
        projections = [cameras.views[pv["index"]].camera.P for pv in per_view]
        # Every view's pixel centres in ENU (solved once: the cross-check reads them too), one
        # polynomial ENU -> UTM map fitted over all of them; then each view's centres (the
        # cloud) and footprint sub-samples (the rasters).
        centres = [height_map_to_enu(height, np.isfinite(height), P)
                   for height, P in zip(heights, projections)]
        checked = [np.isfinite(h) for h in heights]
        cross_check = d.cross_check_m > 0 and len(per_view) >= 2
        if cross_check:
            checked = cross_check_heights(heights, projections, tolerance_m=d.cross_check_m,
                                          min_agreeing=d.cross_check_views, points=centres)
            centres = [tuple(a[keep.ravel()[c[3]]] for a in c)
                       for c, keep in zip(centres, checked)]
        to_map = _enu_to_map(cameras.frame, grid.epsg, centres)
        rasters, conf_rasters, orthos, clouds = [], [], [], []
        for pv, centre, height, keep in zip(per_view, centres, heights, checked):
            (x, y, z, pixel), (sx, sy, sz, spix) = map_view_points(
                centre, height, keep, cameras.views[pv["index"]].camera.P, to_map,
                subsamples=d.subsamples)
            cells = flat_cells(sx, sy, grid)
            rasters.append(rasterise_max_cells(cells, sz, grid))
            if pv["confidence"] is not None:
                conf_rasters.append(rasterise_max_cells(cells, np.ravel(pv["confidence"])[spix],
                                                        grid))
            if ortho_images is not None:
                grey = np.ravel(ortho_images[pv["index"]])[spix]
                orthos.append(value_at_highest(cells, sz, grey, grid))
            if not config.reconstruct.write_cloud:
                continue
            gray = np.clip(np.nan_to_num(images[pv["index"]]) * 255.0, 0, 255).astype(np.uint8)
            # The cloud covers the area's DSM grid, like the DSM (the crops extend beyond it).
            keep = ((x >= grid.x_min) & (x <= grid.x_min + grid.width * grid.resolution)
                    & (y <= grid.y_max) & (y >= grid.y_max - grid.height * grid.resolution))
            clouds.append((x[keep], y[keep], z[keep],
                           np.repeat(gray.ravel()[pixel[keep]][:, None], 3, axis=1)))
        fused, _count = fuse_dsms(rasters, outlier_m=d.outlier_m, min_views=d.min_views)
        conf = _nanmean_stack(conf_rasters, grid.shape)
        # Each cell's grey level: the mean over the views whose height there is the fused one's
        # (within outlier_m, the fusion's own rule), so that no view shows a wall or a lower roof.
        ortho = None
        if ortho_images is not None:
            with np.errstate(invalid="ignore"):
                kept = [np.where(np.abs(h - fused) <= d.outlier_m, o, np.nan)
                        for h, o in zip(rasters, orthos)]
            # Views of other dates or sensors differ in gain and offset: each is brought to the
            # radiometry of the first image given (of those swept as references) before the
            # mean, so that cells seen by one view and cells seen by two look alike.
            first = int(np.argmin([pv["index"] for pv in per_view]))
            kept = [o if k == first else match_radiometry(kept[first], o)
                    for k, o in enumerate(kept)]
            ortho = _nanmean_stack(kept, grid.shape)
        rep["dsm"] = {
            "cross_check": ({"tolerance_m": d.cross_check_m, "views": d.cross_check_views,
                             "kept_fraction": [float(k.sum() / max(1, np.isfinite(h).sum()))
                                               for k, h in zip(checked, heights)]}
                            if cross_check else None),
            "per_view_filled_fraction": [float(np.isfinite(a).mean()) for a in rasters],
            "enu_to_map": {"polynomial": to_map.accurate, "max_error_m": to_map.max_error_m},
        }
    return fused, conf, ortho, clouds


def _write_outputs(fused, conf, ortho, cloud, grid, rep: RunReport, out: OutputFolder, truth):
    """The "outputs" stage's rasters (``ortho`` None: none) and cloud (a ``PLYWriter`` holding
    the points, or None), then the evaluation against ``truth`` if given. Returns (the DSM's
    path in the staging folder, the evaluation or None)."""
    from .dsm import write_dsm_geotiff
    from .imageio import write_geotiff
    from .render import height_png

    with rep.stage("outputs"):
        dsm_path = out.path("dsm.tif")
        write_dsm_geotiff(dsm_path, fused.astype(np.float32), grid)
        write_geotiff(out.path("confidence.tif"), conf.astype(np.float32), epsg=grid.epsg,
                      x_min=grid.x_min, y_max=grid.y_max, resolution=grid.resolution)
        if ortho is not None:
            write_geotiff(out.path("ortho.tif"), ortho.astype(np.float32), epsg=grid.epsg,
                          x_min=grid.x_min, y_max=grid.y_max, resolution=grid.resolution)
        height_png(out.path("dsm.png"), fused, title="satsweep DSM (m above WGS84 ellipsoid)")
        if cloud is not None:
            cloud.commit()
    evaluation = None
    if truth is not None:
        from .evaluate import evaluate_dsm

        with rep.stage("evaluate"):
            evaluation = evaluate_dsm(dsm_path, truth, out_dir=out.path("evaluation"))
            evaluation["prediction"] = os.fspath(out.out_dir / dsm_path.name)  # its final name
            out.path("evaluation/evaluation.json").write_text(to_json(evaluation) + "\n",
                                                              encoding="utf-8")
            rep["evaluation"] = evaluation
    return dsm_path, evaluation
