"""The DSM grid: north up, square cells on the UTM zone of the AOI centre, and its GeoTIFF.

Grid convention (``DSMGrid``): ``x_min``/``y_max`` are the outer corner of the top-left cell
(GDAL's geotransform origin); cell (i, j) (row i, column j) has its centre at
``(x_min + (j + 0.5) * resolution, y_max - (i + 0.5) * resolution)``.
"""

from __future__ import annotations

import dataclasses
import math
import os

import numpy as np

from satsweep.errors import OptionsError

# Points per AOI edge when projecting its outline to UTM: the edges of a lon/lat box are curved
# in UTM, so the corners alone can miss the true extent by up to a few metres on large AOIs.
AOI_EDGE_SAMPLES = 65


# -- grid --------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class DSMGrid:
    """A north-up raster grid in a projected CRS (see the module docstring for the convention)."""

    epsg: int  # EPSG code of the projected CRS (UTM: 326zz / 327zz)
    x_min: float  # west edge of the grid (outer edge of column 0), metres
    y_max: float  # north edge of the grid (outer edge of row 0), metres
    resolution: float  # cell size, metres
    width: int  # number of columns
    height: int  # number of rows

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution) and self.resolution > 0.0):
            raise OptionsError(f"DSMGrid.resolution = {self.resolution!r}: must be > 0 metres")
        if not (math.isfinite(self.x_min) and math.isfinite(self.y_max)):
            raise OptionsError(f"DSMGrid origin ({self.x_min!r}, {self.y_max!r}): must be finite")
        if self.width < 1 or self.height < 1:
            raise OptionsError(f"DSMGrid size {self.width}x{self.height}: must be at least 1x1")

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns)."""
        return self.height, self.width

    @property
    def x_max(self) -> float:
        return self.x_min + self.width * self.resolution

    @property
    def y_min(self) -> float:
        return self.y_max - self.height * self.resolution

    @property
    def geotransform(self) -> tuple[float, float, float, float, float, float]:
        """GDAL geotransform (x_min, res, 0, y_max, 0, -res)."""
        return (self.x_min, self.resolution, 0.0, self.y_max, 0.0, -self.resolution)

    def cell_centers(self) -> tuple[np.ndarray, np.ndarray]:
        """(x of the column centres (width,), y of the row centres (height,)), metres."""
        r = self.resolution
        return self.x_min + (np.arange(self.width) + 0.5) * r, self.y_max - (np.arange(self.height) + 0.5) * r

    def cell_of(self, *, x, y) -> tuple[np.ndarray, np.ndarray]:
        """(row, column) integer indices of the cells holding map points (may be out of range)."""
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        j = np.floor((x - self.x_min) / self.resolution)
        i = np.floor((self.y_max - y) / self.resolution)
        return i, j


def dsm_grid_for_aoi(aoi, resolution: float, epsg: int | None = None) -> DSMGrid:
    """The DSM grid covering an AOI: UTM zone of the AOI centre unless ``epsg`` is given.

    The AOI outline (lon/lat box, densified with ``AOI_EDGE_SAMPLES`` points per edge) is
    projected, and its bounding box is snapped outward to multiples of ``resolution`` metres, so
    grids of the same zone and resolution share cell boundaries.
    """
    from satsweep.geometry.geodesy import lonlat_to_utm, utm_epsg

    resolution = float(resolution)
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise OptionsError(f"resolution = {resolution!r}: must be > 0 metres")
    lon0, lon1 = float(aoi.lon_min), float(aoi.lon_max)
    lat0, lat1 = float(aoi.lat_min), float(aoi.lat_max)
    if epsg is None:
        lon_c, lat_c = aoi.center
        epsg = utm_epsg(lon=lon_c, lat=lat_c)
    t = np.linspace(0.0, 1.0, AOI_EDGE_SAMPLES)
    lons = np.concatenate([lon0 + t * (lon1 - lon0), np.full_like(t, lon1), lon1 - t * (lon1 - lon0), np.full_like(t, lon0)])
    lats = np.concatenate([np.full_like(t, lat0), lat0 + t * (lat1 - lat0), np.full_like(t, lat1), lat1 - t * (lat1 - lat0)])
    x, y = lonlat_to_utm(lon=lons, lat=lats, epsg=int(epsg))
    x_min = math.floor(float(np.min(x)) / resolution) * resolution
    x_max = math.ceil(float(np.max(x)) / resolution) * resolution
    y_min = math.floor(float(np.min(y)) / resolution) * resolution
    y_max = math.ceil(float(np.max(y)) / resolution) * resolution
    return DSMGrid(
        epsg=int(epsg), x_min=x_min, y_max=y_max, resolution=resolution,
        width=max(1, int(round((x_max - x_min) / resolution))),
        height=max(1, int(round((y_max - y_min) / resolution))),
    )


def write_dsm_geotiff(path: str | os.PathLike, array: np.ndarray, grid: DSMGrid) -> None:
    """Write a raster on ``grid`` as a float32 GeoTIFF with NaN nodata (atomically)."""
    from satsweep.io.geotiff import write_geotiff

    a = np.asarray(array)
    if a.shape != grid.shape:
        raise ValueError(f"array shape {a.shape} does not match the grid {grid.shape}")
    write_geotiff(path, a.astype(np.float32), epsg=grid.epsg, x_min=grid.x_min, y_max=grid.y_max,
                  resolution=grid.resolution, nodata=math.nan)
