"""Skew correction: K = [1 s/fy 0; 0 1 0; 0 0 1] K'.

The perspective approximation of an RPC keeps a skew ``s`` in K (pushbroom sensors scan their
rows while the satellite moves). The plane sweep and the MRF assume square-ish pixels without
skew, so each image is sheared by the inverse of the left factor (a per-row horizontal shift)
and its camera keeps K'. ``skew_correct_set`` does it for every view of a ``CameraSet``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from satsweep.errors import CameraError
from satsweep.geometry.camera import CameraSet, PerspectiveCamera
from satsweep.geometry.parallax import reparametrise
from satsweep.threads import map_in_threads

# Rows processed at once by the skew-correction resampler (bounds its padded copy's memory).
_SHEAR_BLOCK_ROWS = 256
# Views sheared at once by skew_correct_set (numpy's arithmetic releases the GIL; each thread
# holds one block of rows of temporaries besides its view's output). 19 grey views of 1550 x 1500
# px on 2 cores: 1.34-1.51 s -> 0.65-0.73 s, the same images (with the gathers shear_rows used
# before the fifty-fourth session).
SKEW_THREADS_MAX = 4


# -- skew correction -----------------------------------------------------------------------------
def _keys_weights(f: np.ndarray) -> np.ndarray:
    """Keys (a = -0.5) cubic convolution weights of the 4 taps at offsets -1, 0, 1, 2 (shape (..., 4))."""
    f = np.asarray(f, dtype=np.float64)
    w = np.empty(f.shape + (4,))
    d = 1.0 + f  # tap -1
    w[..., 0] = -0.5 * d**3 + 2.5 * d**2 - 4.0 * d + 2.0
    w[..., 1] = 1.5 * f**3 - 2.5 * f**2 + 1.0
    g = 1.0 - f  # tap +1
    w[..., 2] = 1.5 * g**3 - 2.5 * g**2 + 1.0
    d = 2.0 - f  # tap +2
    w[..., 3] = -0.5 * d**3 + 2.5 * d**2 - 4.0 * d + 2.0
    return w


def shear_rows(image: np.ndarray, shift: np.ndarray, out_width: int) -> np.ndarray:
    """Resample each row of an image at ``out[r, c] = image[r, c + shift[r]]`` (cubic, float32).

    ``image`` is (rows, cols) or (rows, cols, bands); ``shift`` (px) has one value per row. Keys
    cubic convolution (exact on quadratics); taps beyond the edges repeat the edge pixel, and
    output pixels whose source lies outside ``[0, cols - 1]`` are NaN.
    """
    image = np.asarray(image)
    rows, cols = image.shape[:2]
    shift = np.asarray(shift, dtype=np.float64)
    if shift.shape != (rows,):
        raise CameraError(f"shear_rows: {rows} rows but {shift.shape} shifts")
    m = np.floor(shift)
    weights = _keys_weights(shift - m).astype(np.float32)  # (rows, 4)
    # Tap 0 of output column 0 reads column m - 1, and a row reads out_width + 3 columns from
    # there. Indices beyond the edges repeat the edge pixel: a row whose columns all lie beyond
    # one edge reads the same as one that starts where they just do, so the starts are clamped
    # to [-(out_width + 2), cols - 1] and the rows padded by at most out_width + 2 columns.
    start = np.clip(m.astype(np.int64) - 1, -(out_width + 2), cols - 1)
    out = np.empty((rows, out_width) + image.shape[2:], dtype=np.float32)
    c_out = np.arange(out_width, dtype=np.float64)
    band_axes = ((0, 0),) * (image.ndim - 2)
    for r0 in range(0, rows, _SHEAR_BLOCK_ROWS):
        r1 = min(rows, r0 + _SHEAR_BLOCK_ROWS)
        s = start[r0:r1]
        pad_l = max(0, -int(s.min()))
        pad_r = max(0, int(s.max()) + 3 + out_width - cols)
        block = np.pad(image[r0:r1].astype(np.float32), ((0, 0), (pad_l, pad_r)) + band_axes,
                       mode="edge")
        # Rows that start at the same column (runs of them: the shift of a shear is linear in
        # the row) are resampled together from contiguous slices of the padded block.
        ends = np.flatnonzero(np.diff(s)) + 1
        for a, b in zip(np.concatenate([[0], ends]), np.concatenate([ends, [r1 - r0]])):
            first = int(s[a]) + pad_l
            acc = np.zeros((b - a, out_width) + image.shape[2:], dtype=np.float32)
            for k in range(4):
                wk = weights[r0 + a:r0 + b, k].reshape((-1, 1) + (1,) * (image.ndim - 2))
                acc += wk * block[a:b, first + k:first + k + out_width]
            out[r0 + a:r0 + b] = acc
        src = c_out[None, :] + shift[r0:r1, None]
        outside = (src < -1e-9) | (src > cols - 1 + 1e-9)
        out[r0:r1][outside] = np.nan
    return out


def skew_correct(image: np.ndarray, camera: PerspectiveCamera) -> tuple[np.ndarray, PerspectiveCamera, np.ndarray]:
    """Remove the skew of ``K`` by shearing the image; returns (image', camera', W).

    ``K = A K'`` with ``A = [[1, s/fy, 0], [0, 1, 0], [0, 0, 1]]`` and ``K'`` skew-free
    (``cx' = cx - s cy / fy``). The image is warped at its own resolution by ``W = T A^-1``
    (``pixel_new = W @ pixel_old``): each row ``r`` moves by ``-s r / fy`` columns, plus a whole
    number of columns ``T`` so that no pixel is lost (the output is wider by the total shear,
    rounded up). The returned camera has ``K'' = W K = T K'`` (skew 0), ``R`` and ``t`` unchanged,
    ``P'' = W P`` and the same approximation error (measured in the original image; the shear
    changes it by a factor within ``1 +- |s / fy|``). The image comes back as float32 (rows,
    cols'[, bands]), NaN where the source pixel lies outside the original image.
    """
    image = np.asarray(image)
    rows, cols = image.shape[:2]
    if (rows, cols) != (camera.height, camera.width):
        raise CameraError(f"skew_correct: image is {cols}x{rows} but the camera is "
                          f"{camera.width}x{camera.height}")
    new, W = skew_corrected_camera(camera)
    # new col c' = c - k r + tx  <=>  source c = c' + k r - tx
    shift = -W[0, 1] * np.arange(rows, dtype=np.float64) - W[0, 2]
    warped = shear_rows(image, shift, new.width)
    return warped, new, W


def skew_corrected_camera(camera: PerspectiveCamera) -> tuple[PerspectiveCamera, np.ndarray]:
    """``skew_correct``'s camera and warp ``W`` without the image: (camera', W), camera' of the
    sheared image's size (wider by the total shear, rounded up)."""
    rows, cols = camera.height, camera.width
    k = camera.K[0, 1] / camera.K[1, 1]
    span = k * (rows - 1)  # column shift of the last row relative to the first
    tx = float(math.ceil(max(0.0, span) - 1e-9))  # keep the first column of every row
    out_width = cols + int(math.ceil(abs(span) - 1e-9))
    W = np.array([[1.0, -k, tx], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    K = W @ camera.K
    K[0, 1] = 0.0  # exactly: s - (s / fy) fy
    P = W @ camera.P
    new = PerspectiveCamera(K=K, R=camera.R.copy(), t=camera.t.copy(), P=P, width=out_width,
                            height=rows, error=camera.error)
    return new, W


def skew_correct_set(cameras: CameraSet, images: Sequence[np.ndarray]) -> tuple[CameraSet, list[np.ndarray]]:
    """Skew-correct every view: new cameras (K', P', P4', warp) and the warped images (float32)."""
    if len(images) != len(cameras.views):
        raise CameraError(f"skew_correct_set: {len(images)} images for {len(cameras.views)} views")

    def one(job):
        v, image = job
        img, cam, W = skew_correct(image, v.camera)
        proj = reparametrise(cam, d=v.projection.d, zbar=v.projection.zbar)
        return dataclasses.replace(v, camera=cam, projection=proj, warp=W), img

    done = map_in_threads(one, list(zip(cameras.views, images)), max_threads=SKEW_THREADS_MAX,
                          name="skew")
    return (dataclasses.replace(cameras, views=tuple(v for v, _ in done)),
            [img for _, img in done])
