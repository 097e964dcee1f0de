"""Device buffers described once, in a table that both plans the memory and allocates it.

A ``BufferSpec`` is one device buffer: its name, which is the name of the kernel argument it is
passed as; its element type; and its number of elements as a function of the sizes of one unit
of work (a tile of the sweep, an SGM volume: any object the stage defines). A stage lists the
buffers of a unit of work as a tuple of specs; its memory planner sums ``total_bytes(specs,
sizes)`` (and compares ``largest_bytes`` with the device's largest allocation), and
``DeviceMemory.allocate(specs, sizes)`` creates exactly those buffers, for the length of a
``with`` block: every one of them is released when the block exits, normally or by an exception,
except those the block hands on with ``BufferSet.detach``. ``DeviceMemory`` keeps the running and
the peak total of the bytes its buffers hold.
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

# OpenCL refuses zero-byte buffers: a buffer of no elements (a placeholder argument that the
# kernel does not read) takes this many bytes, in the plan as on the device.
MIN_BUFFER_BYTES = 4


@dataclasses.dataclass(frozen=True)
class BufferSpec:
    """One device buffer: ``name`` (the kernel argument it is passed as), ``dtype``, and
    ``elements(sizes)``, its length in elements for the sizes of a unit of work."""

    name: str
    dtype: Any  # a numpy scalar type (np.float32, np.uint64, ...)
    elements: Callable[[Any], int]

    def nbytes(self, sizes) -> int:
        """Bytes of the buffer for ``sizes`` (at least MIN_BUFFER_BYTES)."""
        return max(np.dtype(self.dtype).itemsize * int(self.elements(sizes)), MIN_BUFFER_BYTES)


def total_bytes(specs: Sequence[BufferSpec], sizes) -> int:
    """Bytes of all the buffers of ``specs`` for ``sizes``."""
    return sum(spec.nbytes(sizes) for spec in specs)


def largest_bytes(specs: Sequence[BufferSpec], sizes) -> int:
    """Bytes of the largest buffer of ``specs`` for ``sizes`` (0 for none)."""
    return max((spec.nbytes(sizes) for spec in specs), default=0)


class BufferSet(Mapping[str, Any]):
    """The buffers of one ``DeviceMemory.allocate`` block, by name (``bufs["cost"]``)."""

    def __init__(self):
        self._buffers: dict[str, Any] = {}
        self._detached: set[str] = set()

    def __getitem__(self, name: str):
        return self._buffers[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._buffers)

    def __len__(self) -> int:
        return len(self._buffers)

    def detach(self, name: str):
        """The buffer ``name``, which the block's end will not release: the caller owns it (and
        releases it, e.g. through the ``pyopencl.array.Array`` it wraps)."""
        self._detached.add(name)
        return self._buffers[name]


class DeviceMemory:
    """Allocates buffer tables in one OpenCL context and accounts for the bytes they hold.

    ``live`` counts the bytes of the buffers allocated and not yet released (a detached buffer
    stays counted: it is still held), ``peak`` the most ``live`` has been.
    """

    def __init__(self, context):
        self.context = context
        self.live = 0
        self.peak = 0

    @contextlib.contextmanager
    def allocate(self, specs: Sequence[BufferSpec], sizes,
                 host: Mapping[str, np.ndarray] | None = None) -> Iterator[BufferSet]:
        """The buffers of ``specs`` for ``sizes`` for the length of the block, released when it
        exits however it exits (those detached excepted). ``host`` gives the initial contents
        of some buffers by name (uploaded on creation), each exactly the buffer's size; the
        others are uninitialised."""
        import pyopencl as cl  # noqa: PLC0415

        host = dict(host or {})
        unknown = set(host) - {spec.name for spec in specs}
        if unknown:
            raise ValueError(f"host data for buffers not in the table: {sorted(unknown)}")
        bufs = BufferSet()
        sizes_of: dict[str, int] = {}
        mf = cl.mem_flags
        try:
            for spec in specs:
                nbytes = spec.nbytes(sizes)
                data = host.get(spec.name)
                if data is None:
                    buf = cl.Buffer(self.context, mf.READ_WRITE, nbytes)
                else:
                    data = np.ascontiguousarray(data, dtype=spec.dtype)
                    if max(data.nbytes, MIN_BUFFER_BYTES) != nbytes:
                        raise ValueError(f"host data for buffer {spec.name}: {data.nbytes} bytes, "
                                         f"the table says {nbytes}")
                    buf = cl.Buffer(self.context, mf.READ_WRITE | mf.COPY_HOST_PTR,
                                    hostbuf=data)
                bufs._buffers[spec.name] = buf
                sizes_of[spec.name] = nbytes
                self.live += nbytes
                self.peak = max(self.peak, self.live)
            yield bufs
        finally:
            for name, buf in bufs._buffers.items():
                if name not in bufs._detached:
                    buf.release()
                    self.live -= sizes_of[name]
