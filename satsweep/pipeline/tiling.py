"""AOI tiling: a large AOI is reconstructed tile by tile, each tile with its own cameras.

The perspective approximation of an RPC holds over a limited area only. Measured on the Pleiades
pair's RPC (``satsweep.camera.approximate_camera``, altitudes 2260..2390 m), the largest error
against the RPC over a square AOI of side 300 m / 1 km / 2 km / 4 km / 10 km is 0.03 / 0.095 /
0.19 / 0.43 / 1.9 px (at 0.5 px per metre of height, 1.9 px is almost 4 m). So, as S2P does, an
AOI wider or taller than ``[reconstruct] tile_m`` is cut into tiles of at most that side: each
tile is reconstructed on its own (crops, cameras, bundle adjustment, sweep, DSM) over its core
grown by ``tile_overlap_m`` of context on every side, and only its core's cells go into the DSM.
The cores partition the AOI's DSM grid, so every cell comes from exactly one tile.

The error also depends on the sensor (at 1 km: 0.01 px for a SkySat RPC, 0.05-0.11 px for
WorldView, Pleiades and SPOT ones, 0.5-0.6 px for PlanetScope's), so an area (the AOI, or a
tile) whose cameras are further than ``[reconstruct] tile_max_error_px`` from their RPCs is cut
again, in 2 x 2 (``split_tile``), down to ``MIN_TILE_M``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from satsweep.errors import OptionsError
from satsweep.geometry.aoi import AOI
from satsweep.products.grid import DSMGrid

# Smallest tile side (m): a tile needs room for its own tie points and for the sweep's context.
MIN_TILE_M = 50.0

# Points per edge of a tile's outline when it is mapped from UTM to lon/lat (the box of the
# mapped outline holds the tile; UTM grid lines are not meridians and parallels).
OUTLINE_SAMPLES = 16


@dataclasses.dataclass(frozen=True)
class Tile:
    """One tile of an AOI's DSM grid; cell ranges are (r0, r1, c0, c1), ends excluded."""

    core: tuple[int, int, int, int]  # the AOI grid's cells this tile fills
    window: tuple[int, int, int, int]  # the AOI grid's cells it is reconstructed on: the core
    # grown by the overlap, within the grid
    grid: DSMGrid  # ``window`` as a grid of its own (same CRS, cells and resolution)
    aoi: AOI  # lon/lat box of ``grid``, within the AOI: what the tile's views must see
    level: int = 0  # how many times a tile was split to make this one

    @property
    def core_in_window(self) -> tuple[slice, slice]:
        """(rows, columns) of the core within the tile's own grid."""
        r0, r1, c0, c1 = self.core
        return slice(r0 - self.window[0], r1 - self.window[0]), \
            slice(c0 - self.window[2], c1 - self.window[2])

    def to_dict(self) -> dict:
        return {"core_cells": list(self.core), "window_cells": list(self.window),
                "level": self.level, "aoi": dataclasses.asdict(self.aoi)}


def _edges(n: int, parts: int) -> list[int]:
    """parts + 1 increasing integer edges from 0 to n, as even as possible."""
    return [int(round(k * n / parts)) for k in range(parts + 1)]


def sub_grid(grid: DSMGrid, r0: int, r1: int, c0: int, c1: int) -> DSMGrid:
    """The cells r0:r1, c0:c1 of ``grid`` as a grid of their own."""
    return DSMGrid(epsg=grid.epsg, x_min=grid.x_min + c0 * grid.resolution,
                   y_max=grid.y_max - r0 * grid.resolution, resolution=grid.resolution,
                   width=c1 - c0, height=r1 - r0)


def grid_lonlat_box(grid: DSMGrid) -> tuple[float, float, float, float]:
    """(lon_min, lat_min, lon_max, lat_max) of a grid's outline, densified before mapping."""
    from satsweep.geometry.geodesy import utm_to_lonlat  # noqa: PLC0415

    t = np.linspace(0.0, 1.0, OUTLINE_SAMPLES)
    x0, x1, y0, y1 = grid.x_min, grid.x_max, grid.y_min, grid.y_max
    xs = np.concatenate([x0 + t * (x1 - x0), np.full_like(t, x1), x1 - t * (x1 - x0), np.full_like(t, x0)])
    ys = np.concatenate([np.full_like(t, y0), y0 + t * (y1 - y0), np.full_like(t, y1), y1 - t * (y1 - y0)])
    lon, lat = utm_to_lonlat(x=xs, y=ys, epsg=grid.epsg)
    return float(np.min(lon)), float(np.min(lat)), float(np.max(lon)), float(np.max(lat))


def _check_overlap(overlap_m: float) -> None:
    if not (math.isfinite(overlap_m) and overlap_m >= 0.0):
        raise OptionsError(f"tile_overlap_m = {overlap_m!r}: must be a finite number of metres >= 0")


def _tiles_of(aoi: AOI, grid: DSMGrid, region: tuple[int, int, int, int], n_rows: int,
              n_cols: int, overlap_m: float, level: int) -> list[Tile]:
    """``region`` of the AOI's ``grid`` cut into n_rows x n_cols tiles, row by row (those outside
    the AOI's lon/lat box left out)."""
    r0, r1, c0, c1 = region
    rows = [r0 + e for e in _edges(r1 - r0, n_rows)]
    cols = [c0 + e for e in _edges(c1 - c0, n_cols)]
    grow = int(math.ceil(overlap_m / grid.resolution - 1e-9))
    tiles = []
    for i in range(n_rows):
        for j in range(n_cols):
            core = (rows[i], rows[i + 1], cols[j], cols[j + 1])
            window = (max(0, core[0] - grow), min(grid.height, core[1] + grow),
                      max(0, core[2] - grow), min(grid.width, core[3] + grow))
            tile_grid = sub_grid(grid, *window)
            lon0, lat0, lon1, lat1 = grid_lonlat_box(tile_grid)
            box = (max(lon0, aoi.lon_min), max(lat0, aoi.lat_min), min(lon1, aoi.lon_max),
                   min(lat1, aoi.lat_max))
            if not (box[0] < box[2] and box[1] < box[3]):
                # A corner of a large AOI's UTM grid can lie wholly outside its lon/lat box (the
                # grid's lines are not meridians): nothing of the AOI to reconstruct there.
                continue
            tile_aoi = AOI(*box)
            tiles.append(Tile(core=core, window=window, grid=tile_grid, aoi=tile_aoi, level=level))
    return tiles


def plan_tiles(aoi: AOI, grid: DSMGrid, *, tile_m: float, overlap_m: float) -> list[Tile]:
    """The tiles of ``aoi``'s DSM ``grid``: one (the whole AOI) when both sides are at most
    ``tile_m`` metres or ``tile_m`` is 0, else the fewest tiles of at most ``tile_m`` per side,
    of equal size to a cell, each reconstructed with ``overlap_m`` of context around it."""
    if not (math.isfinite(tile_m) and tile_m >= 0.0):
        raise OptionsError(f"tile_m = {tile_m!r}: must be a finite number of metres >= 0")
    _check_overlap(overlap_m)
    res = grid.resolution
    full = (0, grid.height, 0, grid.width)
    if tile_m == 0.0 or (grid.width * res <= tile_m and grid.height * res <= tile_m):
        return [Tile(core=full, window=full, grid=grid, aoi=aoi)]
    cells_max = max(1, int(math.floor(tile_m / res + 1e-9)))
    return _tiles_of(aoi, grid, full, -(-grid.height // cells_max), -(-grid.width // cells_max),
                     overlap_m, level=0)


def can_split(tile: Tile, grid: DSMGrid, min_m: float) -> bool:
    """Whether ``split_tile`` would cut ``tile``: a side of at least twice ``min_m``."""
    r0, r1, c0, c1 = tile.core
    return max(r1 - r0, c1 - c0) * grid.resolution >= 2.0 * min_m


def split_tile(tile: Tile, aoi: AOI, grid: DSMGrid, *, overlap_m: float, min_m: float) -> list[Tile]:
    """``tile`` cut in two along each side of at least twice ``min_m`` (so 2 or 4 tiles, row by
    row), each with ``overlap_m`` of context; [tile] itself when neither side is that long."""
    _check_overlap(overlap_m)
    r0, r1, c0, c1 = tile.core
    n_rows = 2 if (r1 - r0) * grid.resolution >= 2.0 * min_m else 1
    n_cols = 2 if (c1 - c0) * grid.resolution >= 2.0 * min_m else 1
    if n_rows == n_cols == 1:
        return [tile]
    return _tiles_of(aoi, grid, tile.core, n_rows, n_cols, overlap_m, level=tile.level + 1)
