#!/usr/bin/env python3
"""Are the multi-date synthetic scenes as hard as real ones? A same-date pair against a
cross-date pair of the same geometry.

Real multi-date stacks: a pair of views from one pass reconstructs well, a pair from two dates
of similar base-to-height ratio much worse (sun, shadows, trees, cars and radiometry differ).
This tool checks that ``satsweep synth``'s multi-date scenes behave so. Each scene has two
acquisitions: views 0 and 1 on the first date (the built-in view angles 0 and 1: off-nadir 10
and 4 degrees, base-to-height 0.20), view 2 on the second date with view 0's angles. So the
pairs (0, 1) and (2, 1) have the same geometry (up to the passes' headings) and differ only by
the date. Each pair is reconstructed by ``satsweep.pipeline.reconstruct`` from its images and
RPCs (no pointing error, the scene's altitude range widened by ALT_MARGIN_M) and evaluated
against the truth (IARPA MVS3DM protocol). The table gives, per seed and per set of date
effects, the dates, the sun, the completeness within 1 m and the median error of both pairs.

    python tools/diag_multidate_pairs.py                         # seeds 0 1 2, 256 px, all effects
    python tools/diag_multidate_pairs.py --size 176 --seeds 0 1 2 3 4 5
    python tools/diag_multidate_pairs.py --effects all none sun vegetation,ground transients radiometry

``--effects`` takes sets of date effects (comma-separated names of
``satsweep.synth.multidate.DATE_EFFECTS``, ``all`` or ``none``): ``none`` is the control, where
only the noise and the pass heading differ between the dates.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from satsweep.config import PipelineConfig  # noqa: E402
from satsweep.errors import OptionsError  # noqa: E402
from satsweep.geometry.altitude import AltitudeRange  # noqa: E402
from satsweep.pipeline.run import reconstruct  # noqa: E402
from satsweep.synth.multidate import DATE_EFFECTS, parse_iso_utc  # noqa: E402
from satsweep.synth.scene import Scene, SynthOptions, generate_scene  # noqa: E402

# Margin around the scene's true altitude range given to the pipeline (m), as satsweep demo.
ALT_MARGIN_M = 5.0
# The views: 0 and 1 on the first date, 2 on the second with view 0's angles.
OFF_NADIR_DEG = (10.0, 4.0, 10.0)
AZIMUTH_DEG = (20.0, 120.0, 20.0)
SAME_DATE_PAIR = (0, 1)
CROSS_DATE_PAIR = (2, 1)


def pair_scene_options(seed: int, size_px: int, effects: tuple[str, ...] = DATE_EFFECTS) -> SynthOptions:
    """The options of the two-date, three-view scene described in the module docstring."""
    return SynthOptions(seed=seed, n_views=3, size_px=size_px, gsd_m=0.5, acquisitions=2,
                        views_per_acquisition=(2, 1), off_nadir_deg=OFF_NADIR_DEG, azimuth_deg=AZIMUTH_DEG,
                        date_effects=tuple(effects), write_metadata=False)


def reconstruct_pair(scene: Scene, pair: tuple[int, int], out: Path,
                     config: PipelineConfig = PipelineConfig()) -> dict:
    """Reconstruct one pair of the scene's views; the aligned metrics against the truth and the
    wall time."""
    lo, hi = scene.alt_range
    t0 = time.perf_counter()
    res = reconstruct([scene.views[k].image for k in pair], scene.aoi, out,
                      alt_range=AltitudeRange(lo - ALT_MARGIN_M, hi + ALT_MARGIN_M), config=config,
                      overwrite=True, truth=scene.truth_dsm, verbose=False, command="diag_multidate_pairs")
    a = res.evaluation["aligned"]
    return {"completeness_1m": a["completeness_1m"], "median_abs_error_m": a["median_abs_error_m"],
            "wall_s": time.perf_counter() - t0}


def parse_effects(text: str) -> tuple[str, ...]:
    if text == "all":
        return DATE_EFFECTS
    if text == "none":
        return ()
    names = tuple(t for t in text.split(",") if t)
    unknown = [n for n in names if n not in DATE_EFFECTS]
    if unknown:
        raise OptionsError(f"--effects {text}: unknown {', '.join(unknown)} "
                           f"(known: {', '.join(DATE_EFFECTS)}, all, none)")
    return names


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="scene seeds")
    p.add_argument("--size", type=int, default=256, help="view side in pixels (0.5 m)")
    p.add_argument("--effects", nargs="+", default=["all"],
                   help="sets of date effects to compare: all, none, or comma-separated names")
    p.add_argument("--out", default=None, help="working folder (default: a temporary one, removed)")
    p.add_argument("--json", default=None, help="also write the rows to this JSON file")
    args = p.parse_args(argv)
    sets = [parse_effects(e) for e in args.effects]
    with tempfile.TemporaryDirectory(prefix="diag-multidate-") as tmp:
        root = Path(args.out) if args.out else Path(tmp)
        rows = []
        for effects in sets:
            label = ",".join(effects) if effects else "none"
            for seed in args.seeds:
                folder = root / f"s{seed}_{args.size}_{label.replace(',', '-')}"
                scene = generate_scene(folder / "scene", pair_scene_options(seed, args.size, effects), overwrite=True)
                a0, a1 = scene.acquisitions
                days = (parse_iso_utc(a1.date_time) - parse_iso_utc(a0.date_time)).days
                same = reconstruct_pair(scene, SAME_DATE_PAIR, folder / "same")
                cross = reconstruct_pair(scene, CROSS_DATE_PAIR, folder / "cross")
                row = {"effects": label, "seed": seed, "size_px": args.size,
                       "dates": [a0.date_time, a1.date_time], "days_apart": days,
                       "sun": [[a.sun_elevation_deg, a.sun_azimuth_deg] for a in (a0, a1)],
                       "leaves": [a0.leaf_density, a1.leaf_density],
                       "transients": [len(a0.transients), len(a1.transients)],
                       "bh": [next(b for i, j, b in scene.pairs if (i, j) == tuple(sorted(pr)))
                              for pr in (SAME_DATE_PAIR, CROSS_DATE_PAIR)],
                       "same": same, "cross": cross}
                rows.append(row)
                print(f"{label:<22} seed {seed}: {a0.date_time[:10]} / {a1.date_time[:10]} ({days:3d} d), "
                      f"sun {a0.sun_elevation_deg:4.1f}/{a0.sun_azimuth_deg:5.1f} -> {a1.sun_elevation_deg:4.1f}/"
                      f"{a1.sun_azimuth_deg:5.1f}, leaves {a0.leaf_density:.2f} -> {a1.leaf_density:.2f}: "
                      f"same-date {same['completeness_1m']:6.1%} ({same['median_abs_error_m']:.3f} m), "
                      f"cross-date {cross['completeness_1m']:6.1%} ({cross['median_abs_error_m']:.3f} m)",
                      flush=True)
    print()
    print(f"{'effects':<22} {'seeds':>5} {'same 1m':>8} {'cross 1m':>8} {'drop':>7}  min drop")
    for effects in sets:
        label = ",".join(effects) if effects else "none"
        sel = [r for r in rows if r["effects"] == label]
        same = sum(r["same"]["completeness_1m"] for r in sel) / len(sel)
        cross = sum(r["cross"]["completeness_1m"] for r in sel) / len(sel)
        drops = [r["same"]["completeness_1m"] - r["cross"]["completeness_1m"] for r in sel]
        print(f"{label:<22} {len(sel):>5} {same:8.1%} {cross:8.1%} {same - cross:7.1%}  {min(drops):.1%}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n", encoding="utf-8")
        print(f"wrote {os.fspath(args.json)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
