"""tools/diag_metric_resolution.py: the truth drawn on offset grids, and what it scores."""

from __future__ import annotations

import numpy as np
import pytest

from satsweep.errors import InputError
from satsweep.io.geotiff import write_geotiff
from tools.diag_metric_resolution import (
    completeness,
    main,
    offset_truth,
    read_dsm,
    scores,
    truth_grid,
)

# The truth on a grid moved by exactly one cell is the truth's own next column (row): the same
# UTM points go through pyproj, up to the rounding of x_min + res + k res against
# x_min + (k + 1) res (nanometres on the ground, far less in height).
WHOLE_CELL_TOL_M = 1e-6


def test_offset_truth_moves_the_grid_east_and_north(small_town):
    truth, info = read_dsm(small_town.truth_dsm)
    grid = truth_grid(small_town)
    assert grid.width == truth.shape[1] and grid.height == truth.shape[0]
    east = offset_truth(small_town, grid.resolution, 0.0, grid=grid)
    north = offset_truth(small_town, 0.0, grid.resolution, grid=grid)
    np.testing.assert_allclose(east[:, :-1], truth[:, 1:], atol=WHOLE_CELL_TOL_M)  # column c -> c+1
    np.testing.assert_allclose(north[1:, :], truth[:-1, :], atol=WHOLE_CELL_TOL_M)  # row r -> r-1


def test_scores_of_the_exact_truth_and_of_a_dsm(small_town, tmp_path):
    truth, info = read_dsm(small_town.truth_dsm)
    res = scores(small_town, (0.0, 0.25), [small_town.truth_dsm])
    # The truth against itself on its own grid is complete; drawn a quarter cell off it is not
    # (cells beside the walls take the wall's other side), and the truth file scored against
    # the offset truths gives those same figures (its cells re-indexed, not interpolated).
    assert res["perfect"][(0.0, 0.0)] == 1.0
    assert res["perfect"][(0.25, 0.0)] < 1.0
    assert res[str(small_town.truth_dsm)][(0.0, 0.0)] == 1.0
    # Keys are (dx east, dy north): the figure of (0.25, 0) is that of the truth moved east.
    east = completeness(offset_truth(small_town, 0.25, 0.0), truth, info.resolution)
    north = completeness(offset_truth(small_town, 0.0, 0.25), truth, info.resolution)
    assert east != north
    assert res["perfect"][(0.25, 0.0)] == east and res["perfect"][(0.0, 0.25)] == north


def test_a_dsm_in_another_crs_is_an_error_naming_it(small_town, tmp_path, capsys):
    truth, info = read_dsm(small_town.truth_dsm)
    other = 32632 if info.epsg != 32632 else 32633
    path = tmp_path / "other_zone.tif"
    write_geotiff(path, truth, epsg=other, x_min=info.x_min, y_max=info.y_max,
                  resolution=info.resolution)
    with pytest.raises(InputError, match="other_zone.tif.*EPSG"):
        scores(small_town, (0.0,), [path])
    assert main([str(small_town.directory), "--dsm", str(path), "--offsets", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "other_zone.tif" in err[0]
