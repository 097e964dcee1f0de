"""The run's rasters on its DSM grid, assembled on disk from the areas' pieces.

Each finished area (the AOI, or one tile of it) saves its core cells as one ``.npy`` file per
raster in its folder of the run's finished tiles (``save_piece``: an ``AreaPiece``), and its
points as a cloud piece (``save_cloud_piece``), so that what is held in memory is one area's
rasters at a time, whatever the AOI's size, and so that a Dask worker makes the piece
(``satsweep.pipeline.cluster``). The cloud file is written from the pieces in the areas' order
(``append_cloud_piece``). At the end ``assemble`` copies the pieces into one band per raster
on disk (``satsweep.io.bands.RawBand``), ``fill_holes`` fills the DSM's small holes block by
block (exactly as ``satsweep.products.fusion.fill_small_holes`` does on the whole grid: each
block is filled within a margin as wide as the largest hole, which holds every hole that
reaches the block, with its rim) and marks the interpolated cells, and the outputs are written
from the bands (``satsweep.io.cog``).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Mapping, Sequence

import numpy as np

from satsweep.io.bands import RawBand

if TYPE_CHECKING:  # pragma: no cover
    from satsweep.products.grid import DSMGrid

# The rasters an area gives: (type, value where no area gives one).
BANDS = {"dsm": (np.float32, np.nan), "confidence": (np.float32, np.nan),
         "ortho": (np.float32, np.nan), "count": (np.uint8, 0)}
# Values of the interpolated-cells mask.
MEASURED, INTERPOLATED, NO_HEIGHT = 0, 1, 255
# Side (cells) of the blocks the holes are filled in (each read with its margin).
FILL_BLOCK_CELLS = 1024
# Rows of cells copied or scanned at once when a band is read whole, block by block.
SCAN_ROWS = 1024


@dataclasses.dataclass(frozen=True)
class AreaPiece:
    """One finished area's rasters over its core cells, on disk."""

    folder: Path
    core: tuple[int, int, int, int]  # (r0, r1, c0, c1) of the run's grid, ends excluded
    bands: tuple[str, ...]

    def path(self, band: str) -> Path:
        return self.folder / f"{band}.npy"

    def load(self, band: str) -> np.ndarray:
        return np.load(self.path(band))


def save_piece(folder: str | os.PathLike, core: tuple[int, int, int, int],
               rasters: Mapping[str, np.ndarray]) -> AreaPiece:
    """Save an area's core-cell rasters (each of the core's shape) in ``folder``; each file is
    written under a temporary name and renamed, and ``piece.json`` last, so a piece whose
    ``piece.json`` exists is whole."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    r0, r1, c0, c1 = core
    for name, array in rasters.items():
        array = np.asarray(array)
        if array.shape != (r1 - r0, c1 - c0):
            raise ValueError(f"{name}: shape {array.shape} is not the core's {(r1 - r0, c1 - c0)}")
        tmp = folder / f".{name}.tmp.npy"
        np.save(tmp, array)
        os.replace(tmp, folder / f"{name}.npy")
    meta = {"core": list(core), "bands": list(rasters)}
    tmp = folder / ".piece.json.tmp"
    tmp.write_text(json.dumps(meta), encoding="utf-8")
    os.replace(tmp, folder / "piece.json")
    return AreaPiece(folder=folder, core=tuple(core), bands=tuple(rasters))


def load_piece(folder: str | os.PathLike) -> AreaPiece:
    """The piece saved in ``folder`` (``save_piece``)."""
    folder = Path(folder)
    meta = json.loads((folder / "piece.json").read_text(encoding="utf-8"))
    return AreaPiece(folder=folder, core=tuple(meta["core"]), bands=tuple(meta["bands"]))


# The files of an area's cloud piece: float64 (n, 3) x, y, z (UTM, height) and uint8 (n, 3)
# colours, in the order the area's reference views gave them.
CLOUD_XYZ, CLOUD_RGB = "cloud_xyz.npy", "cloud_rgb.npy"
# Points copied at a time from a cloud piece into the cloud file.
CLOUD_CHUNK_POINTS = 2**20


def _cloud_in(cloud, grid) -> tuple:
    """The points of a cloud (x, y, z, colours) whose DSM cell lies in ``grid``."""
    x, y, z, colours = cloud
    i, j = grid.cell_of(x=x, y=y)
    keep = (i >= 0) & (i < grid.height) & (j >= 0) & (j < grid.width)
    return x[keep], y[keep], z[keep], colours[keep]


def save_cloud_piece(folder: str | os.PathLike, clouds: Sequence[tuple],
                     core: "DSMGrid | None") -> int:
    """Save an area's clouds (per reference view: x, y, z and (n, 3) uint8 colours) as one
    piece in ``folder``, keeping the points whose cell lies in ``core`` (None: all); each file
    under a temporary name, then renamed. Returns the number of points."""
    folder = Path(folder)
    parts = [c if core is None else _cloud_in(c, core) for c in clouds]
    xyz = (np.stack([np.concatenate([p[k] for p in parts]) for k in range(3)], axis=1)
           if parts else np.zeros((0, 3)))
    rgb = np.concatenate([p[3] for p in parts]) if parts else np.zeros((0, 3), np.uint8)
    for name, array in ((CLOUD_XYZ, xyz.astype(np.float64)), (CLOUD_RGB, rgb.astype(np.uint8))):
        tmp = folder / f".{name}.tmp.npy"
        np.save(tmp, array)
        os.replace(tmp, folder / name)
    return int(xyz.shape[0])


def append_cloud_piece(writer, folder: str | os.PathLike) -> int:
    """Append the cloud piece saved in ``folder`` to a ``PLYWriter``, a chunk at a time (the
    piece is memory-mapped); the number of points."""
    folder = Path(folder)
    xyz = np.load(folder / CLOUD_XYZ, mmap_mode="r")
    rgb = np.load(folder / CLOUD_RGB, mmap_mode="r")
    for k in range(0, xyz.shape[0], CLOUD_CHUNK_POINTS):
        block = np.asarray(xyz[k:k + CLOUD_CHUNK_POINTS])
        writer.append(block[:, 0], block[:, 1], block[:, 2],
                      colors=np.asarray(rgb[k:k + CLOUD_CHUNK_POINTS]))
    return int(xyz.shape[0])


def assemble(grid: "DSMGrid", pieces: Sequence[AreaPiece], work: str | os.PathLike,
             bands: Sequence[str]) -> dict[str, RawBand]:
    """One band per name of ``bands`` on ``grid`` (of the type ``BANDS`` gives it, and its
    value where no piece has one), from the pieces, in ``work``."""
    work = Path(work)
    out = {name: RawBand.create(work / f"{name}.raw", grid.shape, *BANDS[name]) for name in bands}
    for piece in pieces:
        r0, _, c0, _ = piece.core
        for name in bands:
            if name in piece.bands:
                out[name].write(r0, c0, piece.load(name))
    return out


@dataclasses.dataclass(frozen=True)
class Filled:
    """The DSM with its small holes filled, the mask of its interpolated cells, and counts."""

    dsm: RawBand  # float32, NaN where no height
    interpolated: RawBand  # uint8: MEASURED, INTERPOLATED or NO_HEIGHT
    filled_cells: int  # cells given a height by the filling
    valid_cells: int  # cells with a height, filled ones included


def fill_holes(dsm: RawBand, work: str | os.PathLike, *, max_hole_cells: int,
               method: Literal["min", "supported_min", "median"], border_holes: bool = True,
               block: int = FILL_BLOCK_CELLS) -> Filled:
    """``fill_small_holes`` of the whole band, block by block (see the module docstring)."""
    from satsweep.products.fusion import fill_small_holes

    work = Path(work)
    h, w = dsm.shape
    out = RawBand.create(work / "dsm_filled.raw", dsm.shape, np.float32, np.nan)
    mask = RawBand.create(work / "interpolated.raw", dsm.shape, np.uint8, NO_HEIGHT)
    margin = max(int(max_hole_cells), 0) + 1  # a hole of max_hole_cells and its rim
    filled = valid = 0
    for r0 in range(0, h, block):
        for c0 in range(0, w, block):
            r1, c1 = min(r0 + block, h), min(c0 + block, w)
            inner_values = dsm.read(r0, r1, c0, c1)
            before = np.isfinite(inner_values)
            if before.all() or not before.any() or max_hole_cells <= 0:
                # No hole here, or one of the whole block (larger than any hole that is filled).
                result = inner_values
            else:
                wr0, wr1 = max(r0 - margin, 0), min(r1 + margin, h)
                wc0, wc1 = max(c0 - margin, 0), min(c1 + margin, w)
                window = dsm.read(wr0, wr1, wc0, wc1)
                # A hole that reaches the block from the window's edge (not the grid's) spans the
                # margin: more than max_hole_cells, never filled, as on the whole grid.
                done, _ = fill_small_holes(window, max_hole_cells=max_hole_cells, method=method,
                                           border_holes=border_holes)
                result = done[r0 - wr0:r1 - wr0, c0 - wc0:c1 - wc0]
            after = np.isfinite(result)
            out.write(r0, c0, result)
            mask.write(r0, c0, np.where(before, MEASURED, np.where(after, INTERPOLATED, NO_HEIGHT))
                       .astype(np.uint8))
            filled += int(np.count_nonzero(after & ~before))
            valid += int(np.count_nonzero(after))
    return Filled(dsm=out, interpolated=mask, filled_cells=filled, valid_cells=valid)


def decimated(band: RawBand, max_side: int) -> np.ndarray:
    """The band's cells every ``ceil(max(shape) / max_side)`` rows and columns (a small copy for
    a quick look), read by blocks of rows."""
    h, w = band.shape
    step = max(1, -(-max(h, w) // max_side))
    chunk = max(step, SCAN_ROWS // step * step)  # a multiple of step: every block starts on one
    # A copy of each block's samples: a view would keep the whole block alive.
    rows = [band.read(r0, min(r0 + chunk, h), 0, w)[::step, ::step].copy()
            for r0 in range(0, h, chunk)]
    return np.concatenate(rows) if rows else np.zeros((0, 0), band.dtype)
