"""Semi-global matching (Hirschmueller 2008) on the OpenCL device (``kernels/sgm.cl``).

Path costs along 4 or 8 scanline directions are summed, then the sweep's streaming
winner-take-all (``kernels/wta.cl``) runs on the aggregated volume. The conventions of the cost
volume, labels and penalties are those of :mod:`satsweep.dense.mrf`.
"""

from __future__ import annotations

import time

import numpy as np

from satsweep.dense.mrf import (
    MRFOptions,
    MRFResult,
    _check_guide,
    _check_heights,
    _check_label_base,
    _check_scale,
    _check_visible,
    _check_volume,
    _equiangular_offset,
    _finish,
    _parabola_offset,
)
from satsweep.errors import DeviceError, InputError
from satsweep.opencl.constants import SGM_MAX_LABELS, SGM_SCAN_GUARD, WTA_NSTATE, WTA_SLOT, WTA_VEC
from satsweep.opencl.device import Device

# Scanline directions (dx, dy) of SGM, in the order their path costs are added; 4 paths use the
# first four (horizontal and vertical), 8 paths all of them.
SGM_DIRECTIONS: tuple[tuple[int, int], ...] = (
    (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1))
# Work-items per scanline on GPUs when sgm_work_group = 0 (a warp/wavefront shares a scanline).
_SGM_GPU_WORK_GROUP = 32
# One-work-item SGM (CPUs): scanlines per work-item of the vertical and diagonal directions, which
# then read neighbouring pixels each round (sgm.cl). Measured on PoCL, 770^2 x 136 labels, one
# accumulating path: vertical 0.143 s with 1, 0.117 s with 4, 0.066 s with 8, 0.087 s with 16;
# diagonal 0.106 / 0.068 / 0.073 / 0.088 s. Rows stay one per work-item: they are contiguous
# already (0.046 s with 1, 0.067 s with 8). Private arrays hold 2 x (3 labels + 4) floats per
# scanline, capped at SGM_PRIVATE_BYTES per work-item (fewer scanlines for many labels).
SGM_CPU_LINES = 8
SGM_PRIVATE_BYTES = 64 * 1024


# ---------------------------------------------------------------------------------------------
# semi-global matching (device)
# ---------------------------------------------------------------------------------------------
def sgm_work_group(device: Device, options: MRFOptions, n_labels: int) -> int:
    """Work-items per scanline: the option, or 1 on CPUs and 32 on GPUs, within device limits."""
    wg = options.sgm_work_group
    if wg == 0:
        wg = _SGM_GPU_WORK_GROUP if device.info.kind == "gpu" else 1
    max_wg = int(device.cl_device.max_work_group_size)
    while wg > 1 and wg > max_wg:
        wg //= 2
    local_bytes = 4 * (n_labels + wg)
    if local_bytes > int(device.cl_device.local_mem_size):
        raise DeviceError(f"{device.info.label}: SGM over {n_labels} planes needs "
                          f"{local_bytes} bytes of local memory, the device has "
                          f"{int(device.cl_device.local_mem_size)}")
    return wg


def sgm_program_requests(device: Device, options: MRFOptions,
                         n_labels: int) -> list[tuple[str, dict]]:
    """The (source, defines) of the programs that SGM over ``n_labels`` labels builds: sgm.cl,
    and wta.cl for the winner-take-all of the sums (``Device.prebuild`` takes this list)."""
    wg = sgm_work_group(device, options, n_labels)
    lines = sgm_lines_per_item(wg, n_labels)
    return [("sgm", {"SGM_NL": n_labels, "SGM_WG": wg, "SGM_LINES": lines}),
            ("wta", _WTA_PIXEL_MAJOR_DEFINES)]


# wta.cl's defines for wta_pixel_major and wta_close: NSRC and the census radii matter only to
# wta_finalize, which SGM does not use.
_WTA_PIXEL_MAJOR_DEFINES = {"NSRC": 1, "CENSUS_RX": 1, "CENSUS_RY": 1}


def sgm_lines_per_item(work_group: int, n_labels: int) -> int:
    """Most scanlines one work-item of sgm_path steps together (sgm.cl's SGM_LINES): 1 with a
    work-group per scanline, else ``SGM_CPU_LINES`` within ``SGM_PRIVATE_BYTES`` of private
    arrays."""
    if work_group > 1:
        return 1
    per_line = 2 * 4 * (3 * n_labels + 4)
    return max(1, min(SGM_CPU_LINES, SGM_PRIVATE_BYTES // per_line))


def _check_device_array(device: Device, arr, layout: str, instead: str) -> None:
    """A device volume must be a C-contiguous 3-D float32 pyopencl Array of this device's context
    without offset (``layout`` and ``instead`` complete the messages)."""
    if arr.dtype != np.float32 or arr.ndim != 3 or not arr.flags.c_contiguous:
        raise InputError(None, f"cost_volume: device array must be C-contiguous float32 "
                               f"{layout}, got {arr.dtype} {arr.shape}")
    if arr.context != device.context:
        raise InputError(None, "cost_volume: device array lives in another OpenCL context")
    if arr.offset != 0:
        raise InputError(None, f"cost_volume: device array is a view with an offset; pass a "
                               f"{instead}")


def _as_device_volume(device: Device, cost_volume, shape):
    """(buffer, (L, H, W), owned) for a numpy volume, a pyopencl Array or a Buffer; owned: the
    buffer was uploaded here (from a numpy volume) and may be released after use."""
    import pyopencl as cl  # noqa: PLC0415
    import pyopencl.array as cla  # noqa: PLC0415

    if isinstance(cost_volume, cla.Array):
        _check_device_array(device, cost_volume, "(planes, H, W)", "copy or its buffer with shape=")
        return cost_volume.data, tuple(int(s) for s in cost_volume.shape), False
    if isinstance(cost_volume, cl.Buffer):
        if shape is None or len(shape) != 3:
            raise InputError(None, "cost_volume: a pyopencl Buffer needs shape=(planes, H, W)")
        shape = tuple(int(s) for s in shape)
        if cost_volume.size < 4 * shape[0] * shape[1] * shape[2]:
            raise InputError(None, f"cost_volume: buffer of {cost_volume.size} bytes is smaller "
                                   f"than float32 {shape}")
        return cost_volume, shape, False
    c = np.ascontiguousarray(_check_volume(cost_volume), dtype=np.float32)
    buf = cl.Buffer(device.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=c)
    return buf, c.shape, True


def _pixel_major_volume(device: Device, cost_volume) -> tuple[int, int, int]:
    """(L, H, W) of a PIXEL-MAJOR (H, W, L) device volume, checked as ``_as_device_volume``
    checks a plane-major one."""
    import pyopencl.array as cla  # noqa: PLC0415

    if not isinstance(cost_volume, cla.Array):
        raise InputError(None, "cost_volume: a pixel-major volume must be a C-contiguous float32 "
                               "pyopencl Array (H, W, L) without offset")
    _check_device_array(device, cost_volume, "(H, W, L)", "copy")
    h, w, n_labels = (int(s) for s in cost_volume.shape)
    if min(h, w, n_labels) < 1:
        raise InputError(None, f"cost_volume: expected (H, W, L), got shape {cost_volume.shape}")
    return n_labels, h, w


def _volume_shape(cost_volume, shape) -> tuple[int, int, int]:
    """(L, H, W) of a host volume, a pyopencl Array, or a Buffer with its ``shape``."""
    import pyopencl as cl  # noqa: PLC0415
    import pyopencl.array as cla  # noqa: PLC0415

    if isinstance(cost_volume, cla.Array):
        dims = tuple(int(s) for s in cost_volume.shape)
    elif isinstance(cost_volume, cl.Buffer):
        if shape is None or len(shape) != 3:
            raise InputError(None, "cost_volume: a pyopencl Buffer needs shape=(planes, H, W)")
        dims = tuple(int(s) for s in shape)
    else:
        dims = _check_volume(cost_volume).shape
    if len(dims) != 3 or min(dims) < 1:
        raise InputError(None, f"cost_volume: expected (planes, H, W), got shape {dims}")
    return dims  # type: ignore[return-value]


def _ragged_dims(device: Device, cost_volume, label_count, label_offset,
                 capacity) -> tuple[int, int, int]:
    """(L, H, W) of a RAGGED pixel-major device volume: a 1-D float32 ``pyopencl.array.Array``
    whose pixel p holds its label_count[p] labels from label_offset[p] on; L, the labels SGM is
    built for, is ``capacity``, at least the largest count (``sgm_refine`` gives the planes the
    windows are drawn from, so that SGM's program is the full search's, which the pipeline
    builds ahead)."""
    import pyopencl.array as cla  # noqa: PLC0415

    if label_count is None:
        raise InputError(None, "label_offset: needs label_count (a ragged volume's labels)")
    if not isinstance(cost_volume, cla.Array) or cost_volume.ndim != 1 \
            or cost_volume.dtype != np.float32 or cost_volume.offset != 0 \
            or cost_volume.context != device.context:
        raise InputError(None, "cost_volume: a ragged volume (label_offset) must be a 1-D float32 "
                               "pyopencl Array of this device's context without offset")
    n = np.asarray(label_count)
    o = np.asarray(label_offset)
    if n.ndim != 2 or o.shape != n.shape or o.dtype != np.uint64 \
            or not np.issubdtype(n.dtype, np.integer):
        raise InputError(None, f"label_offset: expected uint64 of the label counts' shape "
                               f"{n.shape}, got {o.dtype} {o.shape}")
    if n.size and (n.min() < 1 or int((o + n.astype(np.uint64)).max()) > cost_volume.size):
        raise InputError(None, f"label_offset: pixels' labels reach past the volume's "
                               f"{cost_volume.size} floats")
    if capacity is None or not int(n.max()) <= capacity <= SGM_MAX_LABELS:
        raise InputError(None, f"label_count: counts up to {int(n.max())} outside the "
                               f"{capacity} labels SGM is built for (at most {SGM_MAX_LABELS})")
    return int(capacity), n.shape[0], n.shape[1]


def sgm_scan_scratch_floats(width: int, n_labels: int) -> int:
    """Floats of sgm_scan's scratch for both scans (sgm.cl's 2 x SGM_SCAN_SCRATCH(w))."""
    return 2 * ((6 * width + 2) * (n_labels + 2 * SGM_SCAN_GUARD) + 6 * width)


def _check_sgm_size(device: Device, dims: tuple[int, int, int]) -> None:
    """The label count fits sgm.cl and one volume fits a device allocation."""
    n_labels, h, w = dims
    if n_labels > SGM_MAX_LABELS:
        raise InputError(None, f"cost_volume: {n_labels} planes, SGM supports at most "
                               f"{SGM_MAX_LABELS}")
    nbytes = 4 * n_labels * h * w
    if nbytes > device.max_alloc_bytes:
        raise DeviceError(f"{device.info.label}: an SGM volume of {nbytes / 2**20:.0f} MiB "
                          f"({n_labels} planes x {h} x {w}) exceeds the largest allocation "
                          f"({device.max_alloc_bytes / 2**20:.0f} MiB): refine smaller tiles")


def sgm_aggregate(device: Device, cost_volume, guide, options: MRFOptions, *,
                  cost_scale: float = 1.0, shape: tuple[int, int, int] | None = None,
                  pixel_major: bool = False, label_base=None, label_count=None):
    """Sum of the SGM path costs over ``options.sgm_paths`` directions, on the device.

    ``cost_volume``: (L, H, W) float32 as a numpy array, a ``pyopencl.array.Array`` in the
    device's context, or a ``pyopencl.Buffer`` (then ``shape`` is required). Invalid entries
    (<= SATSWEEP_INVALID / 2, or NaN) count as ``cost_scale``. P1 = sgm_p1 * cost_scale,
    P2 = sgm_p2 * cost_scale, adapted to the guide as documented in kernels/sgm.cl. The volume
    is turned pixel-major on the device, aggregated, and turned back; at most three volumes are
    held at once. With ``pixel_major``, ``cost_volume`` is already in SGM's layout, a
    ``pyopencl.array.Array`` (H, W, L) (as ``PlaneSweep.run(volume_on_device=True)`` leaves
    it), whose entries are all valid costs, and it is aggregated as it is. ``label_base``
    ((H, W) integers, optional): label d of pixel p is plane label_base[p] + d (label bands of a
    coarse-to-fine search, kernels/sgm.cl). ``label_count`` ((H, W) integers in 1..L, with
    ``label_base``): pixel p has only labels d < label_count[p]; its other labels are neither
    read nor written (their sums are undefined). Returns a ``pyopencl.array.Array`` (L, H, W)
    float32 on the device.
    """
    import pyopencl.array as cla  # noqa: PLC0415

    agg_pm, prg, _ = _sgm_aggregate_pixel_major(device, cost_volume, guide, options,
                                                cost_scale=cost_scale, shape=shape,
                                                pixel_major=pixel_major, label_base=label_base,
                                                label_count=label_count)
    h, w, n_labels = agg_pm.shape
    queue = device.queue
    agg = cla.empty(queue, (n_labels, h, w), np.float32)
    device.kernel(prg, "sgm_to_plane_major")(queue, (h * w,), None, agg_pm.data, agg.data,
                                             np.int32(h * w))
    queue.finish()
    agg_pm.data.release()
    return agg


def _sgm_aggregate_pixel_major(device: Device, cost_volume, guide, options: MRFOptions, *,
                               cost_scale: float, shape: tuple[int, int, int] | None,
                               pixel_major: bool = False, label_base=None, label_count=None,
                               label_offset=None, label_capacity: int | None = None):
    """``sgm_aggregate`` without the final transposition: ((H, W, L) device array, program,
    bands), or for a ragged volume (``label_offset``) a 1-D device array laid out like it;
    bands: the (count, offset) device arrays of a banded volume (each pixel's labels and where
    they start; the regular layout's when the caller gave none), else None. ``label_capacity``:
    the labels SGM is built for over a ragged volume (``_ragged_dims``)."""
    import pyopencl.array as cla  # noqa: PLC0415

    scale = _check_scale(cost_scale)
    ragged = label_offset is not None
    if ragged and not pixel_major:
        raise InputError(None, "label_offset: a ragged volume is a pixel-major device volume "
                               "(pixel_major = True)")
    n_labels, h, w = _ragged_dims(device, cost_volume, label_count, label_offset,
                                  label_capacity) if ragged \
        else _pixel_major_volume(device, cost_volume) if pixel_major \
        else _volume_shape(cost_volume, shape)
    g = _check_guide(guide, (h, w))
    base, count = _check_label_base(label_base, (h, w), n_labels, None, label_count)
    if ragged and base is None:
        raise InputError(None, "label_offset: needs label_base (the windows' first planes)")
    if not ragged:
        _check_sgm_size(device, (n_labels, h, w))
    source, defines = sgm_program_requests(device, options, n_labels)[0]
    wg, max_lines = defines["SGM_WG"], defines["SGM_LINES"]
    prg = device.build(source, defines)
    queue = device.queue
    guide_d = cla.to_device(queue, g)
    # The kernel reads base and count only when banded; one-entry buffers stand in otherwise.
    base_d = cla.to_device(queue, base if base is not None else np.zeros(1, np.int32))
    if base is not None and count is None:
        count = np.full((h, w), n_labels, np.int32)
    count_d = cla.to_device(queue, count if count is not None else np.zeros(1, np.int32))
    if base is not None and not ragged:  # the regular layout: pixel p's labels from p L on
        label_offset = np.arange(h * w, dtype=np.uint64).reshape(h, w) * np.uint64(n_labels)
    offset_d = cla.to_device(queue, np.ascontiguousarray(label_offset, dtype=np.uint64)
                             if base is not None else np.zeros(1, np.uint64))
    n_pix = h * w
    i32, f32 = np.int32, np.float32
    if pixel_major:
        cost_pm = cost_volume  # the caller's, in SGM's layout already
    else:
        # Pixel-major copy of the costs (invalid entries replaced), aggregated in that layout.
        buf, _, owned = _as_device_volume(device, cost_volume, shape)
        cost_pm = cla.empty(queue, (h, w, n_labels), np.float32)
        device.kernel(prg, "sgm_to_pixel_major")(queue, (n_pix,), None, buf, cost_pm.data,
                                                 i32(n_pix), f32(scale))
        if owned:
            buf.release()  # the uploaded host volume is no longer needed on the device
    agg_pm = cla.empty(queue, cost_volume.shape if ragged else (h, w, n_labels), np.float32)
    inv_sigma = 0.0 if options.sgm_p2_sigma == 0.0 else 1.0 / options.sgm_p2_sigma
    if options.sgm_scan and wg == 1:
        _sgm_scans(device, prg, cost_pm, guide_d, agg_pm, (h, w, n_labels), options, scale,
                   inv_sigma, (base_d, count_d, offset_d, base is not None))
    else:
        kernel = device.kernel(prg, "sgm_path")
        for i, (dx, dy) in enumerate(SGM_DIRECTIONS[:options.sgm_paths]):
            n_lines = h if dy == 0 else (w if dx == 0 else w + h - 1)
            lines = 1 if dy == 0 else max_lines  # scanlines per work-item (1 when wg > 1)
            kernel(queue, (-(-n_lines // lines) * wg,), (wg,), cost_pm.data, guide_d.data,
                   agg_pm.data, i32(w), i32(h), i32(dx), i32(dy), f32(options.sgm_p1 * scale),
                   f32(options.sgm_p2 * scale), f32(inv_sigma), i32(1 if i > 0 else 0),
                   base_d.data, count_d.data, offset_d.data, i32(0 if base is None else 1),
                   i32(lines))
        queue.finish()
    if not pixel_major:
        cost_pm.data.release()
    return agg_pm, prg, ((count_d, offset_d) if base is not None else None)


def _sgm_scans(device: Device, prg, cost_pm, guide_d, agg_pm, dims: tuple[int, int, int],
               options: MRFOptions, scale: float, inv_sigma: float, bands) -> None:
    """agg_pm = the sum of the SGM path costs by sgm.cl's two raster scans (sgm_scan, its two
    phases) over dims = (H, W, L); bands = (base, count, offset, banded) as sgm_scan takes
    them."""
    base_d, count_d, offset_d, banded = bands
    import pyopencl.array as cla  # noqa: PLC0415

    h, w, n_labels = dims
    queue = device.queue
    scratch = cla.empty(queue, (sgm_scan_scratch_floats(w, n_labels),), np.float32)
    try:
        kernel = device.kernel(prg, "sgm_scan")
        for phase in (0, 1):
            kernel(queue, (2,), (1,), cost_pm.data, guide_d.data, agg_pm.data, scratch.data,
                   np.int32(w), np.int32(h), np.float32(options.sgm_p1 * scale),
                   np.float32(options.sgm_p2 * scale), np.float32(inv_sigma),
                   np.int32(options.sgm_paths), np.int32(phase), base_d.data, count_d.data,
                   offset_d.data, np.int32(1 if banded else 0))
        queue.finish()
    finally:
        scratch.data.release()


def _closed_wta_state(device: Device, agg_pm, dims: tuple[int, int, int],
                      bands=None) -> np.ndarray:
    """wta.cl's CLOSED winner-take-all state (WTA_NSTATE, H, W) of a whole PIXEL-MAJOR device
    volume of dims (H, W, L): ``wta_pixel_major`` (the same state as streaming the planes through
    ``wta_update``, without turning the volume plane-major first), then ``wta_close`` (each
    pixel's last plane tested, M2 the second local minimum or else MAX, as ``wta_finalize``
    closes a state). With ``bands`` (the (count, offset) device arrays of
    ``_sgm_aggregate_pixel_major``), each pixel's state after its count planes from its offset
    on."""
    import pyopencl.array as cla  # noqa: PLC0415

    h, w, n_labels = dims
    prg = device.build("wta", _WTA_PIXEL_MAJOR_DEFINES)
    queue = device.queue
    n_pix = h * w
    state = cla.empty(queue, (WTA_NSTATE, h, w), np.float32)
    counted = bands is not None
    count_d, offset_d = bands if counted else (cla.to_device(queue, np.zeros(1, np.int32)),
                                               cla.to_device(queue, np.zeros(1, np.uint64)))
    device.kernel(prg, "wta_pixel_major")(queue, (-(-n_pix // WTA_VEC),), None, agg_pm.data,
                                          np.int32(n_pix), np.int32(n_labels), count_d.data,
                                          offset_d.data, np.int32(1 if counted else 0),
                                          state.data)
    device.kernel(prg, "wta_close")(queue, (n_pix,), None, state.data, np.int32(n_pix),
                                    np.int32(n_labels), count_d.data,
                                    np.int32(1 if counted else 0))
    return state.get()


def sgm_refine(device: Device, cost_volume, guide, heights, options: MRFOptions, *,
               cost_scale: float = 1.0, visible=None, reject_range_edges: bool = True,
               shape: tuple[int, int, int] | None = None,
               pixel_major: bool = False, label_base=None, label_count=None,
               label_offset=None) -> MRFResult:
    """SGM aggregation, then winner-take-all with sub-plane refinement and confidence.

    The argmin, the parabola and the second local minimum are those of the sweep's WTA
    (wta.cl, run on the aggregated volume); the confidence margin is divided by
    ``sgm_paths * cost_scale`` since each path adds about one cost. See ``sgm_aggregate`` for the
    inputs (``pixel_major``, ``label_base``, ``label_count``) and ``MRFResult`` for the outputs;
    with ``label_base``, ``heights`` holds every plane and ``visible`` must be 2-D, and the range
    edges are each pixel's window's (its first and its label_count-th label). ``label_offset``
    ((H, W) uint64, with pixel_major, label_base and label_count): the volume is RAGGED, a 1-D
    device array in which pixel p's label_count[p] labels start at label_offset[p] (as
    ``PlaneSweep.run`` leaves a coarse-to-fine volume: each pixel holds just its window).
    """
    t0 = time.perf_counter()
    ragged = label_offset is not None
    # SGM over a ragged volume is built for every plane, as over the full search's volume.
    capacity = np.size(heights) if ragged else None
    dims = _ragged_dims(device, cost_volume, label_count, label_offset, capacity) \
        if ragged else _pixel_major_volume(device, cost_volume) if pixel_major \
        else _volume_shape(cost_volume, shape)
    n_labels = dims[0]
    hts = _check_heights(heights, n_labels, banded=label_base is not None)
    base, count = _check_label_base(label_base, dims[1:], n_labels, hts.size, label_count)
    vis = _check_visible(visible, dims)
    if base is not None and vis is not None and vis.ndim == 3:
        raise InputError(None, "visible: with label_base, give one mask per pixel (H, W)")
    agg_pm, _, bands = _sgm_aggregate_pixel_major(device, cost_volume, guide, options,
                                                  cost_scale=cost_scale, shape=shape,
                                                  pixel_major=pixel_major, label_base=base,
                                                  label_count=count, label_offset=label_offset,
                                                  label_capacity=capacity)
    try:
        s = _closed_wta_state(device, agg_pm, (dims[1], dims[2], n_labels),
                              bands).astype(np.float64)
    finally:
        agg_pm.data.release()
    # The winner-take-all of the sums is wta.cl's (its closed state); the sub-plane fit through
    # the best label's sums and the confidence's scale are the MRF's own (mrf.py).
    n_last = n_labels if count is None else count  # labels per pixel
    m1, m1p, m1n, c2 = (s[WTA_SLOT[f]] for f in ("M1", "M1P", "M1N", "M2"))
    i1 = s[WTA_SLOT["I1"]].astype(np.int64)
    fit = _equiangular_offset if options.sgm_subplane == "equiangular" else _parabola_offset
    offset = fit(m1p, m1, m1n, (i1 > 0) & (i1 < n_last - 1))
    conf = (c2 - m1) / (options.sgm_paths * _check_scale(cost_scale))
    return _finish(i1, offset, conf, m1, hts, vis, reject_range_edges,
                   time.perf_counter() - t0, label_base=base, n_labels=n_last)
