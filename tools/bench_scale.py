#!/usr/bin/env python3
"""Peak memory and time of `satsweep reconstruct` against the AOI's size (issue 27, item 4), and
against the number of Dask workers on a synthetic area (issue 28; ``--workers``).

The Pleiades pair of the shared data sees about 0.5 km x 0.5 km. The AOIs here are squares of
0.5, 2 and 8 km (by default) centred on it, so the DSM grid grows 256-fold while the imagery
stays the same: the tiles outside the images are left without heights, and what grows is what
the run holds for the grid (the DSM, confidence and orthophoto rasters, the hole filling, the
GeoTIFFs). Each run is a new `satsweep reconstruct` process, and its report gives the peak
resident memory (VmHWM) at the end of each stage.

    python tools/bench_scale.py                   # 0.5, 2, 8 km
    python tools/bench_scale.py --sides 0.5 2     # quicker

Workers (``--workers 1 2``): a synthetic town of ``--synth-km`` on a side (2 views at 0.5 m;
generated once into a cache folder) reconstructed in tiles of ``--tile-m`` by
`satsweep reconstruct --workers N`, a new process per run. Each run gives its wall time, the
tiles' seconds (the sum over the tiles of each task's own time), the peak resident memory of
each worker process (VmHWM, from the report's ``execution``) and of the main process, and the
DSM's digest (the runs must agree bit for bit). The extrapolation to a ``--scene-km`` scene
scales the tiles' seconds by the number of tiles, divides them by N workers at the efficiency
the 2-worker run measured, and adds the main process's assembly (the fill and outputs stages)
scaled by the number of cells:

    python tools/bench_scale.py --workers 1 2 --synth-km 1 --tile-m 500
"""

from __future__ import annotations

import argparse
import json
import math
import os
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


def synthetic_scene(side_km: float, cache: Path):
    """A 2-view synthetic town of ``side_km`` (0.5 m), generated once into ``cache``."""
    sys.path.insert(0, str(REPO))
    from satsweep.synth.scene import SynthOptions, generate_scene  # noqa: PLC0415

    size = int(round(side_km * 1000.0 / 0.5))
    folder = cache / f"synth_{size}px"
    if not (folder / "scene.json").is_file():
        t = time.perf_counter()
        generate_scene(folder, SynthOptions(seed=0, n_views=2, size_px=size, gsd_m=0.5),
                       overwrite=True)
        print(f"synthetic scene of {size} px per view made in {time.perf_counter() - t:.0f} s")
    return _scene_files(folder)


def _scene_files(folder: Path) -> dict:
    meta = json.loads((folder / "scene.json").read_text())
    a = meta["aoi"]
    return {"images": sorted(str(p) for p in folder.glob("view_*.tif")),
            "aoi": f"{a['lon_min']},{a['lat_min']},{a['lon_max']},{a['lat_max']}",
            "alt": [str(meta["altitude_range"][0] - 5.0), str(meta["altitude_range"][1] + 5.0)],
            "side_m": 2.0 * meta["aoi_half_m"]}


def run_workers(scene: dict, workers: int, tile_m: float, out: Path, extra: list[str]) -> dict:
    config = out.parent / f"tiles_{tile_m:g}.toml"
    config.write_text(f"[reconstruct]\ntile_m = {tile_m}\n")
    cmd = [sys.executable, "-m", "satsweep", "reconstruct", *scene["images"], "--aoi",
           scene["aoi"], "--alt-range", *scene["alt"], "--config", str(config), "--out",
           str(out), "--workers", str(workers), "--quiet", *extra]
    t = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if done.returncode not in (0, 3):
        raise SystemExit(f"{workers} workers failed ({done.returncode}): {done.stderr.strip()}")
    sys.path.insert(0, str(REPO / "tools"))
    from digest_outputs import digests  # noqa: PLC0415

    return {"workers": workers, "wall_s": wall, "report": json.loads((out / "report.json")
                                                                      .read_text()),
            "digests": digests(out)}


def bench_workers(args) -> int:
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    scene = synthetic_scene(args.synth_km, cache)
    print(f"synthetic town {scene['side_m']:.0f} m square, tiles of {args.tile_m:g} m")
    print(f"{'workers':>7} {'tiles':>5} {'wall s':>7} {'tiles s':>8} {'s/tile':>7} "
          f"{'worker peak MiB':>16} {'main peak MiB':>14} {'fill+out s':>10}  identical")
    runs = []
    with tempfile.TemporaryDirectory(prefix="satsweep-bench-workers-") as tmp:
        for n in args.workers:
            r = run_workers(scene, n, args.tile_m, Path(tmp) / f"w{n}", args.set)
            rep, ex = r["report"], r["report"]["execution"]
            tiles = ex["tiles_computed"]
            assembly = rep["timings_s"].get("fill", 0.0) + rep["timings_s"].get("outputs", 0.0)
            same = "-" if not runs else str(r["digests"] == runs[0]["digests"])
            r.update(tiles=tiles, tile_s=ex["tile_seconds"], assembly_s=assembly,
                     worker_peak=ex["max_worker_peak_memory_mb"],
                     main_peak=rep["peak_memory_mb"]["total"])
            runs.append(r)
            print(f"{n:>7} {tiles:>5} {r['wall_s']:>7.1f} {r['tile_s']:>8.1f} "
                  f"{r['tile_s'] / tiles:>7.2f} {r['worker_peak']:>16.0f} {r['main_peak']:>14.0f} "
                  f"{assembly:>10.2f}  {same}")
    one = runs[0]
    two = next((r for r in runs if r["workers"] == 2), None)
    side = scene["side_m"]
    scale_cells = (args.scene_km * 1000.0 / side) ** 2
    per_tile = one["tile_s"] / one["tiles"]
    n_tiles = one["tiles"] * scale_cells
    assembly = one["assembly_s"] * scale_cells
    if two is not None:
        print(f"\n2 workers on this machine's {os.cpu_count()} cores: {one['wall_s'] / two['wall_s']:.2f}"
              f" times the speed of 1 (each PoCL worker spreads its kernels over every core)")
    # On a cluster each worker has cores (or a GPU) of its own: it finishes a tile as the one
    # worker here did, and the tiles are independent; the assembly stays in the main process.
    print(f"{args.scene_km:g} x {args.scene_km:g} km scene: {n_tiles:.0f} tiles like these "
          f"({per_tile:.1f} s each on one worker), assembly about {assembly:.0f} s (fill and "
          "outputs scaled by the cells), each worker on cores of its own:")
    for n in args.extrapolate:
        hours = (math.ceil(n_tiles / n) * per_tile + assembly) / 3600.0
        print(f"  {n:>4} workers: about {hours:.2f} h, {one['worker_peak']:.0f} MiB per worker")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sides", type=float, nargs="+", default=[0.5, 2.0, 8.0], metavar="KM")
    p.add_argument("--set", action="append", default=[], metavar="ARG",
                   help="extra argument for satsweep reconstruct (repeatable)")
    p.add_argument("--workers", type=int, nargs="+", default=None, metavar="N",
                   help="the workers benchmark instead: a synthetic area run with N workers")
    p.add_argument("--synth-km", type=float, default=2.0, help="synthetic area's side (km)")
    p.add_argument("--tile-m", type=float, default=500.0, help="tile side (m)")
    p.add_argument("--scene-km", type=float, default=20.0, help="side of the extrapolated scene")
    p.add_argument("--extrapolate", type=int, nargs="+", default=[1, 8, 32, 128, 512],
                   metavar="N",
                   help="worker counts of the extrapolation")
    p.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "satsweep-bench-scale"),
                   help="folder keeping the synthetic scene between runs")
    args = p.parse_args(argv)
    if args.workers:
        return bench_workers(args)
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
