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

    # Keep at most this many SIFT keypoints per view (the strongest by local contrast). Only the
    # principal points are adjusted, so a few hundred matches per pair pin them: on the Pleiades
    # pair 3000 keypoints gave 890 verified matches and the same shifts as 6000 (1627 matches)
    # to 0.002 px, in 0.6 s of adjustment instead of 1.1-1.6 s; the 8 synthetic scenes of
    # tools/bench_e2e.py gave the same DSMs to 0.001 m; tools/bench_ba.py's 3 views: residual
    # pointing errors at most 0.074 px (0.070 px with 6000), 1.6 s instead of 3.0 s.
    max_features: int = 3000
    # SIFT runs on the views resampled by this factor (area average), its keypoints mapped back to
    # full-resolution pixels; the tie points then take their sub-pixel positions from
    # refine_window_px, not from SIFT. tools/bench_ba.py, 3 views of 1000 px, seeds 0 / 1: 0.5
    # gives features in 0.35 s instead of 0.95-1.0 s and pointing errors left after the gauge of
    # at most 0.062 / 0.065 px, against 0.074 / 0.110 px for full-resolution SIFT unrefined (0.5
    # unrefined: 0.43 / 0.42 px). 1: SIFT on the views as they are.
    feature_scale: float = 0.5
    # Views whose smaller side is below this (px) are searched at full resolution: small views
    # have few features to spare (a 256 px scene of tests/sparse/test_bundle.py kept 27 verified matches
    # on one pair at half resolution, where min_matches is 30).
    feature_scale_min_px: int = 512
    # Side (px) of the window over which each tie point of a track is registered to the track's
    # first view (Lucas-Kanade, translation only, after the other view is warped into the first
    # by the cameras' homography of the ground plane, so that rotation and scale between the
    # views do not bias it); 0 keeps the keypoints' own positions. Most keypoints lie on
    # building edges, where a window holds surfaces at several heights and a translation
    # registers a compromise: a smaller window holds less of them. tools/bench_ba.py, 3 views of
    # 1000 px, 5 scenes (biases 2 and 50 px), largest error after the gauge with
    # refine_keep_fraction 0.5: 0.040 px (7), 0.037 (9), 0.043 (11), 0.073 (15).
    refine_window_px: int = 9
    # A tie point that the refinement moves farther than this (px) from its keypoint is dropped
    # (the match or the registration is wrong): half-resolution keypoints are good to ~1 px.
    refine_max_shift_px: float = 2.0
    # Of each pair of views, the registered tie points whose windows match best (lowest grey-level
    # residual) are kept in this proportion for the fine adjustment: the others straddle
    # surfaces at different heights, where the registration is off by tenths of a pixel
    # (measured against a synthetic town's truth: median 0.11 px in the best quarter, 1.4 px in
    # the worst). Same benchmark as refine_window_px, window 9: largest error 0.102 px (1),
    # 0.057 (0.7), 0.047 (0.6), 0.037 (0.5), 0.042 (0.4), 0.041 (0.3).
    refine_keep_fraction: float = 0.5
    # SIFT contrast threshold (OpenCV units: Lowe's 0.03 is 0.09 here, as OpenCV divides by the 3
    # octave layers); lower than OpenCV's 0.04 because tonemapped satellite crops are low-contrast.
    contrast_threshold: float = 0.02
    # Lowe's ratio test: nearest / second-nearest descriptor distance must be below this.
    ratio: float = 0.8
    # Keep a match only when each feature is the other's nearest neighbour.
    mutual: bool = True
    # Geometric verification: "cameras" = epipolar geometry of the approximated cameras (with an
    # unknown common offset: the pointing error); "affine" = RANSAC of an affine fundamental matrix.
    geometric_model: Literal["cameras", "affine"] = "cameras"
    # Inlier threshold (px) of the geometric verification: point-to-epipolar-line distance in the
    # second image. SIFT keypoints are good to ~0.3-0.5 px; 1.5 px keeps them and rejects blunders.
    ransac_threshold_px: float = 1.5
    # RANSAC samples drawn for the affine fundamental matrix.
    ransac_iterations: int = 1000
    # A pair with fewer verified matches than this is not used (its matches are unreliable);
    # every view needs at least one such pair.
    min_matches: int = 30
    # Seed of the RANSAC sampling (results are deterministic for a given seed).
    seed: int = 0
    # -- the pair graph (satsweep.sparse.graph): which pairs of views are matched ---------------
    # Each view is matched in this many pairs, its best candidates (after the spanning tree that
    # links every view; satsweep.sparse.graph.select_pairs): the matching then grows linearly
    # with the number of views. With 3, the synthetic stacks of tools/bench_ba.py match 8 of
    # their 10 pairs (5 views), 16 of 45 (10) and 31 of 190 (20), and recover pointing errors
    # of 50 px to 0.02-0.03 px; with 2, up to 0.041 px (10 views).
    pair_neighbours: int = 3
    # Two views are a candidate pair when at least this fraction of the AOI is seen by both.
    pair_min_overlap: float = 0.2
    # Base-to-height ratios of the preferred pairs: below, the pair's heights are poorly
    # triangulated; above, its views differ too much for SIFT. Pairs outside count a quarter.
    pair_bh_range: tuple[float, float] = (0.02, 0.6)
    # Strongest features per view matched between every two candidate views to score the pairs
    # by appearance (verified matches among them); 0: no probe (score by overlap and B/H alone).
    # Probing every pair grows with the square of the views, but 300 features of 3000 cost
    # 1/100 of the arithmetic of a full matching (measured: ~10 ms a pair against ~0.2 s).
    pair_probe_features: int = 300
    # A view that its pairs do not tie to the largest group of views is matched with up to this
    # many more of its candidates before it is dropped.
    pair_repair: int = 3
    # Samples (east, north, up) of the AOI cube for the sparse stage's own perspective cameras
    # (the pipeline fits its own later): on a 1000 px synthetic view, (20, 20, 8) gives cameras
    # as close to the RPC over a dense (60, 60, 15) grid as (30, 30, 10) (0.0283 and 0.0285 px
    # at most over the scene's heights, 0.152 px over 670 m of them), in a fifth of the time.
    camera_grid: tuple[int, int, int] = (20, 20, 8)
    # -- the altitude range from the adjusted tie points (satsweep.sparse.tiepoints) -----------
    # Tie points whose reprojection error with the corrected cameras exceeds this (px) in any
    # view are not used for the altitude range (wrong matches, moving objects); their keypoints
    # are good to about a pixel (SIFT at half resolution).
    altitude_max_error_px: float = 1.0
    # Fewer usable tie points than this inside the AOI cannot bound its heights.
    altitude_min_points: int = 20
    # The lowest end of the range comes from the tie points seen by at least this many views
    # (when altitude_min_points of them are usable; all of them otherwise), the highest from
    # all: wrong matches of two views reach metres to kilometres from the scene, the ground is
    # seen by many views and the highest roofs by few (satsweep.sparse.tiepoints).
    altitude_floor_views: int = 3
    # Each end is the lowest (highest) altitude that at least this many tie points share within
    # altitude_support_m: a wrong match has a height of its own, the ground and a roof do not.
    altitude_support: int = 2
    # ... or this fraction of the tie points, when more: stacks of many views have more wrong
    # matches of two views (a 20-view synthetic stack: 8 points up to 9 m above its roofs).
    altitude_support_fraction: float = 0.001
    # The height window (m) of altitude_support: about the height noise of the tie points
    # (keypoints good to a pixel: 1-3 m at the base-to-height ratios of satellite stereo).
    altitude_support_m: float = 3.0
    # The margin (m) below the lowest end. tools/bench_ba.py, 13 synthetic stacks of 3-20 views
    # (biases 2-50 px): the lowest supported tie point lay up to 5.9 m below the ground (noise),
    # and the ranges held the truth on all 13, at most 10.9 m wider below.
    altitude_margin_below_m: float = 5.0
    # The margin (m) above the highest end. Same stacks: the highest supported tie point lay
    # 1.7 m above to 13.1 m below the highest roof (plain roofs have no features); the ranges
    # were at most 16.7 m wider above (25 m on one stack, whose two wrong matches lay 9-10 m
    # above its roofs).
    altitude_margin_above_m: float = 15.0

    def check(self) -> None:
        self._require(self.max_features >= 8, "max_features", "must be at least 8")
        self._require(math.isfinite(self.feature_scale) and 0.1 <= self.feature_scale <= 1.0,
                      "feature_scale", "must be in [0.1, 1]")
        self._require(self.feature_scale_min_px >= 0, "feature_scale_min_px", "must be >= 0")
        self._require(self.refine_window_px == 0 or 5 <= self.refine_window_px <= 63,
                      "refine_window_px", "must be 0 (no refinement) or in [5, 63] pixels")
        self._require(math.isfinite(self.refine_keep_fraction) and 0.0 < self.refine_keep_fraction <= 1.0,
                      "refine_keep_fraction", "must be a fraction in (0, 1]")
        self._require(math.isfinite(self.refine_max_shift_px) and self.refine_max_shift_px > 0.0,
                      "refine_max_shift_px", "must be a positive number of pixels")
        self._require(math.isfinite(self.contrast_threshold) and self.contrast_threshold > 0.0,
                      "contrast_threshold", "must be a positive number")
        self._require(0.0 < self.ratio <= 1.0, "ratio", "must be in (0, 1]")
        self._require(math.isfinite(self.ransac_threshold_px) and self.ransac_threshold_px > 0.0,
                      "ransac_threshold_px", "must be a positive number of pixels")
        self._require(self.ransac_iterations >= 1, "ransac_iterations", "must be at least 1")
        self._require(self.min_matches >= 5, "min_matches",
                      "must be at least 5 (the affine model needs 4 matches plus redundancy)")
        self._require(self.seed >= 0, "seed", "must be >= 0")
        self._require(self.pair_neighbours >= 1, "pair_neighbours", "must be at least 1")
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
        self._require(self.altitude_min_points >= 2, "altitude_min_points", "must be at least 2")
        self._require(self.altitude_floor_views >= 2, "altitude_floor_views", "must be at least 2")
        self._require(self.altitude_support >= 1, "altitude_support", "must be at least 1")
        self._require(math.isfinite(self.altitude_support_fraction)
                      and 0.0 <= self.altitude_support_fraction < 0.5,
                      "altitude_support_fraction", "must be a fraction in [0, 0.5)")
        self._require(math.isfinite(self.altitude_support_m) and self.altitude_support_m >= 0.0,
                      "altitude_support_m", "must be a finite number of metres >= 0")
        for name in ("altitude_margin_below_m", "altitude_margin_above_m"):
            v = getattr(self, name)
            self._require(math.isfinite(v) and v >= 0.0, name, "must be a finite number of metres >= 0")
