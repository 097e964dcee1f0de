"""Time the synthetic-scene generator: one 512x512 view (ray casting + shading), the pieces
around it, and a whole default scene.

    python tools/bench_synth.py [--size 512] [--views 3] [--supersampling 2] [--scene]
    python tools/bench_synth.py --scene --views 20 --acquisitions 10   # a multi-date scene

Prints seconds per step; ``--scene`` also times ``generate_scene`` end to end (into a temporary
folder that is removed afterwards), with ``--acquisitions N`` a multi-date scene of N dates
(each date's surface, shadows and views are timed in its progress lines).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# This checkout's satsweep first, not an installed one (a run from another worktree measures
# that worktree's code).
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main(argv=None) -> int:
    from satsweep.products.grid import dsm_grid_for_aoi
    from satsweep.synth.scene import (
        SynthOptions,
        _aoi_box,
        design_scene,
        generate_scene,
        render_radiance,
        truth_dsm,
    )
    from satsweep.synth.town import ShadowMap, build_surface, cast_rays, sun_vector

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=512, help="view width and height (px)")
    p.add_argument("--views", type=int, default=3, help="views of the whole-scene run")
    p.add_argument("--supersampling", type=int, default=2, help="rays per pixel side")
    p.add_argument("--view", type=int, default=2, help="which view to time (2 = most oblique of the defaults)")
    p.add_argument("--scene", action="store_true", help="also time generate_scene end to end")
    p.add_argument("--acquisitions", type=int, default=0, help="dates of the --scene run (0: one date)")
    args = p.parse_args(argv)

    opts = SynthOptions(size_px=args.size, n_views=max(args.views, args.view + 1), supersampling=args.supersampling)
    print(f"cpus available: {len(os.sched_getaffinity(0))}, numpy {np.__version__}")
    t = time.perf_counter()
    design = design_scene(opts)
    e0, n0, e1, n1 = design.world
    grid = build_surface(seed=opts.seed, e_min=e0, n_min=n0, e_max=e1, n_max=n1, cell_m=opts.cell_m,
                         aoi_half_m=design.aoi_half_m)
    t_surface = time.perf_counter() - t
    t = time.perf_counter()
    shadows = ShadowMap(grid, sun_vector(elevation_deg=opts.sun_elevation_deg, azimuth_deg=opts.sun_azimuth_deg))
    t_shadow = time.perf_counter() - t
    cam = design.cameras[args.view]
    t = time.perf_counter()
    render_radiance(grid, shadows, cam, supersampling=args.supersampling)
    t_render = time.perf_counter() - t
    n_rays = cam.width * cam.height * args.supersampling ** 2
    # Ray casting alone, on the pixel centres.
    r, c = np.meshgrid(np.arange(cam.height, dtype=float), np.arange(cam.width, dtype=float), indexing="ij")
    o, d = cam.ray(col=c.ravel(), row=r.ravel())
    t = time.perf_counter()
    cast_rays(grid, o, d)
    t_cast = time.perf_counter() - t
    t = time.perf_counter()
    truth_dsm(grid, design.frame, dsm_grid_for_aoi(_aoi_box(design.frame, design.aoi_half_m), opts.dsm_resolution_m))
    t_dsm = time.perf_counter() - t
    print(f"surface grid {grid.shape[1]}x{grid.shape[0]} cells: {t_surface:.2f} s; shadow map: {t_shadow:.2f} s")
    print(f"render {cam.width}x{cam.height} view {args.view} ({n_rays} rays, "
          f"{args.supersampling}x{args.supersampling} supersampling): {t_render:.2f} s "
          f"({n_rays / t_render / 1e6:.2f} M rays/s)")
    print(f"cast {cam.width * cam.height} pixel-centre rays: {t_cast:.2f} s")
    print(f"truth DSM: {t_dsm:.2f} s")
    if args.scene:
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            generate_scene(os.path.join(tmp, "scene"), SynthOptions(size_px=args.size, n_views=args.views,
                                                                     supersampling=args.supersampling,
                                                                     acquisitions=args.acquisitions),
                           log=lambda m: print("  " + m))
            dates = f", {args.acquisitions} dates" if args.acquisitions else ""
            print(f"generate_scene ({args.views} views{dates}): {time.perf_counter() - t:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
