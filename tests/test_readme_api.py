"""The README's Python API examples run as written and give a sensible DSM and height map."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"

# Sanity bounds for the examples' 256 px town (2 views, B/H 0.20). They check that the examples
# do what the README says, not the accuracy (tests/pipeline/test_pipeline.py and tools/bench_e2e.py do):
# at this size the run measured 0.25 m / 80% within 1 m.
EXAMPLE_MAX_MEDIAN_M = 0.5
EXAMPLE_MIN_COMPLETENESS = 0.6
# The perspective approximation of a synthetic RPC over a 128 m AOI (measured: 0.003 px).
EXAMPLE_MAX_CAMERA_ERROR_PX = 0.05
# Share of the reference's pixels the single-pair sweep must give a height to (measured: 99%).
EXAMPLE_MIN_VALID = 0.8


def _python_blocks(section: str) -> list[str]:
    text = README.read_text(encoding="utf-8")
    start = text.index(f"## {section}\n")
    end = text.find("\n## ", start + 1)
    return re.findall(r"```python\n(.*?)```", text[start:end if end >= 0 else None], re.S)


def test_readme_python_api_examples_run(cl_device, tmp_path, monkeypatch):
    blocks = _python_blocks("Python API")
    assert len(blocks) == 2
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("SATSWEEP_DEVICE", cl_device.info.spec)  # open_device() takes this one
    namespace: dict = {}

    exec(compile(blocks[0], "README.md (Python API, 1)", "exec"), namespace)  # noqa: S102
    run = namespace["result"]
    assert run.report["settings"]["sweep"]["step_px"] == 0.35  # the override reached the run
    assert (tmp_path / run.dsm_path).samefile(tmp_path / "out" / "dsm.tif")
    aligned = run.evaluation["aligned"]
    assert aligned["median_abs_error_m"] <= EXAMPLE_MAX_MEDIAN_M
    assert aligned["completeness_1m"] >= EXAMPLE_MIN_COMPLETENESS

    exec(compile(blocks[1], "README.md (Python API, 2)", "exec"), namespace)  # noqa: S102
    cams, sweep, alt = namespace["cams"], namespace["result"], namespace["alt"]
    assert max(v.camera.error.max_px for v in cams.views) <= EXAMPLE_MAX_CAMERA_ERROR_PX
    assert sweep.valid.mean() >= EXAMPLE_MIN_VALID
    heights = sweep.altitude[sweep.valid]
    assert np.all((heights >= alt.min) & (heights <= alt.max))
