"""Coarse-to-fine plane windows (``[sweep] search = "coarse_to_fine"``, with SGM).

A full sweep evaluates every plane at every pixel, though the surface at a pixel lies near a few
of them. This stage gives each square block of the reference a window of consecutive planes: the
reference is first swept (and refined by SGM) at half resolution over every other plane; each
block's window then spans the coarse plane indices found in the block and a halo around it, plus
a margin of planes on each side. The full-resolution sweep and SGM evaluate only the windows
(``sweep.PlaneWindows``; SGM compares the same planes across blocks and steps through each
pixel's own window, so that a block across a cliff does not widen the others', kernels/sgm.cl).
Where every block would hold most of the planes (a city at 0.3 m: each 64 px block holds a roof
and the ground), each pixel may get its own window instead (``block`` = 1), over the coarse
indices within the halo of it; such a window spans a roof's planes, the ground's and all the
facade's between them, and with bands (``[sweep] window_bands``) the sweep evaluates only the
bands of planes around the halo's coarse indices (``PlaneWindows.bands``).

Conventions: a half-resolution pixel (i, j) is the mean of full-resolution pixels (2i, 2j) to
(2i + 1, 2j + 1), so its centre lies at full-resolution (2j + 0.5, 2i + 0.5) (pixel (0, 0) = the
centre of the first pixel, as everywhere).
"""

from __future__ import annotations

import numpy as np

from satsweep.dense.sweep import BAND_PLANES, PlaneWindows, band_words

# Fewest planes, and smallest image side (pixels), for which a coarse pass is worth its cost.
MIN_PLANES = 24
MIN_SIDE_PX = 32

# Half-resolution pixel -> full-resolution pixel (homogeneous), and its inverse.
_UP = np.array([[2.0, 0.0, 0.5], [0.0, 2.0, 0.5], [0.0, 0.0, 1.0]])
_DOWN = np.linalg.inv(_UP)


def downsample2(image: np.ndarray) -> np.ndarray:
    """Mean of 2x2 pixel blocks (float32); an odd last row or column is left out."""
    a = np.asarray(image, dtype=np.float32)
    h, w = a.shape[0] // 2 * 2, a.shape[1] // 2 * 2
    a = a[:h, :w]
    return np.ascontiguousarray(0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2]
                                        + a[1::2, 1::2]), dtype=np.float32)


def half_resolution_homographies(homographies: np.ndarray) -> np.ndarray:
    """Reference -> source plane homographies (..., 3, 3) re-expressed between the
    half-resolution images of ``downsample2``."""
    return _DOWN @ np.asarray(homographies, dtype=np.float64) @ _UP


def upsample_index(coarse_index: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A half-resolution map onto the full-resolution pixels of ``shape`` (each full pixel takes
    the half-resolution pixel it belongs to; an odd last row or column takes the last one)."""
    h, w = shape
    c = np.asarray(coarse_index)
    rows = np.minimum(np.arange(h) // 2, c.shape[0] - 1)
    cols = np.minimum(np.arange(w) // 2, c.shape[1] - 1)
    return c[rows[:, None], cols[None, :]]


def worth_a_coarse_pass(shape: tuple[int, int], n_planes: int) -> bool:
    """Whether a reference of ``shape`` swept over ``n_planes`` planes gains from windows."""
    return n_planes >= MIN_PLANES and min(shape) >= MIN_SIDE_PX


def fill_from_nearest(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``values`` (H, W) with every pixel not ``known`` given the value of its nearest known
    pixel: OpenCV's labelled distance transform (5x5 mask), which labels the known pixels (the
    zeros of its input) in raster order; its pick is within 0.14 px of the exact Euclidean
    nearest distance (measured)."""
    import cv2  # noqa: PLC0415

    _d, label = cv2.distanceTransformWithLabels((~known).astype(np.uint8), cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    return np.asarray(values)[known][label - 1]


def _square(radius: int) -> np.ndarray:
    """The (2 radius + 1)^2 square structuring element of OpenCV's erode and dilate."""
    return np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)


# _LOW_BITS[k]: the k lowest bits of a 32-bit word set (k = 0 .. 32).
_LOW_BITS = np.array([(1 << k) - 1 for k in range(33)], np.uint32)


def _or_within(words: np.ndarray, radius: int) -> np.ndarray:
    """(..., H, W) unsigned bit sets: each pixel's OR over the pixels within ``radius`` (a
    square) of it, those outside the image ignored (the bitwise form of OpenCV's dilation with
    ``_square(radius)`` and replicated borders, which adds nothing outside either), in two
    separable passes of shifted ORs."""
    rows = words.copy()
    for d in range(1, radius + 1):
        rows[..., d:] |= words[..., :-d]
        rows[..., :-d] |= words[..., d:]
    out = rows.copy()
    for d in range(1, radius + 1):
        out[..., d:, :] |= rows[..., :-d, :]
        out[..., :-d, :] |= rows[..., d:, :]
    return out


def _bands(index: np.ndarray, n_planes: int, radius: int, margin: int) -> np.ndarray:
    """(words, H, W) uint32: each pixel's band set, bit k set where some index i of ``index``
    within ``radius`` pixels of it (a square) has floor(i) - margin .. ceil(i) + margin (within
    the planes) meet planes [k BAND_PLANES, (k + 1) BAND_PLANES). Each pixel's own bands are
    one run of bits per word, [lo, hi], then ORed over the square (``_or_within``): one pass
    per word instead of a dilation per band (a 1088 px tile of 240 planes, 60 bands: 0.12 ->
    0.04 s)."""
    # (the planes as whole numbers before the division: a float's floor division is slower)
    lo = np.clip(np.floor(index) - margin, 0, n_planes - 1).astype(np.int32) // BAND_PLANES
    hi = np.clip(np.ceil(index) + margin, 0, n_planes - 1).astype(np.int32) // BAND_PLANES
    own = np.empty((band_words(n_planes),) + index.shape, np.uint32)
    for w in range(own.shape[0]):
        # bits [first, end) of word w (none where first >= end)
        first = np.clip(lo - 32 * w, 0, 32)
        end = np.clip(hi + 1 - 32 * w, 0, 32)
        own[w] = _LOW_BITS[end] & ~_LOW_BITS[first]
    return _or_within(own, radius)


def plane_windows(plane_index: np.ndarray, n_planes: int, *, block: int, halo: int,
                  margin: int, max_fraction: float, pixel_fallback: bool = False,
                  bands: bool = False, band_halo: int | None = None) -> PlaneWindows | None:
    """Per-block plane windows from a full-resolution map of (fractional) plane indices.

    ``plane_index``: (H, W), NaN where the coarse pass found nothing (filled from the nearest
    known pixel). Each block sweeps floor(min) - margin .. ceil(max) + margin (within the
    planes) of the indices in the block grown by ``halo`` pixels (``block`` = 1: each pixel
    its own window, over the pixels within ``halo`` of it); ``n_planes`` of the result is
    the widest of these windows (SGM is built for every plane whatever the windows,
    ``sgm.sgm_refine``, so that the pipeline builds its program ahead). When the blocks would
    sweep more than ``max_fraction`` of the planes on average, windows of one pixel each if
    ``pixel_fallback`` and they sweep no more; else (or when nothing is known) None: sweep
    every plane. With ``bands``, windows of one pixel also get their band sets
    (``PlaneWindows.bands``): the bands of BAND_PLANES planes that hold floor(i) - margin ..
    ceil(i) + margin of an index i within ``band_halo`` pixels (default and at most: ``halo``;
    within the planes); the planes between a roof's and the ground's indices beside it are left
    out.
    """
    import cv2  # noqa: PLC0415

    idx = np.asarray(plane_index, dtype=np.float64)
    known = np.isfinite(idx)
    if not known.any():
        return None
    if not known.all():
        idx = fill_from_nearest(idx, known)
    kernel = _square(halo)
    # Min / max over the window, pixels outside the image ignored (= scipy's mode "nearest").
    lo_px = cv2.erode(idx, kernel, borderType=cv2.BORDER_REPLICATE)
    hi_px = cv2.dilate(idx, kernel, borderType=cv2.BORDER_REPLICATE)
    h, w = idx.shape
    for side in (block, 1) if pixel_fallback and block > 1 else (block,):
        lo, hi = lo_px, hi_px
        if side > 1:
            nby, nbx = -(-h // side), -(-w // side)
            pad = ((0, nby * side - h), (0, nbx * side - w))
            lo = np.pad(lo, pad, constant_values=np.inf).reshape(nby, side, nbx, side).min(
                axis=(1, 3))
            hi = np.pad(hi, pad, constant_values=-np.inf).reshape(nby, side, nbx, side).max(
                axis=(1, 3))
        lo = np.clip(np.floor(lo) - margin, 0, n_planes - 1).astype(np.int64)
        hi = np.clip(np.ceil(hi) + margin, 0, n_planes - 1).astype(np.int64)
        count = hi - lo + 1
        if count.mean() <= max_fraction * n_planes:
            pixel_bands = None
            if bands and side == 1:
                reach = halo if band_halo is None else min(band_halo, halo)
                pixel_bands = _bands(idx, n_planes, reach, margin)
            return PlaneWindows(block=side, first=lo, n_planes=int(count.max()), count=count,
                                bands=pixel_bands)
    return None
