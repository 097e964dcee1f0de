"""Buffer tables (satsweep/opencl/buffers.py): sizes, allocation, release on every exit."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest

from satsweep.opencl.buffers import (
    MIN_BUFFER_BYTES,
    BufferSpec,
    DeviceMemory,
    largest_bytes,
    total_bytes,
)

SPECS = (BufferSpec("cost", np.float32, lambda n: 3 * n),
         BufferSpec("codes", np.uint64, lambda n: n),
         BufferSpec("seen", np.uint8, lambda n: 0))


def test_sizes_follow_the_table():
    assert [s.nbytes(10) for s in SPECS] == [120, 80, MIN_BUFFER_BYTES]
    assert total_bytes(SPECS, 10) == 120 + 80 + MIN_BUFFER_BYTES
    assert largest_bytes(SPECS, 10) == 120 and largest_bytes((), 10) == 0


class _FakeBuffer:
    """Stands in for pyopencl.Buffer: records its size, contents and release."""

    made: list[_FakeBuffer] = []

    def __init__(self, context, flags, size=0, hostbuf=None):
        self.size = size if hostbuf is None else hostbuf.nbytes
        self.data = None if hostbuf is None else hostbuf.copy()
        self.released = False
        _FakeBuffer.made.append(self)

    def release(self):
        assert not self.released, "released twice"
        self.released = True


def test_every_buffer_is_released_on_any_exit_but_the_detached(monkeypatch):
    monkeypatch.setattr(cl, "Buffer", _FakeBuffer)
    _FakeBuffer.made = []
    mem = DeviceMemory(context=None)
    with pytest.raises(RuntimeError, match="kernel failed"):
        with mem.allocate(SPECS, 10, host={"cost": np.arange(30, dtype=np.float32)}) as bufs:
            assert set(bufs) == {"cost", "codes", "seen"}
            np.testing.assert_array_equal(bufs["cost"].data, np.arange(30))
            assert mem.live == mem.peak == total_bytes(SPECS, 10)
            raise RuntimeError("kernel failed")
    assert all(b.released for b in _FakeBuffer.made) and len(_FakeBuffer.made) == 3
    assert mem.live == 0 and mem.peak == total_bytes(SPECS, 10)
    with mem.allocate(SPECS[:1], 4) as bufs:
        kept = bufs.detach("cost")
        with mem.allocate(SPECS[1:], 4):
            pass
    assert not kept.released and all(b.released for b in _FakeBuffer.made if b is not kept)
    assert mem.live == SPECS[0].nbytes(4)  # still held, by the caller now


def test_host_data_must_match_the_table(monkeypatch):
    monkeypatch.setattr(cl, "Buffer", _FakeBuffer)
    _FakeBuffer.made = []
    mem = DeviceMemory(context=None)
    with pytest.raises(ValueError, match="cost: 40 bytes, the table says 120"):
        with mem.allocate(SPECS, 10, host={"cost": np.zeros(10, np.float32)}):
            pass
    with pytest.raises(ValueError, match="not in the table"):
        with mem.allocate(SPECS, 10, host={"other": np.zeros(10, np.float32)}):
            pass
    assert all(b.released for b in _FakeBuffer.made) and mem.live == 0


def test_buffers_on_a_device(cl_device):
    mem = DeviceMemory(cl_device.context)
    data = np.arange(30, dtype=np.float32)
    with mem.allocate(SPECS, 10, host={"cost": data}) as bufs:
        out = np.empty_like(data)
        cl.enqueue_copy(cl_device.queue, out, bufs["cost"])
        np.testing.assert_array_equal(out, data)
        assert bufs["codes"].size == 80 and bufs["seen"].size == MIN_BUFFER_BYTES
    assert mem.live == 0
