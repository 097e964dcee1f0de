#!/usr/bin/env python3
"""How far from the truth are the tie points of the sparse stage's fine adjustment?

On synthetic scenes (``satsweep synth``) the stage runs as tools/bench_ba.py's sparse mode runs
it (the crops ``satsweep reconstruct`` takes, the RPCs' own altitude range). The observations it
hands to its fine adjustment are measured against the truth: each track's first observation
(the window the others were registered to) is ray-cast through its view's true camera (the
fitted camera shifted by the scene's true pointing bias) onto the true surface, and the point found
is projected into the track's other views. Only the error across each view's epipolar line of
that ray is the matching's own: the part along it is a height, which the point absorbs. The
table gives, per scene, the median |error across| (px) of the observations on flat ground (the
truth within FLAT_M over FLAT_RADIUS_M around the point) and near a step, split by whether the
view shares the first view's date (multi-date scenes), the share within 0.1 px, and the worst
view's correction after the gauge (tools/bench_ba.py's measure). The truth is the scene's height
field itself (``Scene.surface()``), which covers the crops (the truth DSM covers only the AOI);
observations whose track's ray meets no surface are counted as "off truth" and not measured.

``--oracle`` runs the stage again (it is deterministic) and changes the fine adjustment's input:
``exact`` moves every observation but the tracks' first to its true position (what the solver,
the gauge and the measure reach with perfect registrations); ``within`` keeps only those within
``--threshold`` px of the truth (``--across``: the error across the epipolar line only). The
twenty-eighth session's figures (docs/measurements.md) come from this measure.

    python tools/diag_tie_errors.py SCENE_DIR [SCENE_DIR ...]
    python tools/diag_tie_errors.py --oracle exact SCENE_DIR
    python tools/diag_tie_errors.py --oracle within --threshold 0.3 SCENE_DIR
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tools"))  # bench_ba, also when imported as tools.diag_tie_errors

from satsweep.products.points import solve_ground_en  # noqa: E402
from satsweep.sparse import stage as sparse_stage_module  # noqa: E402
from satsweep.sparse.bundle import shift_principal_point  # noqa: E402
from satsweep.sparse.tracks import Observations  # noqa: E402
from satsweep.sparse.triangulation import project, projection_stack  # noqa: E402
from satsweep.synth.scene import Scene  # noqa: E402

from bench_ba import gauge_error, sparse_inputs  # noqa: E402

# Ray casting: heights stepped down by this much (m) from above the truth's highest cell.
RAY_STEP_M = 0.02
# "Flat ground": the truth's cells within FLAT_RADIUS_M of the point span less than FLAT_M.
FLAT_M = 0.3
FLAT_RADIUS_M = 2.0
# Share of the observations counted as precise: within this many px across the epipolar line.
PRECISE_PX = 0.1


class TruthSurface:
    """The scene's true surface (``Scene.surface()``, the height field the views were rendered
    from, over the whole rendered world: the crops reach past the AOI) seen from the ENU frame
    of the stage's cameras."""

    def __init__(self, scene: Scene, frame) -> None:
        self.grid = scene.surface()
        self.scene_frame = scene.frame
        self.frame = frame
        self.top = self.grid.max_height()  # scene ENU up (m)
        self.bottom = self.grid.min_height()

    def _in_scene(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lon, lat, alt = self.frame.to_geodetic(e=X[:, 0], n=X[:, 1], u=X[:, 2])
        return self.scene_frame.from_geodetic(lon=lon, lat=lat, alt=alt)

    def above(self, X: np.ndarray) -> np.ndarray:
        """How far (m) the points X (stage ENU, (N, 3)) lie above the surface; NaN off it."""
        e, n, u = self._in_scene(X)
        return u - self.grid.height(e=e, n=n)

    def span(self, X: np.ndarray) -> np.ndarray:
        """The surface's range of heights (m) within FLAT_RADIUS_M of the points X (a 5 x 5
        pattern of samples); NaN where part of it lies off the surface."""
        e, n, _ = self._in_scene(X)
        steps = np.linspace(-FLAT_RADIUS_M, FLAT_RADIUS_M, 5)
        de, dn = (a.ravel() for a in np.meshgrid(steps, steps))
        h = self.grid.height(e=e[:, None] + de[None, :], n=n[:, None] + dn[None, :])
        return h.max(axis=1) - h.min(axis=1)

    def ray_cast(self, P: np.ndarray, views: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """The first surface point (stage ENU, (N, 3)) on each pixel ``xy`` of view ``views``
        of the cameras ``P`` (V, 3, 4), to RAY_STEP_M; NaN where a ray meets none."""
        lon, lat, _ = self.scene_frame.to_geodetic(e=np.zeros(1), n=np.zeros(1), u=np.zeros(1))
        # the stage frame's up of the scene's highest and lowest surface (within mm over an AOI)
        hi = self.frame.from_geodetic(lon=lon, lat=lat, alt=self.scene_frame.alt0 + self.top)[2][0]
        lo = self.frame.from_geodetic(lon=lon, lat=lat, alt=self.scene_frame.alt0 + self.bottom)[2][0]
        points = np.full((len(xy), 3), np.nan)
        alive = np.ones(len(xy), bool)
        for up in np.arange(hi + 1.0, lo - 1.0, -RAY_STEP_M):
            idx = np.flatnonzero(alive)
            if not len(idx):
                break
            X = np.full((len(idx), 3), up)
            for v in np.unique(views[idx]):
                k = views[idx] == v
                X[k, 0], X[k, 1] = solve_ground_en(P[v], col=xy[idx[k], 0], row=xy[idx[k], 1], u=up)
            with np.errstate(invalid="ignore"):  # off the surface: NaN, never a hit
                hit = self.above(X) <= 0.0
            points[idx[hit]] = X[hit]
            alive[idx[hit]] = False
        return points


def observation_errors(P: np.ndarray, obs: Observations, surface: TruthSurface) -> dict:
    """Per observation of ``obs`` (tracks grouped, first observation first), with the true
    cameras ``P``: ``true_xy`` (where the first observation's truth point lies in its view),
    ``across`` (signed px across the epipolar line), ``error`` (whole, px), ``flat`` and
    ``first`` (bool), ``head_view``."""
    first = np.r_[True, obs.point[1:] != obs.point[:-1]]
    track = np.cumsum(first) - 1
    heads = np.flatnonzero(first)
    X = surface.ray_cast(P, obs.view[heads], obs.xy[heads])[track]
    true_xy = project(P, obs.view, X)[0]
    up = X.copy()
    up[:, 2] += 1.0
    along = project(P, obs.view, up)[0] - true_xy
    along /= np.linalg.norm(along, axis=1, keepdims=True) + 1e-12
    d = obs.xy - true_xy
    flat = np.zeros(len(X), bool)
    ok = np.isfinite(X[:, 0])
    with np.errstate(invalid="ignore"):
        flat[ok] = surface.span(X[ok]) < FLAT_M
    return {"true_xy": true_xy, "across": d[:, 1] * along[:, 0] - d[:, 0] * along[:, 1],
            "error": np.hypot(*d.T), "flat": flat, "first": first,
            "head_view": obs.view[heads][track]}


def _worst_view(scene: Scene, result) -> float:
    kept = list(result.kept)
    residual, _ = gauge_error([result.tied.cameras[v] for v in kept], result.corrections_px[kept],
                              np.array([scene.views[v].bias_px for v in kept]),
                              result.tied.points.mean(axis=0))
    return float(np.abs(residual).max())


def _median(a: np.ndarray) -> float | None:
    return round(float(np.median(np.abs(a))), 3) if a.size else None


def diagnose(scene_dir: str, oracle: str, threshold: float, across_only: bool) -> dict:
    scene = Scene.load(scene_dir)
    views, prior = sparse_inputs(scene)
    index = {Path(v.path).name: k for k, v in enumerate(views)}
    original = sparse_stage_module.adjust_observations
    captured: dict = {}
    state: dict = {}

    def true_cameras(cams, names):
        idx = [index[n] for n in names]
        shifts = [np.asarray(scene.views[v].bias_px) - state["coarse"][v] for v in idx]
        return projection_stack([shift_principal_point(c, s) for c, s in zip(cams, shifts)]), idx

    def capture(cams, obs, options, names=None):
        captured.update(cams=cams, obs=obs, names=list(names))
        return original(cams, obs, options, names=names)

    def change(cams, obs, options, names=None):
        P, _ = true_cameras(cams, names)
        m = observation_errors(P, obs, state["surface"])
        known = np.isfinite(m["true_xy"][:, 0])  # tracks whose first point the truth holds
        if oracle == "exact":
            xy = np.where(m["first"][:, None], obs.xy, m["true_xy"])
            obs = Observations(point=obs.point, view=obs.view, xy=xy, n_points=obs.n_points)
            obs = obs.subset(known)
        else:
            error = np.abs(m["across"]) if across_only else m["error"]
            with np.errstate(invalid="ignore"):
                obs = obs.subset(known & (m["first"] | (error <= threshold)))
        return original(cams, obs, options, names=names)

    try:
        sparse_stage_module.adjust_observations = capture
        result = sparse_stage_module.sparse_stage(views, scene.aoi, prior)
        state.update(coarse=result.coarse_corrections_px, surface=TruthSurface(scene, result.frame))
        row = {"scene": Path(scene_dir).name, "kept": len(result.kept),
               "worst_view_px": round(_worst_view(scene, result), 4)}
        P, idx = true_cameras(captured["cams"], captured["names"])
        obs = captured["obs"]
        m = observation_errors(P, obs, state["surface"])
        acquisition = np.array([-1 if scene.views[v].acquisition is None else scene.views[v].acquisition
                                for v in idx])
        same = acquisition[m["head_view"]] == acquisition[obs.view]
        valid = ~m["first"] & np.isfinite(m["across"])
        row["off_truth_n"] = int(np.sum(~m["first"] & ~np.isfinite(m["across"])))
        for name, date in (("same_date", same), ("other_date", ~same)):
            for where, place in (("flat", m["flat"]), ("near_step", ~m["flat"])):
                sel = valid & date & place
                row[f"{name}_{where}_n"] = int(sel.sum())
                row[f"{name}_{where}_across_px"] = _median(m["across"][sel])
                row[f"{name}_{where}_precise"] = (round(float(np.mean(np.abs(m["across"][sel]) < PRECISE_PX)), 3)
                                                  if sel.any() else None)
        if oracle != "none":
            sparse_stage_module.adjust_observations = change
            again = sparse_stage_module.sparse_stage(views, scene.aoi, prior)
            row["oracle"] = oracle if oracle == "exact" else (
                f"within {threshold:g} px" + (" across" if across_only else ""))
            row["oracle_worst_view_px"] = round(_worst_view(scene, again), 4)
    finally:
        sparse_stage_module.adjust_observations = original
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scenes", nargs="+", help="synthetic scene folders (satsweep synth)")
    p.add_argument("--oracle", choices=("none", "exact", "within"), default="none",
                   help="run the stage again with its fine adjustment's input changed (see above)")
    p.add_argument("--threshold", type=float, default=0.3, help="--oracle within: px (default 0.3)")
    p.add_argument("--across", action="store_true",
                   help="--oracle within: the error across the epipolar line only")
    p.add_argument("--json", type=Path, help="also write the rows here")
    args = p.parse_args(argv)
    rows = []
    print("scene | kept | worst view px | off truth | same date: flat / near a step, median |across| px (n, "
          f"share < {PRECISE_PX:g} px) | other dates: flat / near a step | oracle")
    for folder in args.scenes:
        r = diagnose(folder, args.oracle, args.threshold, args.across)
        rows.append(r)

        def cell(name):
            out = []
            for where in ("flat", "near_step"):
                if r[f"{name}_{where}_n"]:
                    out.append(f"{r[f'{name}_{where}_across_px']:.3f} ({r[f'{name}_{where}_n']}, "
                               f"{r[f'{name}_{where}_precise']:.2f})")
                else:
                    out.append("-")
            return " / ".join(out)

        oracle = f"{r['oracle']}: {r['oracle_worst_view_px']:.4f} px" if "oracle" in r else "-"
        print(f"{r['scene']} | {r['kept']} | {r['worst_view_px']:.4f} | {r['off_truth_n']} | "
              f"{cell('same_date')} | "
              f"{cell('other_date')} | {oracle}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
