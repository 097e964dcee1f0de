"""The heap policy of the ``satsweep`` command (the process, not the library).

A reconstruction allocates and frees buffers of hundreds of megabytes again and again: every
cost-volume tile, the per-reference volumes that SGM aggregates (on PoCL, OpenCL buffers are
host memory) and the DSM stage's point arrays. glibc serves each allocation above at most
32 MiB with fresh pages from ``mmap`` and gives them back on ``free``, so every such buffer pays
one page fault per 4 KiB page when it is first written: about 650,000 faults and 2.5-2.7 s of
system time in one ``satsweep reconstruct`` of the Pleiades pair. ``keep_freed_memory`` asks
glibc (``mallopt``) to serve large allocations from its heap and to keep what is freed there, so
that later buffers reuse pages already mapped: about 310,000 faults and 1.1-1.3 s of system
time, and the command 0.5 s shorter (10.35-11.03 s -> 9.85-10.57 s in 3 interleaved pairs of
runs on 2 cores). The cost is that the process keeps its
peak memory until it exits, which suits a command that runs one job; a library user's process
is left alone. ``SATSWEEP_KEEP_HEAP=0`` turns it off; on other C libraries it does nothing.
"""

from __future__ import annotations

import ctypes
import os

# mallopt parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
# Free memory at the top of the heap is given back to the system only above this (bytes).
_TRIM_THRESHOLD_BYTES = (1 << 31) - 1
# The environment variable that turns the policy off when set to "0".
ENV_SWITCH = "SATSWEEP_KEEP_HEAP"


def _is_glibc() -> bool:
    try:
        return os.confstr("CS_GNU_LIBC_VERSION").startswith("glibc")
    except (AttributeError, ValueError, OSError):
        return False


def keep_freed_memory() -> bool:
    """Serve large allocations from the heap and keep freed memory mapped (glibc only).

    Returns whether the policy is in effect: False when ``SATSWEEP_KEEP_HEAP=0``, when the C
    library is not glibc, or when glibc refuses a setting.
    """
    if os.environ.get(ENV_SWITCH, "1").strip() == "0" or not _is_glibc():
        return False
    mallopt = getattr(ctypes.CDLL(None), "mallopt", None)
    if mallopt is None:
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD_BYTES))
