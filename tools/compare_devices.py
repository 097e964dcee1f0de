#!/usr/bin/env python3
"""Do two OpenCL devices give the same DSM? The Pleiades pair reconstructed on each, compared.

Issue 6 asks that height maps "must not depend on the device beyond float rounding: PoCL and GPU
height maps agree to within 0.05 m median where both are available". This tool runs the whole
``reconstruct`` on the real Pleiades pair of the shared data (the region and altitudes of
``tools/bench_e2e.py``) once per device and MRF method, and compares each device's DSM with the
first device's over the cells both have: median and 95th percentile of |difference|, the share of
cells within TOLERANCE_M, and the cells only one of them has. It also prints each run's wall time
and stage seconds, so a GPU run gives the GPU figures beside PoCL's.

    python tools/compare_devices.py --devices 0:0 1:0            # e.g. PoCL against a GPU
    python tools/compare_devices.py --devices 0:0 0:0 --mrf none # one device twice: identical
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))

from bench_e2e import PLEIADES_ALT_RANGE, pleiades_aoi  # noqa: E402

from satsweep.config import PipelineConfig  # noqa: E402
from satsweep.geometry.altitude import AltitudeRange  # noqa: E402
from satsweep.io.geotiff import read_geotiff  # noqa: E402
from satsweep.pipeline.run import reconstruct  # noqa: E402

# Issue 6's bound on the median height difference between devices (m).
TOLERANCE_M = 0.05


def compare(a: np.ndarray, b: np.ndarray) -> dict:
    """Figures of |a - b| over the cells both have, and the cells only one has."""
    both = np.isfinite(a) & np.isfinite(b)
    d = np.abs(a[both].astype(np.float64) - b[both].astype(np.float64))
    return {
        "common_cells": int(both.sum()),
        "only_one": int((np.isfinite(a) != np.isfinite(b)).sum()),
        "median_abs_m": float(np.median(d)) if d.size else float("nan"),
        "p95_abs_m": float(np.percentile(d, 95)) if d.size else float("nan"),
        "within_tolerance": float(np.mean(d <= TOLERANCE_M)) if d.size else float("nan"),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--devices", nargs="+", required=True, metavar="SPEC",
                   help="device specs as `satsweep devices` lists them (PLATFORM:DEVICE); the first "
                        "is the reference")
    p.add_argument("--mrf", nargs="+", choices=["none", "sgm", "graphcut"], default=["none", "sgm"],
                   help="MRF methods to run (default: none and sgm)")
    p.add_argument("--pleiades", default=os.fspath(REPO.parent / "shared" / "data" / "pleiades_pair"),
                   help="folder of the Pleiades pair (img_01.tif, img_02.tif)")
    p.add_argument("--out", default=None, help="folder for the reconstructions (default: temporary)")
    args = p.parse_args(argv)
    if len(args.devices) < 2:
        p.error("give at least two --devices (the first is the reference)")

    pair = Path(args.pleiades)
    images = [pair / "img_01.tif", pair / "img_02.tif"]
    aoi = pleiades_aoi(pair)
    alt = AltitudeRange(*PLEIADES_ALT_RANGE)
    with tempfile.TemporaryDirectory(prefix="satsweep-compare-devices-") as tmp:
        root = Path(args.out) if args.out else Path(tmp)
        for method in args.mrf:
            dsms = []
            for k, spec in enumerate(args.devices):
                config = PipelineConfig().override("reconstruct", device=spec).override(
                    "mrf", method=method)
                out = root / f"{method}_{k}"
                t0 = time.perf_counter()
                res = reconstruct(images, aoi, out, alt_range=alt, config=config, overwrite=True,
                                  verbose=False, command="compare_devices")
                wall = time.perf_counter() - t0
                dsms.append(read_geotiff(res.dsm_path)[0])
                stages = ", ".join(f"{s} {v:.2f}" for s, v in res.report["timings_s"].items()
                                   if s != "total")
                print(f"mrf {method}, device {spec} ({res.report['device']['device_name']}): "
                      f"{wall:.2f} s ({stages})")
            for spec, dsm in zip(args.devices[1:], dsms[1:]):
                c = compare(dsms[0], dsm)
                verdict = "met" if c["median_abs_m"] <= TOLERANCE_M else "not met"
                print(f"mrf {method}, {args.devices[0]} vs {spec}: median |difference| "
                      f"{c['median_abs_m']:.4f} m, 95th percentile {c['p95_abs_m']:.4f} m, "
                      f"{c['within_tolerance']:.1%} within {TOLERANCE_M} m over "
                      f"{c['common_cells']} common cells, {c['only_one']} cells in one DSM only "
                      f"(issue 6: median <= {TOLERANCE_M} m: {verdict})")
    return 0


if __name__ == "__main__":
    from satsweep.errors import SatsweepError

    try:
        sys.exit(main())
    except SatsweepError as exc:
        print(f"compare_devices: error: {exc}", file=sys.stderr)
        sys.exit(2)
