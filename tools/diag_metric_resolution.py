#!/usr/bin/env python3
"""How finely does completeness within 1 m resolve a DSM on a synthetic scene?

A synthetic scene's ``truth_dsm.tif`` holds the highest surface point of each 0.5 m cell (the
lidar convention: a cell that a roof or a crown overhangs by a few centimetres is at the roof's
height). The IARPA MVS3DM alignment (``satsweep evaluate``) shifts a prediction by whole cells
only, so a DSM that is exact but placed a fraction of a cell off (the geolocation left by the
pointing: the bundle adjustment's gauge, a pair's common error) is scored against a truth whose
cells straddle its own, and every cell beside a wall or a crown's rim can fail. This tool
measures that resolution on a scene:

- the **exact truth drawn on grids offset by sub-cell shifts** (``truth_dsm`` of the scene's
  surface on the truth grid moved by (dx, dy) metres, x east, y north), scored against the truth
  by the MVS3DM protocol: what a perfect DSM scores when it is that far off;
- with ``--dsm``, each DSM **scored against the truth drawn on each offset grid** (its cells
  taken by nearest neighbour, as ``satsweep evaluate`` resamples): the same as moving the DSM by
  (-dx, -dy) before the whole-cell alignment. The spread between the best and the worst offset
  is how much of its figure is the sub-cell placement.

    python tools/diag_metric_resolution.py SCENE_DIR
    python tools/diag_metric_resolution.py SCENE_DIR --dsm OUT_A/dsm.tif OUT_B/dsm.tif
    python tools/diag_metric_resolution.py SCENE_DIR --offsets 0 0.1 0.25 --json out.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from satsweep.errors import InputError, SatsweepError  # noqa: E402
from satsweep.products.evaluate import (  # noqa: E402
    EvaluateOptions,
    evaluate_arrays,
    read_dsm,
    resample_to_grid,
)
from satsweep.products.grid import DSMGrid  # noqa: E402
from satsweep.synth.scene import Scene, truth_dsm  # noqa: E402

# Offsets (m) tried along each axis by default: a 5 x 5 grid within a cell's half (0.25 m on
# 0.5 m cells); larger offsets are whole-cell shifts plus one of these, which the alignment
# takes care of.
DEFAULT_OFFSETS_M = (-0.2, -0.1, 0.0, 0.1, 0.2)


def truth_grid(scene: Scene) -> DSMGrid:
    """The grid of the scene's ``truth_dsm.tif``."""
    t, info = read_dsm(scene.truth_dsm)
    return DSMGrid(epsg=info.epsg, x_min=info.x_min, y_max=info.y_max, resolution=info.resolution,
                   width=t.shape[1], height=t.shape[0])


def offset_truth(scene: Scene, dx_m: float, dy_m: float, *, grid: DSMGrid | None = None,
                 surface=None) -> np.ndarray:
    """The scene's truth DSM drawn on its grid moved by (dx_m east, dy_m north)."""
    grid = grid if grid is not None else truth_grid(scene)
    moved = dataclasses.replace(grid, x_min=grid.x_min + dx_m, y_max=grid.y_max + dy_m)
    return truth_dsm(surface if surface is not None else scene.surface(), scene.frame, moved)


def completeness(pred: np.ndarray, truth: np.ndarray, resolution: float) -> float:
    """MVS3DM completeness within 1 m after the whole-cell alignment (same grid)."""
    report = evaluate_arrays(pred, truth, resolution, EvaluateOptions())
    return float(report["aligned"]["completeness_1m"])


def scores(scene: Scene, offsets_m, dsms=()) -> dict:
    """{"perfect": {(dx, dy): completeness}, dsm path: {(dx, dy): completeness}}."""
    grid = truth_grid(scene)
    surface = scene.surface()
    truth, _ = read_dsm(scene.truth_dsm)
    preds = [(str(p), *read_dsm(p)) for p in dsms]
    for name, _, info in preds:
        if info.epsg != grid.epsg:
            raise InputError(name, f"EPSG:{info.epsg}, the truth's is EPSG:{grid.epsg}: "
                                   "reproject it onto the truth's UTM zone")
    out: dict = {"perfect": {}}
    for dx in offsets_m:
        for dy in offsets_m:
            moved = offset_truth(scene, dx, dy, grid=grid, surface=surface)
            out["perfect"][(dx, dy)] = completeness(moved, truth, grid.resolution)
            for name, a, info in preds:
                p = resample_to_grid(a, info, x_min=grid.x_min + dx, y_max=grid.y_max + dy,
                                     cell_x=grid.resolution, cell_y=grid.resolution,
                                     shape=moved.shape)
                out.setdefault(name, {})[(dx, dy)] = completeness(p, moved, grid.resolution)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scene", help="a scene directory written by satsweep synth")
    p.add_argument("--dsm", nargs="*", default=[], help="DSM GeoTIFFs of that scene to score")
    p.add_argument("--offsets", nargs="+", type=float, default=list(DEFAULT_OFFSETS_M),
                   help="offsets (m) along each axis, every (dx, dy) pair tried")
    p.add_argument("--json", help="write the figures here")
    args = p.parse_args(argv)
    try:
        res = scores(Scene.load(args.scene), args.offsets, args.dsm)
    except SatsweepError as exc:
        print(f"diag_metric_resolution: error: {exc}", file=sys.stderr)
        return 2
    print(f"{'':40s} {'at (0, 0)':>9s} {'best':>6s} {'worst':>6s} {'mean':>6s}   (% within 1 m)")
    for name, v in res.items():
        at0 = v.get((0.0, 0.0))
        vals = np.array(list(v.values())) * 100
        best = max(v, key=v.get)
        label = ("exact truth, offset" if name == "perfect"
                 else Path(name).parent.name + "/" + Path(name).name)
        first = "" if at0 is None else f"{100 * at0:9.2f}"
        print(f"{label[-40:]:40s} {first:>9s} {vals.max():6.2f} {vals.min():6.2f} "
              f"{vals.mean():6.2f}   best at {best}")
    if args.json:
        Path(args.json).write_text(json.dumps(
            {k: [{"dx_m": dx, "dy_m": dy, "completeness_1m": c} for (dx, dy), c in v.items()]
             for k, v in res.items()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
