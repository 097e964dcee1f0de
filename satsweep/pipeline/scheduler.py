"""The areas of a run (the AOI, or its tiles) processed in turn into one DSM grid, then the
outputs.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from satsweep.config import PipelineConfig
from satsweep.errors import InputError
from satsweep.geometry.altitude import resolve_altitude_range
from satsweep.geometry.aoi import AOI
from satsweep.pipeline.area import _CUT, _LATER, _reconstruct_area
from satsweep.pipeline.outputs import OutputFolder, ReconstructResult, _write_outputs
from satsweep.pipeline.report import RunReport


def _reconstruct_tiles(paths, aoi, out: OutputFolder, grid, pending, cloud, rep: RunReport,
                       device, *, alt_range, dem, config: PipelineConfig,
                       truth) -> ReconstructResult:
    """The areas of ``pending`` (tiles, cut again where their cameras need it) into the DSM,
    confidence and orthophoto rasters on ``grid`` and the ``cloud`` writer, then the outputs."""
    from satsweep.pipeline.tiling import MIN_TILE_M, can_split, split_tile, sub_grid
    from satsweep.products.fusion import fill_small_holes

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
        from satsweep.geometry.camera import write_cameras

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
    from satsweep.errors import AOIError
    from satsweep.geometry.altitude import altitude_range_from_rpcs
    from satsweep.geometry.rpc import RPCModel
    from satsweep.io.images import image_shape
    from satsweep.io.views import aoi_footprint

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


def _cloud_in(cloud, grid) -> tuple:
    """The points of a cloud (x, y, z, colours) whose DSM cell lies in ``grid``."""
    x, y, z, colours = cloud
    i, j = grid.cell_of(x=x, y=y)
    keep = (i >= 0) & (i < grid.height) & (j >= 0) & (j < grid.width)
    return x[keep], y[keep], z[keep], None if colours is None else colours[keep]
