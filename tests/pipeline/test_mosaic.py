"""The mosaic on disk: pieces assembled into bands, and holes filled block by block exactly as
the whole-grid filling does."""

from __future__ import annotations

import numpy as np
import pytest

from satsweep.io.bands import RawBand
from satsweep.pipeline.mosaic import (
    INTERPOLATED,
    MEASURED,
    NO_HEIGHT,
    assemble,
    decimated,
    fill_holes,
    load_piece,
    save_piece,
)
from satsweep.products.fusion import fill_small_holes
from satsweep.products.grid import DSMGrid


def _dsm_with_holes(seed: int, shape=(90, 110)) -> np.ndarray:
    """A smooth surface with holes of every size (single cells to large gaps), some touching the
    border."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:shape[0], 0:shape[1]]
    a = (100.0 + 0.1 * x + 3.0 * np.sin(y / 7.0)).astype(np.float32)
    for _ in range(40):
        r, c = rng.integers(0, shape[0]), rng.integers(0, shape[1])
        h, w = rng.integers(1, 12, size=2)
        a[r:r + h, c:c + w] = np.nan
    return a


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("method", ["min", "median", "supported_min"])
@pytest.mark.parametrize("border_holes", [True, False])
def test_blockwise_filling_is_the_whole_grid_filling(tmp_path, seed, method, border_holes):
    a = _dsm_with_holes(seed)
    band = RawBand.create(tmp_path / "dsm.raw", a.shape, np.float32, np.nan)
    band.write(0, 0, a)
    expected, count = fill_small_holes(a, max_hole_cells=30, method=method,
                                       border_holes=border_holes)
    filled = fill_holes(band, tmp_path, max_hole_cells=30, method=method,
                        border_holes=border_holes, block=16)
    np.testing.assert_array_equal(filled.dsm.read(0, 90, 0, 110), expected)
    assert filled.filled_cells == count and filled.valid_cells == np.isfinite(expected).sum()
    mask = filled.interpolated.read(0, 90, 0, 110)
    np.testing.assert_array_equal(mask == MEASURED, np.isfinite(a))
    np.testing.assert_array_equal(mask == INTERPOLATED, np.isfinite(expected) & ~np.isfinite(a))
    np.testing.assert_array_equal(mask == NO_HEIGHT, ~np.isfinite(expected))


def test_pieces_assemble_into_the_grid(tmp_path):
    grid = DSMGrid(epsg=32631, x_min=0.0, y_max=100.0, resolution=1.0, width=30, height=20)
    rng = np.random.default_rng(2)
    truth = np.full(grid.shape, np.nan, np.float32)
    pieces = []
    for k, core in enumerate([(0, 10, 0, 30), (10, 20, 0, 12), (10, 20, 12, 30)]):
        r0, r1, c0, c1 = core
        values = rng.normal(size=(r1 - r0, c1 - c0)).astype(np.float32)
        truth[r0:r1, c0:c1] = values
        pieces.append(save_piece(tmp_path / f"area_{k}", core, {"dsm": values}))
    pieces = [load_piece(p.folder) for p in pieces]  # as another process would find them
    bands = assemble(grid, pieces, tmp_path, ["dsm", "ortho"])
    np.testing.assert_array_equal(bands["dsm"].read(0, 20, 0, 30), truth)
    assert np.isnan(bands["ortho"].read(0, 20, 0, 30)).all()
    np.testing.assert_array_equal(decimated(bands["dsm"], 10), truth[::3, ::3])
