"""SIFT features of the views: the first step of the sparse stage (:mod:`satsweep.sparse.stage`).

Features are detected once per view and serve the pair graph, the pointing-error correction
(:mod:`satsweep.sparse.bundle`) and the altitude range alike: the same ground features are
found in every view and triangulated with the approximated perspective cameras, the way a
vision pipeline (COLMAP, VisSat) does.

Conventions
-----------
- Pixels are (col, row) = (x, y) of the image a camera refers to; pixel (0, 0) is the centre of the
  first pixel. OpenCV's SIFT is run with ``enable_precise_upscale`` so its keypoints follow the
  same convention (without it they are biased by a quarter pixel).
- World points are in the cameras' ENU frame (metres); a camera is anything with a 3x4 ``P``
  (:class:`satsweep.geometry.camera.PerspectiveCamera`) mapping homogeneous ENU points to homogeneous pixels.

Features and their positions
----------------------------
SIFT runs on views of at least ``feature_scale_min_px`` resampled by ``feature_scale`` (half by
default: three times faster, and the descriptors match as well); the keypoints find the tie
points, not their sub-pixel positions. Those come from
:func:`satsweep.sparse.tracks.register_observations`, which registers each track's observations
to its first one by Lucas-Kanade after warping the views onto each other with the cameras'
ground-plane homography; the best registered of each pair of views (the windows over one
surface, not over a building edge) are good to about 0.1 px against a synthetic town's truth,
where SIFT keypoints are good to ~0.3-0.5 px at full resolution.
"""

from __future__ import annotations

import numpy as np

from satsweep.errors import CameraError
from satsweep.sparse.options import SparseOptions


# -- features ------------------------------------------------------------------------------------
def feature_scale_for(shape: tuple[int, ...], options: SparseOptions) -> float:
    """The resampling factor SIFT gets for an image of ``shape``: ``options.feature_scale``, or 1
    for views whose smaller side is below ``options.feature_scale_min_px``."""
    return 1.0 if min(shape[:2]) < options.feature_scale_min_px else options.feature_scale


def _to_u8(image: np.ndarray) -> np.ndarray:
    """A tonemapped image in [0, 1] (NaN: 0) quantised to 8 bits, as OpenCV's SIFT and
    Lucas-Kanade require."""
    return np.round(_unit(image) * 255.0).astype(np.uint8)


def _unit(image: np.ndarray) -> np.ndarray:
    """A tonemapped image as float64 in [0, 1], NaN as 0."""
    return np.clip(np.nan_to_num(np.asarray(image, dtype=np.float64), nan=0.0), 0.0, 1.0)


def detect_features(
    image: np.ndarray, *, max_features: int, contrast_threshold: float = 0.02, scale: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints and descriptors of a tonemapped image.

    ``image``: 2-D float array with values in [0, 1] (``satsweep.imageio.tonemap``); it is
    quantised to 8 bits, which OpenCV's SIFT requires. Returns ``(xy, descriptors)``: ``xy`` is
    ``(N, 2)`` float64 (col, row) with pixel (0, 0) the centre of the first pixel, ``descriptors``
    ``(N, 128)`` float32, strongest keypoints (largest DoG response) first, so that the first
    ``n`` rows are the view's ``n`` most repeatable features (the pair graph probes those). At
    most ``max_features`` keypoints (the strongest) are kept; keypoints
    that OpenCV duplicates for several orientations at one location are all kept (they describe
    different gradients, and the mutual check keeps at most one of them per match). With
    ``scale`` < 1 SIFT runs on the image resampled by that factor (area average) and ``xy`` is
    mapped back to the pixels of ``image``.
    """
    import cv2

    a = np.asarray(image, dtype=np.float64)
    if a.ndim != 2:
        raise CameraError(f"detect_features needs a 2-D image, got shape {a.shape}")
    if not 0.0 < scale <= 1.0:
        raise CameraError(f"detect_features: scale must be in (0, 1], got {scale}")
    fx = fy = 1.0
    if scale < 1.0:
        h, w = a.shape
        ws, hs = max(1, round(w * scale)), max(1, round(h * scale))
        small = cv2.resize(_unit(a).astype(np.float32), (ws, hs), interpolation=cv2.INTER_AREA)
        u8 = _to_u8(small)
        fx, fy = ws / w, hs / h  # the scales cv2.resize applied per axis
    else:
        u8 = _to_u8(a)
    # Arguments: nfeatures, nOctaveLayers, contrastThreshold, edgeThreshold, sigma,
    # enable_precise_upscale (maps pixel x of the original to 2x of the upsampled octave: no
    # quarter-pixel bias of the keypoints).
    sift = cv2.SIFT_create(int(max_features), 3, float(contrast_threshold), 10.0, 1.6, True)
    keypoints, descriptors = sift.detectAndCompute(u8, None)
    if not keypoints:
        return np.zeros((0, 2), dtype=np.float64), np.zeros((0, 128), dtype=np.float32)
    order = np.argsort([-abs(k.response) for k in keypoints], kind="stable")
    xy = np.array([keypoints[k].pt for k in order], dtype=np.float64)
    descriptors = np.asarray(descriptors, dtype=np.float32)[order]
    if scale < 1.0:
        # cv2.resize puts the centre of resampled pixel i at (i + 0.5) / f - 0.5.
        xy = (xy + 0.5) / np.array([fx, fy]) - 0.5
    return xy, np.asarray(descriptors, dtype=np.float32)
