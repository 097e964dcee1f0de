"""The "dsm" stage of one area: its reference views' height maps -> cross-check -> points over
each pixel's footprint -> per-view rasters -> fused DSM, confidence and orthophoto.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Sequence

import numpy as np

from satsweep.config import PipelineConfig


def _nanmean_stack(arrays: list[np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """Per-cell mean over the arrays that have a value there; NaN where none has one."""
    if not arrays:
        return np.full(shape, np.nan, np.float32)
    stack = np.stack(arrays).astype(np.float64)
    have = np.isfinite(stack)
    n = have.sum(axis=0)
    total = np.where(have, stack, 0.0).sum(axis=0)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan).astype(np.float32)


# Metres added around the pixel centres' box for the ENU -> map fit: the footprint sub-samples
# lie within half a pixel of their centres (well under this at any satellite's ground sampling).
FOOTPRINT_PAD_M = 5.0


def _enu_to_map(frame, epsg: int, points: list[tuple[np.ndarray, ...]]):
    """The ENU -> (UTM, height) map (``dsm.ENUToMap``) fitted over the bounding box of the
    points, widened by ``FOOTPRINT_PAD_M`` for their footprint sub-samples."""
    from satsweep.products.points import ENUToMap

    lo, hi = np.zeros(3), np.ones(3)  # any box when there is no point at all
    present = [p for p in points if p[0].size]
    if present:  # the box of every view's points, without concatenating millions of them
        lo = np.array([min(p[k].min() for p in present) for k in range(3)])
        hi = np.array([max(p[k].max() for p in present) for k in range(3)])
        lo[:2] -= FOOTPRINT_PAD_M
        hi[:2] += FOOTPRINT_PAD_M
    return ENUToMap.fit(frame, epsg, e_range=(lo[0], hi[0]), n_range=(lo[1], hi[1]),
                        u_range=(lo[2], hi[2]))


@dataclasses.dataclass(eq=False)
class _ViewRasters:
    """One reference view's part of the "dsm" stage: its rasters on the area's grid and its
    cloud (None: not made)."""

    rule: str  # DSMOptions.view_raster_for's
    raster: np.ndarray | None = None  # its heights
    confidence: np.ndarray | None = None  # its confidence (the largest of its points' per cell)
    ortho: np.ndarray | None = None  # the grey level of each cell's highest point
    green: np.ndarray | None = None  # the vegetation index of each cell's highest point
    cloud: tuple | None = None  # (x, y, z, colours) of its points on the grid


@dataclasses.dataclass(eq=False)
class AreaRasters:
    """One area's rasters on its grid, before hole filling, and the "dsm" stage's figures."""

    dsm: np.ndarray  # float32 heights above the ellipsoid, NaN where none
    confidence: np.ndarray  # float32, NaN where no view has a value
    ortho: np.ndarray | None  # the orthophoto (None: not asked for)
    count: np.ndarray  # uint8: reference views whose heights made each cell's (0: none)
    clouds: list  # per reference view: (x, y, z, colours) of its points on the grid
    fusion: str  # "median" or "consensus"
    cross_check: dict | None  # tolerance, views and kept fraction per view; None: no check
    per_view_filled_fraction: list[float]
    enu_to_map: dict  # whether the polynomial ENU -> map fit was used, and its error
    per_view_raster: list[str] = dataclasses.field(default_factory=list)  # max, quantile
    vertical_offsets_m: list[float] | None = None  # per reference view, the offset removed from
    # its raster before the consensus ([dsm] coregister); None: not co-registered
    leaf_on_crown_cells: int | None = None  # cells given the crowns' tops of the views of dates
    # in leaf ([dsm] leaf_on_crowns); None: the rule did not run (fewer than two such views)
    crown_hole_cells: int | None = None  # empty cells given a small raised object's height that
    # views of two passes agree on ([dsm] crown_holes); None: the rule did not run
    green_crown_cells: int | None = None  # cells given the highest height of the views that see
    # leaves there ([dsm] green_crowns); None: the rule did not run (no colour images)
    thin_raised_cells: int | None = None  # consensus cells left to the hole filling ([dsm]
    # thin_raised_max_share); None: the rule did not run (median fusion, or a share of 0)
    valley_cells: int | None = None  # consensus cells in valleys of its counts left to the hole
    # filling besides those ([dsm] valley_min_share); None: neither rule ran

    def to_report(self) -> dict:
        return {"fusion": self.fusion, "cross_check": self.cross_check,
                "per_view_filled_fraction": self.per_view_filled_fraction,
                "per_view_raster": self.per_view_raster,
                "vertical_offsets_m": self.vertical_offsets_m,
                "leaf_on_crown_cells": self.leaf_on_crown_cells,
                "crown_hole_cells": self.crown_hole_cells,
                "green_crown_cells": self.green_crown_cells,
                "thin_raised_cells": self.thin_raised_cells,
                "valley_cells": self.valley_cells,
                "enu_to_map": self.enu_to_map}


def _agreeing_views(rasters, fused: np.ndarray, cells: np.ndarray, members: np.ndarray,
                    count: np.ndarray, tolerance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The consensus's members and counts, ``cells`` (given new heights after it) taking the
    views within ``tolerance_m`` of their new height."""
    with np.errstate(invalid="ignore"):
        near = np.stack([np.abs(r - fused) <= tolerance_m for r in rasters])
    return np.where(cells[None], near, members), np.where(cells, near.sum(axis=0), count)


def _view_gsd(P: np.ndarray, centres: tuple[np.ndarray, ...]) -> float:
    """Metres per pixel of a view (camera ``P``) at the median height of its points ``centres``
    (``height_map_to_enu``'s (e, n, u, pixel), at least one)."""
    from satsweep.geometry.camera import ground_sample_distance

    return ground_sample_distance(P, (0.0, 0.0, float(np.median(centres[2]))))


def area_rasters(per_view, cameras, images, grid, config: PipelineConfig, rep, *,
                 ortho_images=None, leaf_season: Sequence[float | None] | None = None,
                 passes: Sequence[int | None] | None = None,
                 vegetation_images: Sequence[np.ndarray] | None = None) -> AreaRasters:
    """The "dsm" stage of one area on its ``grid``: each reference view's height map
    (``per_view``: ``sweeps.ReferenceHeights``) -> cross-check -> points over each pixel's
    footprint (ENU -> UTM) -> per-view rasters -> fusion, with the orthophoto of
    ``ortho_images``' values (the views' in the cameras' pixels; None: no orthophoto) and one
    cloud (x, y, z, grey colours) per reference view. ``leaf_season`` and ``passes`` (per view,
    as ``similarity.leaf_season`` and ``similarity.acquisition_passes``; None: unknown) give the
    consensus the crowns' tops of the views of dates in leaf (``[dsm] leaf_on_crowns``) and of
    the views of two passes where it leaves a crown's cell empty (``[dsm] crown_holes``), and
    the free-space check the views matched with a source of their own pass
    (``[dsm] visibility_bare_far_m``).
    ``vegetation_images`` (per view, its vegetation index in the cameras' pixels; None: images
    without colour) give it the crowns' tops of the views that see leaves there (``[dsm]
    green_crowns``)."""
    from satsweep.dense.selection import LEAF_ON_SEASON
    from satsweep.io.images import VEGETATION_INDEX_MIN
    from satsweep.products.fusion import (
        FOOTPRINT_EDGE_PX,
        FUSION_THREADS_MAX,
        consensus_dsms,
        cross_check_heights,
        crown_hole_tops,
        dropped_edge_pixels,
        fine_pixels,
        flat_cells,
        fuse_dsms,
        green_crown_tops,
        green_raised_pixels,
        leaf_on_crown_tops,
        rasterise_dense_view_cells,
        rasterise_max_cells,
        raised_count_valleys,
        raised_pixels,
        small_regions,
        thin_raised_minority,
        vertical_offsets,
        visibility_check_heights,
    )
    from satsweep.products.ortho import match_radiometry, values_at_highest
    from satsweep.products.points import (
        height_map_to_enu,
        map_view_points,
        spread_to_footprint_edges,
    )
    from satsweep.threads import map_in_threads

    d = config.dsm
    with rep.stage("dsm"):
        heights = [np.where(pv.valid, pv.height, np.nan) for pv in per_view]
        projections = [cameras.views[pv.index].camera.P for pv in per_view]
        # Every view's pixel centres in ENU (solved once: the cross-check reads them too), one
        # polynomial ENU -> UTM map fitted over all of them; then each view's centres (the
        # cloud) and footprint sub-samples (the rasters).
        centres = map_in_threads(lambda k: height_map_to_enu(heights[k], np.isfinite(heights[k]),
                                                             projections[k]),
                                 range(len(heights)), max_threads=FUSION_THREADS_MAX,
                                 name="fusion")
        checked = [np.isfinite(h) for h in heights]
        fusion = d.fusion_for(len(per_view))
        # The consensus compares the views cell by cell: no agreement check before it, but a
        # free-space check (views from the other sides see the ground where views from one
        # side put a facade at its roof's height, products.fusion.visibility_check_heights).
        cross_check = d.cross_check_m > 0 and len(per_view) >= 2 and fusion == "median"
        visibility = d.visibility_check and len(per_view) >= 2 and fusion == "consensus"
        check = None  # the pixel-level check's settings, for the report
        if cross_check:
            checked = cross_check_heights(heights, projections, tolerance_m=d.cross_check_m,
                                          min_agreeing=d.cross_check_views, points=centres)
            check = {"tolerance_m": d.cross_check_m, "views": d.cross_check_views}
        elif visibility:
            # The views whose pixels are finer than the cells (each view's GSD, taken once).
            fine = [c[2].size > 0 and fine_pixels(_view_gsd(P, c), grid.resolution)
                    for P, c in zip(projections, centres)]
            # Those that see far past from visibility_leaf_on_far_m on: a date in leaf
            # (unknown: not).
            trusted = [
                f and leaf_season is not None and leaf_season[pv.index] is not None
                and leaf_season[pv.index] >= LEAF_ON_SEASON
                for f, pv in zip(fine, per_view)]
            # Those matched with a source of their own date (pass) see far past from
            # visibility_bare_far_m on the points that their own image does not show green (a
            # stack without colour or dates: none).
            bare = [f and passes is not None and passes[pv.index] is not None
                    and any(passes[s] == passes[pv.index] for s in pv.source_indices)
                    for f, pv in zip(fine, per_view)]
            green = None
            if vegetation_images is not None and d.visibility_bare_far_m > 0.0:
                green = [np.ravel(vegetation_images[pv.index])[c[3]] >= VEGETATION_INDEX_MIN
                         for pv, c in zip(per_view, centres)]
            checked = visibility_check_heights(
                heights, projections, tolerance_m=d.consensus_tolerance_m,
                far_m=d.visibility_far_m, points=centres, slack_px=d.visibility_slack_px,
                confidences=[pv.confidence for pv in per_view],
                slack_min_confidence=d.visibility_slack_confidence,
                trusted_far_m=d.visibility_leaf_on_far_m, trusted_views=trusted,
                bare_far_m=d.visibility_bare_far_m if green is not None else 0.0,
                bare_views=bare, green=green,
                voter_min_confidence=d.visibility_voter_confidence, voter_views=fine)
            check = {"check": "free space", "tolerance_m": d.consensus_tolerance_m,
                     "far_m": d.visibility_far_m, "slack_px": d.visibility_slack_px,
                     "slack_min_confidence": d.visibility_slack_confidence,
                     "voter_min_confidence": d.visibility_voter_confidence,
                     "voter_views": [bool(f) for f in fine],
                     "leaf_on_far_m": d.visibility_leaf_on_far_m,
                     "leaf_on_fine": [bool(t) for t in trusted],
                     "bare_far_m": d.visibility_bare_far_m if green is not None else 0.0,
                     "bare_views": [bool(b) for b in bare]}
        if check is not None:
            centres = [tuple(a[keep.ravel()[c[3]]] for a in c)
                       for c, keep in zip(centres, checked)]
        to_map = _enu_to_map(cameras.frame, grid.epsg, centres)
        # The green crowns' rule reads the vegetation index at each cell's top (consensus only).
        green_images = vegetation_images if fusion == "consensus" else None

        def view_rasters(k: int) -> _ViewRasters:
            """Reference view k's rasters and cloud (each view's depend on its own maps only:
            the views run in threads, with the sequential loop's results)."""
            pv, P, centre, height, keep = (per_view[k], projections[k], centres[k], heights[k],
                                           checked[k])
            (x, y, z, pixel), (sx, sy, sz, spix) = map_view_points(
                centre, height, keep, P, to_map, subsamples=d.subsamples)
            rule = d.view_raster_for(flat_cells(x, y, grid))
            keeps_tops = rule == "quantile" and d.small_object_top
            # The pixels of small raised objects (tree crowns), and the view's raised pixels and
            # pixel size they come from, which the green-top rule below reads too.
            small = raised = gsd = None
            if d.small_object_area_m2 > 0.0 and pixel.size and (d.subsamples > 1 or keeps_tops):
                # Their regions are found on the map before the check, which would split
                # buildings into small pieces where it drops facades (v20 seeds 0-5: 91.60% /
                # 0.896 m against 91.48% / 0.905 m on the checked map).
                gsd = _view_gsd(P, centre)  # a median over the view's points: once
                raised = raised_pixels(height, gsd)  # also the green rule's, below
                small = small_regions(raised, gsd, d.small_object_area_m2)
            if small is not None and d.subsamples > 1:
                # Small raised objects reach the cells they overhang.
                sx, sy, sz, spix = spread_to_footprint_edges(
                    (x, y, z, pixel), (sx, sy, sz, spix), small.ravel(), d.subsamples,
                    FOOTPRINT_EDGE_PX)
            top = small if keeps_tops else None
            if top is not None and d.green_top and vegetation_images is not None:
                # Crowns in clumps or against walls: raised regions larger than small ones
                # (top is small's, so gsd and raised are set above).
                top = top | green_raised_pixels(height, vegetation_images[pv.index], gsd,
                                                raised=raised)
            if rule == "quantile" and d.edge_min_confidence > 0.0:
                # Pixels finer than the cells: those on the high side of a step that matched
                # poorly are edges and facades at the roof's height (points in the air).
                drop = dropped_edge_pixels(height, pv.confidence, d.edge_min_confidence,
                                           keep=top).ravel()
                kept_centres, kept_samples = ~drop[pixel], ~drop[spix]
                x, y, z, pixel = (a[kept_centres] for a in (x, y, z, pixel))
                sx, sy, sz, spix = (a[kept_samples] for a in (sx, sy, sz, spix))
            cells = flat_cells(sx, sy, grid)
            out = _ViewRasters(rule=rule)
            if rule == "quantile":
                out.raster = rasterise_dense_view_cells(
                    cells, sz, grid, top=None if top is None else top.ravel()[spix])
            else:
                out.raster = rasterise_max_cells(cells, sz, grid)
            out.confidence = rasterise_max_cells(cells, np.ravel(pv.confidence)[spix], grid)
            # The grey level (orthophoto) and the vegetation index of each cell's highest point.
            wanted = {name: np.ravel(image[pv.index])[spix]
                      for name, image in (("ortho", ortho_images), ("green", green_images))
                      if image is not None}
            for name, at_top in zip(wanted, values_at_highest(cells, sz, list(wanted.values()),
                                                              grid)):
                setattr(out, name, at_top)
            if not config.reconstruct.write_cloud:
                return out
            gray = np.clip(np.nan_to_num(images[pv.index]) * 255.0, 0, 255).astype(np.uint8)
            # The cloud covers the area's DSM grid, like the DSM (the crops extend beyond it).
            keep = ((x >= grid.x_min) & (x <= grid.x_min + grid.width * grid.resolution)
                    & (y <= grid.y_max) & (y >= grid.y_max - grid.height * grid.resolution))
            out.cloud = (x[keep], y[keep], z[keep],
                         np.repeat(gray.ravel()[pixel[keep]][:, None], 3, axis=1))
            return out

        done = map_in_threads(view_rasters, range(len(per_view)), max_threads=FUSION_THREADS_MAX,
                              name="fusion")
        rasters = [v.raster for v in done]
        view_rules = [v.rule for v in done]
        # One per view, in the views' order (zipped with the consensus's members and offsets):
        # each view has every one that was asked for, none those that were not.
        conf_rasters = [v.confidence for v in done]
        orthos = [v.ortho for v in done] if ortho_images is not None else []
        greens = [v.green for v in done] if green_images is not None else []
        clouds = [v.cloud for v in done] if config.reconstruct.write_cloud else []
        offsets_m = leaf_cells = hole_cells = green_cells = thin_cells = valley_cells = None
        if fusion == "consensus":
            view_sets = [(pv.index, *pv.source_indices) for pv in per_view]
            # A stack of fewer distinct views than asked needs them all, not the impossible.
            distinct = min(d.consensus_min_distinct_views, len(set().union(*view_sets)))
            consensus = functools.partial(
                consensus_dsms, tolerance_m=d.consensus_tolerance_m,
                min_views=d.consensus_min_views, view_sets=view_sets,
                min_distinct_views=distinct, min_share=d.consensus_min_share)
            if d.coregister:
                offsets = vertical_offsets(rasters, consensus(rasters)[0])
                offsets_m = [round(float(o), 3) for o in offsets]
                rasters = [r - np.float32(o) for r, o in zip(rasters, offsets)]
                clouds = [(x, y, z - o, c) for (x, y, z, c), o in zip(clouds, offsets)]
            fused, count, members = consensus(rasters)
            if d.thin_raised_max_share > 0.0 or d.valley_min_share > 0.0:
                # Narrow gaps' floors matched at their walls' heights go to the hole filling.
                thin = thin_raised_minority(fused, count, len(rasters),
                                            max_share=d.thin_raised_max_share,
                                            resolution_m=grid.resolution)
                valley = raised_count_valleys(fused, count, len(rasters),
                                              min_share=d.valley_min_share,
                                              resolution_m=grid.resolution)
                thin_cells, valley_cells = int(thin.sum()), int((valley & ~thin).sum())
                emptied = thin | valley
                fused = np.where(emptied, np.float32(np.nan), fused)
                count = np.where(emptied, 0, count).astype(count.dtype)
                members = members & ~emptied[None]
            view_passes = [None if passes is None else passes[pv.index] for pv in per_view]
            in_leaf = [k for k, pv in enumerate(per_view)
                       if view_passes[k] is not None and leaf_season is not None
                       and leaf_season[pv.index] is not None
                       and leaf_season[pv.index] >= LEAF_ON_SEASON]
            tol = d.consensus_tolerance_m
            if d.leaf_on_crowns and len(in_leaf) >= 2:
                fused, raised = leaf_on_crown_tops(
                    fused, [rasters[k] for k in in_leaf], [view_passes[k] for k in in_leaf],
                    tolerance_m=tol, resolution_m=grid.resolution,
                    max_area_m2=d.small_object_area_m2)
                leaf_cells = int(raised.sum())
                members, count = _agreeing_views(rasters, fused, raised, members, count, tol)
            if d.crown_holes and sum(v is not None for v in view_passes) >= 2:
                fused, filled = crown_hole_tops(fused, rasters, view_passes, tolerance_m=tol,
                                                resolution_m=grid.resolution,
                                                max_area_m2=d.small_object_area_m2)
                hole_cells = int(filled.sum())
                members, count = _agreeing_views(rasters, fused, filled, members, count, tol)
            if d.green_crowns and vegetation_images is not None:
                fused, raised = green_crown_tops(fused, rasters, greens,
                                                 resolution_m=grid.resolution,
                                                 max_area_m2=d.small_object_area_m2)
                green_cells = int(raised.sum())
                members, count = _agreeing_views(rasters, fused, raised, members, count, tol)
            # The confidence of the views that agree on the cell's height.
            conf = _nanmean_stack([np.where(m, c, np.nan) for m, c in zip(members, conf_rasters)],
                                  grid.shape)
        else:
            fused, count = fuse_dsms(rasters, outlier_m=d.outlier_m, min_views=d.min_views)
            conf = _nanmean_stack(conf_rasters, grid.shape)
            with np.errstate(invalid="ignore"):  # the fusion's own rule: within outlier_m
                members = [np.abs(h - fused) <= d.outlier_m for h in rasters]
        # Each cell's grey level: the mean over the views whose height there is the fused one's,
        # so that no view shows a wall or a lower roof.
        ortho = None
        if ortho_images is not None:
            kept = [np.where(m, o, np.nan) for m, o in zip(members, orthos)]
            # Views of other dates or sensors differ in gain and offset: each is brought to the
            # radiometry of the first image given (of those swept as references) before the
            # mean, so that cells seen by one view and cells seen by two look alike.
            first = int(np.argmin([pv.index for pv in per_view]))
            kept = [o if k == first else match_radiometry(kept[first], o)
                    for k, o in enumerate(kept)]
            ortho = _nanmean_stack(kept, grid.shape)
        if check is not None:
            check["kept_fraction"] = [float(k.sum() / max(1, np.isfinite(h).sum()))
                                      for k, h in zip(checked, heights)]
    return AreaRasters(dsm=fused, confidence=conf, ortho=ortho,
                       count=np.minimum(count, 255).astype(np.uint8), clouds=clouds,
                       fusion=fusion, cross_check=check,
                       per_view_filled_fraction=[float(np.isfinite(a).mean()) for a in rasters],
                       per_view_raster=view_rules, vertical_offsets_m=offsets_m,
                       leaf_on_crown_cells=leaf_cells, crown_hole_cells=hole_cells,
                       green_crown_cells=green_cells, thin_raised_cells=thin_cells,
                       valley_cells=valley_cells,
                       enu_to_map={"polynomial": to_map.accurate,
                                   "max_error_m": to_map.max_error_m})
