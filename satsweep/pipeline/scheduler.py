"""The areas of a run (the AOI in one piece, or its tiles) reconstructed in turn into one mosaic.

Tiles come from ``satsweep.pipeline.tiling``. Each tile takes the images that see it (a large
AOI need not lie in every image); one seen by fewer than two is left without heights. An area
answers ``Split`` when its cameras are too far from the RPCs (its 2 x 2 parts go to the front of
the queue) and ``Wait`` when its views match too poorly for their own bundle adjustment (it goes
to the back, once, and then takes the median of the other tiles' pointing corrections: a
pointing error is a translation of the whole image). Each finished area fills its core cells of
the mosaic and appends its points to the cloud.
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from satsweep.errors import InputError
from satsweep.pipeline.altitude import prior_altitude_range
from satsweep.pipeline.area import (
    AreaJob,
    AreaResult,
    RunContext,
    Split,
    Wait,
    median_shifts,
    run_area,
    sources_seeing,
)
from satsweep.pipeline.mosaic import AreaPiece, save_piece

if TYPE_CHECKING:  # pragma: no cover
    from satsweep.geometry.aoi import AOI
    from satsweep.io.sources import ImageSource
    from satsweep.pipeline.tiling import Tile
    from satsweep.products.grid import DSMGrid
    from satsweep.products.ply import PLYWriter


@dataclasses.dataclass(eq=False)
class Mosaic:
    """What the areas of a run made: their pieces on disk (each area's core cells of the DSM,
    confidence and orthophoto rasters, see ``satsweep.pipeline.mosaic``) and their figures."""

    grid: "DSMGrid"
    pieces: list[AreaPiece]  # in the order the areas finished
    done: list[tuple["Tile", AreaResult]]  # the same areas, without their arrays
    splits: list[dict[str, Any]]  # the areas cut again: cells, camera error, parts
    unseen: list[dict[str, Any]]  # the tiles seen by fewer than two images

    @property
    def tiled(self) -> bool:
        """More than one area, or part of the AOI left unseen."""
        return len(self.done) > 1 or bool(self.unseen)


def _cloud_in(cloud, grid) -> tuple:
    """The points of a cloud (x, y, z, colours) whose DSM cell lies in ``grid``."""
    x, y, z, colours = cloud
    i, j = grid.cell_of(x=x, y=y)
    keep = (i >= 0) & (i < grid.height) & (j >= 0) & (j < grid.width)
    return x[keep], y[keep], z[keep], None if colours is None else colours[keep]


def reconstruct_areas(sources: Sequence["ImageSource"], aoi: "AOI", grid: "DSMGrid",
                      tiles: list["Tile"], cloud: "PLYWriter | None", ctx: RunContext,
                      work: str | os.PathLike) -> Mosaic:
    """Every area of ``tiles`` (cut again where their cameras need it) into a ``Mosaic`` on
    ``grid``, its pieces saved in ``work``; their points go to ``cloud``."""
    from satsweep.pipeline.tiling import MIN_TILE_M, can_split, split_tile, sub_grid

    r, rep = ctx.config.reconstruct, ctx.report
    mosaic = Mosaic(grid=grid, pieces=[], done=[], splits=[], unseen=[])
    shifts: dict[str, list] = {s.path: [] for s in sources}  # per image, its tiles' corrections
    deferred = set()  # tiles put back once, for want of matches
    pending = list(tiles)
    whole = (0, grid.height, 0, grid.width)
    t_start = time.perf_counter()
    while pending:
        tile = pending.pop(0)
        tile_sources = list(sources)
        if tile.core != whole:
            # Splits add tiles as the run goes: the count is of the tiles queued now.
            done = len(mosaic.done)
            spent = time.perf_counter() - t_start
            left = (f"; {spent:.0f} s so far, about {spent / done * (len(pending) + 1):.0f} s "
                    "left" if done else "")
            rep.log(f"tile {done + 1} ({len(pending)} more queued): cells {tile.core}{left}")
            prior = prior_altitude_range(sources, tile.aoi, alt_range=ctx.alt_range, dem=ctx.dem)
            tile_sources = sources_seeing(sources, tile.aoi, prior)
            if len(tile_sources) < 2:
                rep.warn(f"cells {tile.core} are seen by {len(tile_sources)} image(s): left "
                         "without heights")
                mosaic.unseen.append({"core_cells": list(tile.core),
                                      "images": [s.name for s in tile_sources]})
                continue
        borrowed = (dict(zip([s.path for s in tile_sources],
                             median_shifts([shifts[s.path] for s in tile_sources])))
                    if all(shifts[s.path] for s in tile_sources) else None)
        job = AreaJob(sources=tile_sources, aoi=tile.aoi, grid=tile.grid,
                      split_above_px=(r.tile_max_error_px if can_split(tile, grid, MIN_TILE_M)
                                      else 0.0),
                      borrowed_shifts=borrowed,
                      may_wait=borrowed is None and bool(pending) and id(tile) not in deferred)
        outcome = run_area(job, ctx)
        if isinstance(outcome, Wait):
            deferred.add(id(tile))
            pending.append(tile)
            continue
        if isinstance(outcome, Split):  # the cameras are too far from the RPCs: cut it again
            parts = split_tile(tile, aoi, grid, overlap_m=r.tile_overlap_m, min_m=MIN_TILE_M)
            rep.log(f"cameras up to {outcome.max_error_px:.3f} px from the RPCs over cells "
                    f"{tile.core} (more than tile_max_error_px = {r.tile_max_error_px:g}): "
                    f"{len(parts)} tiles")
            mosaic.splits.append({"core_cells": list(tile.core),
                                  "max_error_px": outcome.max_error_px, "into": len(parts)})
            pending[:0] = parts
            continue
        rows, cols = tile.core_in_window
        area = outcome.rasters
        core = {"dsm": area.dsm[rows, cols], "confidence": area.confidence[rows, cols],
                "count": area.count[rows, cols]}
        if area.ortho is not None:
            core["ortho"] = area.ortho[rows, cols]
        mosaic.pieces.append(save_piece(Path(work) / f"area_{len(mosaic.pieces):04d}",
                                        tile.core, core))
        for piece in area.clouds:  # the whole AOI's area kept the grid's points already
            x, y, z, colours = (piece if tile.core == whole
                                else _cloud_in(piece, sub_grid(grid, *tile.core)))
            cloud.append(x, y, z, colors=colours)
        mosaic.done.append((tile, outcome.without_arrays()))
        for path, shift in (outcome.shifts or {}).items():
            shifts[path].append(shift)
    if not mosaic.done:
        raise InputError(None, f"no tile of the AOI is seen by two of the images "
                               f"({', '.join(s.name for s in sources)})")
    return mosaic
