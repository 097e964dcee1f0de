"""Sweep and MRF refinement of a whole reference view, tile by tile.

The reference is cut into tiles that fit the device budget (``mrf_tile_side``); each tile is
swept with the MRF's overlap, its cost volume refined (on the device for SGM) and its interior
kept. With a coarse-to-fine search a half-resolution pass first gives each block of the
reference a window of planes (``coarse_plane_index``, :mod:`satsweep.dense.coarse`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from satsweep.errors import DeviceError

if TYPE_CHECKING:
    from satsweep.dense.mrf import MRFOptions
    from satsweep.dense.sweep import SweepOptions


# Smallest interior side (pixels) of an MRF tile (below it, overlaps dominate the work).
MIN_MRF_TILE_PX = 64
# Cost volumes budgeted per MRF tile on the device. SGM's buffer tables (satsweep.dense.sgm) hold
# two volume-sized buffers at a time (the pixel-major costs, kept by the sweep or copied, and the
# sums; or, while a host volume is converted, it and its copy), plus per-pixel arrays (guide,
# windows, the WTA state) and the scan's scratch (about 12 / H of a volume): the third volume is
# room for those. A bound rather than a sum of the tables, kept as it was: the MRF tiles, and so
# the results, depend on it.
SGM_DEVICE_VOLUMES = 3


def mrf_tile_side(n_planes: int, mrf: MRFOptions, budget_bytes: int,
                  max_alloc_bytes: int) -> int:
    """Interior side (pixels) of the tiles of ``sweep_refine_tiled``.

    ``mrf.tile_px``, reduced so that the cost volume of one tile with its overlap fits
    ``SGM_DEVICE_VOLUMES`` times in the device budget and once in one device allocation.
    DeviceError when even a ``MIN_MRF_TILE_PX`` tile does not fit.
    """
    per_px = 4 * n_planes
    o = mrf.tile_overlap_px
    fit_budget = math.isqrt(max(budget_bytes // (SGM_DEVICE_VOLUMES * per_px), 0)) - 2 * o
    fit_alloc = math.isqrt(max(max_alloc_bytes // per_px, 0)) - 2 * o
    side = min(mrf.tile_px, fit_budget, fit_alloc)
    if side < MIN_MRF_TILE_PX:
        raise DeviceError(f"the MRF's cost volume of a {MIN_MRF_TILE_PX}-pixel tile with its "
                          f"{o}-pixel overlap over {n_planes} planes does not fit the device "
                          f"budget of {budget_bytes / 2**20:.0f} MiB: raise "
                          "sweep.memory_fraction, or lower mrf.tile_overlap_px or the planes")
    return side


def _source_windows(hom: np.ndarray, tile_shape: tuple[int, int],
                    src_shapes: Sequence[tuple[int, int]]) -> list[tuple[int, int, int, int]]:
    """Per source, the window (x0, y0, x1, y1), end exclusive, that a tile's sweep reads.

    ``hom`` (n_planes, n_src, 3, 3) maps tile pixels to source pixels. Where the denominator is
    positive at the tile's corners, a plane maps the tile onto the convex quadrilateral of its
    corners' images, so the box of every plane's corners, with one pixel more for the bilinear
    neighbours, holds every position the sweep samples; clamped to the source, the window keeps
    each position's validity and sampled value (a position outside the source is outside the
    window on the same side, which then ends at the source's edge). A source whose denominator
    is not positive at some corner gets its whole image.
    """
    th, tw = tile_shape
    corners = np.array([[0.0, tw - 1.0, 0.0, tw - 1.0], [0.0, 0.0, th - 1.0, th - 1.0],
                        [1.0, 1.0, 1.0, 1.0]])
    out = []
    for s, (sh, sw) in enumerate(src_shapes):
        mapped = hom[:, s] @ corners  # (n_planes, 3, 4)
        if not (mapped[:, 2] > 0).all():
            out.append((0, 0, sw, sh))
            continue
        u, v = mapped[:, 0] / mapped[:, 2], mapped[:, 1] / mapped[:, 2]
        x0 = min(max(int(math.floor(u.min())) - 1, 0), sw - 1)
        y0 = min(max(int(math.floor(v.min())) - 1, 0), sh - 1)
        x1 = min(max(int(math.ceil(u.max())) + 2, x0 + 1), sw)
        y1 = min(max(int(math.ceil(v.max())) + 2, y0 + 1), sh)
        out.append((x0, y0, x1, y1))
    return out


def mrf_sweep_options(sweep: SweepOptions, mrf: MRFOptions) -> SweepOptions:
    """The sweep options of a sweep whose cost volume ``mrf`` refines: the guided filter radius
    is the method's own (``mrf.sgm_sweep_gf_radius``, ``mrf.gc_sweep_gf_radius``) when that is
    set; otherwise, and without an MRF, ``sweep`` as is."""
    radius = {"sgm": mrf.sgm_sweep_gf_radius, "graphcut": mrf.gc_sweep_gf_radius}.get(mrf.method)
    return sweep if radius is None else sweep.replace(gf_radius=radius)


def mrf_sweep_wants_wta(sweep: SweepOptions, mrf: MRFOptions) -> bool:
    """Whether the sweep under an MRF runs its own winner-take-all: the graph cut starts from it
    (and the left-right check compares it); SGM needs only the volume."""
    return mrf.method != "sgm" or sweep.lr_check


def sweep_refine_tiled(device, ref_image, src_images: Sequence, homographies, heights,
                       sweep: SweepOptions, mrf: MRFOptions, *,
                       progress: Callable[[int, int], None] | None = None):
    """Plane sweep plus MRF refinement of one reference view, tile by tile.

    The reference is cut into tiles of interior side ``mrf_tile_side``; each tile is swept with
    ``mrf.tile_overlap_px`` more pixels on every side (homographies composed with the tile's
    offset), its filtered cost volume refined by ``mrf.method`` (for SGM the volume never leaves
    the device), and its interior kept. So host and device hold one tile's cost volume at a
    time (and, with several tiles, only the windows of the sources that the tile reads), and a
    reference that fits one tile gives exactly the untiled result. The images are
    prefiltered once, whole (the MRF's guide is the reference as given); the left-right check
    (``sweep.lr_check``) runs once on the assembled winner-take-all map, as the untiled sweep
    does. The sweep runs with ``mrf_sweep_options(sweep, mrf)``. With ``sweep.search =
    "coarse_to_fine"`` and SGM, the reference is first swept and refined at half resolution
    (``coarse_plane_index``) and each tile then sweeps plane windows (``satsweep.dense.coarse``).
    ``progress(done, total)`` is called after each tile. Returns (HeightMap whose split counts
    the MRF tiles, MRF seconds).
    """
    from satsweep.dense.coarse import plane_windows  # noqa: PLC0415
    from satsweep.dense.mrf import refine  # noqa: PLC0415
    from satsweep.dense.planes import visible_at
    from satsweep.dense.sweep import HeightMap, PlaneSweep, WorkSplit, prefilter, tile_grid

    ref = guide = np.ascontiguousarray(ref_image, dtype=np.float32)
    srcs = raw_srcs = [np.ascontiguousarray(s, dtype=np.float32) for s in src_images]
    if sweep.prefilter_sigma_px > 0:
        ref = prefilter(ref, sweep.prefilter_sigma_px)
        srcs = [prefilter(s, sweep.prefilter_sigma_px) for s in srcs]
    hom = np.asarray(homographies, dtype=np.float64)
    hts = np.asarray(heights, dtype=np.float64)
    engine = PlaneSweep(device, mrf_sweep_options(sweep, mrf).replace(lr_check=False,
                                                                      prefilter_sigma_px=0.0))
    h_img, w_img = ref.shape
    # SGM runs on the device: the tile's volume stays there. The graph cut runs on the host.
    on_device = mrf.method == "sgm"
    with_wta = mrf_sweep_wants_wta(sweep, mrf)
    # From the images as given: the coarse pass prefilters its own half-resolution images.
    coarse, seconds = coarse_plane_index(device, guide, raw_srcs, hom, hts, sweep, mrf)
    side = mrf_tile_side(hts.size, mrf, engine.budget_bytes(), device.max_alloc_bytes)
    height = np.full((h_img, w_img), np.nan)
    plane_index = np.zeros((h_img, w_img), np.float32)
    confidence = np.zeros((h_img, w_img), np.float32)
    cost_min = np.zeros((h_img, w_img), np.float32)
    valid = np.zeros((h_img, w_img), bool)
    if with_wta:  # the sweep's winner-take-all map, for the left-right check
        wta_index = np.zeros((h_img, w_img), np.float32)
        wta_valid = np.zeros((h_img, w_img), bool)
    n_tiles, peak, window_planes = 0, 0, 0
    swept = total = 0  # pixel-planes swept, and of the whole search, over the tiles
    tiles = list(tile_grid(w_img, h_img, side, side, mrf.tile_overlap_px))
    for x0, y0, x1, y1, tx0, ty0, tx1, ty1 in tiles:
        shift = np.array([[1.0, 0.0, tx0], [0.0, 1.0, ty0], [0.0, 0.0, 1.0]])
        tile_hom = hom @ shift
        tile_srcs = srcs
        if len(tiles) > 1:
            # Upload only the part of each source the tile reads, not whole images per tile.
            windows = _source_windows(tile_hom, (ty1 - ty0, tx1 - tx0), [a.shape for a in srcs])
            tile_srcs = [a[wy0:wy1, wx0:wx1] for a, (wx0, wy0, wx1, wy1) in zip(srcs, windows)]
            back = np.array([[[1.0, 0.0, -wx0], [0.0, 1.0, -wy0], [0.0, 0.0, 1.0]]
                             for wx0, wy0, _, _ in windows])
            tile_hom = back[None] @ tile_hom
        planes = None  # this tile's plane windows (coarse-to-fine), else every plane
        if coarse is not None:
            planes = plane_windows(coarse[ty0:ty1, tx0:tx1], hts.size,
                                   block=sweep.window_block_px, halo=sweep.window_halo_px,
                                   margin=sweep.window_margin_planes,
                                   max_fraction=sweep.window_max_fraction,
                                   pixel_fallback=sweep.window_pixel_fallback,
                                   bands=sweep.window_bands,
                                   band_halo=sweep.window_band_halo_px)
        tile_ref, r = ref[ty0:ty1, tx0:tx1], None
        if with_wta:
            r, volume = engine.height_map_with_cost_volume(tile_ref, tile_srcs, tile_hom, hts,
                                                           windows=planes, on_device=on_device)
        elif on_device:
            volume = engine.cost_volume_on_device(tile_ref, tile_srcs, tile_hom, hts,
                                                  windows=planes)
        else:
            volume = engine.cost_volume(tile_ref, tile_srcs, tile_hom, hts, windows=planes)
        window_planes = max(window_planes, hts.size if planes is None else planes.n_planes)
        tile_px = (ty1 - ty0) * (tx1 - tx0)
        total += tile_px * hts.size
        # (the planes swept, of every other row and column of the tile: windows of one pixel
        # change little from pixel to pixel, and every pixel's band set costs a tenth of a
        # second per Mpx to count)
        swept += tile_px * hts.size if planes is None \
            else float(planes.swept((ty1 - ty0, tx1 - tx0), step=2).mean()) * tile_px
        initial = None if not with_wta else \
            np.clip(np.rint(r.plane_index), 0, hts.size - 1).astype(np.int32)
        with volume:  # a device volume is freed here
            m = refine(device, volume, guide[ty0:ty1, tx0:tx1], hts, mrf,
                       cost_scale=float(sweep.census_bits),
                       reject_range_edges=sweep.reject_range_edges, initial_labels=initial)
        keep = (slice(y0 - ty0, y1 - ty0), slice(x0 - tx0, x1 - tx0))
        out = (slice(y0, y1), slice(x0, x1))
        # Pixels that no source sees at the chosen plane are invalid.
        seen = visible_at(tile_hom, m.labels, [a.shape for a in tile_srcs])
        valid[out] = m.valid[keep] & seen[keep]
        if with_wta:
            wta_index[out], wta_valid[out] = r.plane_index[keep], r.valid[keep]
        height[out] = m.height[keep]
        plane_index[out] = m.plane_index[keep]
        confidence[out] = m.confidence[keep]
        cost_min[out] = m.cost_min[keep]
        n_tiles += 1
        peak = max(peak, engine.last_split.peak_device_bytes)
        seconds += m.seconds
        if progress is not None:
            progress(n_tiles, len(tiles))
    if sweep.lr_check:
        valid &= engine.lr_mask(wta_index, wta_valid, ref, srcs, hom, hts)
    height[~valid] = np.nan
    split = WorkSplit(n_tiles=n_tiles, peak_device_bytes=peak,
                      window_planes=window_planes if coarse is not None else None,
                      window_share=swept / total if coarse is not None else None)
    return HeightMap(height=height, plane_index=plane_index, confidence=confidence, valid=valid,
                     cost_min=cost_min, split=split), seconds


def coarse_pass_planes(sweep: SweepOptions, mrf: MRFOptions, shape: tuple[int, int],
                       n_planes: int) -> int:
    """The planes of the coarse pass that ``sweep_refine_tiled`` runs before sweeping a
    reference of ``shape`` over ``n_planes`` planes (every ``sweep.coarse_plane_stride``-th
    plane), or 0 where it runs none: only a coarse-to-fine search under SGM without the
    left-right check has one, and only where the reference gains from it
    (``coarse.worth_a_coarse_pass``)."""
    from satsweep.dense.coarse import worth_a_coarse_pass  # noqa: PLC0415

    if sweep.search != "coarse_to_fine" or mrf.method != "sgm" or sweep.lr_check \
            or not worth_a_coarse_pass(shape, n_planes):
        return 0
    return len(range(0, n_planes, sweep.coarse_plane_stride))


def coarse_plane_index(device, ref_image, src_images: Sequence, homographies, heights,
                       sweep: SweepOptions, mrf: MRFOptions) -> tuple[np.ndarray | None, float]:
    """The coarse pass of a coarse-to-fine sweep: the images at half resolution
    (``coarse.downsample2``) swept over every ``sweep.coarse_plane_stride``-th plane and refined
    by ``mrf`` (a full search, tiled as ``sweep_refine_tiled`` tiles), as a map of
    full-resolution plane indices (NaN where invalid) over the reference's pixels. Returns
    (None, 0) where ``coarse_pass_planes`` says there is no coarse pass (another search or MRF,
    or a reference too small or with too few planes to gain); else (map, MRF seconds).
    """
    from satsweep.dense.coarse import downsample2, half_resolution_homographies, upsample_index

    hts = np.asarray(heights, dtype=np.float64)
    shape = np.shape(ref_image)
    if not coarse_pass_planes(sweep, mrf, shape, hts.size):
        return None, 0.0
    stride = sweep.coarse_plane_stride
    planes = slice(0, hts.size, stride)  # coarse_pass_planes counts these
    half, seconds = sweep_refine_tiled(
        device, downsample2(ref_image), [downsample2(s) for s in src_images],
        half_resolution_homographies(np.asarray(homographies)[planes]), hts[planes],
        sweep.replace(search="full"), mrf)
    index = np.where(half.valid, float(stride) * half.plane_index, np.nan)
    return upsample_index(index, shape), seconds
