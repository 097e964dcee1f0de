#!/usr/bin/env python3
"""Benchmark of the MRF refinements (satsweep.dense.mrf): time and accuracy of SGM and graph cut.

Runs both methods on the same synthetic cost volume (``mrf.synthetic_roof_volume``: textured
terrain around a large weakly textured roof, known true plane per pixel) and prints, per method:
wall time, time per megapixel per 100 planes, and the accuracy on the roof and on the terrain
(median |error| and completeness = fraction of pixels within 1 m), next to winner-take-all, and
SGM followed by the height map's weighted median (kernels/median.cl). The last lines are the
ratios of the median's time to SGM's and of SGM's to the graph cut's, measured in this run.

    python tools/bench_mrf.py                       # 256 x 256 pixels, 100 planes
    python tools/bench_mrf.py --size 1024 --planes 128 --repeats 3
    python tools/bench_mrf.py --aexpansion          # also PyMaxflow's plain aexpansion_grid

Timings are the best of ``--repeats`` runs; the SGM program is built before timing. SGM times
include the upload of the volume, the layout changes and the winner-take-all on the device.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from satsweep.dense import graphcut, mrf  # noqa: E402
from satsweep.dense import sgm as sgm_mod  # noqa: E402
from satsweep.dense.median import weighted_median  # noqa: E402
from satsweep.dense.volume import CostVolume  # noqa: E402
from satsweep.opencl.device import open_device  # noqa: E402
from tests import synthetic_volumes  # noqa: E402

COMPLETENESS_M = 1.0  # |error| threshold of the completeness figure (metres)


def _accuracy(height: np.ndarray, valid: np.ndarray, scene: synthetic_volumes.SyntheticVolume,
              mask: np.ndarray) -> tuple[float, float]:
    err = np.where(valid, np.abs(height - scene.truth_height), np.inf)[mask]
    return float(np.median(err)), float(np.mean(err < COMPLETENESS_M))


def _best_time(fn, repeats: int):
    best, out = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def _aexpansion_seconds(scene: synthetic_volumes.SyntheticVolume, options: mrf.MRFOptions) -> float:
    """PyMaxflow's aexpansion_grid with one global truncated-linear matrix (no contrast term)."""
    import maxflow  # noqa: PLC0415

    n_labels = scene.cost.shape[0]
    k = np.arange(n_labels)
    v = options.gc_smoothness * scene.cost_scale * np.minimum(
        np.abs(k[:, None] - k[None, :]), options.gc_truncation_labels).astype(np.float64)
    d = np.ascontiguousarray(np.moveaxis(scene.cost, 0, -1), dtype=np.float64)
    t0 = time.perf_counter()
    maxflow.aexpansion_grid(d, v, max_cycles=options.gc_iterations)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", type=int, nargs="+", default=[256],
                   help="image size: SIDE or ROWS COLS (default 256)")
    p.add_argument("--planes", type=int, default=100, help="number of planes (default 100)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--repeats", type=int, default=1, help="best of this many runs (default 1)")
    p.add_argument("--device", default=None, help="auto|cpu|gpu|PLATFORM:DEVICE")
    p.add_argument("--aexpansion", action="store_true",
                   help="also time PyMaxflow's aexpansion_grid on the full volume (slow)")
    p.add_argument("--gc-levels", type=int, default=None, help="override MRFOptions.gc_levels")
    p.add_argument("--gc-window", type=int, default=None,
                   help="override MRFOptions.gc_label_window")
    p.add_argument("--sgm-paths", type=int, choices=(4, 8), default=None)
    p.add_argument("--median-radius", type=int, default=4,
                   help="window radius (px) of the weighted median after SGM (default 4: 1.2 m "
                   "at 0.3 m, the consensus areas' [mrf] consensus_median_radius_m)")
    args = p.parse_args(argv)
    rows, cols = (args.size * 2)[:2] if len(args.size) == 1 else args.size[:2]

    opts = mrf.MRFOptions()
    if args.gc_levels is not None:
        opts = opts.replace(gc_levels=args.gc_levels)
    if args.gc_window is not None:
        opts = opts.replace(gc_label_window=args.gc_window)
    if args.sgm_paths is not None:
        opts = opts.replace(sgm_paths=args.sgm_paths)

    scene = synthetic_volumes.synthetic_roof_volume((rows, cols), args.planes, seed=args.seed)
    device = open_device(args.device)
    mpx_100 = rows * cols / 1e6 * args.planes / 100.0
    print(f"volume {args.planes} planes x {rows} x {cols} ({scene.cost.nbytes / 2**20:.0f} MiB), "
          f"device {device.info.label}")
    print(f"options: {opts.to_dict()}")

    volume, crop = CostVolume(scene.cost), CostVolume(scene.cost[:, :8, :8])
    # Build the SGM and WTA programs outside the timing.
    sgm_mod.sgm_refine(device, crop, scene.guide[:8, :8], scene.heights, opts,
                       cost_scale=scene.cost_scale)

    rows_out = []
    t_wta, wta = _best_time(lambda: mrf.wta_labels(volume), args.repeats)
    everywhere = np.ones(scene.roof.shape, bool)
    rows_out.append(("wta (host argmin)", t_wta,
                     _accuracy(scene.heights[wta], everywhere, scene, scene.roof),
                     _accuracy(scene.heights[wta], everywhere, scene, ~scene.roof)))
    t_sgm, sgm = _best_time(lambda: sgm_mod.sgm_refine(device, volume, scene.guide, scene.heights,
                                                       opts, cost_scale=scene.cost_scale),
                            args.repeats)
    form = "two raster scans" if opts.sgm_scan else "a launch per direction"
    rows_out.append((f"sgm ({opts.sgm_paths} paths, {form})", t_sgm,
                     _accuracy(sgm.height, sgm.valid, scene, scene.roof),
                     _accuracy(sgm.height, sgm.valid, scene, ~scene.roof)))
    # The height map's weighted median after SGM (kernels/median.cl), its program built first.
    def median():
        return weighted_median(device, sgm.height, sgm.valid, scene.guide,
                               radius=args.median_radius, sigma=opts.median_sigma)

    median()
    t_median, smoothed = _best_time(median, args.repeats)
    rows_out.append((f"sgm + weighted median ({args.median_radius} px)", t_sgm + t_median,
                     _accuracy(smoothed, sgm.valid, scene, scene.roof),
                     _accuracy(smoothed, sgm.valid, scene, ~scene.roof)))
    # The other form of SGM's aggregation (MRFOptions.sgm_scan), in the same run (CPUs only:
    # GPUs run one work-group per scanline, which has no scan form).
    if sgm_mod.sgm_work_group(device, opts, args.planes) == 1:
        other = opts.replace(sgm_scan=not opts.sgm_scan)
        sgm_mod.sgm_refine(device, crop, scene.guide[:8, :8], scene.heights, other,
                           cost_scale=scene.cost_scale)
        t_other, res = _best_time(lambda: sgm_mod.sgm_refine(device, volume, scene.guide,
                                                             scene.heights, other,
                                                             cost_scale=scene.cost_scale),
                                  args.repeats)
        form = "two raster scans" if other.sgm_scan else "a launch per direction"
        rows_out.append((f"sgm ({other.sgm_paths} paths, {form})", t_other,
                         _accuracy(res.height, res.valid, scene, scene.roof),
                         _accuracy(res.height, res.valid, scene, ~scene.roof)))
    t_gc, gc = _best_time(lambda: graphcut.graphcut_refine(volume, scene.guide, scene.heights,
                                                           opts, cost_scale=scene.cost_scale),
                          args.repeats)
    rows_out.append((f"graphcut (levels {opts.gc_levels}, window {opts.gc_label_window})", t_gc,
                     _accuracy(gc.height, gc.valid, scene, scene.roof),
                     _accuracy(gc.height, gc.valid, scene, ~scene.roof)))

    print()
    print(f"| method | time (s) | s / Mpx / 100 planes | roof median err (m) | roof completeness "
          f"(<{COMPLETENESS_M:g} m) | terrain completeness |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, t, (rmed, rcomp), (_, tcomp) in rows_out:
        print(f"| {name} | {t:.3f} | {t / mpx_100:.2f} | {rmed:.2f} | {rcomp:.3f} | {tcomp:.3f} |")
    if args.aexpansion:
        t_ae = _aexpansion_seconds(scene, opts)
        print(f"| aexpansion_grid (full label range, global smoothness, timing only) | {t_ae:.3f} "
              f"| {t_ae / mpx_100:.2f} | | | |")
    print()
    print(f"weighted median / SGM time ratio: {t_median / t_sgm:.3f} "
          f"({t_median / (rows * cols / 1e6):.3f} s per Mpx)")
    print(f"SGM / graph-cut time ratio: {t_sgm / t_gc:.3f} "
          f"(SGM {t_sgm / mpx_100:.2f} s, graph cut {t_gc / mpx_100:.2f} s per Mpx per 100 planes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
