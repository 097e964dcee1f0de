"""The ``satsweep`` command line: thin argparse subcommands over the typed API.

Every ``SatsweepError`` becomes one line on stderr (``satsweep: error: <file>: <problem>``) and
exit code 2; nothing is written for a run that fails on its input.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import re
import signal
import sys
import threading
import warnings
from typing import Callable, Iterator, Sequence

from satsweep import __version__
from satsweep.errors import RetiredOptionWarning, SatsweepError

Handler = Callable[[argparse.Namespace], int]

# Exit code of a run that finished but whose warnings say the result is doubtful, with --strict.
EXIT_DOUBTFUL = 3
# Seconds after which a SIGTERM or SIGHUP that came during an import is sent again.
SIGNAL_RETRY_S = 0.05


class _Parser(argparse.ArgumentParser):
    """argparse that takes a value starting with a minus and a digit (``--aoi -70.5,-33.4,...``,
    ``--alt-range -12 40``, ``-1e9``) as a value, not as an unknown option: satsweep has no
    option that looks like a number."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-(\d|\.\d)")


class Terminated(BaseException):
    """SIGTERM or SIGHUP, raised in the main thread so that a run cleans up as on Ctrl-C."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


FIXED_VIEW_HELP = ("an image whose RPC is trusted (repeatable): the bundle adjustment holds its "
                   "correction at zero and corrects the others to agree with it, as ASP's "
                   "fixed cameras or S2P's reference image; an error if it cannot be tied "
                   "(default: none, the corrections smallest on average)")


@contextlib.contextmanager
def _termination_raises():
    """While inside: SIGTERM and SIGHUP raise ``Terminated`` (as SIGINT raises
    KeyboardInterrupt), so a killed run removes its staging folder; the previous handlers are
    restored after."""

    def raise_terminated(signum, frame):
        if frame is not None and frame.f_code.co_filename.startswith("<frozen importlib"):
            # An exception raised in the import system's lock callbacks is printed and ignored
            # ("Exception ignored in: _get_module_lock.<locals>.cb"): the run would go on. The
            # signal is sent again a moment later, once the import is through.
            threading.Timer(SIGNAL_RETRY_S, os.kill, (os.getpid(), signum)).start()
            return
        raise Terminated(signum)

    previous = {}
    for name in ("SIGTERM", "SIGHUP"):
        signum = getattr(signal, name, None)
        if signum is None:  # pragma: no cover - Windows has no SIGHUP
            continue
        try:
            previous[signum] = signal.signal(signum, raise_terminated)
        except ValueError:  # not the main thread: signals cannot be handled here
            pass
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


# -- devices -----------------------------------------------------------------------------------
def _add_devices(sub) -> None:
    p = sub.add_parser(
        "devices",
        help="list OpenCL platforms/devices and whether each can build a kernel",
        description="List every OpenCL device with its memory and whether it builds and runs a "
        "trivial kernel, and show which one --device/SATSWEEP_DEVICE would select.",
    )
    p.add_argument("--device", default=None, help="auto|cpu|gpu|PLATFORM:DEVICE (default: $SATSWEEP_DEVICE or auto)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.set_defaults(handler=_cmd_devices)


def _cmd_devices(args: argparse.Namespace) -> int:
    from satsweep.opencl import device as sdev

    devices = sdev.list_devices(check_build=True)
    selected = None
    select_error = None
    try:
        selected = sdev.select_device(args.device)
    except SatsweepError as exc:
        select_error = str(exc)
    if args.json:
        print(json.dumps({
            "devices": [d.as_dict() for d in devices],
            "selected": selected.spec if selected else None,
            "error": select_error,
        }, indent=2))
    else:
        if not devices:
            print("no OpenCL device found")
        for d in devices:
            mark = "*" if selected is not None and d.spec == selected.spec else " "
            build = "builds kernels" if d.can_build else f"CANNOT BUILD KERNELS ({d.build_error})"
            print(
                f"{mark} {d.spec:5s} {d.kind:5s} {d.platform_name} / {d.device_name}: "
                f"{d.global_mem_bytes / 2**30:.1f} GiB global, "
                f"{d.max_alloc_bytes / 2**30:.1f} GiB max alloc, {d.compute_units} CUs, {build}"
            )
        if selected is not None:
            print(f"selected: {selected.label}")
    if select_error:
        print(f"satsweep: error: {select_error}", file=sys.stderr)
        return 2
    return 0


# -- shared by the commands that read images ------------------------------------------------------
def _add_image_inputs(p) -> None:
    """IMAGE..., --aoi, --alt-range, --dem: the inputs of cameras and reconstruct."""
    p.add_argument("images", nargs="+", metavar="IMAGE", help="TIFF images with an RPC (tag or sidecar)")
    p.add_argument("--aoi", required=True, help="LON_MIN,LAT_MIN,LON_MAX,LAT_MAX (degrees) or a GeoJSON file")
    p.add_argument("--alt-range", nargs=2, type=float, metavar=("MIN", "MAX"), default=None,
                   help="heights in metres above the WGS84 ellipsoid (default: from --dem, else "
                   "from the SIFT tie points between the views, triangulated with the adjusted "
                   "cameras, near the AOI)")
    p.add_argument("--dem", default=None, metavar="FILE", help="DEM GeoTIFF giving the altitude range")
    p.add_argument("--rpc-dir", default=None, metavar="DIR",
                   help="take each image's RPC from DIR/<image stem>_RPC.TXT instead of its own "
                   "(the rpc/ folder of an earlier run or of cameras --adjust, or another "
                   "tool's adjusted RPCs); an image without one there is an error")
    p.add_argument("--mask-dir", default=None, metavar="DIR",
                   help="masks of the pixels to leave out (clouds), one per image that has "
                   "one: DIR/<image file name>.msk, a raster of the image's size, 0 = leave out "
                   "(GDAL's mask convention; without this option, each image's own GDAL mask "
                   "is used: IMAGE.msk beside it or a mask inside it)")


def _cli_altitude_range(args: argparse.Namespace):
    """The --alt-range given on the command line (None if absent); errors name the option."""
    from satsweep.errors import AOIError
    from satsweep.geometry.altitude import AltitudeRange

    if args.alt_range is None:
        return None
    try:
        return AltitudeRange(*args.alt_range)
    except AOIError as exc:
        raise AOIError(f"--alt-range {args.alt_range[0]:g} {args.alt_range[1]:g}: {exc}") from None


# -- cameras -----------------------------------------------------------------------------------
def _add_cameras(sub) -> None:
    p = sub.add_parser(
        "cameras",
        help="approximate each image's RPC by a perspective camera over the AOI",
        description="Fit a pinhole camera K[R|t] to each image's RPC over the AOI cube (AOI box x "
        "altitude range) in a local ENU frame, report its error against the RPC, and write "
        "DIR/cameras.json (with the plane-plus-parallax 4x4 matrices the sweep uses).",
    )
    _add_image_inputs(p)
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (cameras.json, images/)")
    p.add_argument("--adjust", action="store_true",
                   help="correct RPC pointing errors as reconstruct does (the sparse stage: "
                   "SIFT matches over a graph of pairs, a coarse translation per view, then the "
                   "bundle adjustment of the principal points); cameras.json gets the adjusted "
                   "cameras and a 'ba' section, DIR/rpc/ each view's RPC with its correction "
                   "folded in, and views that cannot be tied are left out with a warning")
    p.add_argument("--fixed-view", action="append", default=None, metavar="IMAGE",
                   help=FIXED_VIEW_HELP + " (with --adjust)")
    p.add_argument("--skew-correct", action="store_true",
                   help="shear the images so that K has no skew; write them to DIR/images/")
    p.add_argument("--grid", nargs=3, type=int, metavar=("NE", "NN", "NU"), default=None,
                   help="samples of the AOI cube along east, north, up (default 100 100 20)")
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty --out folder")
    p.set_defaults(handler=_cmd_cameras)


def _cmd_cameras(args: argparse.Namespace) -> int:
    import dataclasses

    from satsweep.config import PipelineConfig
    from satsweep.errors import OptionsError
    from satsweep.geometry.aoi import parse_aoi
    from satsweep.geometry.camera import write_cameras
    from satsweep.geometry.skew import skew_correct_set
    from satsweep.io.atomic import check_output_dir
    from satsweep.pipeline.altitude import tie_and_range
    from satsweep.pipeline.outputs import RPC_DIR, write_corrected_rpcs
    from satsweep.pipeline.prepare import (
        correct_pointing,
        crop_views,
        fit_cameras,
        open_run_sources,
        sources_seeing_the_aoi,
    )

    if args.fixed_view and not args.adjust:
        raise OptionsError("--fixed-view holds a view's pointing correction at zero: it needs "
                           "--adjust")
    check_output_dir(args.out, overwrite=args.overwrite)
    config = _with_fixed_views(PipelineConfig().override("reconstruct", adjust="on"),
                               args.fixed_view)
    if args.grid is not None:
        config = config.override("camera", grid_size=tuple(args.grid))
    aoi = parse_aoi(args.aoi)
    # The views, their pointing corrections and the altitude range as reconstruct takes them.
    sources = open_run_sources(args.images, config, rpc_dir=args.rpc_dir,
                               mask_dir=args.mask_dir)
    alt_range = _cli_altitude_range(args)
    sources, _ = sources_seeing_the_aoi(sources, aoi, config, alt_range=alt_range,
                                        dem=args.dem)  # (views of other places: warned)
    tied = tie_and_range(sources, aoi, alt_range=alt_range,
                         dem=args.dem, config=config, adjust=args.adjust)
    sparse, alt = tied.sparse, tied.altitude.range  # (doubts about them: logged warnings)
    views, _ = crop_views(tied.sources, aoi, alt, config,
                          extra_margin_px=tied.correction_margin_px if args.adjust else 0)
    cameras = fit_cameras(views, aoi, alt, config)
    images, corrections = None, None
    if args.adjust:  # ([reconstruct] adjust = on: views that cannot be tied are an error)
        cameras, adjustment = correct_pointing(cameras, views, sparse, tied.untied, config)
        fine = sparse.to_dict()["fine"] or {}
        ba = {**adjustment.to_report(), "method": "sparse stage", "points": fine.get("points"),
              "reprojection_error_px": fine.get("reprojection_error_px")}
        cameras = dataclasses.replace(cameras, ba=ba)
        if ba["reprojection_error_px"]:
            e = ba["reprojection_error_px"]
            print(f"bundle adjustment: {ba['points']} points, median reprojection error "
                  f"{e['before']['median']:.3f} -> {e['after']['median']:.3f} px")
        for name, shift in adjustment.named_sparse_shifts():
            print(f"  {name}: principal point shift ({shift[0]:+.3f}, {shift[1]:+.3f}) px")
        corrections = {v.path: s for v, s in zip(views, adjustment.own_shifts)}
    if args.skew_correct:  # the images written are the crops' own values, sheared
        cameras, images = skew_correct_set(cameras, [v.image for v in views])
    cameras = write_cameras(args.out, cameras, images)
    f = cameras.frame
    print(f"ENU origin: lon {f.lon0:.7f}, lat {f.lat0:.7f}, alt {f.alt0:.2f} m; UTM EPSG:{cameras.utm_epsg}; "
          f"AOI {aoi}, altitudes {alt} ({tied.altitude.source}); parallax plane u = {cameras.d:.2f} m")
    print(cameras.table())
    print(f"wrote {args.out}/cameras.json" + (f" and {len(images)} images in {args.out}/images/" if images else ""))
    if corrections is not None:  # the RPCs with the corrections folded in, for other tools
        rpcs = write_corrected_rpcs(os.path.join(args.out, RPC_DIR), tied.sources, corrections)
        print(f"wrote {len(rpcs)} corrected RPCs in {args.out}/{RPC_DIR}/")
    for warning in cameras.warnings:
        print(f"satsweep: warning: {warning}", file=sys.stderr)
    return 0


# -- evaluate ----------------------------------------------------------------------------------
def _add_evaluate(sub) -> None:
    p = sub.add_parser(
        "evaluate",
        help="score a DSM against a ground-truth DSM (IARPA MVS3DM or DFC2019 protocol), JSON on stdout",
        description="Resample PRED onto the grid of TRUTH (same EPSG code) and print the metrics as "
        "JSON. --protocol mvs3dm (default): search the horizontal shift (integer truth cells up to "
        "--max-shift metres) and vertical offset (median difference) with the least median absolute "
        "error; report the aligned and unaligned median_abs_error_m, completeness_1m, rmse_m and "
        "shift. --protocol dfc (DFC2019 / US3D): mask the --classification cells of --water-class "
        "(default 9, ASPRS water), take the integer shift up to --max-shift-cells that maximises the "
        "normalised cross-correlation, remove the mean vertical offset, and report "
        "mean_abs_error_m, median_abs_error_m, rmse_m, completeness_1m, valid_fraction and shift.",
    )
    p.add_argument("pred", metavar="PRED.tif", help="predicted DSM (GeoTIFF, projected CRS in metres)")
    p.add_argument("truth", metavar="TRUTH.tif", help="ground-truth DSM (GeoTIFF, same EPSG code)")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="also write error_map.png, error_histogram.png, error.tif, evaluation.json here")
    p.add_argument("--protocol", choices=("mvs3dm", "dfc"), default=None,
                   help="IARPA MVS3DM (default) or the DFC2019 / US3D protocol")
    p.add_argument("--max-shift", type=float, default=None, metavar="M",
                   help="mvs3dm: horizontal shift search radius in metres (default 2)")
    p.add_argument("--max-shift-cells", type=int, default=None, metavar="N",
                   help="dfc: horizontal shift search radius in truth cells (default 4)")
    p.add_argument("--classification", metavar="CLS.tif", default=None,
                   help="dfc: class codes on the truth grid (GeoTIFF); --water-class cells are masked")
    p.add_argument("--water-class", type=int, action="append", default=None, metavar="CODE",
                   help="dfc: a class code to mask, repeatable (default 9, ASPRS water)")
    p.add_argument("--threshold", type=float, default=None, metavar="M",
                   help="completeness threshold in metres (default 1)")
    p.add_argument("--resampling", choices=("nearest", "bilinear"), default=None,
                   help="how PRED is sampled onto the truth grid (default nearest)")
    p.set_defaults(handler=_cmd_evaluate)


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from satsweep.errors import OptionsError
    from satsweep.pipeline.report import to_json
    from satsweep.products.evaluate import EvaluateOptions, evaluate_dsm

    protocol = args.protocol or "mvs3dm"
    wrong = ([("--max-shift-cells", args.max_shift_cells), ("--classification", args.classification),
              ("--water-class", args.water_class)] if protocol == "mvs3dm" else [("--max-shift", args.max_shift)])
    for flag, value in wrong:
        if value is not None:
            other = "dfc" if protocol == "mvs3dm" else "mvs3dm"
            raise OptionsError(f"{flag} is an option of --protocol {other}, not of --protocol {protocol}")
    given = {"max_shift_m": args.max_shift, "threshold_m": args.threshold, "resampling": args.resampling,
             "protocol": args.protocol, "dfc_max_shift_cells": args.max_shift_cells,
             "water_classes": None if args.water_class is None else tuple(args.water_class)}
    options = EvaluateOptions(**{k: v for k, v in given.items() if v is not None})
    report = evaluate_dsm(args.pred, args.truth, options, out_dir=args.out, classification=args.classification)
    print(to_json(report))
    return 0


# -- synth -------------------------------------------------------------------------------------
def _add_synth(sub) -> None:
    p = sub.add_parser(
        "synth",
        help="generate synthetic satellite views of a known surface (RPC images + truth DSM)",
        description="Render a seeded synthetic town seen by linear pushbroom satellites: uint16 "
        "TIFF views with their RPC (tag 50844 and _RPC.TXT sidecars), truth_dsm.tif (UTM, 0.5 m) "
        "and scene.json (AOI, altitude range, views' angles, pointing biases and base-to-height "
        "ratios). A view with bias b shows ground point X at RPC(X) + b. With --acquisitions the "
        "views are taken on several dates (sun, shadows, trees, cars and radiometry change; the "
        "truth does not), with a .IMD sidecar and a GDAL_METADATA tag giving each view's date "
        "and sun angles.",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (created if missing)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default 0)")
    p.add_argument("--views", type=int, default=None, metavar="N", help="number of views (default 3)")
    p.add_argument("--size", type=int, default=None, metavar="PIX", help="view width and height in pixels (default 512)")
    p.add_argument("--gsd", type=float, default=None, metavar="M", help="ground sample distance in metres (default 0.5)")
    p.add_argument("--bias", type=float, default=None, metavar="PX",
                   help="max pointing bias per axis in pixels; view 0 has none (default 0)")
    p.add_argument("--location", default=None, metavar="LON,LAT", help="scene centre in degrees (default 2.3488,48.8534; "
                   "write --location=-70.5,-33.4 when the longitude is negative)")
    p.add_argument("--acquisitions", type=int, default=None, metavar="N",
                   help="multi-date scene: the views grouped into N acquisitions (passes of 1-3 views) on N "
                   "dates, each with its own sun, shadows, trees, grass, cars, radiometry and pass geometry "
                   "(default 0: one date); --views then defaults to 2N")
    p.add_argument("--large-bias", type=float, default=None, metavar="PX",
                   help="largest extra pointing error (pixels, any direction) of a quarter of the views after "
                   "view 0, on top of --bias (default 0)")
    p.add_argument("--start-date", default=None, metavar="YYYY-MM-DD",
                   help="multi-date: first day of the 13 months the dates are drawn in (default 2019-01-01)")
    p.add_argument("--no-metadata", action="store_true",
                   help="multi-date: write no .IMD sidecars nor GDAL_METADATA tags (dates and sun angles)")
    p.add_argument("--product", choices=("dn16", "rgb8"), default=None,
                   help="the views' images: dn16, 12-bit numbers in uint16 (default), or rgb8, 8-bit RGB "
                   "stretched per image as pansharpened deliveries (WorldView-3, Pleiades) are")
    p.add_argument("--rpc-height-scale", type=float, default=None, metavar="M",
                   help="fit each RPC over this many metres of heights above and below the scene's "
                   "middle (its HEIGHT_SCALE), as real deliveries' RPCs do (about 500 m for WorldView "
                   "and Pleiades): a reconstruction without --alt-range or --dem then crops whole views, "
                   "as it does on real ones (default 0: the scene's own heights, about 70 m)")
    p.add_argument("--overwrite", action="store_true", help="replace the scene in a non-empty --out folder")
    p.set_defaults(handler=_cmd_synth)


def _cmd_synth(args: argparse.Namespace) -> int:
    from satsweep.synth.scene import SynthOptions, generate_scene, parse_location

    views = args.views
    if views is None and args.acquisitions:
        views = min(2 * args.acquisitions, 64)
    given = {"seed": args.seed, "n_views": views, "size_px": args.size, "gsd_m": args.gsd,
             "bias_px": args.bias, "acquisitions": args.acquisitions, "large_bias_px": args.large_bias,
             "start_date": args.start_date, "write_metadata": False if args.no_metadata else None,
             "product": args.product, "rpc_height_scale_m": args.rpc_height_scale}
    if args.location is not None:
        given["location"] = parse_location(args.location)
    if args.gsd is not None:
        # The true surface must be sampled at half the GSD or finer (SynthOptions.cell_m's
        # check): a WorldView-3 GSD of 0.3 m needs cells of 0.15 m, not the default 0.25.
        given["cell_m"] = min(SynthOptions.cell_m, args.gsd / 2.0)
    options = SynthOptions(**{k: v for k, v in given.items() if v is not None})
    scene = generate_scene(args.out, options, overwrite=args.overwrite, log=print)
    a = scene.aoi
    print(f"AOI {a.lon_min:.7f},{a.lat_min:.7f},{a.lon_max:.7f},{a.lat_max:.7f} "
          f"({2 * scene.aoi_half_m:.1f} m square); altitudes {scene.alt_range[0]:.2f} .. {scene.alt_range[1]:.2f} m")
    if scene.acquisitions:
        for acq in scene.acquisitions:
            print(f"acquisition {acq.index} ({acq.date_time}, sun {acq.sun_elevation_deg:g}/{acq.sun_azimuth_deg:g} "
                  f"deg): views {', '.join(str(k) for k in acq.views)}")
        same = [bh for i, j, bh in scene.pairs if scene.views[i].acquisition == scene.views[j].acquisition]
        print(f"{len(scene.pairs)} pairs, base-to-height {min(bh for *_, bh in scene.pairs):.3f} .. "
              f"{max(bh for *_, bh in scene.pairs):.3f}; {len(same)} within an acquisition")
    else:
        for i, j, bh in scene.pairs:
            print(f"pair {i}-{j}: base-to-height {bh:.3f}")
    print(f"wrote {scene.scene_file}")
    return 0


# -- reconstruct / demo ------------------------------------------------------------------------
def _add_pipeline_options(p) -> None:
    """Options shared by reconstruct and demo; each overrides the --config file."""
    p.add_argument("--config", metavar="FILE.toml", default=None,
                   help="TOML file with a table per stage ([reconstruct], [camera], [sparse], "
                   "[bundle], [views], [sweep], [mrf], [dsm]); the command line overrides it")
    p.add_argument("--device", default=None, help="auto|cpu|gpu|PLATFORM:DEVICE (default: "
                   "$SATSWEEP_DEVICE or auto)")
    p.add_argument("--mrf", choices=("none", "sgm", "graphcut"), default=None,
                   help="height-map refinement after the sweep (default from the config: sgm)")
    p.add_argument("--resolution", type=float, default=None, metavar="M",
                   help="DSM cell size in metres (default 0.5)")
    p.add_argument("--adjust", choices=("auto", "on", "off"), default=None,
                   help="bundle adjustment of principal points (default auto: on with 3+ views, "
                   "and with 2 views when their features match)")
    p.add_argument("--fixed-view", action="append", default=None, metavar="IMAGE",
                   help=FIXED_VIEW_HELP)
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="run the tiles of a tiled AOI on a local Dask cluster of N worker "
                   "processes, each with its own device context (default: 1 on a CPU device, "
                   "in this process without Dask, as one PoCL worker already uses every core; 2 "
                   "on a GPU); an AOI in one piece always runs in this process")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run the tiles on a running Dask cluster (tcp://HOST:8786: dask-jobqueue "
                   "on Slurm or PBS, Kubernetes) whose workers see the images and --out at the "
                   "same paths (default: $SATSWEEP_SCHEDULER, else local workers)")
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty --out folder")
    p.add_argument("--quiet", action="store_true",
                   help="no progress lines on stderr (warnings are still printed)")
    p.add_argument("--strict", action="store_true",
                   help=f"exit with code {EXIT_DOUBTFUL} (after writing the outputs) when a warning "
                   "says the result is doubtful: heights piling up at an end of the altitude "
                   "range, a DSM mostly empty")


def _pipeline_config(args: argparse.Namespace):
    from satsweep.config import PipelineConfig

    config = PipelineConfig.from_toml(args.config) if args.config else PipelineConfig()
    config = config.override("reconstruct", device=args.device, adjust=args.adjust,
                             workers=args.workers, scheduler=args.scheduler)
    config = config.override("mrf", method=args.mrf)
    config = _with_fixed_views(config, args.fixed_view)
    return config.override("dsm", resolution=args.resolution)


def _with_fixed_views(config, fixed_view):
    """``config`` with the ``--fixed-view`` files (if any) as ``[bundle] fixed_views``."""
    return config.override("bundle", fixed_views=tuple(fixed_view) if fixed_view else None)


def _add_reconstruct(sub) -> None:
    p = sub.add_parser(
        "reconstruct",
        help="images with RPCs + an area of interest -> DSM (GeoTIFF), point cloud, report",
        description="Crop and tonemap the images, approximate their RPCs by perspective cameras, "
        "correct pointing errors by bundle adjustment, sweep planes on the OpenCL device, refine "
        "with an MRF, and fuse the height maps into a DSM on the UTM grid of the AOI. Writes "
        "dsm.tif, confidence.tif, ortho.tif, cloud.ply, dsm.png, cameras.json, rpc/ (the "
        "corrected RPCs), config.toml and report.json into --out (all at the end: a failed run "
        "writes nothing). Negative "
        "coordinates may be written as they are: --aoi -70.5,-33.4,-70.4,-33.3.",
    )
    _add_image_inputs(p)
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--truth", default=None, metavar="TRUTH.tif",
                   help="a ground-truth DSM: evaluate the result against it (report.json, evaluation/)")
    p.add_argument("--resume", action="store_true",
                   help="reuse the tiles that an interrupted or failed run into --out finished "
                   "(kept in --out/.satsweep-tiles; a tile whose inputs or settings changed is "
                   "computed again)")
    _add_pipeline_options(p)
    p.set_defaults(handler=_cmd_reconstruct)


def _cmd_reconstruct(args: argparse.Namespace) -> int:
    from satsweep.geometry.aoi import parse_aoi
    from satsweep.pipeline.run import reconstruct

    config = _pipeline_config(args)
    aoi = parse_aoi(args.aoi)
    alt = _cli_altitude_range(args)
    result = reconstruct(args.images, aoi, args.out, alt_range=alt, dem=args.dem, config=config,
                         overwrite=args.overwrite, truth=args.truth, verbose=not args.quiet,
                         resume=args.resume, rpc_dir=args.rpc_dir, mask_dir=args.mask_dir)
    _print_summary(result)
    return _exit_code(result, args)


def _exit_code(result, args: argparse.Namespace) -> int:
    """0, or EXIT_DOUBTFUL with --strict when a warning said the result is doubtful."""
    doubtful = [w["message"] for w in result.report.get("warnings", []) if w["doubtful"]]
    if args.strict and doubtful:
        print(f"satsweep: --strict: {len(doubtful)} warning(s) say the result is doubtful",
              file=sys.stderr)
        return EXIT_DOUBTFUL
    return 0


def _peak_memory_text(rep) -> str:
    peak = rep.get("peak_memory_mb", {}).get("total")
    return "" if peak is None else f", peak memory {peak / 1024:.1f} GiB"


def _print_summary(result) -> None:
    rep = result.report
    t = rep["timings_s"]
    print(f"DSM: {result.dsm_path} ({rep['dsm']['width']}x{rep['dsm']['height']} cells of "
          f"{rep['dsm']['resolution_m']:g} m, EPSG:{rep['dsm']['epsg']}, "
          f"{100 * rep['dsm']['filled_fraction']:.1f}% filled) in {t['total']:.1f} s on "
          f"{rep['device']['device_name']}" + _peak_memory_text(rep))
    if result.evaluation is not None:
        a = result.evaluation["aligned"]
        u = result.evaluation["unaligned"]
        comp = next(k for k in a if k.startswith("completeness_"))
        print(f"accuracy vs truth (IARPA MVS3DM, aligned): median |error| "
              f"{a['median_abs_error_m']:.3f} m, {comp} {100 * a[comp]:.1f}%, RMSE "
              f"{a['rmse_m']:.3f} m; unaligned: {u['median_abs_error_m']:.3f} m, "
              f"{100 * u[comp]:.1f}%")
        d = result.evaluation.get("dfc")
        if d is not None:
            print(f"accuracy vs truth (DFC2019, shifted and mean offset removed): mean |error| "
                  f"{d['mean_abs_error_m']:.3f} m, median {d['median_abs_error_m']:.3f} m, "
                  f"{100 * d['completeness_1m']:.1f}% within 1 m, {100 * d['valid_fraction']:.1f}% "
                  "of the truth's cells filled")


def _add_demo(sub) -> None:
    p = sub.add_parser(
        "demo",
        help="built-in example: synthesise a scene, reconstruct it, evaluate against its truth",
        description="Generate a small synthetic town seen by pushbroom satellites (with exact "
        "RPCs and a truth DSM), reconstruct it with the full pipeline from the images and RPCs "
        "alone, and print the accuracy against the truth.",
    )
    p.add_argument("--out", default=None, metavar="DIR",
                   help="folder for scene/ and reconstruction/ (default: a new temporary folder)")
    p.add_argument("--views", type=int, default=None, metavar="N", help="number of views (default 2)")
    p.add_argument("--size", type=int, default=None, metavar="PIX", help="image side in pixels (default 512)")
    p.add_argument("--bias", type=float, default=None, metavar="PX",
                   help="max pointing bias injected per view (default 0)")
    p.add_argument("--seed", type=int, default=None, help="scene seed (default 0)")
    _add_pipeline_options(p)
    p.set_defaults(handler=_cmd_demo)


def _cmd_demo(args: argparse.Namespace) -> int:
    from satsweep.demo import DemoOptions, run_demo

    given = {"n_views": args.views, "size_px": args.size, "bias_px": args.bias, "seed": args.seed}
    options = DemoOptions(**{k: v for k, v in given.items() if v is not None})
    out_dir, result = run_demo(args.out, options=options, config=_pipeline_config(args),
                               overwrite=args.overwrite, verbose=not args.quiet)
    print(f"demo folder: {out_dir}")
    _print_summary(result)
    return _exit_code(result, args)


# -- config ------------------------------------------------------------------------------------
def _add_config(sub) -> None:
    p = sub.add_parser(
        "config",
        help="print every option of every stage as commented TOML (defaults, or a file over them)",
        description="Print the configuration as TOML, each option with the comment that explains "
        "it: the defaults, or with --config the values of FILE over the defaults (checked like "
        "reconstruct checks them: unknown tables or keys and bad values are errors). Redirect it "
        "to a file to start a configuration for reconstruct/demo --config.",
    )
    p.add_argument("--config", metavar="FILE.toml", default=None,
                   help="a configuration to check and show over the defaults")
    p.set_defaults(handler=_cmd_config)


def _cmd_config(args: argparse.Namespace) -> int:
    from satsweep.config import PipelineConfig

    if args.config is None:
        text = PipelineConfig().to_toml(header="satsweep configuration: the defaults")
    else:
        text = PipelineConfig.from_toml(args.config).to_toml(
            header=f"satsweep configuration: {args.config} over the defaults")
    sys.stdout.write(text)
    return 0


# -- entry point -------------------------------------------------------------------------------
# In the order `satsweep --help` lists them: the main job first.
_COMMANDS = [_add_demo, _add_reconstruct, _add_synth, _add_cameras, _add_evaluate, _add_devices,
             _add_config]


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="satsweep",
        description="Satellite multi-view stereo: RPC images + an area of interest -> DSM.",
    )
    parser.add_argument("--version", action="version", version=f"satsweep {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for add in _COMMANDS:
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        with _termination_raises(), warnings.catch_warnings(), _warnings_logged():
            # numpy's RuntimeWarnings (a degenerate determinant, an empty mean) come from inputs
            # whose consequences satsweep checks and reports itself, in the user's terms.
            warnings.filterwarnings("ignore", category=RuntimeWarning, module=r"numpy(\.|$)")
            warnings.showwarning = _show_warning
            return int(args.handler(args) or 0)
    except SatsweepError as exc:
        print(f"satsweep: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("satsweep: interrupted", file=sys.stderr)
        return 130
    except (Terminated, Exception) as exc:
        # SIGTERM or SIGHUP; one that lands while Python builds a class (a module's import:
        # type.__new__ calls __set_name__) comes back as a RuntimeError caused by ``Terminated``.
        terminated = terminated_cause(exc)
        if terminated is None:
            raise
        print(f"satsweep: terminated ({signal.Signals(terminated.signum).name})", file=sys.stderr)
        return 128 + terminated.signum


_python_showwarning = warnings.showwarning


class _WarningLines(logging.Handler):
    """The warnings satsweep's modules log (logger ``satsweep.*``) while no run report takes
    them (``satsweep cameras``, ``synth``, ``evaluate``) as ``satsweep: warning:`` lines on
    stderr; other loggers' warnings as Python's last-resort handler prints them."""

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if record.name == "satsweep" or record.name.startswith("satsweep."):
            message = f"satsweep: warning: {message}"
        print(message, file=sys.stderr, flush=True)


@contextlib.contextmanager
def _warnings_logged() -> Iterator[None]:
    """While inside: :class:`_WarningLines` on the root logger (a run report's capture stops
    satsweep's records before they reach it)."""
    root = logging.getLogger()
    handler = _WarningLines(level=logging.WARNING)
    root.addHandler(handler)
    try:
        yield
    finally:
        root.removeHandler(handler)


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """satsweep's own warnings (a retired option in a config file) as ``satsweep: warning:``
    lines, the others as Python shows them."""
    if issubclass(category, RetiredOptionWarning):
        print(f"satsweep: warning: {message}", file=sys.stderr)
    else:
        _python_showwarning(message, category, filename, lineno, file, line)


def terminated_cause(exc: BaseException) -> Terminated | None:
    """The ``Terminated`` in ``exc``'s chain of causes and contexts, or None."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, Terminated):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


# The host's linear algebra works on small matrices (camera fits, 3x3 solves, bundle
# adjustments of a few hundred points), where BLAS threads only cost: on 2 cores shared with
# other jobs (load 6-7) the Pleiades pair's `satsweep cameras` took 2.5-3.5 s with OpenBLAS's
# default threads and 0.9-1.0 s with one. The command sets one thread unless the environment
# says otherwise; a library user's process is left alone.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def console_main(argv: Sequence[str] | None = None) -> int:
    """The ``satsweep`` command: ``main`` (of ``argv``, default the command line) under the
    command's heap policy (see ``heap``) and with single-threaded BLAS
    (``BLAS_THREAD_VARIABLES``; numpy is not imported yet here)."""
    import os  # noqa: PLC0415

    for name in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    from satsweep.heap import keep_freed_memory  # noqa: PLC0415

    keep_freed_memory()
    return main(argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(console_main())
