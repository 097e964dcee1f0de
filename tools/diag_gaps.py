#!/usr/bin/env python3
"""Where a DSM of a synthetic scene is wrong between buildings, and what the DFC offset costs.

For a run of ``satsweep reconstruct`` on a ``satsweep synth`` scene: its DSM is evaluated by the
DFC protocol (``satsweep evaluate --protocol dfc``), and its aligned error is split over the
"gaps" of the truth: ground cells that a closing of the raised cells (RAISED_M above the lowest
cell within RAISED_WINDOW_M) by GAP_WIDTH_M fills (alleys, courtyards, inner corners). Each gap
cell's floor is tested for visibility from every view (a march from the floor towards the view's
satellite through the truth DSM); the table gives the gaps' share of the cells and of the absolute
error (also by the gaps' widths, WIDTH_CLASSES_M), how many views see their floors, how much the
MAE would fall were the gap cells that N views see (and that come out more than 1 m high) right,
and, from the run's report, how many of its reference views see those floors and have a source
that sees them too. Last, the protocol's mean vertical offset: where it leaves the correct cells
(within 1 m), and the MAE at the median offset instead (what the blunders' imbalance costs).

    python tools/diag_gaps.py SCENE_DIR RUN_DIR/dsm.tif [--report RUN_DIR/report.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from satsweep.products.evaluate import EvaluateOptions, evaluate_dsm, read_dsm  # noqa: E402
from satsweep.synth.scene import Scene  # noqa: E402

# A cell is raised where the truth lies this much above its lowest cell within RAISED_WINDOW_M.
RAISED_M = 2.5
RAISED_WINDOW_M = 30.0
# Gaps: what a closing of the raised cells by a square this wide (m) adds.
GAP_WIDTH_M = 4.5
# The visibility march: steps (m of height) up to this far above the floor; a floor is seen
# where the truth stays under the ray (with this much slack, m, for the raster's interpolation).
MARCH_STEP_M = 0.25
MARCH_TOP_M = 60.0
MARCH_SLACK_M = 0.1
# Views that see a gap's floor, for the bounds on what the gaps cost.
SEEN_BY = (3, 5, 8)
# Correct cells: aligned error within this (m), the completeness's threshold.
CORRECT_M = EvaluateOptions().threshold_m
# The gaps by width: those that a closing by a square of each of these sides (m) fills, each
# class holding the narrower ones (at 0.5 m cells: 3, 5, 7, 9 and 13 cells; a square of k cells
# fills the gaps of up to k - 1 cells across).
WIDTH_CLASSES_M = (1.0, 2.0, 3.0, 4.0, 6.0)


def raised_cells(truth: np.ndarray, resolution: float) -> np.ndarray:
    """The cells of a truth DSM (NaN: no data) RAISED_M above its lowest within RAISED_WINDOW_M."""
    from scipy.ndimage import minimum_filter

    window = 2 * int(round(RAISED_WINDOW_M / resolution)) + 1
    ground = minimum_filter(np.nan_to_num(truth, nan=np.inf), window)
    return truth - ground > RAISED_M


def _gaps(raised: np.ndarray, truth: np.ndarray, resolution: float, width_m: float) -> np.ndarray:
    """What a closing of ``raised`` by a square of ``width_m`` adds, on the truth's cells."""
    from scipy.ndimage import binary_closing

    side = 2 * int(round(width_m / 2.0 / resolution)) + 1
    closed = binary_closing(raised, structure=np.ones((side, side), bool))
    return closed & ~raised & np.isfinite(truth)


def gap_cells(truth: np.ndarray, resolution: float,
              width_m: float = GAP_WIDTH_M) -> tuple[np.ndarray, np.ndarray]:
    """(raised, gap) masks of a truth DSM (NaN: no data) on cells of ``resolution`` m: the gaps
    are what a closing of the raised cells by a square of ``width_m`` adds."""
    raised = raised_cells(truth, resolution)
    return raised, _gaps(raised, truth, resolution, width_m)


def gap_width_shares(truth: np.ndarray, error: np.ndarray, resolution: float) -> list[dict]:
    """Per width of WIDTH_CLASSES_M, the gaps that a closing by a square that wide fills: their
    share of ``error``'s valid cells and of its absolute error (``error``: on the truth's grid,
    NaN where not compared)."""
    valid = np.isfinite(error)
    total = float(np.abs(error[valid]).sum())
    raised = raised_cells(truth, resolution)
    rows = []
    for width in WIDTH_CLASSES_M:
        g = _gaps(raised, truth, resolution, width) & valid
        rows.append({"closing_m": width,
                     "cell_share": round(float(g.sum() / max(1, valid.sum())), 4),
                     "error_share": round(float(np.abs(error[g]).sum() / total), 4)
                     if total > 0 else 0.0})
    return rows


def floor_visibility(scene: Scene, truth: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(N, views) bool: whether each view sees the floor of truth cells (rows, cols)."""
    from scipy.ndimage import map_coordinates

    res = scene.dsm_grid.resolution
    floor = truth[rows, cols]
    height = np.nan_to_num(truth, nan=-np.inf)  # off the truth: nothing blocks
    seen = np.zeros((len(rows), len(scene.views)), bool)
    for k, view in enumerate(scene.views):
        tilt, azimuth = np.radians(view.off_nadir_deg), np.radians(view.azimuth_deg)
        east, north = np.sin(azimuth) * np.tan(tilt), np.cos(azimuth) * np.tan(tilt)  # m per m up
        ok = np.ones(len(rows), bool)
        for up in np.arange(MARCH_STEP_M, MARCH_TOP_M, MARCH_STEP_M):
            h = map_coordinates(height, [rows - north * up / res, cols + east * up / res], order=1,
                                mode="constant", cval=-np.inf)
            ok &= h <= floor + up + MARCH_SLACK_M
        seen[:, k] = ok
    return seen


def _view_index(name: str, scene: Scene) -> int:
    names = [v.image.name for v in scene.views]
    return names.index(Path(name).name)


def diagnose(scene_dir: str, dsm: str, report: str | None) -> dict:
    scene = Scene.load(scene_dir)
    with tempfile.TemporaryDirectory() as tmp:
        evaluation = evaluate_dsm(dsm, scene.truth_dsm, EvaluateOptions(protocol="dfc"), out_dir=tmp)
        error, _ = read_dsm(Path(tmp) / "error.tif")
    truth, _ = read_dsm(scene.truth_dsm)
    _, gap = gap_cells(truth, scene.dsm_grid.resolution)
    valid = np.isfinite(error)
    n = int(valid.sum())
    total = float(np.abs(error[valid]).sum())
    out = {"scene": Path(scene_dir).name, "dfc_mae_m": round(float(evaluation["mean_abs_error_m"]), 4),
           "offset_m": round(float(evaluation["shift"]["dz_m"]), 4)}
    g = gap & valid
    out.update(gap_share=round(float(g.sum() / n), 4),
               gap_error_share=round(float(np.abs(error[g]).sum() / total), 4),
               gap_high_share=round(float(np.mean(error[g] > CORRECT_M)), 4))
    out["gap_widths"] = gap_width_shares(truth, error, scene.dsm_grid.resolution)
    rows, cols = np.nonzero(g)
    seen = floor_visibility(scene, truth, rows, cols)
    count = seen.sum(axis=1)
    e = error[rows, cols]
    out["views_seeing_floor_quartiles"] = [float(q) for q in np.percentile(count, [25, 50, 75])]
    for k in SEEN_BY:
        sel = count >= k
        out[f"seen_by_{k}_cells"] = int(sel.sum())
        out[f"seen_by_{k}_high_share"] = round(float(np.mean(e[sel] > CORRECT_M)), 4) if sel.any() else None
        out[f"seen_by_{k}_mae_bound_m"] = round(float(np.abs(e[sel & (e > CORRECT_M)]).sum() / n), 4)
    if report is not None and Path(report).is_file():
        programs = json.loads(Path(report).read_text())["view_selection"]["references"]
        refs = [_view_index(p["reference"], scene) for p in programs]
        sources = [[_view_index(s, scene) for s in p["sources"]] for p in programs]
        high5 = (count >= 5) & (e > CORRECT_M)
        see = np.stack([seen[:, r] for r in refs], axis=1)
        pair = np.stack([seen[:, r] & seen[:, src].any(axis=1) for r, src in zip(refs, sources)], axis=1)
        out["references"] = len(refs)
        if high5.any():
            out["high_seen_by_5_references_seeing_median"] = float(np.median(see[high5].sum(axis=1)))
            out["high_seen_by_5_four_references_with_a_source_share"] = round(
                float(np.mean(pair[high5].sum(axis=1) >= 4)), 4)
    right = valid & (np.abs(error) <= CORRECT_M)
    ev = error[valid]
    out.update(correct_cells_median_m=round(float(np.median(error[right])), 4),
               high_mass_m=round(float(ev[ev > CORRECT_M].sum() / n), 4),
               low_mass_m=round(float(ev[ev < -CORRECT_M].sum() / n), 4),
               mae_at_median_offset_m=round(float(np.abs(ev - np.median(ev)).mean()), 4))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scene", help="the synthetic scene folder (satsweep synth)")
    p.add_argument("dsm", help="the run's dsm.tif")
    p.add_argument("--report", help="the run's report.json (default: beside the DSM)")
    args = p.parse_args(argv)
    report = args.report or str(Path(args.dsm).with_name("report.json"))
    print(json.dumps(diagnose(args.scene, args.dsm, report), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
