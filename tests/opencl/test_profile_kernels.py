"""tools/profile_kernels.py: each kernel's launches counted on the queues it profiles."""

from __future__ import annotations

import numpy as np
import pyopencl as cl

from satsweep.opencl import device as sdev
from tools.profile_kernels import KernelProfile, format_totals

N = 1000  # elements of the self-test kernel's arrays
RUNS = 3  # its launches on the profiled queue


def _scale_add(dev: sdev.Device) -> tuple[object, tuple]:
    """The self-test kernel of ``dev`` and its arguments over N elements."""
    prg = dev.build("selftest", {"SCALE": "2.0f"})
    a = np.arange(N, dtype=np.float32)
    mf = cl.mem_flags
    a_buf = cl.Buffer(dev.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
    out_buf = cl.Buffer(dev.context, mf.WRITE_ONLY, a.nbytes)
    return dev.kernel(prg, "scale_add"), (a_buf, out_buf, np.int32(N))


def test_profile_counts_the_launches_on_profiled_queues(cl_device):
    """RUNS launches on a queue made while the profile is installed are counted, with their
    device time; a launch on a queue made before is not; the results are the kernel's own; and
    pyopencl's classes are given back on leaving."""
    queue_class, call = cl.CommandQueue, cl.Kernel.__call__
    kernel_before, args_before = _scale_add(cl_device)
    with KernelProfile() as profile:
        dev = sdev.Device(cl_device.info)  # its queue is made now: a profiling one
        kernel, args = _scale_add(dev)
        for _ in range(RUNS):
            kernel(dev.queue, (N,), None, *args)
        kernel_before(cl_device.queue, (N,), None, *args_before)
        out = np.empty(N, np.float32)
        cl.enqueue_copy(dev.queue, out, args[1])
        dev.queue.finish()
    cl_device.queue.finish()
    assert cl.CommandQueue is queue_class and cl.Kernel.__call__ is call
    np.testing.assert_array_equal(out, 3.0 * np.arange(N, dtype=np.float32))
    totals = profile.totals()
    assert set(totals) == {"scale_add"}
    seconds, launches = totals["scale_add"]
    assert launches == RUNS
    assert seconds > 0.0
    lines = format_totals(totals)
    assert lines[0].endswith(f"over {RUNS} launches")
    assert "scale_add" in lines[1]
