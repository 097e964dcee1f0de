"""End to end: images + AOI -> DSM, point cloud and report (``satsweep reconstruct``).

Stages (each timed in the report):
  altitude  without --alt-range or --dem: the range from tie points (satsweep.pipeline.altitude)
  views     read the images' windows that see the AOI cube, tonemap (satsweep.pipeline.prepare)
  cameras   perspective approximation of every RPC over the AOI (satsweep.geometry.camera)
  adjust    bundle adjustment of principal points (satsweep.sparse.bundle), per ``reconstruct.adjust``
  skew      shear images so that K has no skew (satsweep.geometry.skew)
  select    reference views and their sources (satsweep.dense.selection)
  sweep     OpenCL plane sweep per reference view (satsweep.dense.sweep), then the MRF
            (satsweep.dense.mrf; satsweep.pipeline.sweeps drives them)
  dsm       height maps -> cross-check across the reference views (satsweep.products.fusion) ->
            points over each pixel's footprint (ENU -> UTM) -> per-view rasters -> fusion
            (satsweep.pipeline.rasters) -> the mosaic's holes filled
  outputs   dsm.tif, confidence.tif, ortho.tif, cloud.ply, dsm.png, cameras.json, rpc/,
            config.toml, report.json (satsweep.pipeline.outputs)

An AOI wider or taller than ``[reconstruct] tile_m`` runs every stage from the altitude range to
the DSM's fusion tile by tile (``satsweep.pipeline.scheduler``, ``satsweep.pipeline.tiling``: each
tile with its own cameras); the tiles' cores fill one DSM grid, whose holes are then filled, and
the outputs are written once. Each area is a task (``satsweep.pipeline.cluster``) that runs in
this process or on Dask workers (``[reconstruct] workers``, ``scheduler``) and leaves its results
in the output's finished-tiles folder, which ``resume`` reuses after an interrupted run. The
stages hand each other typed results; the report serialises them at the end.

Outputs are first written into a hidden staging folder inside DIR and renamed into DIR only
when every stage has succeeded: a failed run leaves what DIR held before untouched.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import sys
from pathlib import Path
from typing import Sequence

from satsweep.config import PipelineConfig
from satsweep.errors import InputError, OptionsError, SatsweepError
from satsweep.geometry.altitude import AltitudeRange
from satsweep.geometry.aoi import AOI
from satsweep.io.sources import refuse_folders, refuse_too_few, report_names
from satsweep.pipeline.outputs import (
    RPC_DIR,
    OutputFolder,
    ReconstructResult,
    evaluate_products,
    write_products,
)
from satsweep.pipeline.preload import start_preloading
from satsweep.pipeline.report import RunReport
from satsweep.pipeline.scheduler import Mosaic, reconstruct_areas


def reconstruct(images: Sequence[str | os.PathLike], aoi: AOI, out_dir: str | os.PathLike, *,
                alt_range: AltitudeRange | None = None, dem: str | os.PathLike | None = None,
                config: PipelineConfig = PipelineConfig(), overwrite: bool = False,
                truth: str | os.PathLike | None = None, verbose: bool = True,
                command: str = "reconstruct", resume: bool = False,
                rpc_dir: str | os.PathLike | None = None,
                mask_dir: str | os.PathLike | None = None) -> ReconstructResult:
    """Run the whole pipeline; see the module docstring for the stages and outputs.

    ``aoi`` may be given as an ``AOI`` or as a string for ``parse_aoi``, ``alt_range`` as an
    ``AltitudeRange`` or a (min, max) pair. ``resume``: reuse the tiles that an interrupted or
    failed run into ``out_dir`` finished (``satsweep.pipeline.cluster``). ``rpc_dir``: a folder
    holding each image's RPC as ``<stem>_RPC.TXT`` (another run's rpc/, another tool's adjusted
    RPCs), taken instead of the images' own. ``mask_dir``: a folder holding masks of pixels to
    leave out (clouds), ``<image file name>.msk`` (``satsweep.io.masks``), for the images that
    have one there. Every bad argument is a ``SatsweepError``."""
    # Everything that can be checked cheaply is checked before anything is written.
    paths, aoi, alt_range = _checked_arguments(images, aoi, alt_range, config)
    check_run_size(aoi, config)
    if rpc_dir is not None and not os.path.isdir(rpc_dir):
        raise InputError(rpc_dir, "the RPC folder does not exist")
    if mask_dir is not None and not os.path.isdir(mask_dir):
        raise InputError(mask_dir, "the mask folder does not exist")
    if truth is not None:
        check_truth_dsm(truth, aoi)
    out = None
    try:
        # Inside the try: an interruption just after the folder is made still aborts it.
        out = OutputFolder(out_dir, overwrite=overwrite, resume=resume)
        result = _reconstruct(paths, aoi, out, alt_range=alt_range, dem=dem, config=config,
                              truth=truth, verbose=verbose, command=command, rpc_dir=rpc_dir,
                              mask_dir=mask_dir)
    except BaseException as exc:
        if out is None:  # refused before anything was written (OutputFolder cleans up itself)
            raise
        # An interrupted or crashed run keeps its finished tiles for --resume; one refused for
        # its inputs, options or data needs something changed first, and keeps nothing.
        kept = out.abort(keep_tiles=not isinstance(exc, SatsweepError)
                         or getattr(exc, "resumable", False))
        if kept:
            print(f"satsweep: {kept} finished tile(s) kept in {out.cache}: run the same command "
                  "with --resume (resume=True) to reuse them", file=sys.stderr, flush=True)
        raise
    out.commit()
    return result


def _reconstruct(paths, aoi, out: OutputFolder, *, alt_range, dem, config: PipelineConfig,
                 truth, verbose: bool, command: str, rpc_dir=None,
                 mask_dir=None) -> ReconstructResult:
    from satsweep.geometry.geodesy import utm_epsg
    from satsweep.pipeline.cluster import (
        RunSettings,
        open_runner,
        resolve_device_spec,
        worker_device,
    )
    from satsweep.pipeline.prepare import open_run_sources, sources_seeing_the_aoi
    from satsweep.pipeline.tiling import plan_tiles
    from satsweep.products.grid import dsm_grid_for_aoi

    start_preloading()
    rep = RunReport(command, verbose=verbose)
    rep["settings"] = config.to_dict()
    rep["inputs"] = {"images": paths, "aoi": dataclasses.asdict(aoi), "dem": dem and os.fspath(dem),
                     "truth": truth and os.fspath(truth), "rpc_dir": rpc_dir and os.fspath(rpc_dir),
                     "mask_dir": mask_dir and os.fspath(mask_dir)}

    settings = RunSettings(config=config, device=resolve_device_spec(config.reconstruct.device),
                           alt_range=alt_range, dem=None if dem is None else os.fspath(dem),
                           verbose=verbose)
    sources = open_run_sources(paths, config, rpc_dir=rpc_dir, mask_dir=mask_dir)
    rep["inputs"]["rpcs"] = [None if s.rpc.source is None else os.fspath(s.rpc.source)
                             for s in sources]  # where each image's RPC was read
    rep["inputs"]["masks"] = [None if s.mask is None else s.mask.describe()
                              for s in sources]  # each image's mask of pixels to leave out
    for s in sources:
        if s.mask is not None:
            rep.log(f"{s.name}: masked by {s.mask.describe()}")
    sources, elsewhere = sources_seeing_the_aoi(sources, aoi, config, alt_range=alt_range,
                                                dem=dem, report=rep)
    if elsewhere:  # views of other places
        rep["inputs"]["left_out"] = elsewhere
    for source in sources:
        for problem in (source.acquisition.warnings if source.acquisition is not None else ()):
            rep.warn(problem)

    # The DSM grid: the UTM zone of the AOI centre (every tile's, too), cells of --resolution.
    lon_c, lat_c = aoi.center
    grid = dsm_grid_for_aoi(aoi, config.dsm.resolution, epsg=utm_epsg(lon=lon_c, lat=lat_c))
    r = config.reconstruct
    tiles = plan_tiles(aoi, grid, tile_m=r.tile_m, overlap_m=r.tile_overlap_m)
    if len(tiles) > 1:
        rep.log(f"AOI of {grid.width * grid.resolution:.0f} m x {grid.height * grid.resolution:.0f}"
                f" m: {len(tiles)} tiles of at most {r.tile_m:g} m, each with its own cameras")
    runner = open_runner(settings, tiles, len(sources), rep)
    try:
        if runner.kind == "in-process":  # the tiles run on this process's device
            device = worker_device(settings.device)
            rep["device"] = device.info.as_dict()
            rep.log(f"device: {device.info.label}")
            builds_before = device.build_totals()
        elif runner.kind == "scheduler":  # workers elsewhere, in other folders: whole paths
            sources = [dataclasses.replace(
                s, path=os.path.abspath(s.path),
                mask=s.mask and dataclasses.replace(s.mask, path=os.path.abspath(s.mask.path)))
                for s in sources]
            if settings.dem is not None:
                settings = dataclasses.replace(settings, dem=os.path.abspath(settings.dem))
        with rep.capturing_warnings():
            mosaic = reconstruct_areas(sources, aoi, grid, tiles, settings, runner, out.cache,
                                       rep)
            _report_execution(rep, runner, mosaic)
            if runner.kind == "in-process":
                _report_kernel_builds(rep, device, builds_before)
            return _finish(mosaic, settings, rep, out, truth)
    finally:
        runner.close()


def _report_kernel_builds(rep: RunReport, device, before: tuple[int, float]) -> None:
    """The kernels this run compiled (``device.kernel_builds``): programs and the seconds their
    builds took, part of them in the background during the sparse stage. A process's first run
    builds its programs (seconds each on PoCL without its disk cache, milliseconds with it);
    a later run in the same process reuses them."""
    programs, seconds = device.build_totals()
    builds = {"programs": programs - before[0], "seconds": seconds - before[1]}
    rep["device"] = {**rep["device"], "kernel_builds": builds}
    if builds["programs"]:
        rep.log(f"kernels: {builds['programs']} programs built in {builds['seconds']:.1f} s "
                "(partly in the background)")


def _report_execution(rep: RunReport, runner, mosaic: Mosaic) -> None:
    """The report's ``execution`` section; the device, when the tiles ran on workers."""
    from satsweep.pipeline.cluster import execution_summary

    rep["execution"] = execution_summary(runner, reused=mosaic.reused, computed=mosaic.computed,
                                         retries=mosaic.retries,
                                         outcomes=mosaic.computed_outcomes)
    if rep["device"] is None:
        devices = {}
        for outcome in mosaic.outcomes:
            if outcome.device is not None:
                devices.setdefault(outcome.device["platform_name"] + " / "
                                   + outcome.device["device_name"], outcome.device)
        if devices:
            rep["device"] = next(iter(devices.values()))
            rep.log(f"device: {', '.join(devices)}")
        if len(devices) > 1:
            rep.warn(f"the tiles ran on different devices ({'; '.join(devices)}): their "
                     "heights may differ in the last bits")


def _finish(mosaic: Mosaic, settings, rep: RunReport, out: OutputFolder,
            truth) -> ReconstructResult:
    """The mosaic's holes filled, the report's figures, the outputs."""
    from satsweep.pipeline.mosaic import append_cloud_piece, assemble, fill_holes
    from satsweep.products.ply import PLYWriter

    config, grid = settings.config, mosaic.grid
    r, d = config.reconstruct, config.dsm
    entries = []  # per area: its cells and its stages' figures
    for area in mosaic.done:
        entries.append({**area.tile.to_dict(), **area.outcome.entry})
    rep["tiling"] = {"tile_m": r.tile_m, "overlap_m": r.tile_overlap_m,
                     "max_error_px": r.tile_max_error_px, "tiles": len(mosaic.done),
                     "splits": mosaic.splits, "unseen": mosaic.unseen}
    if mosaic.failed:
        rep["tiling"]["failed"] = mosaic.failed
    rep["tiling"]["aoi_seen_share"] = dict(zip(report_names(list(mosaic.seen_shares)),
                                               mosaic.seen_shares.values()))
    if mosaic.tiled:
        if settings.alt_range is not None:  # else each tile's range is in its entry
            rep["altitude_range"] = {"min": settings.alt_range.min,
                                     "max": settings.alt_range.max, "source": "user"}
        for k, entry in enumerate(entries):
            entry["cameras_file"] = f"tiles/tile_{k:02d}/cameras.json"
        rep["aoi_tiles"] = entries
    else:  # one piece: its figures at the top of the report, as they always were
        for key, value in entries[0].items():
            if key not in ("core_cells", "window_cells", "level", "aoi"):
                rep[key] = value

    bands = ["dsm", "confidence", "count"] + (["ortho"] if r.write_ortho else [])
    with rep.stage("fill"):
        rasters = assemble(grid, mosaic.pieces, out.work, bands)
        filled = fill_holes(rasters["dsm"], out.work, max_hole_cells=d.fill_max_hole_cells,
                            method=d.fill_method, border_holes=d.fill_border_holes)
        rep["dsm"] = {
            "epsg": grid.epsg, "resolution_m": grid.resolution, "width": grid.width,
            "height": grid.height, "x_min": grid.x_min, "y_max": grid.y_max,
            "filled_fraction": filled.valid_cells / float(grid.width * grid.height),
            "holes_filled_cells": filled.filled_cells,
            **({} if mosaic.tiled else entries[0]["dsm"]),  # a tile's are in its entry
        }
    _check_filled(rep["dsm"]["filled_fraction"], mosaic, rep, config)
    with rep.stage("outputs"):
        # The cloud, from the areas' pieces in their order: one chunk of points at a time.
        cloud = (PLYWriter(out.path("cloud.ply"), with_colors=True,
                           comments=(f"crs EPSG:{grid.epsg}", "generated by satsweep"))
                 if r.write_cloud else None)
        try:
            for area in mosaic.done if cloud is not None else []:
                append_cloud_piece(cloud, area.folder)
            rasters["dsm"], rasters["interpolated"] = filled.dsm, filled.interpolated
            dsm_path = write_products(rasters, cloud, grid, out)
        except BaseException:
            if cloud is not None:
                cloud.abort()
            raise
        if not mosaic.tiled:
            shutil.copyfile(mosaic.done[0].cameras_file, out.path("cameras.json"))
            _copy_rpcs(mosaic.done[0].folder, out, RPC_DIR)
        for entry, area in zip(entries if mosaic.tiled else [], mosaic.done):
            shutil.copyfile(area.cameras_file, out.path(entry["cameras_file"]))
            _copy_rpcs(area.folder, out, str(Path(entry["cameras_file"]).parent / RPC_DIR))
        out.path("config.toml").write_text(config.to_toml(), encoding="utf-8")
    evaluation = evaluate_products(dsm_path, truth, out, rep) if truth is not None else None
    report = rep.finish()
    out.path("report.json").write_text(rep.to_json() + "\n", encoding="utf-8")
    return ReconstructResult(out_dir=out.out_dir, dsm_path=out.out_dir / dsm_path.name,
                             report=report, evaluation=evaluation)


def _copy_rpcs(area_folder: Path, out: OutputFolder, to: str) -> None:
    """An area's corrected RPCs (``write_corrected_rpcs``), if it wrote any, into ``to``."""
    for path in sorted((Path(area_folder) / RPC_DIR).glob("*_RPC.TXT")):
        shutil.copyfile(path, out.path(f"{to}/{path.name}"))


def _check_filled(fraction: float, mosaic: Mosaic, rep: RunReport,
                  config: PipelineConfig) -> None:
    """An error when no cell got a height (no stereo was possible: featureless or identical
    views); a doubtful warning when fewer than ``[reconstruct] warn_filled_below`` of them did."""
    names = sorted({s for area in mosaic.done for s in area.outcome.names})
    if fraction == 0.0:
        raise InputError(None, f"no cell of the DSM got a height: the views "
                               f"({', '.join(names)}) could not be matched over the AOI "
                               "(featureless, cloud-covered or identical images?)")
    floor = config.reconstruct.warn_filled_below
    if fraction < floor:
        rep.warn(f"only {100 * fraction:.1f}% of the DSM's cells got a height (less than "
                        f"[reconstruct] warn_filled_below = {floor:g}): the views match poorly "
                        "over the AOI", doubtful=True)


def _checked_arguments(images, aoi, alt_range, config) -> tuple[list[str], AOI,
                                                                 AltitudeRange | None]:
    """The API's arguments checked and normalised (OptionsError naming the argument; a folder
    given as an image and too few images as ``open_sources`` refuses them)."""
    from satsweep.geometry.aoi import parse_aoi

    if isinstance(images, (str, bytes, os.PathLike)):
        raise OptionsError(f"images: give a list of image paths, not the one path {images!r}")
    try:
        paths = [os.fspath(p) for p in images]
    except TypeError:
        raise OptionsError(f"images: expected a list of image paths, got {images!r}") from None
    refuse_folders(paths)
    refuse_too_few(paths)
    if isinstance(aoi, (str, os.PathLike)):
        aoi = parse_aoi(aoi)
    elif not isinstance(aoi, AOI):
        raise OptionsError(f"aoi: expected an AOI or 'LON_MIN,LAT_MIN,LON_MAX,LAT_MAX' (or a "
                           f"GeoJSON file), got {type(aoi).__name__}")
    if alt_range is not None and not isinstance(alt_range, AltitudeRange):
        try:
            lo, hi = (float(v) for v in alt_range)
        except (TypeError, ValueError):
            raise OptionsError(f"alt_range: expected an AltitudeRange or (min, max) in metres, "
                               f"got {alt_range!r}") from None
        alt_range = AltitudeRange(lo, hi)
    if not isinstance(config, PipelineConfig):
        raise OptionsError(f"config: expected a PipelineConfig, got {type(config).__name__}")
    return paths, aoi, alt_range


def check_truth_dsm(path, aoi: AOI) -> None:
    """Refuse, before reconstructing, a truth DSM that the evaluation could not use: missing,
    not a single-band GeoTIFF, not in the DSM's UTM zone (the evaluation compares on the truth's
    grid, in its CRS)."""
    from satsweep.geometry.geodesy import utm_epsg
    from satsweep.io.geotiff import read_geotiff_info
    from satsweep.io.images import image_shape

    if not Path(path).is_file():
        raise InputError(path, "truth DSM does not exist")
    info = read_geotiff_info(path)
    image_shape(path)  # a readable raster of integer or float samples, or an error naming it
    lon, lat = aoi.center
    epsg = utm_epsg(lon=lon, lat=lat)
    if info.epsg != epsg:
        raise InputError(path, f"truth DSM in EPSG:{info.epsg}, not in the UTM zone of the AOI "
                               f"(EPSG:{epsg}) where the DSM is made: reproject it (gdalwarp "
                               f"-t_srs EPSG:{epsg})")


def check_run_size(aoi: AOI, config: PipelineConfig) -> None:
    """Refuse, before anything is written, an AOI larger than ``[reconstruct] max_aoi_km2`` or
    a DSM grid of more than ``max_dsm_cells`` cells (a whole-world AOI, a resolution in
    millimetres): OptionsError giving the size and the option."""
    from satsweep.geometry.geodesy import utm_epsg
    from satsweep.products.grid import dsm_grid_for_aoi

    r = config.reconstruct
    lon, lat = aoi.center
    grid = dsm_grid_for_aoi(aoi, config.dsm.resolution, epsg=utm_epsg(lon=lon, lat=lat))
    width_m, height_m = grid.width * grid.resolution, grid.height * grid.resolution
    km2 = width_m * height_m / 1e6
    if km2 > r.max_aoi_km2:
        raise OptionsError(f"the AOI is {width_m / 1e3:.1f} km x {height_m / 1e3:.1f} km "
                           f"({km2:.0f} km2), more than [reconstruct] max_aoi_km2 = "
                           f"{r.max_aoi_km2:g}: give a smaller AOI (or raise the limit)")
    cells = float(grid.width) * float(grid.height)
    if cells > r.max_dsm_cells:
        raise OptionsError(f"the DSM grid would have {cells:.3g} cells ({grid.width} x "
                           f"{grid.height} of {grid.resolution:g} m), more than [reconstruct] "
                           f"max_dsm_cells = {r.max_dsm_cells:.3g}: use a coarser --resolution "
                           "(or raise the limit)")
