"""Time the pointing-error correction (``satsweep cameras --adjust``) on a synthetic scene.

    python tools/bench_ba.py [--size 1000] [--views 3] [--bias 2] [--scene DIR] [--repeat 3]

Generates (or reuses, with ``--scene DIR`` holding a ``satsweep synth`` scene) a scene of
``--views`` views of ``--size`` x ``--size`` pixels with pointing biases up to ``--bias`` px, loads
and crops the views, fits the cameras, then times the adjustment stage by stage: SIFT features,
matching (ratio test, mutual check, epipolar verification), tracks, bundle adjustment. Prints
seconds per stage (best of ``--repeat`` runs), the counts and errors of the report, and the
recovered shifts against the injected biases (relative to the mean over views, after removing the
unobservable height/translation motion; see satsweep.sparse.bundle).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time

import numpy as np


def main(argv=None) -> int:
    from satsweep.geometry.altitude import AltitudeRange
    from satsweep.geometry.camera import build_cameras
    from satsweep.io.images import tonemap
    from satsweep.io.views import load_views
    from satsweep.sparse import bundle
    from satsweep.synth.scene import Scene, SynthOptions, generate_scene

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=1000, help="view width and height (px)")
    p.add_argument("--views", type=int, default=3, help="number of views")
    p.add_argument("--bias", type=float, default=2.0, help="max pointing bias per axis (px)")
    p.add_argument("--seed", type=int, default=0, help="scene seed")
    p.add_argument("--scene", help="reuse this synth scene folder (generated there if empty)")
    p.add_argument("--repeat", type=int, default=3, help="runs of the adjustment; the best is shown")
    args = p.parse_args(argv)

    print(f"cpus available: {len(os.sched_getaffinity(0))}, numpy {np.__version__}")
    tmp = None
    folder = args.scene
    if folder is None:
        tmp = folder = tempfile.mkdtemp(prefix="bench_ba_")
    try:
        if os.path.isfile(os.path.join(folder, "scene.json")):
            scene = Scene.load(folder)
            print(f"scene: {folder} (reused)")
        else:
            t = time.perf_counter()
            scene = generate_scene(folder, SynthOptions(seed=args.seed, n_views=args.views, size_px=args.size,
                                                        bias_px=args.bias))
            print(f"scene: generated in {time.perf_counter() - t:.1f} s")
        alt = AltitudeRange(*scene.alt_range)
        t = time.perf_counter()
        views = load_views([v.image for v in scene.views], scene.aoi, alt)
        t_load = time.perf_counter() - t
        t = time.perf_counter()
        cams = build_cameras(views, scene.aoi, alt)
        t_cams = time.perf_counter() - t
        t = time.perf_counter()
        images = [tonemap(v.image) for v in views]
        t_tone = time.perf_counter() - t
        print(f"views: {', '.join(f'{v.width}x{v.height}' for v in views)}; load {t_load:.2f} s, "
              f"cameras {t_cams:.2f} s, tonemap {t_tone:.2f} s (not part of the step timed below)")

        best = None
        for _ in range(max(1, args.repeat)):
            t = time.perf_counter()
            _, report = bundle.adjust_principal_points(cams, images)
            total = time.perf_counter() - t
            if best is None or total < best[0]:
                best = (total, report)
        total, report = best
        for stage, sec in report.seconds.items():
            print(f"  {stage:<11} {sec:6.2f} s")
        print(f"  {'total':<11} {total:6.2f} s   (adjust_principal_points, best of {max(1, args.repeat)})")
        print(f"features per view: {list(report.n_features)}; matches per pair: "
              f"{[k for _, _, k in report.n_matches]}; tracks: {report.n_tracks} "
              f"(lengths {report.track_length_histogram}); points kept: {report.n_points}; "
              f"solver evaluations: {list(report.solver_evaluations)}")
        print(f"reprojection error median/mean: before {report.reproj_before_px[0]:.3f}/"
              f"{report.reproj_before_px[1]:.3f} px, after {report.reproj_after_px[0]:.3f}/"
              f"{report.reproj_after_px[1]:.3f} px")
        biases = np.array([v.bias_px for v in scene.views])
        shifts = np.array(report.principal_point_shift_px)
        A = bundle.gauge_jacobians([v.camera for v in cams.views])
        rel = (shifts - shifts.mean(0)) - (biases - biases.mean(0))
        dX = np.linalg.lstsq(A.reshape(-1, 3), -rel.ravel(), rcond=None)[0]
        resid = rel + A @ dX
        for name, b, s, r in zip(report.names, biases, shifts, resid):
            print(f"  {name}: bias ({b[0]:+.3f}, {b[1]:+.3f}) shift ({s[0]:+.3f}, {s[1]:+.3f}) "
                  f"relative residual after the gauge ({r[0]:+.3f}, {r[1]:+.3f}) px")
        print(f"  unobservable motion removed: dX = ({dX[0]:+.2f}, {dX[1]:+.2f}, {dX[2]:+.2f}) m")
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
