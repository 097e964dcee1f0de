"""The OpenCL device layer: the one place that lists devices, creates contexts and queues, and
builds kernels.

- ``list_devices()`` enumerates every platform/device and, by default, proves that each one can
  build and run a trivial kernel (some installs list a platform that compiles nothing).
- ``select_device(spec)`` resolves ``auto`` | ``cpu`` | ``gpu`` | ``PLATFORM:DEVICE`` (indices, as
  ``satsweep devices`` prints them); ``None`` reads ``SATSWEEP_DEVICE`` and falls back to ``auto``.
  ``auto`` prefers a GPU. A requested device that is missing is a ``DeviceError`` listing what
  exists: there is never a silent fallback to another device.
- ``Device`` holds a context and an in-order queue and builds programs from ``kernels/`` with the
  folder on the include path and compile-time constants as ``-D`` options: each build's own
  sizes and switches, plus the constants that the host and every kernel share
  (``satsweep.opencl.constants.SHARED_DEFINES``, which a build may not redefine). pyopencl's
  binary cache is used, so a second build of the same source and options is fast (though not
  free: 40-100 ms per program on PoCL). ``Device.prebuild`` builds programs that a run will
  need in a background thread while the host does other work; ``Device.build`` then waits for
  them.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import os
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from satsweep.errors import DeviceError, KernelBuildError
from satsweep.opencl.constants import SHARED_DEFINES

ENV_VAR = "SATSWEEP_DEVICE"


def _cl():
    try:
        import pyopencl as cl  # noqa: PLC0415  (imported lazily: importing satsweep needs no ICD)
    except ImportError as exc:  # pragma: no cover - pyopencl is a hard dependency
        raise DeviceError(f"pyopencl cannot be imported: {exc}") from None
    return cl


def kernel_dir() -> Path:
    """The folder holding the ``.cl`` sources and ``common.h`` (inside the installed package)."""
    return Path(str(importlib.resources.files("satsweep.kernels")))


@dataclasses.dataclass(frozen=True)
class DeviceInfo:
    """One OpenCL device as found on this machine."""

    platform_index: int
    device_index: int
    platform_name: str
    device_name: str
    kind: str  # "gpu", "cpu" or "other"
    global_mem_bytes: int
    max_alloc_bytes: int
    compute_units: int
    can_build: bool | None  # None: not checked
    build_error: str | None = None

    @property
    def spec(self) -> str:
        """The PLATFORM:DEVICE spec that selects this device."""
        return f"{self.platform_index}:{self.device_index}"

    @property
    def label(self) -> str:
        return f"{self.spec} {self.platform_name} / {self.device_name} ({self.kind})"

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["spec"] = self.spec
        return d


def _kind(cl, dev) -> str:
    t = dev.type
    if t & cl.device_type.GPU:
        return "gpu"
    if t & cl.device_type.CPU:
        return "cpu"
    return "other"


def _selftest(cl, dev) -> str | None:
    """Build and run selftest.cl on ``dev``; return None on success, else the reason."""
    try:
        ctx = cl.Context([dev])
        queue = cl.CommandQueue(ctx)
        src = (kernel_dir() / "selftest.cl").read_text()
        prg = cl.Program(ctx, src).build(options=_options({"SCALE": 2.0}))
        n = 37
        a = np.arange(n, dtype=np.float32)
        mf = cl.mem_flags
        a_buf = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
        out_buf = cl.Buffer(ctx, mf.WRITE_ONLY, a.nbytes)
        prg.scale_add(queue, (64,), None, a_buf, out_buf, np.int32(n))
        out = np.empty_like(a)
        cl.enqueue_copy(queue, out, out_buf)
        queue.finish()
        if not np.array_equal(out, 2.0 * a + np.arange(n, dtype=np.float32)):
            return "self-test kernel ran but returned wrong values"
        return None
    except Exception as exc:  # any failure means the device is not usable
        first = str(exc).strip().splitlines()
        return f"{type(exc).__name__}: {first[0] if first else ''}"[:300]


_LIST_CACHE: dict[bool, list[DeviceInfo]] = {}
_LIST_LOCK = threading.Lock()


def list_devices(check_build: bool = True) -> list[DeviceInfo]:
    """Every OpenCL device on this machine; with ``check_build`` each is proven to build a kernel.

    The result is cached for the process (devices do not appear while it runs).
    """
    with _LIST_LOCK:
        if check_build in _LIST_CACHE:
            return list(_LIST_CACHE[check_build])
        cl = _cl()
        try:
            platforms = cl.get_platforms()
        except cl.Error:
            platforms = []  # no ICD installed: an empty list, reported by the caller
        out: list[DeviceInfo] = []
        for pi, plat in enumerate(platforms):
            try:
                devices = plat.get_devices()
            except cl.Error:
                devices = []
            for di, dev in enumerate(devices):
                err = _selftest(cl, dev) if check_build else None
                out.append(
                    DeviceInfo(
                        platform_index=pi,
                        device_index=di,
                        platform_name=plat.name.strip(),
                        device_name=dev.name.strip(),
                        kind=_kind(cl, dev),
                        global_mem_bytes=int(dev.global_mem_size),
                        max_alloc_bytes=int(dev.max_mem_alloc_size),
                        compute_units=int(dev.max_compute_units),
                        can_build=(err is None) if check_build else None,
                        build_error=err,
                    )
                )
        _LIST_CACHE[check_build] = out
        return list(out)


def _describe(devices: list[DeviceInfo]) -> str:
    if not devices:
        return "no OpenCL device found (install an ICD: on Debian, apt-get install pocl-opencl-icd)"
    parts = []
    for d in devices:
        state = "" if d.can_build in (True, None) else f" [cannot build kernels: {d.build_error}]"
        parts.append(d.label + state)
    return "available: " + "; ".join(parts)


def select_device(spec: str | None = None) -> DeviceInfo:
    """Resolve a device spec to one usable device; raise DeviceError when it cannot be honoured.

    ``spec`` is ``auto`` (a GPU if one can build kernels, else a CPU), ``cpu``, ``gpu`` or
    ``PLATFORM:DEVICE`` with the indices ``satsweep devices`` prints. ``None`` reads the
    ``SATSWEEP_DEVICE`` environment variable, then defaults to ``auto``.
    """
    if spec is None:
        spec = os.environ.get(ENV_VAR) or "auto"
    spec = spec.strip().lower()
    devices = list_devices(check_build=True)
    usable = [d for d in devices if d.can_build]
    if spec == "auto":
        for kind in ("gpu", "cpu", "other"):
            for d in usable:
                if d.kind == kind:
                    return d
        raise DeviceError(f"no usable OpenCL device; {_describe(devices)}")
    if spec in ("cpu", "gpu"):
        for d in usable:
            if d.kind == spec:
                return d
        raise DeviceError(f"device '{spec}' requested but none is usable; {_describe(devices)}")
    if ":" in spec:
        p, _, q = spec.partition(":")
        try:
            pi, di = int(p), int(q)
        except ValueError:
            raise DeviceError(
                f"device spec '{spec}' is not auto|cpu|gpu|PLATFORM:DEVICE; {_describe(devices)}"
            ) from None
        for d in devices:
            if d.platform_index == pi and d.device_index == di:
                if not d.can_build:
                    raise DeviceError(f"device {d.label} cannot build kernels: {d.build_error}")
                return d
        raise DeviceError(f"device '{spec}' does not exist; {_describe(devices)}")
    raise DeviceError(f"device spec '{spec}' is not auto|cpu|gpu|PLATFORM:DEVICE; {_describe(devices)}")


def _define_value(value) -> str:
    """The text of a -D value: integers as they are, floats as float32 literals (``1.5f``), a
    negative number in parentheses (a macro that expands safely in any expression)."""
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, (int, np.integer)):
        text = str(int(value))
    elif isinstance(value, (float, np.floating)):
        text = repr(float(value)) + "f"
    else:
        return str(value)
    return f"({text})" if text.startswith("-") else text


def _options(defines: Mapping[str, object] | None) -> list[str]:
    """Build options: the kernel folder on the include path, the shared constants and
    ``defines`` as -D definitions. ValueError when ``defines`` redefines a shared constant."""
    defines = dict(defines or {})
    clash = sorted(set(defines) & set(SHARED_DEFINES))
    if clash:
        raise ValueError(f"{', '.join(clash)}: shared constant(s) of satsweep/opencl/constants.py, "
                         "passed to every build; a build's defines may not set them")
    opts = ["-I", str(kernel_dir())]
    for name, value in sorted({**SHARED_DEFINES, **defines}.items()):
        opts.append(f"-D{name}={_define_value(value)}")
    return opts


class Device:
    """A context and an in-order command queue on one device, and the kernels built for it."""

    def __init__(self, info: DeviceInfo):
        cl = _cl()
        self.info = info
        plat = cl.get_platforms()[info.platform_index]
        self.cl_device = plat.get_devices()[info.device_index]
        self.context = cl.Context([self.cl_device])
        self.queue = cl.CommandQueue(self.context)
        self._programs: dict[tuple, object] = {}
        self._kernels: dict[tuple, object] = {}
        # Programs being built in the background (prebuild), and the lock over both dicts.
        self._pending: dict[tuple, Future] = {}
        self._lock = threading.Lock()
        # Programs this Device has compiled and the seconds their builds took (background builds
        # included): a run's report says what its own builds cost (``build_totals``), since a
        # short run's time depends on them (PoCL builds a new source or -D set in seconds, or
        # loads it from its disk cache in milliseconds).
        self._built_programs = 0
        self._build_seconds = 0.0

    @property
    def max_alloc_bytes(self) -> int:
        return self.info.max_alloc_bytes

    @property
    def global_mem_bytes(self) -> int:
        return self.info.global_mem_bytes

    @staticmethod
    def _key(source: str, defines: Mapping[str, object] | None) -> tuple:
        return source, tuple(sorted((defines or {}).items()))

    def build(self, source: str, defines: Mapping[str, object] | None = None):
        """Build ``kernels/<source>.cl`` with ``-D`` constants: ``defines`` and the shared
        constants (``SHARED_DEFINES``, which ``defines`` may not set: KernelBuildError); cached
        per (source, defines). A program that ``prebuild`` is building is waited for (its build
        error raised here)."""
        key = self._key(source, defines)
        with self._lock:
            prg = self._programs.get(key)
            pending = self._pending.get(key)
        if prg is not None:
            return prg
        if pending is not None:
            return pending.result()
        prg = self._compile(source, defines)
        with self._lock:
            self._programs[key] = prg
        return prg

    def prebuild(self, requests: Iterable[tuple[str, Mapping[str, object] | None]]) -> None:
        """Start building the (source, defines) ``requests`` one after the other in a background
        thread and return at once; those already built or pending are skipped. pyopencl releases
        the GIL while a program builds, so the builds overlap host work such as the camera fit
        and the bundle adjustment. Nothing depends on the requests being right: a program that
        is never asked for only cost background time, and one missing is built when asked for."""
        todo = []
        with self._lock:
            for source, defines in requests:
                key = self._key(source, defines)
                if key not in self._programs and key not in self._pending:
                    self._pending[key] = Future()
                    todo.append((key, source, defines))
        if not todo:
            return
        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="satsweep-prebuild")
        pool.submit(self._prebuild, todo)
        pool.shutdown(wait=False)  # the queued builds still run; the thread then ends

    def _prebuild(self, todo) -> None:
        for key, source, defines in todo:
            future = self._pending[key]
            try:
                prg = self._compile(source, defines)
            except BaseException as exc:  # handed to whoever asks for this program
                future.set_exception(exc)
                continue
            with self._lock:
                self._programs[key] = prg
                del self._pending[key]
            future.set_result(prg)

    def build_totals(self) -> tuple[int, float]:
        """(programs compiled, seconds their builds took) by this Device so far; programs
        served from its own cache are not counted."""
        with self._lock:
            return self._built_programs, self._build_seconds

    def _compile(self, source: str, defines: Mapping[str, object] | None):
        t0 = time.perf_counter()
        prg = self._compile_program(source, defines)
        with self._lock:
            self._built_programs += 1
            self._build_seconds += time.perf_counter() - t0
        return prg

    def _compile_program(self, source: str, defines: Mapping[str, object] | None):
        cl = _cl()
        path = kernel_dir() / f"{source}.cl"
        try:
            text = path.read_text()
        except FileNotFoundError:
            raise KernelBuildError(f"{path}: kernel source does not exist") from None
        try:
            options = _options(defines)
        except ValueError as exc:
            raise KernelBuildError(f"{path}: {exc}") from None
        try:
            return cl.Program(self.context, text).build(options=options)
        except cl.Error as exc:
            raise KernelBuildError(
                f"{path}: build failed on {self.info.label}: {str(exc).strip()[:2000]}"
            ) from None

    def kernel(self, program, name: str):
        """The kernel ``name`` of a built ``program``, created once: pyopencl sets up each new
        Kernel object's argument handling anew (a cache lookup of about 0.2 ms), which a sweep of
        hundreds of small tiles would otherwise pay for every launch. Launches set all their
        arguments, so sharing the object between sequential launches is safe."""
        key = (program.int_ptr, name)
        k = self._kernels.get(key)
        if k is None:
            k = self._kernels[key] = _cl().Kernel(program, name)
        return k

    def __repr__(self) -> str:
        return f"Device({self.info.label})"


# Fixed work-group sizes, by number of dimensions, of the kernels that need none in particular
# (each ignores the work-items past its global size): PoCL compiles one work-group function per
# kernel and local size, and given none takes the whole global size (one work-group: one core),
# so a fixed size is compiled once per kernel instead of once per image or tile shape.
FIXED_LOCAL_SIZES = {1: (64,), 2: (16, 8), 3: (16, 4, 1)}


def launch(kernel, queue, gsize: tuple[int, ...], *args):
    """Enqueue ``kernel`` over ``gsize`` rounded up to the fixed local size of its dimension
    (``FIXED_LOCAL_SIZES``)."""
    local = FIXED_LOCAL_SIZES[len(gsize)]
    return kernel(queue, tuple(-(-int(n) // m) * m for n, m in zip(gsize, local)), local, *args)


def open_device(spec: str | None = None) -> Device:
    """Select a device (see ``select_device``) and open a context and queue on it."""
    return Device(select_device(spec))
