"""Every stage of one area (the AOI, or one tile of it), from the views to its DSM rasters."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from satsweep.config import PipelineConfig
from satsweep.errors import CameraError
from satsweep.geometry.altitude import resolve_altitude_range

if TYPE_CHECKING:
    from satsweep.geometry.camera import CameraSet
from satsweep.geometry.altitude import enu_height_range
from satsweep.pipeline.forecast import program_forecast
from satsweep.pipeline.rasters import _area_rasters
from satsweep.pipeline.sweeps import _sweep_references


def _fill_nan(image: np.ndarray) -> np.ndarray:
    """Skew correction leaves NaN where the sheared image has no source pixel: use 0 there (those
    pixels are in the crop margin, outside the AOI footprint)."""
    out = np.asarray(image, dtype=np.float32)
    return np.where(np.isfinite(out), out, np.float32(0.0)).astype(np.float32)


@dataclasses.dataclass
class _Area:
    """What one area (the AOI, or one of its tiles) gives: its DSM on its grid before hole
    filling, the confidence raster, the orthophoto, each reference view's cloud, its cameras and
    its own pointing corrections (its figures are in its section of the report)."""

    dsm: np.ndarray
    confidence: np.ndarray
    ortho: np.ndarray | None  # grey level of each cell's highest point (reconstruct.write_ortho)
    clouds: list
    cameras: "CameraSet"
    shifts: list | None  # per view (dcx, dcy) px of its own bundle adjustment; None without one


# _reconstruct_area's answers for an area to be done otherwise: cut in pieces, its cameras being
# too far from the RPCs; or later, its views matching too poorly to be adjusted, once other
# tiles have given their corrections.
_CUT = "cut"
_LATER = "later"


def _reconstruct_area(paths, aoi, grid, rep, device, *, alt_range, dem, config: PipelineConfig,
                      names, split_above_px: float = 0.0, borrowed_shifts=None,
                      may_wait: bool = False) -> _Area | str:
    """Every stage from the views to the DSM rasters, for one area (the AOI or one tile of it)
    on its ``grid``, its figures set in ``rep`` (a section of the run's report).

    ``_CUT``, after the cameras stage, when a view's perspective approximation is further than
    ``split_above_px`` (> 0) from its RPC. When the views match too poorly for the bundle
    adjustment: the views' principal points are moved by ``borrowed_shifts`` (per view (dcx,
    dcy), other tiles' corrections) if given, else ``_LATER`` if ``may_wait``, else the
    adjustment is skipped with 2 views under ``adjust = auto`` and the error raised otherwise.
    """
    from satsweep.dense.selection import select_views
    from satsweep.geometry import camera as scam
    from satsweep.geometry import skew
    from satsweep.io.images import tonemap
    from satsweep.io.views import load_views
    from satsweep.sparse.bundle import adjust_principal_points, shift_principal_points
    from satsweep.sparse.tiepoints import altitude_range_for_images

    if alt_range is None and dem is None:
        # Neither a range nor a DEM: the RPCs' range (kilometres), narrowed by tie points.
        with rep.stage("altitude"):
            r = config.reconstruct
            alt, rep["altitude_range"] = altitude_range_for_images(
                paths, aoi, config.sparse, quantile=r.tie_altitude_quantile,
                margin_m=r.tie_altitude_margin_m, crop_margin_px=r.crop_margin_px)
        rep.log(f"altitude range {alt.min:.1f}..{alt.max:.1f} m from "
                f"{rep['altitude_range']['tie_points']} tie points (pass --alt-range or --dem to "
                "set it)")
    else:
        alt = resolve_altitude_range(alt_range=alt_range, dem=dem, aoi=aoi)
        rep["altitude_range"] = {"min": alt.min, "max": alt.max,
                                 "source": "user" if alt_range is not None else "dem"}
    with rep.stage("views"):
        views = load_views(paths, aoi, alt, margin_px=config.reconstruct.crop_margin_px)
        images = [tonemap(v.image) for v in views]
        rep["views"] = [{"image": v.path, "crop": [int(v.x0), int(v.y0), int(v.width), int(v.height)]}
                        for v in views]

    with rep.stage("cameras"):
        cameras = scam.build_cameras(views, aoi, alt, config.camera)
        rep["cameras"] = {
            "approx_error_px": {n: v.camera.error.to_dict() for n, v in zip(names, cameras.views)},
            "warnings": list(cameras.warnings),
        }
        for w in cameras.warnings:
            rep.log(f"warning: {w}")
    if split_above_px > 0.0 and max(v.camera.error.max_px for v in cameras.views) > split_above_px:
        return _CUT

    # The kernels the sweep stage will need, built in the background meanwhile.
    device.prebuild(program_forecast(device, cameras, enu_height_range(cameras.frame, aoi, alt),
                                     config))

    mode = config.reconstruct.adjust
    own_shifts = None
    if mode == "off":
        rep["ba"] = {"skipped": "reconstruct.adjust = off"}
    else:
        with rep.stage("adjust"):
            try:
                cameras, ba = adjust_principal_points(cameras, images, config.bundle, config.sparse,
                                                     names=names)
                rep["ba"] = ba.to_dict()
                own_shifts = [list(s) for s in ba.principal_point_shift_px]
            except CameraError as exc:
                if borrowed_shifts is not None:
                    cameras = shift_principal_points(cameras, borrowed_shifts)
                    rep["ba"] = {"skipped": f"not enough matches for the adjustment: {exc}",
                                 "borrowed_principal_point_shift_px": borrowed_shifts}
                    rep.log(f"warning: bundle adjustment of this tile impossible ({exc}); the "
                            "other tiles' pointing corrections are used")
                elif may_wait:
                    rep["ba"] = {"postponed": f"not enough matches for the adjustment: {exc}"}
                    rep.log(f"bundle adjustment of this tile impossible ({exc}): it waits for "
                            "the other tiles' pointing corrections")
                    return _LATER
                elif mode == "on" or len(views) >= 3:
                    raise
                else:
                    rep["ba"] = {"skipped": f"not enough matches for the adjustment: {exc}"}
                    rep.log(f"warning: bundle adjustment skipped: {exc}")

    # The orthophoto's grey levels: the crops' own values (sensor units), the same for every tile
    # (each tile's tonemap stretches its own crop).
    ortho_images = ([np.asarray(v.image, np.float32) for v in views]
                    if config.reconstruct.write_ortho else None)
    if config.reconstruct.skew_correct:
        with rep.stage("skew"):
            unsheared = cameras
            cameras, images = skew.skew_correct_set(cameras, images)
            images = [_fill_nan(im) for im in images]
            if ortho_images is not None:
                _, ortho_images = skew.skew_correct_set(unsheared, ortho_images)

    frame = cameras.frame
    u_range = enu_height_range(frame, aoi, alt)
    with rep.stage("select"):
        selection = select_views([v.camera for v in cameras.views],
                                 mid_height=0.5 * (u_range[0] + u_range[1]),
                                 options=config.views, names=names)
        rep["view_selection"] = selection.to_dict(names)
        for w in selection.warnings:
            rep.log(f"warning: {w}")

    per_view = _sweep_references(device, cameras, images, selection, u_range, config, rep, names,
                                 aoi=aoi, alt_range=alt)
    dsm, confidence, ortho, clouds = _area_rasters(per_view, cameras, images, grid, config, rep,
                                                   ortho_images=ortho_images)
    return _Area(dsm=dsm, confidence=confidence, ortho=ortho, clouds=clouds, cameras=cameras,
                 shifts=own_shifts)
