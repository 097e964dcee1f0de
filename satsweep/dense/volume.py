"""The cost volume of a plane sweep: one type, whichever its place and layout.

A ``CostVolume`` holds, for every pixel p of the reference (H x W) and each of its labels d, the
filtered matching cost of p on the plane that the label stands for: plane ``label_base[p] + d``,
or plane d where there is no base. Lower is better; the units and the other conventions are
those of :mod:`satsweep.dense.mrf`. The sweep makes it (``PlaneSweep.cost_volume``,
``PlaneSweep.cost_volume_on_device``) and the MRF refinements take it (``mrf.refine``).

Its ``data`` is on the host (a numpy array) or on the device (a ``pyopencl.array.Array``,
float32, C-contiguous, without offset; the volume owns it: ``release()``, or a ``with`` block,
frees it), in one of three layouts:

- ``plane_major``: (L, H, W), ``data[d, y, x]``: a host volume of the sweep, the layout the graph
  cut takes. Entries at or below ``SATSWEEP_INVALID / 2``, and NaN, are missing costs.
- ``pixel_major``: (H, W, L), the labels of a pixel contiguous: the layout SGM aggregates in,
  in which the sweep leaves a volume on the device. Every entry is a cost.
- ``ragged``: 1-D, pixel p's ``label_count[p]`` labels from ``data[label_offset[p]]`` on: the
  device volume of a coarse-to-fine sweep whose blocks have windows of their own lengths, each
  pixel holding just its window.

L (``n_labels``) is the labels per pixel: the volume's third axis, or the largest count of a
ragged volume. ``label_base`` ((H, W) integers >= 0, optional) gives each pixel's window of planes
(a coarse-to-fine search); ``label_count`` ((H, W) integers in 1..L, needs a base) says that pixel
p has only labels d < label_count[p] (where a host volume has more, they hold the worst cost; a
device volume's are neither read nor written); ``label_offset`` ((H, W) uint64, in floats) is the
ragged layout's, which needs all three.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from satsweep.errors import InputError

Layout = Literal["plane_major", "pixel_major", "ragged"]


def _device_array_type():
    import pyopencl.array as cla  # noqa: PLC0415  (importing satsweep needs no OpenCL ICD)

    return cla.Array


@dataclasses.dataclass(eq=False)
class CostVolume:
    """A cost volume (see the module docstring); checked on construction (InputError)."""

    data: object  # numpy.ndarray (host, plane_major) or pyopencl.array.Array (device)
    layout: Layout = "plane_major"
    label_base: np.ndarray | None = None  # (H, W) int32: the plane of each pixel's label 0
    label_count: np.ndarray | None = None  # (H, W) int32: labels of each pixel (None: all L)
    label_offset: np.ndarray | None = None  # (H, W) uint64: ragged layout, where labels start

    def __post_init__(self):
        data = self.data
        if self.layout not in ("plane_major", "pixel_major", "ragged"):
            raise InputError(None, f"cost volume: layout {self.layout!r} is not plane_major, "
                                   "pixel_major or ragged")
        if isinstance(data, np.ndarray):
            if self.layout != "plane_major":
                raise InputError(None, f"cost volume: a host volume is plane-major (L, H, W), "
                                       f"not {self.layout}")
            if not np.issubdtype(data.dtype, np.floating):
                raise InputError(None, f"cost volume: expected floats, got dtype {data.dtype}")
        elif isinstance(data, _device_array_type()):
            if data.dtype != np.float32 or not data.flags.c_contiguous or data.offset != 0:
                raise InputError(None, f"cost volume: a device volume must be a C-contiguous "
                                       f"float32 pyopencl Array without offset (a copy, not a "
                                       f"view), got {data.dtype} {data.shape}")
        else:
            raise InputError(None, f"cost volume: data must be a numpy array or a pyopencl "
                                   f"Array, got {type(data).__name__}")
        want_ndim = 1 if self.layout == "ragged" else 3
        if len(data.shape) != want_ndim or min(data.shape) < 1:
            axes = {"plane_major": "(L, H, W)", "pixel_major": "(H, W, L)", "ragged": "(floats,)"}
            raise InputError(None, f"cost volume: a {self.layout} volume is {axes[self.layout]}, "
                                   f"got shape {tuple(data.shape)}")
        if self.layout == "ragged":
            if self.label_base is None or self.label_count is None or self.label_offset is None:
                raise InputError(None, "cost volume: a ragged volume needs label_base, "
                                       "label_count and label_offset")
            shape = np.shape(self.label_count)
        else:
            if self.label_offset is not None:
                raise InputError(None, f"label_offset: only a ragged volume has one, not a "
                                       f"{self.layout} one")
            shape = tuple(data.shape[1:]) if self.layout == "plane_major" \
                else tuple(data.shape[:2])
        if self.label_base is None:
            if self.label_count is not None:
                raise InputError(None, "label_count: needs label_base (the windows' first planes)")
            return
        self.label_base = _per_pixel("label_base", self.label_base, shape, np.int32)
        if self.label_base.size and self.label_base.min() < 0:
            raise InputError(None, "label_base: planes must be >= 0")
        if self.label_count is not None:
            self.label_count = _per_pixel("label_count", self.label_count, shape, np.int32)
            n = self.label_count
            top = int(n.max()) if self.layout == "ragged" else self.dims[0]
            if n.size and (n.min() < 1 or n.max() > top):
                raise InputError(None, f"label_count: counts {n.min()}..{n.max()} outside 1.."
                                       f"{top} (the volume's labels per pixel)")
        if self.layout == "ragged":
            o = np.asarray(self.label_offset)
            if o.shape != shape or o.dtype != np.uint64:
                raise InputError(None, f"label_offset: expected uint64 of the label counts' "
                                       f"shape {shape}, got {o.dtype} {o.shape}")
            self.label_offset = np.ascontiguousarray(o)
            end = int((o + self.label_count.astype(np.uint64)).max())
            if end > data.size:
                raise InputError(None, f"label_offset: pixels' labels reach float {end}, past "
                                       f"the volume's {data.size}")

    @property
    def on_device(self) -> bool:
        """Whether the data is a device array (else a numpy array)."""
        return not isinstance(self.data, np.ndarray)

    @property
    def dims(self) -> tuple[int, int, int]:
        """(L, H, W): labels per pixel (the largest count of a ragged volume), height, width."""
        if self.layout == "plane_major":
            return tuple(int(s) for s in self.data.shape)  # type: ignore[return-value]
        if self.layout == "pixel_major":
            h, w, n = (int(s) for s in self.data.shape)
            return n, h, w
        h, w = self.label_count.shape
        return int(self.label_count.max()), h, w

    @property
    def n_labels(self) -> int:
        return self.dims[0]

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the reference."""
        return self.dims[1:]

    def release(self) -> None:
        """Free a device volume's memory now (nothing for a host volume); the volume is unusable
        after."""
        if self.on_device:
            self.data.data.release()

    def __enter__(self) -> CostVolume:
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _per_pixel(name: str, values, shape: tuple[int, ...], dtype) -> np.ndarray:
    a = np.asarray(values)
    if a.shape != shape or not np.issubdtype(a.dtype, np.integer):
        raise InputError(None, f"{name}: expected integers of shape {shape}, got "
                               f"{a.dtype} {a.shape}")
    return np.ascontiguousarray(a, dtype=dtype)
