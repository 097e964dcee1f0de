"""An edge-aware weighted median of a reference's height map (``kernels/median.cl``).

Each valid pixel takes the weighted median of the valid heights of the window around it, each
weighing ``exp(-(g_q - g_p)^2 / (2 sigma^2) - |q - p|^2 / (2 r^2))`` (``g`` the reference image,
``r`` the window's radius): the heights of the pixel's own surface (its grey level) decide,
those across an image edge hardly count. It removes the height noise of flat roofs and ground
that the consensus of many height maps, cell by cell, does not (each map's noise is its own, but
the consensus takes the median of what agrees within a metre), and keeps the steps where the
image has its edges. Applied under SGM to the references of an area fused by the consensus of
many height maps (``MRFOptions.for_consensus``); measured in docs/measurements.md.

:func:`weighted_median` runs the kernel; tests/reference_median.py holds the same rule in numpy
(float64), which the tests compare it with.
"""

from __future__ import annotations

import math

import numpy as np

from satsweep.errors import OptionsError
from satsweep.opencl.buffers import BufferSpec, DeviceMemory
from satsweep.opencl.constants import SATSWEEP_INVALID

# Largest window radius (px) of the kernel (MEDIAN_MAX_RADIUS in median.cl): 8 windows of
# (2 r + 1)^2 height keys and weights sit in each work-item's private memory (169 taps at 6).
MEDIAN_MAX_RADIUS_PX = 6
# Pixels of a row per work-item of weighted_median8 (its float8 lanes).
MEDIAN_VEC = 8
# Its work-group size: each work-item holds its 8 windows' keys and weights in private memory
# (64 bytes a tap: 10.8 KiB at radius 6), which PoCL keeps on one thread's stack for the whole
# work-group; the work-group PoCL chose itself for a 256 px map (none given) overflowed that
# stack. Work-groups of 1 to 16 run at the same speed there.
MEDIAN_LOCAL = (8, 1)


def wanted_radius_px(radius_m: float, gsd_m: float) -> int:
    """The window radius (px) of a ``radius_m`` window on pixels of ``gsd_m`` metres, rounded,
    before the kernel's bounds (``radius_px``)."""
    if not (math.isfinite(gsd_m) and gsd_m > 0.0):
        raise OptionsError(f"median window: ground sample distance {gsd_m!r} m must be > 0")
    return int(round(radius_m / gsd_m))


def radius_px(radius_m: float, gsd_m: float) -> int:
    """The window radius (px) of a ``radius_m`` window on pixels of ``gsd_m`` metres: rounded,
    at least 1 and at most MEDIAN_MAX_RADIUS_PX."""
    return min(max(wanted_radius_px(radius_m, gsd_m), 1), MEDIAN_MAX_RADIUS_PX)


def median_program(radius: int) -> tuple[str, dict]:
    """The (source, defines) of the weighted median's program for a window of ``radius`` px
    (``Device.build``; the program forecast asks for the same)."""
    return "median", {"MEDIAN_RADIUS": int(radius)}


def _check(height: np.ndarray, valid: np.ndarray, guide: np.ndarray, radius: int,
           sigma: float) -> None:
    if height.ndim != 2 or valid.shape != height.shape or guide.shape != height.shape:
        raise OptionsError(f"weighted median: height {height.shape}, valid {valid.shape} and "
                           f"guide {guide.shape} must be one 2-D shape")
    if not 1 <= radius <= MEDIAN_MAX_RADIUS_PX:
        raise OptionsError(f"weighted median: radius {radius} px must lie in 1 .. "
                           f"{MEDIAN_MAX_RADIUS_PX}")
    if not (math.isfinite(sigma) and sigma > 0.0):
        raise OptionsError(f"weighted median: sigma {sigma!r} must be > 0")


# The median's buffers (names as median.cl's arguments), for a map of sizes (h, w).
MEDIAN_BUFFERS = (BufferSpec("height", np.float32, lambda z: z[0] * z[1]),
                  BufferSpec("guide", np.float32, lambda z: z[0] * z[1]),
                  BufferSpec("out", np.float32, lambda z: z[0] * z[1]))


def weighted_median(device, height: np.ndarray, valid: np.ndarray, guide: np.ndarray, *,
                    radius: int, sigma: float, memory: DeviceMemory | None = None) -> np.ndarray:
    """The weighted median (module docstring) of ``height`` (H, W) where ``valid``, with the
    reference image ``guide`` (H, W) in [0, 1], a window of radius ``radius`` px and a guide
    scale ``sigma``, on ``device`` (a satsweep Device). Float64; ``height`` unchanged where not
    ``valid``. ``memory``: the DeviceMemory that accounts for its buffers (a new one if None);
    they are released on return."""
    import pyopencl as cl  # noqa: PLC0415

    height = np.asarray(height)
    valid = np.asarray(valid, bool)
    guide = np.asarray(guide)
    _check(height, valid, guide, radius, sigma)
    h, w = height.shape
    out = np.array(height, np.float64)
    if not valid.any():
        return out
    host = {"height": np.where(valid, height, SATSWEEP_INVALID).astype(np.float32),
            "guide": np.ascontiguousarray(guide, np.float32)}
    memory = DeviceMemory(device.context) if memory is None else memory
    queue = device.queue
    prg = device.build(*median_program(radius))
    # weighted_median8: 8 pixels of a row per work-item, in work-groups of MEDIAN_LOCAL.
    groups = -(-w // MEDIAN_VEC)
    glob = (-(-groups // MEDIAN_LOCAL[0]) * MEDIAN_LOCAL[0], h)
    result = np.empty((h, w), np.float32)
    with memory.allocate(MEDIAN_BUFFERS, (h, w), host=host) as bufs:
        device.kernel(prg, "weighted_median8")(
            queue, glob, MEDIAN_LOCAL, bufs["height"], bufs["guide"], bufs["out"], np.int32(w),
            np.int32(h), np.float32(1.0 / (2.0 * sigma * sigma)),
            np.float32(1.0 / (2.0 * radius * radius)))
        cl.enqueue_copy(queue, result, bufs["out"])
    out[valid] = result[valid]
    return out
