"""AOI tiling: the tiles' cores partition the DSM grid, their windows and AOIs hold them."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from satsweep.config import PipelineConfig
from satsweep.errors import OptionsError
from satsweep.geometry.aoi import AOI
from satsweep.geometry.geodesy import utm_to_lonlat
from satsweep.pipeline.tiling import can_split, plan_tiles, split_tile
from satsweep.products.grid import dsm_grid_for_aoi

# About 2.2 km x 1.7 km near La Reunion (UTM zone 40 south), a 0.5 m grid.
BIG_AOI = AOI(55.63, -21.245, 55.651, -21.23)
RESOLUTION_M = 0.5


@pytest.fixture(scope="module")
def grid():
    return dsm_grid_for_aoi(BIG_AOI, RESOLUTION_M)


def test_small_aoi_or_no_tiling_is_one_tile(grid):
    for tile_m in (0.0, 5000.0):
        tiles = plan_tiles(BIG_AOI, grid, tile_m=tile_m, overlap_m=50.0)
        assert len(tiles) == 1
        (t,) = tiles
        assert t.core == t.window == (0, grid.height, 0, grid.width)
        assert t.grid == grid and t.aoi == BIG_AOI


@pytest.mark.parametrize("tile_m, overlap_m", [(1000.0, 50.0), (700.0, 0.0), (333.3, 120.0)])
def test_cores_partition_the_grid_and_windows_grow_them(grid, tile_m, overlap_m):
    tiles = plan_tiles(BIG_AOI, grid, tile_m=tile_m, overlap_m=overlap_m)
    side = tile_m / RESOLUTION_M  # cells
    n_rows = math.ceil(grid.height / math.floor(side))
    n_cols = math.ceil(grid.width / math.floor(side))
    assert len(tiles) == n_rows * n_cols  # the fewest tiles of at most tile_m
    cover = np.zeros(grid.shape, np.int32)
    grow = math.ceil(overlap_m / RESOLUTION_M)
    for k, t in enumerate(tiles):
        assert t.level == 0
        r0, r1, c0, c1 = t.core
        assert (r0, c0) == (tiles[k - k % n_cols].core[0], tiles[k % n_cols].core[2])  # row by row
        assert 0 < r1 - r0 <= side and 0 < c1 - c0 <= side
        cover[r0:r1, c0:c1] += 1
        assert t.window == (max(0, r0 - grow), min(grid.height, r1 + grow),
                            max(0, c0 - grow), min(grid.width, c1 + grow))
        # The tile's grid is the window of the AOI's grid: same CRS and cells.
        w0, w1, v0, v1 = t.window
        assert t.grid.epsg == grid.epsg and t.grid.resolution == grid.resolution
        assert t.grid.shape == (w1 - w0, v1 - v0)
        assert t.grid.x_min == pytest.approx(grid.x_min + v0 * RESOLUTION_M, abs=1e-9)
        assert t.grid.y_max == pytest.approx(grid.y_max - w0 * RESOLUTION_M, abs=1e-9)
        rows, cols = t.core_in_window
        assert (rows.stop - rows.start, cols.stop - cols.start) == (r1 - r0, c1 - c0)
        # Its AOI lies within the AOI and holds every window cell centre that the AOI holds.
        a = t.aoi
        assert BIG_AOI.lon_min <= a.lon_min < a.lon_max <= BIG_AOI.lon_max
        assert BIG_AOI.lat_min <= a.lat_min < a.lat_max <= BIG_AOI.lat_max
        ii, jj = np.mgrid[w0:w1:7, v0:v1:7]  # every 7th cell: enough to see an edge missed
        lon, lat = utm_to_lonlat(x=grid.x_min + (jj + 0.5) * RESOLUTION_M,
                                 y=grid.y_max - (ii + 0.5) * RESOLUTION_M, epsg=grid.epsg)
        inside_aoi = ((lon >= BIG_AOI.lon_min) & (lon <= BIG_AOI.lon_max)
                      & (lat >= BIG_AOI.lat_min) & (lat <= BIG_AOI.lat_max))
        inside_tile = (lon >= a.lon_min) & (lon <= a.lon_max) & (lat >= a.lat_min) & (lat <= a.lat_max)
        assert np.all(inside_tile[inside_aoi])
    assert np.all(cover == 1)  # every cell in exactly one core


def test_bad_tile_sizes_are_refused(grid):
    with pytest.raises(OptionsError, match="tile_m"):
        plan_tiles(BIG_AOI, grid, tile_m=-1.0, overlap_m=0.0)
    with pytest.raises(OptionsError, match="tile_overlap_m"):
        plan_tiles(BIG_AOI, grid, tile_m=500.0, overlap_m=math.nan)
    for table, needle in ([{"tile_m": 10.0}, "tile_m"],
                          [{"tile_m": 100.0, "tile_overlap_m": 150.0}, "tile_overlap_m"],
                          [{"tile_max_error_px": -0.1}, "tile_max_error_px"]):
        with pytest.raises(OptionsError, match=needle):
            PipelineConfig.from_mapping({"reconstruct": table})
    assert PipelineConfig.from_mapping({"reconstruct": {"tile_m": 0.0}}).reconstruct.tile_m == 0.0


@pytest.mark.parametrize("core, parts", [((0, 1000, 0, 1000), 4), ((0, 1000, 0, 150), 2),
                                         ((0, 150, 0, 1000), 2), ((0, 150, 0, 150), 1)])
def test_split_tile_cuts_the_long_sides_in_two(grid, core, parts):
    min_m = 50.0  # a side of at least 100 m (200 cells) is cut
    (tile,) = [t for t in plan_tiles(BIG_AOI, grid, tile_m=0.0, overlap_m=0.0)]
    tile = dataclasses.replace(tile, core=core)
    pieces = split_tile(tile, BIG_AOI, grid, overlap_m=20.0, min_m=min_m)
    assert len(pieces) == parts and can_split(tile, grid, min_m) == (parts > 1)
    cover = np.zeros(grid.shape, np.int32)
    for p in pieces:
        r0, r1, c0, c1 = p.core
        cover[r0:r1, c0:c1] += 1
        assert p.level == (1 if parts > 1 else 0)
        assert p.window[0] == max(0, r0 - 40) and p.window[2] == max(0, c0 - 40)
    r0, r1, c0, c1 = core
    assert np.all(cover[r0:r1, c0:c1] == 1) and cover.sum() == (r1 - r0) * (c1 - c0)


def test_a_one_degree_aoi_plans_tiles_inside_its_box():
    """The UTM grid of a large AOI reaches beyond its lon/lat box at the corners: the tiles
    there hold nothing of the AOI and are left out instead of failing."""
    from satsweep.products.grid import dsm_grid_for_aoi

    aoi = AOI(0.0, 40.0, 1.0, 41.0)
    grid = dsm_grid_for_aoi(aoi, 5.0)  # 5 m cells keep the plan small
    tiles = plan_tiles(aoi, grid, tile_m=2000.0, overlap_m=0.0)
    assert len(tiles) > 50
    for t in tiles:
        a = t.aoi
        assert aoi.lon_min <= a.lon_min < a.lon_max <= aoi.lon_max
        assert aoi.lat_min <= a.lat_min < a.lat_max <= aoi.lat_max
    cells = sum((t.core[1] - t.core[0]) * (t.core[3] - t.core[2]) for t in tiles)
    assert cells < grid.width * grid.height  # the corners outside the box are not planned
