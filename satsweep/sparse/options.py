"""The ``[sparse]`` options: features, the pair graph, matching, verification, tracks and the
altitude range drawn from the tie points."""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

from satsweep.options import Options


@dataclasses.dataclass(frozen=True)
class SparseOptions(Options):
    """Options of feature detection, matching and triangulation."""

    max_features: int = 3000  # SIFT keypoints kept per view (the strongest)
    min_matches: int = 15  # verified matches a pair needs to be used
    pair_neighbours: int = 3  # pairs each view is matched in, beyond the spanning tree
    feature_scale: float = 0.5  # SIFT runs on the views resampled by this factor; 1: as they are
    feature_scale_min_px: int = 512  # views whose smaller side (px) is below this: full resolution
    refine_window_px: int = 9  # side (px) of the Lucas-Kanade window registering tie points; 0: none
    refine_window_m: float = 3.9  # ... and at least this much of the ground (m) at the finest
    # view's GSD: stacks of a finer GSD register on more pixels (the nearest odd count, up to
    # 63), those of 0.43 m or more on refine_window_px. On 0.3 m stacks in the form
    # (19 views, seeds 11-13), 9 -> 13 px: worst view after the gauge 0.029 / 0.032 / 0.014 ->
    # 0.019 / 0.020 / 0.012 px, DFC MAE 1.081 / 0.697 / 0.912 -> 1.046 / 0.650 / 0.884 m (at
    # 0.5 m, 11 px lost on the multi-date stacks; docs/measurements.md); 0: refine_window_px
    refine_max_shift_px: float = 2.0  # a tie point the registration moves farther (px) is dropped
    refine_keep_fraction: float = 0.5  # share of each pair's registered tie points kept (best first)
    refine_beside_px: float = 6.0  # each tie point is also registered by 16 windows centred
    # this far (px) and 4/3 of it beside it (4 sides, 4 corners), and its track keeps the window
    # that matches best over all its views: one over one surface where a point on an edge
    # straddles two (v10 multi-date stacks: worst view 0.064 -> 0.033 px on average,
    # docs/measurements.md); 0: centred only
    fine_points_per_view: int = 600  # the registration and the fine adjustment use the tie points
    # that give each view at least this many observations, longest tracks first; 0: all
    extend_points_per_view: int = 1000  # those tie points are also registered in the views that
    # did not match them (at their projection, from the track's first view), at most this many
    # per view, then thinned again to give each view at least this many observations (longest
    # tracks first): ties between dates on many more points; 0: none (600 until the ties between
    # dates were registered at a pixel's contrast scale: with that, 1000 took the worst view of
    # the 20-view multi-date stacks from 0.055 to 0.044 px, docs/measurements.md)
    contrast_threshold: float = 0.01  # SIFT contrast threshold (OpenCV units); 0.02 before the
    # fiftieth session: more keypoints match between dates (3 views of one date each, RPCs
    # like real ones, worst view after the gauge, seeds 0-5: 0.0615 -> 0.0368 px; 7 views of
    # 10, 28 stacks: 0.0671 -> 0.0557 px at worst; docs/measurements.md)
    ratio: float = 0.8  # Lowe's ratio test: nearest / second-nearest descriptor distance below this
    repair_ratio: float = 0.9  # the ratio of a second matching of the pairs into a group of views
    # that would be dropped as untied (other dates under another sun: too few matches pass
    # `ratio`); equal to `ratio`: no second matching
    mutual: bool = True  # keep a match only when each feature is the other's nearest neighbour
    geometric_model: Literal["cameras", "affine"] = "cameras"  # verification by the cameras'
    # epipolar geometry up to an offset, or by RANSAC of an affine fundamental matrix
    ransac_threshold_px: float = 1.5  # inlier distance (px) to the epipolar line
    ransac_iterations: int = 1000  # RANSAC samples of the affine fundamental matrix
    seed: int = 0  # seed of the RANSAC sampling
    min_extent_m: float = 50.0  # the views are tied over the AOI grown about its centre to at
    # least this side (m): a small AOI holds few features, and another date's views match few
    # of them; a pointing error moves the whole image alike. 0: over the AOI alone
    pair_min_overlap: float = 0.2  # least fraction of the AOI two views must both see to pair
    pair_bh_range: tuple[float, float] = (0.02, 0.6)  # base-to-height ratios of the preferred pairs
    pair_probe_features: int = 300  # strongest features matched to score candidate pairs; 0: none
    pair_repair: int = 6  # more candidates tried for a view not tied, before it is dropped
    camera_grid: tuple[int, int, int] = (20, 20, 8)  # samples (east, north, up) of the sparse
    # stage's own cameras
    altitude_max_error_px: float = 1.0  # tie points reprojected farther (px) do not bound heights
    altitude_min_bh: float = 0.01  # tie points whose views' effective base-to-height ratio
    # (triangulation.base_to_height) is lower do not bound heights: two views along nearly one
    # line of sight put their matches hundreds of metres off (bench_multidate one view per date
    # seed 39, 3 views: 84 of 142 tie points at 0.004, range -45..132 m for a town of 98..158 m).
    # No other stack measured has any under 0.019: at 0.02 seed 38's 5 views lost a pair 1.1
    # degrees apart (107 of 328 points at 0.019; DFC MAE 1.762 -> 3.127 m), and at 0.05 the
    # issue-form stacks of 19 views a quarter of theirs (none under 0.022; two of their DSMs
    # moved, +0.012 / +0.018 m)
    altitude_min_points: int = 20  # fewest usable tie points that bound the heights
    altitude_floor_views: int = 3  # the lowest end comes from tie points of this many views
    altitude_floor_fewer_fraction: float = 0.05  # ... or from those of fewer views, where this
    # fraction of them share an altitude below that floor's margin (a ground that few views tie,
    # as on stacks of one view per date); 0: never
    altitude_support: int = 2  # tie points that must share an end's altitude within support_m
    altitude_support_fraction: float = 0.001  # ... or this fraction of them, when more
    altitude_support_m: float = 3.0  # height window (m) of that support
    altitude_support_radius_m: float = 30.0  # the highest end's support lies within this
    # horizontal distance (m) of it, on one roof (two wrong matches share a height by chance
    # anywhere over the AOI); 0: anywhere
    altitude_margin_below_m: float = 2.0  # margin (m) below the lowest end: the supported
    # floor already lies 2-5 m under the ground (the ties' noise), and a deeper range lets
    # shadows match under it. With RPCs spanning 1000 m of heights as real ones do (synth
    # --rpc-height-scale 500; the prior then no longer cuts the margin at 95 m), issue-form
    # seeds 11-13 (19 views of one date each, 0.3 m) 5 m: DFC MAE 1.190 / 0.974 / 0.976 m, floors
    # 9.3 / 7.4 / 5.3 m under the ground; 2: 1.060 / 0.904 / 0.987; 0: 1.047 / 0.894 / 0.991
    # (docs/measurements.md, forty-ninth session). A ground under the floor still shows: the
    # area is swept again lower where its references match many pixels at the floor
    # (pipeline.area.RANGE_WIDEN_FRACTION)
    altitude_margin_above_m: float = 15.0  # margin (m) above the highest end
    altitude_aoi_margin_m: float = 25.0  # tie points this far (m) outside the AOI also bound its
    # heights: a roof across the AOI's edge may have its only features outside it

    ADVANCED = ("feature_scale", "feature_scale_min_px", "refine_window_px",
                "refine_window_m", "refine_max_shift_px", "refine_keep_fraction", "refine_beside_px",
                "fine_points_per_view",
                "extend_points_per_view",
                "contrast_threshold", "ratio", "repair_ratio",
                "mutual", "geometric_model", "ransac_threshold_px", "ransac_iterations", "seed",
                "min_extent_m", "pair_min_overlap", "pair_bh_range", "pair_probe_features",
                "pair_repair",
                "camera_grid", "altitude_max_error_px", "altitude_min_bh", "altitude_min_points",
                "altitude_floor_views", "altitude_floor_fewer_fraction", "altitude_support",
                "altitude_support_fraction", "altitude_support_m", "altitude_support_radius_m",
                "altitude_margin_below_m", "altitude_margin_above_m", "altitude_aoi_margin_m")

    def check(self) -> None:
        self._require(self.max_features >= 8, "max_features", "must be at least 8")
        self._require(math.isfinite(self.feature_scale) and 0.1 <= self.feature_scale <= 1.0,
                      "feature_scale", "must be in [0.1, 1]")
        self._require(self.feature_scale_min_px >= 0, "feature_scale_min_px", "must be >= 0")
        self._require(self.refine_window_px == 0 or 5 <= self.refine_window_px <= 63,
                      "refine_window_px", "must be 0 (no refinement) or in [5, 63] pixels")
        self._require(math.isfinite(self.refine_window_m) and self.refine_window_m >= 0.0,
                      "refine_window_m", "must be >= 0 metres (0: refine_window_px alone)")
        self._require(math.isfinite(self.refine_beside_px)
                      and 0.0 <= self.refine_beside_px <= max(self.refine_window_px, 1),
                      "refine_beside_px", "must be in [0, refine_window_px] pixels (0: the "
                      "centred window only)")
        self._require(self.fine_points_per_view >= 0, "fine_points_per_view", "must be >= 0")
        self._require(self.extend_points_per_view >= 0, "extend_points_per_view",
                      "must be >= 0 (0: tracks not extended)")
        self._require(math.isfinite(self.refine_keep_fraction) and 0.0 < self.refine_keep_fraction <= 1.0,
                      "refine_keep_fraction", "must be a fraction in (0, 1]")
        self._require(math.isfinite(self.refine_max_shift_px) and self.refine_max_shift_px > 0.0,
                      "refine_max_shift_px", "must be a positive number of pixels")
        self._require(math.isfinite(self.contrast_threshold) and self.contrast_threshold > 0.0,
                      "contrast_threshold", "must be a positive number")
        self._require(0.0 < self.ratio <= 1.0, "ratio", "must be in (0, 1]")
        self._require(self.ratio <= self.repair_ratio <= 1.0, "repair_ratio",
                      f"must be in [ratio = {self.ratio:g}, 1]")
        self._require(math.isfinite(self.ransac_threshold_px) and self.ransac_threshold_px > 0.0,
                      "ransac_threshold_px", "must be a positive number of pixels")
        self._require(self.ransac_iterations >= 1, "ransac_iterations", "must be at least 1")
        self._require(self.min_matches >= 5, "min_matches",
                      "must be at least 5 (the affine model needs 4 matches plus redundancy)")
        self._require(self.seed >= 0, "seed", "must be >= 0")
        self._require(self.pair_neighbours >= 1, "pair_neighbours", "must be at least 1")
        self._require(math.isfinite(self.min_extent_m) and 0.0 <= self.min_extent_m <= 5000.0,
                      "min_extent_m", "must be a number of metres in [0, 5000] (0: the AOI alone)")
        self._require(math.isfinite(self.pair_min_overlap) and 0.0 <= self.pair_min_overlap <= 1.0,
                      "pair_min_overlap", "must be a fraction in [0, 1]")
        lo, hi = self.pair_bh_range
        self._require(math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo < hi,
                      "pair_bh_range", "must be (low, high) with 0 <= low < high")
        self._require(self.pair_probe_features == 0 or self.pair_probe_features >= 20,
                      "pair_probe_features", "must be 0 (no probe) or at least 20")
        self._require(self.pair_repair >= 0, "pair_repair", "must be >= 0")
        self._require(all(n >= 2 for n in self.camera_grid), "camera_grid",
                      "needs at least 2 samples along each of east, north and up")
        self._require(math.isfinite(self.altitude_max_error_px) and self.altitude_max_error_px > 0.0,
                      "altitude_max_error_px", "must be a positive number of pixels")
        self._require(math.isfinite(self.altitude_min_bh) and self.altitude_min_bh >= 0.0,
                      "altitude_min_bh", "must be a base-to-height ratio >= 0 (0: every tie point)")
        self._require(self.altitude_min_points >= 2, "altitude_min_points", "must be at least 2")
        self._require(self.altitude_floor_views >= 2, "altitude_floor_views", "must be at least 2")
        self._require(self.altitude_support >= 1, "altitude_support", "must be at least 1")
        self._require(math.isfinite(self.altitude_floor_fewer_fraction)
                      and 0.0 <= self.altitude_floor_fewer_fraction <= 1.0,
                      "altitude_floor_fewer_fraction", "must be a fraction in [0, 1] (0: never)")
        self._require(math.isfinite(self.altitude_support_fraction)
                      and 0.0 <= self.altitude_support_fraction < 0.5,
                      "altitude_support_fraction", "must be a fraction in [0, 0.5)")
        self._require(math.isfinite(self.altitude_support_m) and self.altitude_support_m >= 0.0,
                      "altitude_support_m", "must be a finite number of metres >= 0")
        for name in ("altitude_support_radius_m", "altitude_margin_below_m",
                     "altitude_margin_above_m", "altitude_aoi_margin_m"):
            v = getattr(self, name)
            self._require(math.isfinite(v) and v >= 0.0, name, "must be a finite number of metres >= 0")
