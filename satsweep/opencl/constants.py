"""Constants that the host and the kernels share: the one source of each.

``Device.build`` passes every entry of ``SHARED_DEFINES`` to every kernel build as a ``-D``
definition, and ``kernels/common.h`` refuses to compile without them (``#ifndef X #error``): the
``.cl`` files keep no copy of their own. Host code imports them from here. A build's own
``defines`` may not redefine them (``Device.build`` raises ``KernelBuildError``).

Values are Python numbers; ``Device.build`` writes floats as float32 literals (``3e+38f``), so
the kernels see each float rounded to float32 once, as the host's ``np.float32(X)`` is.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Mapping

# Marker of an invalid float result (height, cost) on the device: costs at or below half of it
# are missing (sgm.cl, satsweep.dense.mrf). A number rather than NaN on purpose, so that
# comparisons behave the same on every device, PoCL with fast-math included.
SATSWEEP_INVALID = -1.0e30

# -- winner-take-all (wta.cl) -------------------------------------------------------------------
# The streaming winner-take-all's "infinite" cost: above any cost, finite in float32.
WTA_BIG = 3.0e38
# The fields of a pixel's winner-take-all state, in the order of their slots: the state of n
# pixels is WTA_NSTATE rows of n floats, field f of pixel k at state[f n + k] (wta.cl documents
# each field). M1 best local-minimum cost, I1 its plane, M1P / M1N the costs of the planes
# before / after it, M2 the second-lowest local minimum, PREV / PREV2 the costs of the last two
# planes seen, MAX the largest cost seen.
WTA_STATE_FIELDS: tuple[str, ...] = ("M1", "I1", "M1P", "M1N", "M2", "PREV", "PREV2", "MAX")
WTA_NSTATE = len(WTA_STATE_FIELDS)
# Slot of each field (the kernels' WTA_S_<FIELD>).
WTA_SLOT: Mapping[str, int] = MappingProxyType({f: i for i, f in enumerate(WTA_STATE_FIELDS)})

# -- vector widths: the kernels' OpenCL vector types (float8) fix them at 8 ---------------------
# Positions per work-item of sweep.cl's split kernels, sweep_warp and sweep_warped_cost.
SWEEP_VEC = 8
# Pixels per work-item of wta.cl's wta_update and wta_pixel_major.
WTA_VEC = 8
# Columns per work-item of guided_filter.cl's column kernels.
GF_COLS_VEC = 8
# Planes per bit of the band sets of sweep.cl's split kernels (satsweep.dense.sweep.group_bands).
SWEEP_BAND_PLANES = 4

# -- semi-global matching (sgm.cl) --------------------------------------------------------------
# Most labels (planes) of an SGM volume: sgm_path's work-group form keeps one float per label in
# local memory.
SGM_MAX_LABELS = 1024
# +inf guard entries on each side of a step in sgm_scan's scratch (its size:
# satsweep.dense.sgm.sgm_scan_scratch_floats).
SGM_SCAN_GUARD = 8

# Every constant above that the kernels read, by the name they read it under.
SHARED_DEFINES: Mapping[str, object] = MappingProxyType({
    "SATSWEEP_INVALID": SATSWEEP_INVALID,
    "WTA_BIG": WTA_BIG,
    "WTA_NSTATE": WTA_NSTATE,
    **{f"WTA_S_{field}": slot for field, slot in WTA_SLOT.items()},
    "SWEEP_VEC": SWEEP_VEC,
    "WTA_VEC": WTA_VEC,
    "GF_COLS_VEC": GF_COLS_VEC,
    "SWEEP_BAND_PLANES": SWEEP_BAND_PLANES,
    "SGM_MAX_LABELS": SGM_MAX_LABELS,
    "SGM_SCAN_GUARD": SGM_SCAN_GUARD,
})
