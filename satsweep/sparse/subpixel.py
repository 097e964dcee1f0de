"""Sub-pixel registration of image windows by Gauss-Newton on Lanczos samples of the images
themselves: the last step of the tie points' registration (:mod:`satsweep.sparse.tracks`), on
the grey levels and on local contrast alike.

OpenCV's pyramidal Lucas-Kanade, which registers the tie points first, takes 8-bit images, so
the other view is warped into the first one's pixels (bilinear, rounded to 8 bits) and Lucas-
Kanade then samples both bilinearly. Bilinear interpolation's error depends on where between
the pixels a sample falls, and between two views the fraction of their pointing offset is much
the same at every tie point, so those errors do not average out over a pair's tie points: on a
texture drawn exactly in both views (tests/sparse/test_subpixel.py), the mean error over 400
windows was up to 0.020 px depending on the offset's fraction, against 0.05 px asked of the
whole adjustment. Here each window's samples are taken where the homography maps them, in the
other view's own pixels, by one Lanczos interpolation of float values (no 8-bit warp): the same
windows' mean error stays within 0.0013 px.

The interpolation matters for each window too: OpenCV's bicubic (Keys' kernel with a = -0.75,
only first-order accurate) left 0.04 px median error per window on that texture, Lanczos (8 x 8
taps) 0.017 px, a cubic B-spline 0.003 px at 4 times Lanczos's time. Samples are OpenCV's
``remap`` (positions to 1/32 px) through :func:`sample_lanczos`, which crops the image to the
samples' reach and splits the work within ``remap``'s limits (fewer than 32767 rows and columns
in and out). :func:`refine_translations` is vectorised over windows.
"""

from __future__ import annotations

import numpy as np

# Gauss-Newton iterations per window from Lucas-Kanade's result, and the step (px) below which a
# window stops. Windows whose views look alike stop within a few steps; between dates each step
# is about 0.6-0.8 of the last (the template's gradients are not the other view's), and steps
# of a hundredth of a pixel or two go on where remap's 1/32 px positions leave the residual
# flat. Measured on tools/bench_multidate.py's scenes (the sparse stage alone, worst view's
# correction after the gauge, docs/measurements.md, forty-sixth session): stopping below
# 1/32 px took 5 views of one view per date, seed 1, to 0.112 px (0.058 below 0.01 px, 0.057
# below 0.005 px, which took 10-view stacks' sparse stage from 4.0 to 5.3 s).
SUBPIXEL_ITERATIONS = 10
SUBPIXEL_EPS_PX = 0.01
# A window that moves farther (px) from Lucas-Kanade's result has not converged to it: it fails.
SUBPIXEL_MAX_MOVE_PX = 0.5
# OpenCV's remap takes images and maps of fewer rows and columns than SHRT_MAX.
_REMAP_LIMIT = 32000
# Pixels around a crop's samples that Lanczos interpolation reads (3 before, 4 after) and one more.
_TAPS_MARGIN = 5


def sample_lanczos(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``image`` (2-D) sampled at (x, y) (float arrays of one shape (n, k): k samples of n
    windows) by OpenCV's Lanczos interpolation, edges replicated: float32 (n, k). A float32
    image within ``remap``'s limits is sampled at once; otherwise the image is cropped to the
    samples' reach (another type converted there only), in groups of windows whose rows and
    reach fit within those limits."""
    import cv2  # noqa: PLC0415

    n, k = x.shape
    if n == 0:
        return np.empty((0, k), np.float32)
    image = np.asarray(image)
    h, w = image.shape
    x = np.asarray(x, np.float32)
    y = np.asarray(y, np.float32)
    if max(n, h, w) < _REMAP_LIMIT and image.dtype == np.float32:  # at once, as it is
        return cv2.remap(image, x, y, cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REPLICATE)
    out = np.empty((n, k), np.float32)
    order = np.argsort(x[:, 0], kind="stable")  # neighbouring windows share a crop

    def run(rows: np.ndarray) -> None:
        xs, ys = x[rows], y[rows]
        with np.errstate(invalid="ignore"):
            x0 = int(np.clip(np.floor(np.nanmin(xs)) - _TAPS_MARGIN, 0, w - 1))
            x1 = int(np.clip(np.ceil(np.nanmax(xs)) + _TAPS_MARGIN + 1, x0 + 1, w))
            y0 = int(np.clip(np.floor(np.nanmin(ys)) - _TAPS_MARGIN, 0, h - 1))
            y1 = int(np.clip(np.ceil(np.nanmax(ys)) + _TAPS_MARGIN + 1, y0 + 1, h))
        if len(rows) > 1 and (len(rows) >= _REMAP_LIMIT or x1 - x0 >= _REMAP_LIMIT
                              or y1 - y0 >= _REMAP_LIMIT):
            half = len(rows) // 2
            run(rows[:half])
            run(rows[half:])
            return
        crop = image[y0:y1, x0:x1]  # a view of a float32 image, else converted here
        if crop.dtype != np.float32:
            crop = crop.astype(np.float32)
        out[rows] = cv2.remap(crop, xs - np.float32(x0), ys - np.float32(y0), cv2.INTER_LANCZOS4,
                              borderMode=cv2.BORDER_REPLICATE)

    run(order)
    return out


def refine_translations(head: np.ndarray, other: np.ndarray, homography: np.ndarray,
                        head_xy: np.ndarray, start: np.ndarray, window_px: int
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each window of ``head`` centred at ``head_xy`` (n, 2) registered in ``other`` by a
    translation: q near ``start`` (n, 2, head's pixels) such that other(H(q + o)) matches
    head(head_xy + o) over the window's offsets o (``window_px`` x ``window_px``), H =
    ``homography`` mapping head's pixels to other's. Gauss-Newton on the window's template
    gradients (forward additive, the gradients held), H taken as its local affine map at each
    window's centre, at most ``SUBPIXEL_ITERATIONS`` steps. Returns (q (n, 2), the residual:
    mean absolute difference of the two windows where the last step began, within
    SUBPIXEL_EPS_PX of q for a window that converged, in the images' units (n,), whether each
    window registered (n,): a template with gradients, finite, within SUBPIXEL_MAX_MOVE_PX of
    its start)."""
    n = len(head_xy)
    r = window_px // 2
    residual = np.full(n, np.inf)
    if n == 0:
        return np.zeros((0, 2)), residual, np.zeros(0, bool)
    head = np.asarray(head, np.float32)  # converted once for every sampling below
    other = np.asarray(other, np.float32)
    # The template and its gradients (central differences) from one ring more of samples.
    ring = np.arange(-r - 1, r + 2, dtype=np.float32)
    side = window_px + 2
    hx = np.asarray(head_xy, np.float32)
    grid_x = np.broadcast_to(hx[:, 0, None, None] + ring[None, None, :], (n, side, side))
    grid_y = np.broadcast_to(hx[:, 1, None, None] + ring[None, :, None], (n, side, side))
    big = sample_lanczos(head, grid_x.reshape(n, -1), grid_y.reshape(n, -1)).reshape(n, side, side)
    template = np.ascontiguousarray(big[:, 1:-1, 1:-1]).reshape(n, -1)
    gx = (0.5 * (big[:, 1:-1, 2:] - big[:, 1:-1, :-2])).reshape(n, -1)
    gy = (0.5 * (big[:, 2:, 1:-1] - big[:, :-2, 1:-1])).reshape(n, -1)
    a = np.einsum("ij,ij->i", gx, gx, dtype=np.float64)
    b = np.einsum("ij,ij->i", gx, gy, dtype=np.float64)
    c = np.einsum("ij,ij->i", gy, gy, dtype=np.float64)
    det = a * c - b * b
    ok = det > 1e-9 * np.maximum(a + c, 1e-12) ** 2  # gradients in two directions
    off_y, off_x = np.mgrid[-r:r + 1, -r:r + 1]
    off_x = off_x.reshape(1, -1).astype(np.float32)
    off_y = off_y.reshape(1, -1).astype(np.float32)
    h = np.asarray(homography, np.float64)
    q = np.asarray(start, np.float64).copy()
    active = ok.copy()
    f32 = np.float32
    for _ in range(SUBPIXEL_ITERATIONS):
        idx = np.flatnonzero(active)
        if len(idx) == 0:
            break
        x, y = q[idx, 0], q[idx, 1]
        s = h[2, 0] * x + h[2, 1] * y + h[2, 2]
        u = (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / s
        v = (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / s
        jxx, jxy = (h[0, 0] - h[2, 0] * u) / s, (h[0, 1] - h[2, 1] * u) / s
        jyx, jyy = (h[1, 0] - h[2, 0] * v) / s, (h[1, 1] - h[2, 1] * v) / s
        mx = jxx.astype(f32)[:, None] * off_x
        mx += jxy.astype(f32)[:, None] * off_y
        mx += u.astype(f32)[:, None]
        my = jyx.astype(f32)[:, None] * off_x
        my += jyy.astype(f32)[:, None] * off_y
        my += v.astype(f32)[:, None]
        res = sample_lanczos(other, mx, my) - template[idx]
        residual[idx] = np.abs(res).mean(axis=1)
        bx = np.einsum("ij,ij->i", gx[idx], res, dtype=np.float64)
        by = np.einsum("ij,ij->i", gy[idx], res, dtype=np.float64)
        dx = (c[idx] * bx - b[idx] * by) / det[idx]
        dy = (a[idx] * by - b[idx] * bx) / det[idx]
        q[idx, 0] -= dx
        q[idx, 1] -= dy
        active[idx[np.hypot(dx, dy) < SUBPIXEL_EPS_PX]] = False
    moved = np.hypot(q[:, 0] - start[:, 0], q[:, 1] - start[:, 1])
    with np.errstate(invalid="ignore"):
        ok &= np.isfinite(q).all(axis=1) & (moved <= SUBPIXEL_MAX_MOVE_PX)
    return q, residual, ok
