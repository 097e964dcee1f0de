"""Run report: stage timings add up, JSON is strict, progress prints bounded lines."""

from __future__ import annotations

import io
import json
import subprocess
import sys

import numpy as np
import pytest

from satsweep.pipeline.report import Progress, RunReport, to_json


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


def test_a_warning_is_given_once():
    stream = io.StringIO()
    rep = RunReport("test", stream=stream)
    rep.warn("view_01.tif: the image sees only about 90% of the AOI footprint")
    rep.warn("view_01.tif: the image sees only about 90% of the AOI footprint")
    rep.warn("view_01.tif: the image sees only about 90% of the AOI footprint", doubtful=True)
    assert stream.getvalue().count("warning: view_01.tif") == 2
    assert [w["doubtful"] for w in rep.data["warnings"]] == [False, True]
    assert rep.doubtful


def test_a_tiles_warnings_say_which_cells_they_are_about():
    """A tile's report puts its cells before each warning, so the same words from two tiles
    are two warnings, each printed once."""
    stream = io.StringIO()
    tiles = [RunReport("tile", stream=stream, where=f"cells {core}: ")
             for core in ((0, 10, 0, 10), (0, 10, 10, 20))]
    for rep in tiles + tiles[:1]:
        rep.warn("view_01.tif: dropped by the sparse stage")
    assert stream.getvalue().splitlines() == [
        "warning: cells (0, 10, 0, 10): view_01.tif: dropped by the sparse stage",
        "warning: cells (0, 10, 10, 20): view_01.tif: dropped by the sparse stage"]
    assert [w["message"] for w in tiles[1].data["warnings"]] == [
        "cells (0, 10, 10, 20): view_01.tif: dropped by the sparse stage"]


def test_progress_throttles_but_always_prints_the_end():
    stream = io.StringIO()
    p = Progress("tiles", 100, stream=stream, interval_s=3600)
    for k in range(1, 101):
        p.update(k)
    lines = stream.getvalue().splitlines()
    assert lines == ["[tiles] 1/100 (1%)", "[tiles] 100/100 (100%)"]


# A stage that touches this much new memory must raise the recorded high-water mark by most of it
# (the allocator may reuse a few MiB that the process had freed before).
_TOUCHED_MIB = 256
_REUSE_SLACK_MIB = 32
# Linux adds each thread's resident-page counts to the process's in batches (64 page events per
# thread), so two readings of the high-water mark can differ by a few hundred KiB either way.
_COUNTER_BATCH_MIB = 2.0

_STAGE_MEMORY_SCRIPT = f"""
import json, sys
import numpy as np
from satsweep.pipeline.report import RunReport
rep = RunReport("test", verbose=False)
with rep.stage("small"):
    pass
with rep.stage("big"):
    a = np.ones({_TOUCHED_MIB} * 2**20 // 8)
del a
json.dump(rep.finish()["peak_memory_mb"], sys.stdout)
"""


# A parent that touches this much before starting another process: the child's own peak must
# stay far below it (Python and numpy take some tens of MiB).
_PARENT_MIB = 512
_CHILD_BASE_LIMIT_MIB = 256

_PARENT_SCRIPT = f"""
import subprocess, sys
import numpy as np
a = np.ones({_PARENT_MIB} * 2**20 // 8)
sys.stdout.write(subprocess.run([sys.executable, "-c", sys.argv[1]], check=True,
                                capture_output=True, text=True).stdout)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"),
                    reason="other platforms report getrusage's figure, which may include the parent's")
def test_peak_memory_is_the_process_own_not_its_parents():
    out = subprocess.run([sys.executable, "-c", _PARENT_SCRIPT, _STAGE_MEMORY_SCRIPT], check=True,
                         capture_output=True, text=True).stdout
    peaks = json.loads(out)
    assert peaks["small"] < _CHILD_BASE_LIMIT_MIB
    assert peaks["big"] - peaks["small"] >= _TOUCHED_MIB - _REUSE_SLACK_MIB


def test_peak_memory_per_stage_rises_where_memory_is_touched():
    out = subprocess.run([sys.executable, "-c", _STAGE_MEMORY_SCRIPT], check=True,
                         capture_output=True, text=True).stdout
    peaks = json.loads(out)
    if not peaks:
        pytest.skip("this platform does not report peak memory")
    assert list(peaks) == ["small", "big", "total"]
    assert peaks["big"] - peaks["small"] >= _TOUCHED_MIB - _REUSE_SLACK_MIB
    # A high-water mark: freeing does not lower it (beyond the kernel's counter batching).
    assert peaks["total"] >= peaks["big"] - _COUNTER_BATCH_MIB
