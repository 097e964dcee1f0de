#!/usr/bin/env python3
"""Benchmark of the OpenCL plane sweep (census + sweep + guided filter + argmin).

Measures voxels per second (reference pixels x planes x sources) of the whole engine on one
device, the time of each stage, and the same maths in vectorised numpy (tests/reference_sweep.py)
in the same run; prints the ratio. The issue's figure is a 1024 x 1024 reference with 2 sources
and 128 planes (the defaults). The numpy reference is slow: it is measured on --numpy-planes
planes and scaled linearly to all planes (the per-plane work is the same; the output says so).

    python tools/bench_sweep.py                     # 1024^2, 2 sources, 128 planes
    python tools/bench_sweep.py --size 256 --planes 32 --json out.json
    python tools/bench_sweep.py --census-kernel split staged   # both census kernels, same run
    python tools/bench_sweep.py --census-ring-weight 0 2       # plain and ring-weighted census
    python tools/bench_sweep.py --census-mask-threshold 0 0.12 # plain and edge-aware census
    python tools/bench_sweep.py --size 10000 --planes 8 --sources 1 --memory-budget-gb 4 \
        --repeat 1 --numpy-planes 0      # the issue's 10000^2 reference within a 4 GB budget
    python tools/bench_sweep.py --windows 1 --filter none --planes 210 --sources 4 \
        --numpy-planes 0                 # windows of one pixel against every plane, same run

With ``--windows BLOCK`` the engine sweeps into a device cost volume (SGM's input, as a
coarse-to-fine reference does) twice per round: every plane, then the plane windows that
``satsweep.dense.coarse.plane_windows`` gives blocks of BLOCK pixels (1: each pixel its own)
over a synthetic city's plane indices (flat roofs of 3-40 planes' height on sloping ground:
what a coarse pass sees in a city block), with ``--window-halo`` and ``--window-margin``; it
prints the share of the pixels' planes swept and the time of the windows over the time of every
plane, rounds interleaved. The images' content does not change the work.

With several ``--census-kernel``, ``--census-ring-weight`` or ``--census-mask-threshold`` values
each combination is timed in
turn (same images, same device) and the ratio of each to the first is printed; the numpy
comparison uses the first.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # the numpy references live with the tests (package tests)

from satsweep.dense.coarse import plane_windows  # noqa: E402
from satsweep.dense.planes import translation_homographies  # noqa: E402
from satsweep.dense.sweep import PlaneSweep, PlaneWindows, SweepOptions  # noqa: E402
from satsweep.opencl.device import open_device  # noqa: E402
from tests import reference_sweep as ref  # noqa: E402


def _scene(size: int, n_src: int, n_planes: int, seed: int = 0):
    """Smooth-noise images and translation homographies (content does not change the work)."""
    rng = np.random.default_rng(seed)
    ref_img = ref.smooth_noise((size, size), 1.0, rng).astype(np.float32)
    srcs = [ref.smooth_noise((size, size), 1.0, rng).astype(np.float32) for _ in range(n_src)]
    angles = np.linspace(0.0, np.pi, n_src, endpoint=False)
    shifts = 0.5 * np.stack([np.cos(angles), np.sin(angles)], axis=1)  # 0.5 px per plane
    heights = np.arange(n_planes, dtype=np.float64)
    return ref_img, srcs, translation_homographies(shifts, heights), heights


# Standard deviation (planes) of the noise on the synthetic coarse plane indices: the half-
# resolution pass, upsampled, is off by a plane or two on most pixels (view 12 of the 1700 px
# stack: a share of 0.43 of its 210 planes swept with the default halo and margin).
CITY_INDEX_NOISE = 1.5


def _city_plane_index(size: int, n_planes: int, seed: int = 1) -> np.ndarray:
    """(size, size) fractional plane indices of a synthetic city block as a coarse pass sees
    it: ground rising by a tenth of the planes across the image, flat rectangular roofs of
    20-90 px sides, 5-50% of the planes above it, over about 40% of the area, and the coarse
    pass's noise (``CITY_INDEX_NOISE`` planes)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size]
    ground = 0.2 * n_planes + 0.1 * n_planes * (xx + yy) / (2.0 * size)
    index = ground.copy()
    covered = np.zeros((size, size), bool)
    while covered.mean() < 0.4:
        w, h = rng.integers(20, 91, size=2)
        x0, y0 = rng.integers(0, max(size - w, 1)), rng.integers(0, max(size - h, 1))
        roof = np.max(ground[y0:y0 + h, x0:x0 + w]) + rng.uniform(0.05, 0.5) * n_planes
        index[y0:y0 + h, x0:x0 + w] = roof
        covered[y0:y0 + h, x0:x0 + w] = True
    index += rng.normal(0.0, CITY_INDEX_NOISE, index.shape)
    return np.clip(index, 0.0, n_planes - 1.0)


def _windows(size: int, n_planes: int, block: int, halo: int, margin: int) -> PlaneWindows:
    """The plane windows of blocks of ``block`` px over ``_city_plane_index`` (never None: a
    fraction of 1 lets any window through)."""
    return plane_windows(_city_plane_index(size, n_planes), n_planes, block=block, halo=halo,
                         margin=margin, max_fraction=1.0)


def _time_volumes(device, options: SweepOptions, ref_img, srcs, hom, heights,
                  windows: PlaneWindows, repeat: int) -> dict:
    """Best-of-``repeat`` seconds of a device cost volume of every plane and of ``windows``,
    interleaved in each round, and each one's stage seconds from a profiled run."""
    def volume(engine, planes):
        engine.cost_volume_on_device(ref_img, srcs, hom, heights, windows=planes).release()

    # Warm-up on a crop with the crop's windows: builds (or loads) every program of both.
    nb = -(-64 // windows.block)
    count = windows.counts((64, 64))[::windows.block, ::windows.block]
    sub = PlaneWindows(block=windows.block, first=windows.first[:nb, :nb],
                       n_planes=int(count.max()), count=np.asarray(windows.count)[:nb, :nb])
    for planes in (None, sub):
        PlaneSweep(device, options).cost_volume_on_device(
            ref_img[:64, :64], [s[:64, :64] for s in srcs], hom, heights,
            windows=planes).release()
    best = {"every_plane": np.inf, "windows": np.inf}
    for _ in range(repeat):
        for name, planes in (("every_plane", None), ("windows", windows)):
            t0 = time.perf_counter()
            volume(PlaneSweep(device, options), planes)
            best[name] = min(best[name], time.perf_counter() - t0)
    stages = {}
    for name, planes in (("every_plane", None), ("windows", windows)):
        prof = PlaneSweep(device, options, profile=True)
        volume(prof, planes)
        stages[name] = dict(sorted(prof.stage_seconds.items()))
    size = ref_img.shape
    share = float(windows.counts(size).sum()) / (size[0] * size[1] * heights.size)
    return {"window_block_px": windows.block, "window_share": share,
            "window_planes": windows.n_planes, "every_plane_seconds": best["every_plane"],
            "windows_seconds": best["windows"],
            "windows_over_every_plane": best["windows"] / best["every_plane"],
            "stage_seconds": stages}


def _numpy_reference(ref_img, srcs, hom, heights, options: SweepOptions, n_sub: int) -> float:
    """Seconds of the numpy pipeline on n_sub planes (cost volume, filter, WTA)."""
    rx, ry = options.census_radii
    sub = hom[:n_sub].astype(np.float32).astype(np.float64)
    t0 = time.perf_counter()
    vol = ref.sweep_volume(ref_img, srcs, sub, rx, ry, options.best_k(len(srcs)),
                           ad_weight=options.ad_weight, ad_truncation=options.ad_truncation,
                           grad_weight=options.grad_weight, grad_truncation=options.grad_truncation,
                           ring_weight=options.census_ring_weight)
    if options.cost_filter == "guided":
        vol = ref.guided_filter(vol, ref_img, options.gf_radius, options.gf_eps)
    elif options.cost_filter == "box":
        vol = ref.box_mean(vol, options.box_radius)
    ref.wta(vol, options.max_cost)
    return time.perf_counter() - t0


def _time_engine(device, options: SweepOptions, ref_img, srcs, hom, heights, voxels: int,
                 repeat: int) -> dict:
    """Best-of-``repeat`` engine seconds and one profiled run's stage seconds."""
    # Warm-up on a crop: builds (or loads from the cache) every program.
    crop = (ref_img[:64, :64], [s[:64, :64] for s in srcs], hom[:4], heights[:4])
    PlaneSweep(device, options).height_map(*crop)
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = PlaneSweep(device, options).height_map(ref_img, srcs, hom, heights)
        best = min(best, time.perf_counter() - t0)
    prof = PlaneSweep(device, options, profile=True)
    prof.height_map(ref_img, srcs, hom, heights)
    stages = dict(sorted(prof.stage_seconds.items()))
    return {"census_kernel": options.census_kernel,
            "census_ring_weight": options.census_ring_weight,
            "census_mask_threshold": options.census_mask_threshold, "tiles": res.split.n_tiles,
            "batches": res.split.n_batches, "peak_device_bytes": res.split.peak_device_bytes,
            "engine_seconds": best,
            "engine_gvoxel_per_s": voxels / best / 1e9, "stage_seconds": stages,
            "stage_gvoxel_per_s": {k: voxels / v / 1e9 for k, v in stages.items() if v > 0}}


def _label(run: dict) -> str:
    """A timed run's settings, as the printed lines name them."""
    return (f"census kernel {run['census_kernel']} (ring weight {run['census_ring_weight']:g}, "
            f"mask {run['census_mask_threshold']:g})")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=1024, help="reference width = height (pixels)")
    p.add_argument("--planes", type=int, default=128)
    p.add_argument("--sources", type=int, default=2)
    p.add_argument("--filter", choices=["guided", "box", "none"], default="guided")
    p.add_argument("--device", default=None, help="auto|cpu|gpu|PLATFORM:DEVICE")
    p.add_argument("--repeat", type=int, default=2, help="timed runs (the best is kept)")
    p.add_argument("--numpy-planes", type=int, default=4,
                   help="planes of the numpy reference run, scaled to --planes (0: skip)")
    p.add_argument("--census-kernel", nargs="+", choices=["split", "staged"], default=["split"],
                   help="SweepOptions.census_kernel values to time (the first is the main figure)")
    p.add_argument("--census-ring-weight", nargs="+", type=float, default=[0.0],
                   help="census_ring_weight values to time (the consensus areas' default: 2)")
    p.add_argument("--census-mask-threshold", nargs="+", type=float, default=[0.0],
                   help="census_mask_threshold values to time (the consensus areas' default: "
                        "0.12)")
    p.add_argument("--memory-budget-gb", type=float, default=None,
                   help="SweepOptions.memory_budget_bytes in GiB (default: the device fraction)")
    p.add_argument("--windows", type=int, default=None, metavar="BLOCK",
                   help="also time plane windows of blocks of BLOCK px (1: one pixel each) "
                        "against every plane, both into a device cost volume (module docstring)")
    p.add_argument("--window-halo", type=int, default=8,
                   help="with --windows: SweepOptions.window_halo_px (its default: 8)")
    p.add_argument("--window-margin", type=int, default=4,
                   help="with --windows: SweepOptions.window_margin_planes (its default: 4)")
    p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = p.parse_args(argv)
    if args.windows is not None and args.windows < 1:
        p.error(f"--windows {args.windows}: a block side must be at least 1 px")

    device = open_device(args.device)
    ref_img, srcs, hom, heights = _scene(args.size, args.sources, args.planes)
    voxels = args.size * args.size * args.planes * args.sources
    print(f"device: {device.info.label}")
    budget = None if args.memory_budget_gb is None else int(args.memory_budget_gb * 2**30)
    runs, first_options = [], None
    for kernel, ring, mask in itertools.product(args.census_kernel, args.census_ring_weight,
                                                args.census_mask_threshold):
        options = SweepOptions(cost_filter=args.filter, census_kernel=kernel,
                               census_ring_weight=ring, census_mask_threshold=mask,
                               memory_budget_bytes=budget)
        first_options = first_options or options
        runs.append(_time_engine(device, options, ref_img, srcs, hom, heights, voxels,
                                 args.repeat))
    out = dict(runs[0])
    out.update({"device": device.info.label, "size": args.size, "planes": args.planes,
                "sources": args.sources, "filter": args.filter, "voxels": voxels})
    if len(runs) > 1:
        out["kernels"] = runs
    for r in runs:
        print(f"{_label(r)}: "
              f"reference {args.size}x{args.size}, "
              f"{args.sources} sources, {args.planes} planes, filter {args.filter}: "
              f"{voxels / 1e9:.3f} Gvoxel, {r['tiles']} tile(s), {r['batches']} batch(es), "
              f"peak {r['peak_device_bytes'] / 2**20:.0f} MiB on the device")
        print(f"engine (upload, census, sweep, filter, argmin, download): {r['engine_seconds']:.3f} s = "
              f"{r['engine_gvoxel_per_s']:.3f} Gvoxel/s (best of {args.repeat})")
        for k, v in r["stage_seconds"].items():
            print(f"  stage {k:7s}: {v:8.3f} s = {voxels / v / 1e9:9.3f} Gvoxel/s (queue drained per stage)")
    for r in runs[1:]:
        print(f"time of {_label(r)} / time of {_label(runs[0])}: "
              f"engine {r['engine_seconds'] / runs[0]['engine_seconds']:.2f}, sweep stage "
              f"{r['stage_seconds'].get('sweep', 0) / runs[0]['stage_seconds'].get('sweep', 1):.2f}")
    if args.windows is not None:
        win = _windows(args.size, args.planes, args.windows, args.window_halo, args.window_margin)
        out["windows"] = w = _time_volumes(device, first_options, ref_img, srcs, hom, heights,
                                           win, args.repeat)
        print(f"device cost volume, every plane: {w['every_plane_seconds']:.3f} s; windows of "
              f"{args.windows} px (halo {args.window_halo} px, margin {args.window_margin} "
              f"planes; share {w['window_share']:.2f} of the pixels' planes, widest "
              f"{w['window_planes']}): {w['windows_seconds']:.3f} s (best of {args.repeat}, "
              f"rounds interleaved)")
        for name in ("every_plane", "windows"):
            print(f"  {name:11s} " + ", ".join(f"{k} {v:.3f} s"
                                               for k, v in w["stage_seconds"][name].items()))
        print(f"time of the windows / time of every plane: {w['windows_over_every_plane']:.2f}")
    best = runs[0]["engine_seconds"]
    if args.numpy_planes > 0:
        n_sub = min(args.numpy_planes, args.planes)
        t_sub = _numpy_reference(ref_img, srcs, hom, heights, first_options, n_sub)
        t_np = t_sub * args.planes / n_sub
        out.update({"numpy_planes_measured": n_sub, "numpy_seconds_measured": t_sub,
                    "numpy_seconds_scaled": t_np, "numpy_gvoxel_per_s": voxels / t_np / 1e9,
                    "speedup_vs_numpy": t_np / best})
        print(f"numpy reference: {t_sub:.2f} s for {n_sub} planes, scaled to {args.planes} planes: "
              f"{t_np:.1f} s = {out['numpy_gvoxel_per_s']:.4f} Gvoxel/s")
        print(f"speed-up of the engine over numpy: {out['speedup_vs_numpy']:.1f}x")
    if args.json:
        tmp = args.json + ".tmp"
        with open(tmp, "w") as fh:
            json.dump(out, fh, indent=2)
        os.replace(tmp, args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
