"""Semi-global matching (Hirschmueller 2008) on the OpenCL device (``kernels/sgm.cl``).

Path costs along 4 or 8 scanline directions are summed (``sgm_aggregate``), then the sweep's
streaming winner-take-all (``kernels/wta.cl``) runs on the sums (``sgm_refine``). The volume is a
``CostVolume`` of any layout; the conventions of the cost volume, labels and penalties are those
of :mod:`satsweep.dense.mrf`. The device buffers are listed in tables (``sgm_input_buffers``,
``sgm_sum_buffers``, ...; ``satsweep.opencl.buffers``) and released however a run ends.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time

import numpy as np

from satsweep.dense.mrf import (
    MRFOptions,
    MRFResult,
    _check_guide,
    _check_heights,
    _check_scale,
    _check_visible,
    _check_windows,
    _equiangular_offset,
    _finish,
    _parabola_offset,
)
from satsweep.dense.volume import CostVolume
from satsweep.errors import DeviceError, InputError
from satsweep.opencl.buffers import BufferSpec, DeviceMemory
from satsweep.opencl.constants import SGM_MAX_LABELS, SGM_SCAN_GUARD, WTA_NSTATE, WTA_SLOT, WTA_VEC
from satsweep.opencl.device import Device, launch

# The 1-D per-pixel kernels (sgm.cl's sgm_to_pixel_major and sgm_to_plane_major, wta.cl's
# wta_pixel_major and wta_close) run at the fixed local size (``launch``): enqueued with none,
# PoCL compiled a work-group function per image size (237 of the 524 that the default suite
# compiled into an empty cache).

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
# sgm.cl is built for a label capacity (SGM_NL), a multiple of this many labels, and serves every
# label count up to it (its kernels take the count): one program per 32 counts rather than one
# per count, so a new AOI or altitude range seldom builds anew (the default suite asked for 53
# counts, each a build and a compile of its kernels on PoCL). 32 is the GPU work-group
# (_SGM_GPU_WORK_GROUP), whose work-items then step through as many labels as with an exact
# build, and a multiple of the CPU vectors (sgm.cl's SGM_VEC); a CPU's steps run over the
# pixel's own labels either way.
SGM_LABEL_STEP = 32


# ---------------------------------------------------------------------------------------------
# semi-global matching (device)
# ---------------------------------------------------------------------------------------------
def sgm_label_capacity(n_labels: int) -> int:
    """The labels sgm.cl is built for to serve ``n_labels`` (its SGM_NL): ``n_labels`` rounded up
    to a multiple of ``SGM_LABEL_STEP``, at most SGM_MAX_LABELS."""
    return min(-(-n_labels // SGM_LABEL_STEP) * SGM_LABEL_STEP, SGM_MAX_LABELS)


def sgm_work_group(device: Device, options: MRFOptions, n_labels: int) -> int:
    """Work-items per scanline: the option, or 1 on CPUs and 32 on GPUs, within device limits;
    ``n_labels``: the program's label capacity (``sgm_label_capacity``)."""
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
    """The (source, defines) of the programs that SGM over ``n_labels`` labels builds: sgm.cl
    for their capacity (``sgm_label_capacity``), and wta.cl for the winner-take-all of the sums
    (``Device.prebuild`` takes this list)."""
    capacity = sgm_label_capacity(n_labels)
    wg = sgm_work_group(device, options, capacity)
    lines = sgm_lines_per_item(wg, capacity)
    return [("sgm", {"SGM_NL": capacity, "SGM_WG": wg, "SGM_LINES": lines}),
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


# ---------------------------------------------------------------------------------------------
# device buffers (satsweep.opencl.buffers: one table plans and allocates; named after the kernel
# arguments they are passed as)
# ---------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class SGMSizes:
    """The sizes of SGM's buffers over one volume."""

    h: int
    w: int
    n_labels: int  # labels per pixel of a plain volume (the planes of a ragged one's windows)
    sum_floats: int  # floats of the sums: a ragged volume's, else n_labels h w
    banded: bool  # label windows: base, count and offset per pixel (else one placeholder each)


def sgm_input_buffers(*, convert: bool) -> tuple[BufferSpec, ...]:
    """The guide and the label windows (base, count, offset: one placeholder entry each without
    windows, which the kernels do not read) and, when the volume is plane-major, its pixel-major
    copy ``cost`` (sgm_to_pixel_major's output, which the paths read)."""
    band = lambda z: z.h * z.w if z.banded else 1  # noqa: E731
    specs = (BufferSpec("guide", np.float32, lambda z: z.h * z.w),
             BufferSpec("base", np.int32, band),
             BufferSpec("count", np.int32, band),
             BufferSpec("offset", np.uint64, band))
    if convert:
        specs += (BufferSpec("cost", np.float32, lambda z: z.n_labels * z.h * z.w),)
    return specs


# A host volume uploaded for sgm_to_pixel_major (released once converted).
SGM_UPLOAD_BUFFERS = (BufferSpec("volume", np.float32, lambda z: z.n_labels * z.h * z.w),)


def sgm_sum_buffers(*, scan: bool) -> tuple[BufferSpec, ...]:
    """The sums of the path costs (pixel-major, as the volume) and, for the raster scans,
    sgm_scan's scratch of both scans."""
    specs = (BufferSpec("agg", np.float32, lambda z: z.sum_floats),)
    if scan:
        specs += (BufferSpec("scratch", np.float32,
                             lambda z: sgm_scan_scratch_floats(z.w, z.n_labels)),)
    return specs


# The winner-take-all state of the sums (wta_pixel_major, wta_close), and the plane-major sums
# that sgm_aggregate returns (sgm_to_plane_major).
SGM_STATE_BUFFERS = (BufferSpec("state", np.float32, lambda z: WTA_NSTATE * z.h * z.w),)
SGM_PLANE_MAJOR_BUFFERS = (BufferSpec("sums", np.float32, lambda z: z.n_labels * z.h * z.w),)


def sgm_scan_scratch_floats(width: int, n_labels: int) -> int:
    """Floats of sgm_scan's scratch for both scans over ``n_labels`` labels (sgm.cl's 2 x
    SGM_SCAN_SCRATCH(w, n_labels), whatever the program's capacity)."""
    return 2 * ((6 * width + 2) * (n_labels + 2 * SGM_SCAN_GUARD) + 6 * width)


# ---------------------------------------------------------------------------------------------
# aggregation and refinement
# ---------------------------------------------------------------------------------------------
def _sgm_labels(device: Device, volume: CostVolume, n_planes: int | None) -> int:
    """The labels SGM is built for over ``volume`` (its L; for a ragged volume ``n_planes``, the
    planes its windows are drawn from, so that SGM's program is the full search's, which the
    pipeline builds ahead), checked against SGM_MAX_LABELS and, for a volume SGM copies or
    aggregates whole, the device's largest allocation; and the device volume's context."""
    if not isinstance(volume, CostVolume):
        raise InputError(None, f"cost_volume: expected a CostVolume, got {type(volume).__name__}")
    if volume.on_device and volume.data.context != device.context:
        raise InputError(None, "cost_volume: device array lives in another OpenCL context")
    n_labels, h, w = volume.dims
    if volume.layout == "ragged":
        if n_planes is None:
            raise InputError(None, "cost_volume: SGM's sums of a ragged volume are refined only "
                                   "(sgm_refine), not returned plane-major")
        if not n_labels <= n_planes <= SGM_MAX_LABELS:
            raise InputError(None, f"label_count: counts up to {n_labels} outside the "
                                   f"{n_planes} labels SGM is built for (at most "
                                   f"{SGM_MAX_LABELS})")
        return n_planes
    if n_labels > SGM_MAX_LABELS:
        raise InputError(None, f"cost_volume: {n_labels} planes, SGM supports at most "
                               f"{SGM_MAX_LABELS}")
    nbytes = 4 * n_labels * h * w
    if nbytes > device.max_alloc_bytes:
        raise DeviceError(f"{device.info.label}: an SGM volume of {nbytes / 2**20:.0f} MiB "
                          f"({n_labels} planes x {h} x {w}) exceeds the largest allocation "
                          f"({device.max_alloc_bytes / 2**20:.0f} MiB): refine smaller tiles")
    return n_labels


@contextlib.contextmanager
def _aggregated(device: Device, mem: DeviceMemory, volume: CostVolume, guide,
                options: MRFOptions, scale: float, n_labels: int):
    """The sum of the SGM path costs over ``options.sgm_paths`` directions of ``volume``, on the
    device, for the length of the block: yields (sizes, the run's buffers: ``agg`` (the sums,
    pixel-major or ragged like the volume), ``count`` and ``offset`` (each pixel's labels and
    where they start, with windows)), all released when the block exits.

    A plane-major volume is first turned pixel-major on the device (its invalid entries, <=
    SATSWEEP_INVALID / 2 or NaN, counting as ``scale``), a host one uploaded for that; a
    pixel-major or ragged device volume is aggregated as it is. P1 = sgm_p1 * scale, P2 =
    sgm_p2 * scale, adapted to the guide as documented in kernels/sgm.cl.
    """
    h, w = volume.shape
    g = _check_guide(guide, (h, w))
    base, count = volume.label_base, volume.label_count
    banded = base is not None
    ragged = volume.layout == "ragged"
    host = {"guide": g, "base": np.zeros(1, np.int32), "count": np.zeros(1, np.int32),
            "offset": np.zeros(1, np.uint64)}
    if banded:  # the kernels read base, count and offset only with windows
        host["base"] = base
        host["count"] = np.full((h, w), n_labels, np.int32) if count is None else count
        host["offset"] = volume.label_offset if ragged else \
            np.arange(h * w, dtype=np.uint64).reshape(h, w) * np.uint64(n_labels)
    source, defines = sgm_program_requests(device, options, n_labels)[0]
    wg, max_lines = defines["SGM_WG"], defines["SGM_LINES"]
    prg = device.build(source, defines)
    queue = device.queue
    convert = volume.layout == "plane_major"
    scan = options.sgm_scan and wg == 1
    sizes = SGMSizes(h=h, w=w, n_labels=n_labels,
                     sum_floats=int(volume.data.size) if ragged else n_labels * h * w,
                     banded=banded)
    n_pix = h * w
    i32, f32 = np.int32, np.float32
    with mem.allocate(sgm_input_buffers(convert=convert), sizes, host=host) as inp:
        if convert:
            # Pixel-major copy of the costs (invalid entries replaced), aggregated in that layout.
            to_pixel_major = device.kernel(prg, "sgm_to_pixel_major")
            if volume.on_device:
                launch(to_pixel_major, queue, (n_pix,), volume.data.data, inp["cost"],
                       i32(n_pix), i32(n_labels), f32(scale))
            else:
                upload = np.ascontiguousarray(volume.data, dtype=np.float32)
                with mem.allocate(SGM_UPLOAD_BUFFERS, sizes, host={"volume": upload}) as up:
                    launch(to_pixel_major, queue, (n_pix,), up["volume"], inp["cost"],
                           i32(n_pix), i32(n_labels), f32(scale))
            cost = inp["cost"]
        else:
            cost = volume.data.data  # the caller's, in SGM's layout already
        with mem.allocate(sgm_sum_buffers(scan=scan), sizes) as sums:
            inv_sigma = 0.0 if options.sgm_p2_sigma == 0.0 else 1.0 / options.sgm_p2_sigma
            bands = (inp["base"], inp["count"], inp["offset"], i32(1 if banded else 0),
                     i32(n_labels))
            if scan:
                # sgm.cl's two raster scans (sgm_scan, its two phases)
                kernel = device.kernel(prg, "sgm_scan")
                for phase in (0, 1):
                    kernel(queue, (2,), (1,), cost, inp["guide"], sums["agg"], sums["scratch"],
                           i32(w), i32(h), f32(options.sgm_p1 * scale),
                           f32(options.sgm_p2 * scale), f32(inv_sigma),
                           i32(options.sgm_paths), i32(phase), *bands)
            else:
                kernel = device.kernel(prg, "sgm_path")
                for i, (dx, dy) in enumerate(SGM_DIRECTIONS[:options.sgm_paths]):
                    n_lines = h if dy == 0 else (w if dx == 0 else w + h - 1)
                    lines = 1 if dy == 0 else max_lines  # scanlines per work-item (1 when wg > 1)
                    kernel(queue, (-(-n_lines // lines) * wg,), (wg,), cost, inp["guide"],
                           sums["agg"], i32(w), i32(h), i32(dx), i32(dy),
                           f32(options.sgm_p1 * scale), f32(options.sgm_p2 * scale),
                           f32(inv_sigma), i32(1 if i > 0 else 0), *bands, i32(lines))
            queue.finish()
            yield sizes, {"agg": sums["agg"], "count": inp["count"], "offset": inp["offset"]}


def sgm_aggregate(device: Device, volume: CostVolume, guide, options: MRFOptions, *,
                  cost_scale: float = 1.0) -> CostVolume:
    """Sum of the SGM path costs over ``options.sgm_paths`` directions, on the device.

    ``volume``: any ``CostVolume`` but a ragged one. Invalid entries of a plane-major volume
    (<= SATSWEEP_INVALID / 2, or NaN) count as ``cost_scale``; a pixel-major one (as
    ``PlaneSweep.cost_volume_on_device`` leaves it) holds valid costs only. P1 = sgm_p1 *
    cost_scale, P2 = sgm_p2 * cost_scale, adapted to the guide as documented in kernels/sgm.cl.
    With label windows (``label_base``), label d of pixel p is plane label_base[p] + d
    (kernels/sgm.cl); a pixel's labels past its ``label_count`` are neither read nor written
    (their sums are undefined). Returns the sums as a plane-major device ``CostVolume`` (L, H,
    W) with the volume's windows; the caller releases it.
    """
    import pyopencl.array as cla  # noqa: PLC0415

    scale = _check_scale(cost_scale)
    n_labels = _sgm_labels(device, volume, None)
    mem = DeviceMemory(device.context)
    queue = device.queue
    with _aggregated(device, mem, volume, guide, options, scale, n_labels) as (sizes, bufs):
        h, w = sizes.h, sizes.w
        prg = device.build(*sgm_program_requests(device, options, n_labels)[0])
        with mem.allocate(SGM_PLANE_MAJOR_BUFFERS, sizes) as out:
            launch(device.kernel(prg, "sgm_to_plane_major"), queue, (h * w,), bufs["agg"],
                   out["sums"], np.int32(h * w), np.int32(n_labels))
            queue.finish()
            sums = cla.Array(queue, (n_labels, h, w), np.float32, data=out.detach("sums"))
    return CostVolume(sums, label_base=volume.label_base, label_count=volume.label_count)


def sgm_refine(device: Device, volume: CostVolume, guide, heights, options: MRFOptions, *,
               cost_scale: float = 1.0, visible=None,
               reject_range_edges: bool = True) -> MRFResult:
    """SGM aggregation (``sgm_aggregate``), then winner-take-all with sub-plane refinement and
    confidence.

    The argmin and the second local minimum are those of the sweep's WTA (wta.cl's closed state
    of the sums: ``wta_pixel_major`` then ``wta_close``); the sub-plane offset is
    ``sgm_subplane``'s fit through the sums of the best plane and its neighbours, and the
    confidence margin is divided by ``sgm_paths * cost_scale`` since each path adds about one
    cost. ``volume``: any ``CostVolume``; with label windows, ``heights`` holds every plane,
    ``visible`` must be 2-D, and the range edges are each pixel's window's (its first and its
    label_count-th label); over a ragged volume (each pixel just its window, as
    ``PlaneSweep.cost_volume_on_device`` leaves a coarse-to-fine volume) SGM is built for every
    plane of ``heights``. See ``MRFResult`` for the outputs.
    """
    import pyopencl as cl  # noqa: PLC0415

    t0 = time.perf_counter()
    scale = _check_scale(cost_scale)
    ragged = isinstance(volume, CostVolume) and volume.layout == "ragged"
    n_labels = _sgm_labels(device, volume, np.size(heights) if ragged else None)
    dims = volume.dims
    hts = _check_heights(heights, dims[0], banded=volume.label_base is not None)
    base, count = _check_windows(volume, hts.size)
    vis = _check_visible(visible, dims)
    if base is not None and vis is not None and vis.ndim == 3:
        raise InputError(None, "visible: with label_base, give one mask per pixel (H, W)")
    mem = DeviceMemory(device.context)
    queue = device.queue
    h, w = dims[1:]
    with _aggregated(device, mem, volume, guide, options, scale, n_labels) as (sizes, bufs):
        prg = device.build("wta", _WTA_PIXEL_MAJOR_DEFINES)
        n_pix, i32 = h * w, np.int32
        counted = i32(1 if base is not None else 0)
        with mem.allocate(SGM_STATE_BUFFERS, sizes) as st:
            launch(device.kernel(prg, "wta_pixel_major"), queue, (-(-n_pix // WTA_VEC),),
                   bufs["agg"], i32(n_pix), i32(n_labels), bufs["count"], bufs["offset"],
                   counted, st["state"])
            launch(device.kernel(prg, "wta_close"), queue, (n_pix,), st["state"], i32(n_pix),
                   i32(n_labels), bufs["count"], counted)
            state = np.empty((WTA_NSTATE, h, w), np.float32)
            cl.enqueue_copy(queue, state, st["state"])
    s = state.astype(np.float64)
    # The winner-take-all of the sums is wta.cl's (its closed state); the sub-plane fit through
    # the best label's sums and the confidence's scale are the MRF's own (mrf.py).
    n_last = n_labels if count is None else count  # labels per pixel
    m1, m1p, m1n, c2 = (s[WTA_SLOT[f]] for f in ("M1", "M1P", "M1N", "M2"))
    i1 = s[WTA_SLOT["I1"]].astype(np.int64)
    fit = _equiangular_offset if options.sgm_subplane == "equiangular" else _parabola_offset
    offset = fit(m1p, m1, m1n, (i1 > 0) & (i1 < n_last - 1))
    conf = (c2 - m1) / (options.sgm_paths * scale)
    return _finish(i1, offset, conf, m1, hts, vis, reject_range_edges,
                   time.perf_counter() - t0, label_base=base, n_labels=n_last)

