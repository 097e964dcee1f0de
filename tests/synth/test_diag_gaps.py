"""tools/diag_gaps.py: the gaps' share of a DSM's error, and the floors' visibility."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from satsweep.products.evaluate import read_dsm
from satsweep.products.grid import write_dsm_geotiff
from tools.diag_gaps import diagnose, floor_visibility, gap_cells

# Height (m) the test adds to every gap cell of the truth: a DSM whose alleys are filled.
FILL_M = 5.0
# The report's figures are rounded to 1e-4.
ROUNDED = 1e-4


def test_floor_visibility_of_a_wall():
    """A floor d metres west of a wall of height H, seen from the east at off-nadir angle t, is
    hidden exactly where d < H tan t; from the west it is always seen."""
    res, height = 0.5, 10.0
    truth = np.zeros((9, 80))
    truth[:, 60:] = height  # the wall's face between columns 59 and 60
    tilt = 30.0
    views = [SimpleNamespace(off_nadir_deg=tilt, azimuth_deg=90.0),   # satellite in the east
             SimpleNamespace(off_nadir_deg=tilt, azimuth_deg=270.0)]  # in the west
    scene = SimpleNamespace(dsm_grid=SimpleNamespace(resolution=res), views=views)
    cols = np.arange(0, 60)
    rows = np.full(len(cols), 4)
    seen = floor_visibility(scene, truth, rows, cols)
    distance = (59.5 - cols) * res  # from the cell's centre to the wall's face
    shadow = height * math.tan(math.radians(tilt))
    clear = np.abs(distance - shadow) > res  # the march's steps and the raster's interpolation
    np.testing.assert_array_equal(seen[clear, 0], distance[clear] >= shadow)
    assert seen[:, 1].all()


@pytest.fixture(scope="module")
def filled(small_town, tmp_path_factory):
    """The truth with its gaps FILL_M higher, written as a run's DSM."""
    truth, _ = read_dsm(small_town.truth_dsm)
    _, gap = gap_cells(truth, small_town.dsm_grid.resolution)
    dsm = truth.copy()
    dsm[gap] += FILL_M
    path = tmp_path_factory.mktemp("gaps") / "dsm.tif"
    write_dsm_geotiff(path, dsm, small_town.dsm_grid)
    return path, float(gap[np.isfinite(truth)].mean())


def test_a_dsm_with_filled_gaps(small_town, filled):
    """Gaps FILL_M too high, elsewhere exact: after the protocol's mean offset (FILL_M times the
    gaps' share s) the gaps hold half the absolute error, all of them high, the correct cells
    sit at -FILL_M s, and the median offset would leave FILL_M s of MAE."""
    path, s = filled
    assert 0.0 < s < 0.5
    row = diagnose(str(small_town.directory), str(path), None)
    assert row["offset_m"] == pytest.approx(-FILL_M * s, abs=ROUNDED)
    assert row["dfc_mae_m"] == pytest.approx(2.0 * FILL_M * s * (1.0 - s), abs=ROUNDED)
    assert row["gap_share"] == pytest.approx(s, abs=ROUNDED)
    assert row["gap_error_share"] == pytest.approx(0.5, abs=ROUNDED)
    assert row["gap_high_share"] == 1.0
    assert row["correct_cells_median_m"] == pytest.approx(-FILL_M * s, abs=ROUNDED)
    assert row["mae_at_median_offset_m"] == pytest.approx(FILL_M * s, abs=ROUNDED)
