#!/usr/bin/env python3
"""Peak memory and time of `satsweep reconstruct` against the AOI's size (issue 27, item 4).

The Pleiades pair of the shared data sees about 0.5 km x 0.5 km. The AOIs here are squares of
0.5, 2 and 8 km (by default) centred on it, so the DSM grid grows 256-fold while the imagery
stays the same: the tiles outside the images are left without heights, and what grows is what
the run holds for the grid (the DSM, confidence and orthophoto rasters, the hole filling, the
GeoTIFFs). Each run is a new `satsweep reconstruct` process, and its report gives the peak
resident memory (VmHWM) at the end of each stage.

    python tools/bench_scale.py                   # 0.5, 2, 8 km
    python tools/bench_scale.py --sides 0.5 2     # quicker
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PLEIADES = REPO.parent / "shared" / "data" / "pleiades_pair"
# The centre of the Pleiades pair's region (the AOI of tools/bench_e2e.py) and its heights.
CENTRE_LON, CENTRE_LAT = 55.650212, -21.230532
ALT_RANGE = ("2260", "2390")
METRES_PER_DEGREE = 111_320.0


def square_aoi(side_km: float) -> str:
    half_lat = side_km * 500.0 / METRES_PER_DEGREE
    half_lon = half_lat / math.cos(math.radians(CENTRE_LAT))
    return (f"{CENTRE_LON - half_lon:.7f},{CENTRE_LAT - half_lat:.7f},"
            f"{CENTRE_LON + half_lon:.7f},{CENTRE_LAT + half_lat:.7f}")


def run(side_km: float, out: Path, extra: list[str]) -> dict:
    cmd = [sys.executable, "-m", "satsweep", "reconstruct", str(PLEIADES / "img_01.tif"),
           str(PLEIADES / "img_02.tif"), "--aoi", square_aoi(side_km), "--alt-range", *ALT_RANGE,
           "--out", str(out), "--quiet", *extra]
    t = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if done.returncode not in (0, 3):
        raise SystemExit(f"side {side_km} km failed ({done.returncode}): {done.stderr.strip()}")
    report = json.loads((out / "report.json").read_text())
    return {"side_km": side_km, "wall_s": wall, "report": report}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sides", type=float, nargs="+", default=[0.5, 2.0, 8.0], metavar="KM")
    p.add_argument("--set", action="append", default=[], metavar="ARG",
                   help="extra argument for satsweep reconstruct (repeatable)")
    args = p.parse_args(argv)
    if not (PLEIADES / "img_01.tif").is_file():
        print(f"{PLEIADES} is absent: this benchmark needs the shared data", file=sys.stderr)
        return 2
    print(f"{'side':>6} {'grid':>13} {'tiles':>6} {'filled':>7} {'peak MiB':>9} "
          f"{'peak after sweep':>16} {'wall s':>7}  stages (s)")
    with tempfile.TemporaryDirectory(prefix="satsweep-bench-scale-") as tmp:
        for side in args.sides:
            r = run(side, Path(tmp) / f"side_{side:g}", args.set)
            rep = r["report"]
            peak = rep["peak_memory_mb"]
            dsm = rep["dsm"]
            stages = ", ".join(f"{k} {v:.1f}" for k, v in rep["timings_s"].items() if k != "total")
            print(f"{side:>5g}k {dsm['width']:>6}x{dsm['height']:<6} {rep['tiling']['tiles']:>6} "
                  f"{100 * dsm['filled_fraction']:>6.2f}% {peak['total']:>9.0f} "
                  f"{peak.get('mrf', peak.get('sweep', float('nan'))):>16.0f} "
                  f"{r['wall_s']:>7.1f}  {stages}")
            for path in sorted((Path(tmp) / f"side_{side:g}").glob("*.tif")):
                print(f"{'':>8}{path.name}: {path.stat().st_size / 2**20:.1f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
