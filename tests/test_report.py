"""Run report: stage timings add up, JSON is strict, progress prints bounded lines."""

from __future__ import annotations

import io
import json

import numpy as np

from satsweep.report import Progress, RunReport, to_json


def test_stage_timings_accumulate_and_json_is_strict():
    stream = io.StringIO()
    rep = RunReport("test", stream=stream)
    for _ in range(2):
        with rep.stage("sweep"):
            pass
    rep["figures"] = {"nan": float("nan"), "arr": np.arange(3), "f": np.float32(1.5)}
    data = json.loads(to_json(rep.finish()))
    assert data["timings_s"]["sweep"] >= 0 and "total" in data["timings_s"]
    assert data["figures"] == {"nan": None, "arr": [0, 1, 2], "f": 1.5}
    assert stream.getvalue().count("[sweep] done") == 2


def test_progress_throttles_but_always_prints_the_end():
    stream = io.StringIO()
    p = Progress("tiles", 100, stream=stream, interval_s=3600)
    for k in range(1, 101):
        p.update(k)
    lines = stream.getvalue().splitlines()
    assert lines == ["[tiles] 1/100 (1%)", "[tiles] 100/100 (100%)"]
