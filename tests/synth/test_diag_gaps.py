"""tools/diag_gaps.py: the gaps' share of a DSM's error, and the floors' visibility."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from satsweep.products.evaluate import read_dsm
from satsweep.products.grid import write_dsm_geotiff
from tools.diag_gaps import WIDTH_CLASSES_M, diagnose, floor_visibility, gap_cells, gap_width_shares

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


def test_gap_width_shares_of_two_alleys():
    """Two blocks 10 m high with an alley of 2 cells (1 m) between them and one of 6 cells (3 m)
    beyond: the alleys are in the classes whose square spans more cells than they do (3 and 7
    cells at 0.5 m), and each class's shares are its alleys' cells and their absolute error (5 m
    in the alleys, 1 m elsewhere)."""
    res = 0.5
    # (the blocks 10 cells from the borders: the widest square's closing reaches 6 past them)
    truth = np.zeros((50, 80))
    truth[10:41, 10:25] = 10.0
    truth[10:41, 27:45] = 10.0  # the narrow alley: columns 25-26
    truth[10:41, 51:60] = 10.0  # the wide one: columns 45-50
    narrow = np.zeros(truth.shape, bool)
    narrow[10:41, 25:27] = True
    wide = np.zeros(truth.shape, bool)
    wide[10:41, 45:51] = True
    error = np.where(narrow | wide, 5.0, 1.0)
    error[0, :] = np.nan  # not compared: counted nowhere
    valid = np.isfinite(error)
    total = np.abs(error[valid]).sum()
    rows = gap_width_shares(truth, error, res)
    assert [r["closing_m"] for r in rows] == list(WIDTH_CLASSES_M)
    for r in rows:
        side = 2 * int(round(r["closing_m"] / 2.0 / res)) + 1
        g = (narrow if side > 2 else np.zeros_like(narrow)) | (wide if side > 6 else False)
        assert r["cell_share"] == pytest.approx(g.sum() / valid.sum(), abs=ROUNDED)
        assert r["error_share"] == pytest.approx(np.abs(error[g]).sum() / total, abs=ROUNDED)


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
