"""tools/bench_multidate.py's --baseline: which runs changed between two of its --json files."""

from __future__ import annotations

import json

import pytest

from tools.bench_multidate import SAME_TOL, compare_rows, main


def _row(seed, views, mae, holds=True, scene="s_a", kind="views", **extra):
    row = {"seed": seed, "kind": kind, "k": len(views), "views": list(views), "scene": scene,
           "altitude_range": [95.0, 165.0], "truth_range": [99.0, 150.0], "references": 3,
           "median_m": 0.2, "completeness_1m": 0.8, "dfc_mae_m": mae, "dfc_valid": 0.99,
           "pointing_px": 0.02, "range_holds_truth": holds}
    row.update(extra)
    return row


def test_compare_rows_lists_what_changed_and_the_means():
    before = [_row(0, [0, 1, 2], 2.0), _row(0, [0, 1, 2, 3, 4], 1.0),
              _row(1, [0, 1, 2], 3.0, holds=False), _row(2, [0, 2, 4], 4.0),
              _row(0, [0, 1], 5.0, kind="same-date pair")]
    after = [_row(0, [0, 1, 2], 2.0 + SAME_TOL / 2),  # the same figure
             _row(0, [0, 1, 2, 3, 4], 1.5),
             _row(1, [0, 1, 2], 3.0, holds=False, altitude_range=[80.0, 165.0]),
             {"seed": 2, "kind": "views", "k": 3, "views": [0, 2, 4], "scene": "s_a",
              "error": "no tie"},
             _row(0, [0, 1], 5.0, kind="same-date pair"),
             _row(3, [0, 1, 2], 1.0)]
    cmp = compare_rows(before, after)
    assert cmp["matched"] == 5
    assert [(a["seed"], a["k"], a.get("error"), b.get("error")) for a, b in cmp["changed"]] == [
        (0, 5, None, None), (1, 3, None, None), (2, 3, None, "no tie")]
    assert [r["seed"] for r in cmp["only_after"]] == [3] and cmp["only_before"] == []
    # the means over the runs with a DSM in both: seeds 0 (twice) and 1, and the pair
    assert cmp["scored"] == 4
    assert cmp["mean_dfc_mae_m"] == pytest.approx(((2 + 1 + 3 + 5) / 4, (2 + 1.5 + 3 + 5) / 4))
    assert cmp["ranges_holding_truth"] == (3, 3)


def test_compare_rows_keeps_scenes_apart():
    """Rows of two scenes with one seed and the same views (another --dates, --size) are two
    runs; a row written before rows named their scene matches either."""
    before = [_row(0, [0, 1, 2], 1.0, scene="s0_d5"), _row(0, [0, 1, 2], 2.0, scene="s0_d10")]
    after = [_row(0, [0, 1, 2], 2.0, scene="s0_d10"), _row(0, [0, 1, 2], 1.0, scene="s0_d5")]
    cmp = compare_rows(before, after)
    assert cmp["matched"] == 2 and cmp["changed"] == []
    unnamed = [_row(0, [0, 1, 2], 1.0, scene=None)]
    cmp = compare_rows(unnamed, [_row(0, [0, 1, 2], 1.25, scene="s0_d5")])
    assert cmp["matched"] == 1 and len(cmp["changed"]) == 1


def test_a_bad_baseline_file_stops_before_any_run(tmp_path, capsys):
    bad = tmp_path / "before.json"
    bad.write_text(json.dumps({"rows": []}))
    with pytest.raises(SystemExit) as exc:
        main(["--baseline", str(bad), "--scenes", str(tmp_path / "scenes")])
    assert exc.value.code == 2
    assert "before.json: not a JSON file of this tool's rows" in capsys.readouterr().err
    assert not (tmp_path / "scenes").exists()
