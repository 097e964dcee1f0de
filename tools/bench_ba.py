"""Accuracy and time of the pointing-error correction on synthetic stacks of 2 to 64 views.

    python tools/bench_ba.py [--views 3 5 10 20] [--seeds 0 1] [--size 1000] [--bias 50]
                             [--scenes DIR] [--prior-extra 300] [--mode sparse|adjust|both]
                             [--repeat 3] [--json FILE]

For every view count and seed it generates a ``satsweep synth`` scene (kept in ``--scenes DIR``
as ``vNN_sS_pP_bB`` and reused when there; a temporary folder otherwise) of ``--size`` px views
with pointing biases drawn up to ``--bias`` px per axis, then times and checks:

- ``sparse``: :func:`satsweep.sparse.stage.sparse_stage`, the views cropped at a prior altitude
  range (the RPCs' range widened by ``--prior-extra`` m on each side, as coarse as a real RPC's
  offset +- scale). The time is that of the call (features to altitude range), best of
  ``--repeat``; the pair graph, the views kept, and the altitude range against the truth.
- ``adjust``: :func:`satsweep.sparse.bundle.adjust_principal_points` (``satsweep cameras
  --adjust``), the views cropped at the scene's own altitude range and cameras fitted there.

Accuracy: a bias b_v (content of X at RPC(X) + b_v) is recovered only up to the motion of the
whole scene no image sees, s_v = b_v - A_v dX (A_v the Jacobian of view v's projection at the
tie points' centroid; see satsweep.sparse.bundle). The error printed is ``max |s_v - b_v + A_v
dX|`` over the views and both axes, dX fitted by least squares (3 unknowns). The scene recovered
is the true one moved by dX, so the altitude range is checked against the true surface's
altitudes moved by dX_up ("truth in the corrections' frame"), and against the plain truth.

The last lines summarise per view count: worst error, median time, whether every altitude range
held the truth, and the times relative to that of 5 views (the fewest when there is no 5).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# This checkout's satsweep first, not an installed one (a run from another worktree measures
# that worktree's code).
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _scene(folder: str, views: int, seed: int, size: int, bias: float):
    from satsweep.synth.scene import Scene, SynthOptions, generate_scene

    if os.path.isfile(os.path.join(folder, "scene.json")):
        return Scene.load(folder), 0.0
    t = time.perf_counter()
    scene = generate_scene(folder, SynthOptions(seed=seed, n_views=views, size_px=size, bias_px=bias),
                           overwrite=True)
    return scene, time.perf_counter() - t


def gauge_removed(A: np.ndarray, shifts: np.ndarray, biases: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-view residual (V, 2) of shifts - biases after the motion of the scene (ENU m) that
    no image sees, fitted by least squares to the views' Jacobians ``A`` (V, 2, 3), and that
    motion dX."""
    diff = np.asarray(shifts, np.float64) - np.asarray(biases, np.float64)
    dX = np.linalg.lstsq(A.reshape(-1, 3), -diff.ravel(), rcond=None)[0]
    return diff + A @ dX, dX


def gauge_error(cameras, shifts: np.ndarray, biases: np.ndarray, point) -> tuple[np.ndarray, np.ndarray]:
    """:func:`gauge_removed` with the Jacobians of perspective ``cameras`` at ``point``."""
    from satsweep.sparse.bundle import gauge_jacobians

    return gauge_removed(gauge_jacobians(cameras, point), shifts, biases)


def sparse_inputs(scene, prior_extra: float = 0.0):
    """(views, prior range) the sparse stage gets in --mode sparse: the crops ``satsweep
    reconstruct`` takes at the RPCs' own altitude range widened by ``prior_extra`` m."""
    from satsweep.geometry.altitude import AltitudeRange, altitude_range_from_rpcs
    from satsweep.io.views import load_views

    rpc = altitude_range_from_rpcs([v.rpc() for v in scene.views], warn=False)
    prior = AltitudeRange(rpc.min - prior_extra, rpc.max + prior_extra)
    return load_views([v.image for v in scene.views], scene.aoi, prior), prior


def _run_sparse(scene, prior_extra: float, repeat: int) -> dict:
    from satsweep.sparse.stage import sparse_stage

    views, prior = sparse_inputs(scene, prior_extra)
    best = None
    for _ in range(max(1, repeat)):
        t, c = time.perf_counter(), time.process_time()
        res = sparse_stage(views, scene.aoi, prior)
        total, cpu = time.perf_counter() - t, time.process_time() - c
        if best is None or total < best[0]:
            best = (total, res, cpu)
    total, res, cpu = best
    kept = list(res.kept)
    biases = np.array([v.bias_px for v in scene.views])
    cams = [res.tied.cameras[v] for v in kept]
    centroid = res.tied.points.mean(axis=0)
    resid, dX = gauge_error(cams, res.corrections_px[kept], biases[kept], centroid)
    coarse, _ = gauge_error(cams, res.coarse_corrections_px[kept], biases[kept], centroid)
    lo, hi = scene.alt_range
    alt = res.altitude_range
    d = res.to_dict()
    out = {
        "seconds": total, "cpu_seconds": cpu,
        "stages": {k: round(v, 3) for k, v in res.seconds.items()}, "kept": len(kept), "dropped": [x.message() for x in res.dropped],
        "pairs_matched": d["pair_graph"]["matched"], "all_pairs": d["pair_graph"]["all_pairs"],
        "matches": [p["matches"] for p in d["pair_graph"]["pairs"]],
        "max_bias_px": float(np.abs(biases).max()),
        "error_px": float(np.abs(resid).max()), "coarse_error_px": float(np.abs(coarse).max()),
        "median_error_px": float(np.median(np.abs(resid))),
        "sigma_px": [round(float(s), 4) for s in res.correction_sigma_px[kept]],
        "motion_m": [round(float(x), 2) for x in dX],
        "fine_points": d["fine"]["points"] if d["fine"] else 0,
        "reprojection_px": d["fine"]["reprojection_error_px"]["after"]["median"] if d["fine"] else None,
        "truth_m": [lo, hi],
        "altitude_m": None if alt is None else [alt.min, alt.max],
        "altitude_tie_points": res.altitude.get("tie_points"),
    }
    if alt is not None:
        tlo, thi = lo + dX[2], hi + dX[2]
        out["altitude_contains_truth"] = bool(alt.min <= tlo and alt.max >= thi)
        out["altitude_excess_m"] = [round(tlo - alt.min, 2), round(alt.max - thi, 2)]
        out["altitude_contains_plain_truth"] = bool(alt.min <= lo and alt.max >= hi)
    return out


def _run_adjust(scene, repeat: int) -> dict:
    from satsweep.geometry.altitude import AltitudeRange
    from satsweep.geometry.camera import build_cameras
    from satsweep.io.images import tonemap
    from satsweep.io.views import load_views
    from satsweep.sparse import bundle

    alt = AltitudeRange(*scene.alt_range)
    views = load_views([v.image for v in scene.views], scene.aoi, alt)
    cams = build_cameras(views, scene.aoi, alt)
    images = [tonemap(v.image) for v in views]
    best = None
    for _ in range(max(1, repeat)):
        t = time.perf_counter()
        _, report = bundle.adjust_principal_points(cams, images)
        total = time.perf_counter() - t
        if best is None or total < best[0]:
            best = (total, report)
    total, report = best
    biases = np.array([v.bias_px for v in scene.views])
    shifts = np.array(report.principal_point_shift_px)
    resid, dX = gauge_error([v.camera for v in cams.views], shifts, biases, (0.0, 0.0, 0.0))
    return {"seconds": total, "stages": {k: round(v, 3) for k, v in report.seconds.items()},
            "error_px": float(np.abs(resid).max()), "motion_m": [round(float(x), 2) for x in dX],
            "points": report.n_points, "reprojection_px": report.reproj_after_px[0],
            "matches": [k for _, _, k in report.n_matches]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--views", type=int, nargs="+", default=[3], help="view counts")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="scene seeds")
    p.add_argument("--size", type=int, default=1000, help="view width and height (px)")
    p.add_argument("--bias", type=float, default=2.0, help="max pointing bias per axis (px)")
    p.add_argument("--scenes", help="keep the scenes in this folder (reused when there)")
    p.add_argument("--prior-extra", type=float, default=300.0,
                   help="prior range of the sparse stage: the RPCs' range widened by this (m)")
    p.add_argument("--mode", choices=("sparse", "adjust", "both"), default="both")
    # The fastest of three: one run's time moves by 10-20% with the machine's load, which is
    # the size of what the 20 / 5 views ratio is compared against.
    p.add_argument("--repeat", type=int, default=3, help="runs per scene; the fastest is kept")
    p.add_argument("--json", help="write every run's figures to this file")
    args = p.parse_args(argv)

    print(f"cpus available: {len(os.sched_getaffinity(0))}, numpy {np.__version__}")
    tmp = None
    root = args.scenes
    if root is None:
        tmp = root = tempfile.mkdtemp(prefix="bench_ba_")
    runs = []
    try:
        for n in args.views:
            for seed in args.seeds:
                folder = os.path.join(root, f"v{n:02d}_s{seed}_p{args.size}_b{args.bias:g}")
                scene, gen = _scene(folder, n, seed, args.size, args.bias)
                row = {"views": n, "seed": seed, "size": args.size, "bias": args.bias,
                       "generated_s": round(gen, 1)}
                if args.mode in ("sparse", "both"):
                    row["sparse"] = r = _run_sparse(scene, args.prior_extra, args.repeat)
                    print(f"{n:2d} views seed {seed}: sparse {r['seconds']:6.2f} s (CPU "
                          f"{r['cpu_seconds']:.2f} s), kept {r['kept']}, "
                          f"pairs {r['pairs_matched']}/{r['all_pairs']}, error {r['error_px']:.4f} px "
                          f"(coarse {r['coarse_error_px']:.3f}), reprojection {r['reprojection_px']:.3f} "
                          f"px, {r['fine_points']} points, motion {r['motion_m']} m")
                    print(f"    altitude {r['altitude_m']} from {r['altitude_tie_points']} tie points, "
                          f"truth {r['truth_m']}: contains truth in the corrections' frame "
                          f"{r.get('altitude_contains_truth')} (excess {r.get('altitude_excess_m')} m), "
                          f"plain truth {r.get('altitude_contains_plain_truth')}")
                    print(f"    stages {r['stages']}")
                    if r["dropped"]:
                        print(f"    dropped: {r['dropped']}")
                if args.mode in ("adjust", "both"):
                    row["adjust"] = a = _run_adjust(scene, args.repeat)
                    print(f"{n:2d} views seed {seed}: adjust {a['seconds']:6.2f} s, error "
                          f"{a['error_px']:.4f} px, reprojection {a['reprojection_px']:.3f} px, "
                          f"{a['points']} points, stages {a['stages']}")
                runs.append(row)
                sys.stdout.flush()
        print("summary (worst error over seeds, median time):")
        times = {}
        for n in args.views:
            rows = [r for r in runs if r["views"] == n]
            parts = [f"{n:2d} views:"]
            for mode in ("sparse", "adjust"):
                if mode in rows[0]:
                    err = max(r[mode]["error_px"] for r in rows)
                    sec = float(np.median([r[mode]["seconds"] for r in rows]))
                    times.setdefault(mode, {})[n] = sec
                    parts.append(f"{mode} error <= {err:.4f} px, {sec:.2f} s;")
                    if mode == "sparse":
                        cpu = float(np.median([r[mode]["cpu_seconds"] for r in rows]))
                        times.setdefault("sparse CPU", {})[n] = cpu
                        held = all(r[mode].get("altitude_contains_truth") for r in rows)
                        parts.append(f"CPU {cpu:.2f} s; altitude range holds the truth: {held};")
            print("  " + " ".join(parts))
        for mode, t in times.items():
            if len(t) > 1:
                base = 5 if 5 in t else min(t)  # the reference: 20 views / 5 views
                ratios = ", ".join(f"{n} views {t[n] / t[base]:.2f}" for n in sorted(t) if n != base)
                print(f"  {mode}: time relative to {base} views: {ratios}")
        if args.json:
            with open(args.json, "w", encoding="utf-8") as fh:
                json.dump(runs, fh, indent=1)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
