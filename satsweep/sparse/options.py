"""The ``[sparse]`` options: features, matching, verification and tracks."""

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
    # views do not bias it); 0 keeps the keypoints' own positions.
    refine_window_px: int = 15
    # A tie point that the refinement moves farther than this (px) from its keypoint is dropped
    # (the match or the registration is wrong): half-resolution keypoints are good to ~1 px.
    refine_max_shift_px: float = 2.0
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

    def check(self) -> None:
        self._require(self.max_features >= 8, "max_features", "must be at least 8")
        self._require(math.isfinite(self.feature_scale) and 0.1 <= self.feature_scale <= 1.0,
                      "feature_scale", "must be in [0.1, 1]")
        self._require(self.feature_scale_min_px >= 0, "feature_scale_min_px", "must be >= 0")
        self._require(self.refine_window_px == 0 or 5 <= self.refine_window_px <= 63,
                      "refine_window_px", "must be 0 (no refinement) or in [5, 63] pixels")
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
