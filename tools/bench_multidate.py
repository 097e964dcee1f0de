#!/usr/bin/env python3
"""Multi-date, many-view benchmark (issue 26): accuracy and time for 2, 5, 10 and 20 views.

Each seed's scene (``satsweep synth --acquisitions``) holds the most views asked for (20 by
default), grouped into passes of 1-3 views on about half as many dates over 13 months: sun,
shadows, vegetation, transients and radiometry differ between dates, viewing azimuths come from
all around, and a quarter of the views carry pointing errors of half to all of ``--large-bias``
pixels (50 by default) on top of ``--bias`` (2); ``--dates N`` sets the number of dates (as
many as views: one view per date, so no same-date pair). Every view has its acquisition metadata
(``.IMD`` sidecar) unless ``--no-metadata``. ``--product rgb8`` writes them as 8-bit RGB
stretched per image, as pansharpened deliveries are (the real stacks' form).

For each number of views k, the k views are taken evenly over the scene's views (in date
order), always with view 0, and reconstructed by ``satsweep.pipeline.reconstruct`` from their
images and raw RPCs, with no altitude range (the pipeline's own tie points set it) unless
``--given-range``; the DSM is scored against the exact truth by both protocols:
IARPA MVS3DM (median |error| and completeness within 1 m after its alignment) and DFC2019 (mean
absolute error after the NCC shift and the mean vertical offset; valid fraction); the table
also gives the MVS3DM alignment's horizontal shift and the share of the truth's cells it compares
(those a shift moves off the DSM's border count as incomplete: about 0.8 points per row or column
of cells at 384 px, so whole-cell shifts move a small scene's figure by that much), and the
pointing corrections' error: the worst view's correction against its true bias after removing
the unobservable motion of the scene, as tools/bench_ba.py measures it ("point px", over the
views the run kept; json ``pointing_views``). The best
single same-date pair of the scene (each pair of views of one pass) is the reference the issue
compares the 10-view result with: at least 5 points more completeness within 1 m.

    python tools/bench_multidate.py                        # seeds 0 1, 2/5/10/20 views, 384 px
    python tools/bench_multidate.py --views 2 5 10 --size 256 --seeds 0
    python tools/bench_multidate.py --given-range --no-metadata --json out.json
    python tools/bench_multidate.py --views 10 --seeds 0 1 2 3 4 5 --product rgb8 --no-pairs
    # a change's before and after: the same arguments, the earlier run's --json as baseline
    python tools/bench_multidate.py --views 3 5 --dates 5 --seeds 0 1 2 --json before.json
    python tools/bench_multidate.py --views 3 5 --dates 5 --seeds 0 1 2 --baseline before.json
    # stacks in the issue's form (WorldView-3: 0.3 m, 8-bit RGB, 19 views on 13 dates):
    python tools/bench_multidate.py --seeds 7 12 --views 19 --dates 13 --size 850 --gsd 0.3 \
        --product rgb8 --bias 3 --large-bias 36 --location=-81.66,30.32 --no-pairs
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from satsweep.config import PipelineConfig  # noqa: E402
from satsweep.errors import SatsweepError  # noqa: E402
from satsweep.geometry.altitude import AltitudeRange  # noqa: E402
from satsweep.geometry.geodesy import ENUFrame  # noqa: E402
from satsweep.pipeline.run import reconstruct  # noqa: E402
from satsweep.products.evaluate import EvaluateOptions, evaluate_dsm  # noqa: E402
from satsweep.synth.scene import Scene, SynthOptions, generate_scene, parse_location  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # (imported as tools.bench_multidate)
from bench_ba import gauge_removed  # noqa: E402

# Margin around the truth's altitude range when --given-range is asked for (m).
ALT_MARGIN_M = 5.0
# The figure: completeness within 1 m of 10 views at least this much above the best
# same-date pair's.
TARGET_GAIN_POINTS = 5.0


def scene_options(seed: int, n_views: int, size: int, bias: float, large_bias: float,
                  metadata: bool, product: str = "dn16", dates: int | None = None,
                  gsd: float = 0.5, location: tuple[float, float] | None = None,
                  rpc_height_scale: float = 0.0) -> SynthOptions:
    extra = {} if location is None else {"location": location}
    if rpc_height_scale:
        extra["rpc_height_scale_m"] = rpc_height_scale
    return SynthOptions(seed=seed, n_views=n_views, size_px=size, gsd_m=gsd, bias_px=bias,
                        acquisitions=dates or max(1, n_views // 2), large_bias_px=large_bias,
                        write_metadata=metadata, product=product,
                        # the true surface sampled at half the GSD or finer (as satsweep synth)
                        cell_m=min(SynthOptions.cell_m, gsd / 2.0), **extra)


def get_scene(cache: Path, options: SynthOptions, log) -> Scene:
    name = (f"s{options.seed}_v{options.n_views}_px{options.size_px}_b{options.bias_px:g}"
            f"_l{options.large_bias_px:g}_m{int(bool(options.write_metadata))}"
            + ("" if options.product == "dn16" else f"_{options.product}")
            + ("" if options.acquisitions == max(1, options.n_views // 2)
               else f"_d{options.acquisitions}")
            + ("" if options.gsd_m == 0.5 else f"_g{options.gsd_m:g}")
            + ("" if options.location == SynthOptions.location
               else f"_at{options.location[0]:g},{options.location[1]:g}")
            + ("" if not options.rpc_height_scale_m else f"_h{options.rpc_height_scale_m:g}"))
    folder = cache / name
    if (folder / "scene.json").is_file():
        return Scene.load(folder)
    t = time.perf_counter()
    scene = generate_scene(folder, options, overwrite=True)
    log(f"generated {name} in {time.perf_counter() - t:.0f} s")
    return scene


def subset(n_total: int, k: int) -> list[int]:
    """k view indices spread evenly over the scene's views, view 0 first."""
    return sorted(set(int(round(x)) for x in np.linspace(0, n_total - 1, k)))[:k]


def score(dsm: Path, truth: Path) -> dict:
    """Both protocols' figures, with the MVS3DM alignment's shift and the share of the truth's
    cells it compares: the DSM covers the AOI only, so a shifted prediction leaves the truth's
    cells along one or two borders without a value, which count as incomplete."""
    report = evaluate_dsm(dsm, truth)
    mvs = report["aligned"]
    dfc = evaluate_dsm(dsm, truth, EvaluateOptions(protocol="dfc"))
    shift = mvs["shift"]
    return {"median_m": mvs["median_abs_error_m"], "completeness_1m": mvs["completeness_1m"],
            "dfc_mae_m": dfc["mean_abs_error_m"], "dfc_valid": dfc["valid_fraction"],
            "mvs_shift_m": [shift["dx_m"], shift["dy_m"], shift["dz_m"]],
            "mvs_compared": mvs["compared_cells"] / report["truth_cells"]}


def pointing_error(scene: Scene, views: list[int], shifts: dict) -> float | None:
    """Worst view's pointing correction against the scene's true bias (px, the largest
    component), after removing the motion of the whole scene that no image can see (as
    tools/bench_ba.py's): ``shifts`` maps the views' file names to the run's corrections
    (report ``ba.principal_point_shift_px``). Each view's gauge Jacobian d(pixel)/d(east,
    north, up) is its RPC's, by central differences of 1 m in the ENU frame of the AOI's centre
    at the middle of the truth's heights. Views the run dropped (no correction) take no part; None with fewer
    than two corrected views (adjustment off)."""
    views = [i for i in views if scene.views[i].image.name in shifts]
    names = [scene.views[i].image.name for i in views]
    if len(views) < 2:
        return None
    aoi = scene.aoi
    frame = ENUFrame(lon0=(aoi.lon_min + aoi.lon_max) / 2.0, lat0=(aoi.lat_min + aoi.lat_max) / 2.0,
                     alt0=sum(scene.alt_range) / 2.0)
    step = np.vstack([np.eye(3), -np.eye(3)])  # +-1 m along east, north, up
    lon, lat, alt = frame.to_geodetic(e=step[:, 0], n=step[:, 1], u=step[:, 2])
    A = np.zeros((len(views), 2, 3))
    for k, i in enumerate(views):
        col, row = scene.views[i].rpc().projection(lon=lon, lat=lat, alt=alt)
        A[k] = (np.stack([col, row])[:, :3] - np.stack([col, row])[:, 3:]) / 2.0
    residual, _ = gauge_removed(A, [shifts[n] for n in names],
                                [scene.views[i].bias_px for i in views])
    return float(np.abs(residual).max())


def run(scene: Scene, views: list[int], out: Path, args, config: PipelineConfig) -> dict:
    images = [scene.views[i].image for i in views]
    alt = None
    if args.given_range:
        lo, hi = scene.alt_range
        alt = AltitudeRange(lo - ALT_MARGIN_M, hi + ALT_MARGIN_M)
    t = time.perf_counter()
    try:
        result = reconstruct(images, scene.aoi, out, alt_range=alt, config=config,
                             verbose=not args.quiet, overwrite=True)
    except SatsweepError as exc:
        return {"views": views, "error": str(exc), "seconds": time.perf_counter() - t}
    rep = result.report
    row = {"views": views, "seconds": time.perf_counter() - t,
           "stages": {k: v for k, v in rep["timings_s"].items() if k != "total"},
           "altitude_range": [rep.get("altitude_range", {}).get("min"),
                              rep.get("altitude_range", {}).get("max")],
           "truth_range": list(scene.alt_range),
           "references": len(rep.get("sweep", [])), "fusion": rep["dsm"].get("fusion"),
           "kernel_builds": (rep.get("device") or {}).get("kernel_builds"),
           **score(result.dsm_path, scene.truth_dsm)}
    shifts = rep.get("ba", {}).get("principal_point_shift_px", {}) or {}
    row["pointing_px"] = pointing_error(scene, views, shifts)
    row["pointing_views"] = sum(scene.views[i].image.name in shifts for i in views)
    lo, hi = row["altitude_range"]
    t_lo, t_hi = scene.alt_range
    row["range_holds_truth"] = lo is not None and lo <= t_lo and hi >= t_hi
    return row


def same_date_pairs(scene: Scene) -> list[tuple[int, int]]:
    """The pairs of views of one acquisition (pass)."""
    groups: dict = {}
    for i, v in enumerate(scene.views):
        groups.setdefault(v.acquisition if v.acquisition is not None else -1 - i, []).append(i)
    return [p for g in groups.values() for p in itertools.combinations(g, 2)]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--views", type=int, nargs="+", default=[2, 5, 10, 20])
    p.add_argument("--size", type=int, default=384, help="view side (pixels)")
    p.add_argument("--gsd", type=float, default=0.5,
                   help="ground sample distance (m; WorldView-3: 0.3); the DSM stays at 0.5 m")
    p.add_argument("--location", default=None, metavar="LON,LAT",
                   help="scene centre in degrees (satsweep synth's default: Paris); write "
                   "--location=-81.66,30.32 when the longitude is negative")
    p.add_argument("--bias", type=float, default=2.0, help="pointing error of every view (px)")
    p.add_argument("--large-bias", type=float, default=50.0,
                   help="largest extra pointing error of a quarter of the views (px)")
    p.add_argument("--no-metadata", action="store_true", help="views without .IMD sidecars")
    p.add_argument("--product", choices=("dn16", "rgb8"), default="dn16",
                   help="the views' images (satsweep synth --product): rgb8 = 8-bit RGB stretched per "
                   "image, as WorldView-3 and Pleiades pansharpened deliveries are")
    p.add_argument("--dates", type=int, default=None,
                   help="acquisition dates of the scene (default: half its views, in passes of 1-3 "
                   "views); as many as views: one view per date, as most real stacks are")
    p.add_argument("--rpc-height-scale", type=float, default=0.0, metavar="M",
                   help="fit the views' RPCs over this many metres above and below the scene "
                   "(satsweep synth --rpc-height-scale; real deliveries: about 500), so that a run "
                   "without an altitude range crops whole views as on real data (default 0: the "
                   "scene's own heights)")
    p.add_argument("--given-range", action="store_true",
                   help="give the truth's altitude range (widened by 5 m) instead of none")
    p.add_argument("--no-pairs", action="store_true", help="skip the same-date pairs")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    p.add_argument("--scenes", default=os.path.join(tempfile.gettempdir(),
                                                    "satsweep-bench-multidate"))
    p.add_argument("--json", default=None, help="also write every figure to this file")
    p.add_argument("--baseline", default=None, metavar="JSON",
                   help="an earlier run's --json: also list the runs whose figures differ from "
                   "it, and the means over the runs both have (a change's before and after)")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    baseline = None
    if args.baseline is not None:
        try:
            baseline = json.loads(Path(args.baseline).read_text())
        except (OSError, ValueError) as exc:
            p.error(f"{args.baseline}: not a JSON file of this tool's rows ({exc})")
        if not isinstance(baseline, list) or not all(isinstance(r, dict) and "seed" in r
                                                     for r in baseline):
            p.error(f"{args.baseline}: not a JSON file of this tool's rows (--json)")
    location = None
    if args.location is not None:
        try:
            location = parse_location(args.location)
        except SatsweepError as exc:
            p.error(str(exc))

    config = PipelineConfig()
    for item in args.set:
        key, _, value = item.partition("=")
        section, _, name = key.partition(".")
        value = json.loads(value)
        # JSON has no tuples: a list is a tuple option's value (census_window = [3, 3]).
        config = config.override(section, **{name: tuple(value) if isinstance(value, list)
                                             else value})

    def log(msg):
        print(f"[bench_multidate] {msg}", file=sys.stderr, flush=True)

    cache = Path(args.scenes)
    cache.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="satsweep-bench-multidate-") as tmp:
        for seed in args.seeds:
            scene = get_scene(cache, scene_options(seed, max(args.views), args.size, args.bias,
                                                   args.large_bias, not args.no_metadata,
                                                   args.product, args.dates, args.gsd,
                                                   location, args.rpc_height_scale), log)
            for k in args.views:
                views = subset(len(scene.views), k)
                row = run(scene, views, Path(tmp) / f"s{seed}_k{k}", args, config)
                row.update(seed=seed, k=k, kind="views", scene=scene.directory.name)
                rows.append(row)
                log(f"seed {seed}, {k} views: " + (row.get("error") or
                    f"{row['median_m']:.3f} m, {100 * row['completeness_1m']:.1f}% within 1 m, "
                    f"DFC MAE {row['dfc_mae_m']:.3f} m ({row['seconds']:.0f} s)"))
            if not args.no_pairs:
                for pair in same_date_pairs(scene):
                    row = run(scene, list(pair), Path(tmp) / f"s{seed}_p{pair[0]}_{pair[1]}",
                              args, config)
                    row.update(seed=seed, k=2, kind="same-date pair", scene=scene.directory.name)
                    rows.append(row)
    print_table(rows)
    if baseline is not None:
        print_comparison(compare_rows(baseline, rows), args.baseline)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


# The figures of a row that make it "changed" against a baseline (--baseline), and how far apart
# two values may be and still be the same figure (JSON keeps a float64 to the bit; 1e-9 leaves
# room for a file written by hand).
COMPARED = ("error", "altitude_range", "references", "median_m", "completeness_1m", "dfc_mae_m",
            "dfc_valid", "pointing_px")
SAME_TOL = 1e-9


def _row_key(row: dict) -> tuple:
    """A run's identity across two runs of this tool, its scene's folder apart: seed, kind and
    views."""
    return (row["seed"], row["kind"], tuple(row["views"]))


def _same_run(a: dict, b: dict) -> bool:
    """Two rows of one run: the same ``_row_key`` and scene folder (a row written before rows
    named their scene matches any)."""
    return (_row_key(a) == _row_key(b)
            and (a.get("scene") is None or b.get("scene") is None or a["scene"] == b["scene"]))


def _same(a, b) -> bool:
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return abs(a - b) <= SAME_TOL
    return a == b


def compare_rows(before: list[dict], after: list[dict]) -> dict:
    """Two runs' rows matched by ``_same_run`` (the first match of each): ``changed`` (before,
    after) pairs whose COMPARED figures differ, the rows of one run only, and over the matched
    runs with a DSM in both: their count, mean DFC MAE (m) and how many ranges hold the truth,
    before and after."""
    pairs, used = [], set()
    for b in after:
        a = next((k for k, r in enumerate(before) if k not in used and _same_run(r, b)), None)
        if a is not None:
            used.add(a)
            pairs.append((before[a], b))
    matched = {id(b) for _, b in pairs}
    changed = [(a, b) for a, b in pairs
               if not all(_same(a.get(f), b.get(f)) for f in COMPARED)]
    scored = [(a, b) for a, b in pairs if "error" not in a and "error" not in b]
    n = len(scored)
    return {"matched": len(pairs), "changed": changed,
            "only_before": [r for k, r in enumerate(before) if k not in used],
            "only_after": [r for r in after if id(r) not in matched],
            "scored": n,
            "mean_dfc_mae_m": ((sum(a["dfc_mae_m"] for a, _ in scored) / n,
                                sum(b["dfc_mae_m"] for _, b in scored) / n) if n else None),
            "ranges_holding_truth": (sum(bool(a["range_holds_truth"]) for a, _ in scored),
                                     sum(bool(b["range_holds_truth"]) for _, b in scored))}


def _summary(row: dict) -> str:
    if "error" in row:
        return "error: " + row["error"]
    lo, hi = row["altitude_range"]
    return (f"DFC MAE {row['dfc_mae_m']:.3f} m, {100 * row['completeness_1m']:.1f}% within 1 m, "
            f"range {lo:.1f}..{hi:.1f}, point {_px(row.get('pointing_px'))} px")


def print_comparison(cmp: dict, name: str) -> None:
    print(f"\nagainst {name}: {cmp['matched']} runs in both, {len(cmp['changed'])} changed, "
          f"{len(cmp['only_after'])} only in this run, {len(cmp['only_before'])} only in "
          f"{name}")
    for a, b in cmp["changed"]:
        t_lo, t_hi = b.get("truth_range") or a.get("truth_range") or (math.nan, math.nan)
        what = f"{b['k']} views" if b["kind"] == "views" else b["kind"]
        print(f"  seed {b['seed']}, {what} {b['views']} (truth "
              f"{t_lo:.1f}..{t_hi:.1f}): {_summary(a)}\n"
              f"    -> {_summary(b)}")
    if cmp["scored"]:
        (m0, m1), (h0, h1) = cmp["mean_dfc_mae_m"], cmp["ranges_holding_truth"]
        print(f"  over the {cmp['scored']} runs with a DSM in both: mean DFC MAE {m0:.3f} -> "
              f"{m1:.3f} m; ranges holding the truth {h0} -> {h1}")


def _px(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def _built(builds: dict | None) -> str:
    """The seconds of the run's kernel builds (part of "total s": a process's first stack builds
    its kernels, seconds on PoCL without its disk cache; "-": none built)."""
    return "-" if not builds or not builds["programs"] else f"{builds['seconds']:.1f}"


def print_table(rows: list[dict]) -> None:
    print(f"{'seed':>4} {'kind':<15} {'k':>3} {'refs':>4} {'med m':>6} {'<1m %':>6} "
          f"{'MAE m':>6} {'valid':>6} {'shift m':>10} {'cmp %':>6} {'range (truth)':>26} "
          f"{'point px':>8} {'sparse s':>8} {'total s':>7} {'built s':>7}")
    for r in rows:
        if "error" in r:
            print(f"{r['seed']:>4} {r['kind']:<15} {r['k']:>3} error: {r['error']}")
            continue
        lo, hi = r["altitude_range"]
        t_lo, t_hi = r["truth_range"]
        sparse = r["stages"].get("sparse", 0.0)
        dx, dy, _ = r["mvs_shift_m"]
        print(f"{r['seed']:>4} {r['kind']:<15} {r['k']:>3} {r['references']:>4} "
              f"{r['median_m']:>6.3f} {100 * r['completeness_1m']:>6.1f} {r['dfc_mae_m']:>6.3f} "
              f"{r['dfc_valid']:>6.3f} {f'{dx:+.1f},{dy:+.1f}':>10} "
              f"{100 * r['mvs_compared']:>6.1f} "
              f"{f'{lo:.0f}..{hi:.0f} ({t_lo:.0f}..{t_hi:.0f})':>26} "
              f"{_px(r.get('pointing_px')):>8} {sparse:>8.1f} {r['seconds']:>7.1f} "
              f"{_built(r.get('kernel_builds')):>7}")
    for seed in sorted({r["seed"] for r in rows}):
        pairs = [r for r in rows if r["seed"] == seed and r["kind"] == "same-date pair"
                 and "error" not in r]
        ten = [r for r in rows if r["seed"] == seed and r["kind"] == "views" and r["k"] == 10
               and "error" not in r]
        if pairs and ten:
            best = max(r["completeness_1m"] for r in pairs)
            gain = 100 * (ten[0]["completeness_1m"] - best)
            print(f"seed {seed}: 10 views {100 * ten[0]['completeness_1m']:.1f}% vs best same-date "
                  f"pair {100 * best:.1f}%: {gain:+.1f} points (target >= +{TARGET_GAIN_POINTS:g})")


if __name__ == "__main__":
    sys.exit(main())
