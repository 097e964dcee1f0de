"""The OpenCL device layer: listing, selection rules, kernel builds with -D constants."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pytest

from satsweep import cli
from satsweep.errors import DeviceError, KernelBuildError
from satsweep.opencl import device as sdev

# A device may contract a*b+c into one fused multiply-add (PoCL does): one rounding fewer than
# numpy's two, so results may differ by about one float32 ulp.
FMA_RTOL = 2 * np.finfo(np.float32).eps


def test_every_listed_usable_device_ran_the_selftest():
    devices = sdev.list_devices(check_build=True)
    usable = [d for d in devices if d.can_build]
    assert usable, f"no usable OpenCL device: {sdev._describe(devices)}"
    for d in devices:
        assert (d.build_error is None) == bool(d.can_build)
        assert d.global_mem_bytes > 0 and d.max_alloc_bytes > 0


def test_auto_prefers_gpu_then_cpu():
    usable = [d for d in sdev.list_devices() if d.can_build]
    chosen = sdev.select_device("auto")
    expected_kind = "gpu" if any(d.kind == "gpu" for d in usable) else usable[0].kind
    assert chosen.kind == expected_kind


def test_explicit_spec_selects_that_device():
    for d in sdev.list_devices():
        if d.can_build:
            assert sdev.select_device(d.spec) == d


def test_env_var_is_read_when_no_spec(monkeypatch):
    d = next(d for d in sdev.list_devices() if d.can_build)
    monkeypatch.setenv(sdev.ENV_VAR, d.spec)
    assert sdev.select_device(None) == d


@pytest.mark.parametrize("spec", ["7:3", "banana", "x:y"])
def test_missing_or_malformed_device_is_an_error_listing_what_exists(spec):
    with pytest.raises(DeviceError) as info:
        sdev.select_device(spec)
    message = str(info.value)
    assert spec in message
    for d in sdev.list_devices():
        assert d.spec in message  # the error lists what exists


def test_gpu_request_without_gpu_does_not_fall_back():
    if any(d.kind == "gpu" and d.can_build for d in sdev.list_devices()):
        pytest.skip("this machine has a usable GPU; the no-fallback case needs a machine without")
    with pytest.raises(DeviceError, match="'gpu' requested"):
        sdev.select_device("gpu")


def test_build_passes_defines_and_runs(cl_device):
    prg = cl_device.build("selftest", {"SCALE": 3.5})
    n = 100
    a = np.random.default_rng(0).random(n).astype(np.float32)
    mf = cl.mem_flags
    a_buf = cl.Buffer(cl_device.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a)
    out_buf = cl.Buffer(cl_device.context, mf.WRITE_ONLY, a.nbytes)
    prg.scale_add(cl_device.queue, (128,), None, a_buf, out_buf, np.int32(n))
    out = np.empty_like(a)
    cl.enqueue_copy(cl_device.queue, out, out_buf)
    expected = np.float32(3.5) * a + np.arange(n, dtype=np.float32)
    np.testing.assert_allclose(out, expected, rtol=FMA_RTOL, atol=0)
    # The same source and defines come back from the per-device program cache.
    assert cl_device.build("selftest", {"SCALE": 3.5}) is prg


def test_missing_define_is_a_named_build_error(cl_device):
    with pytest.raises(KernelBuildError, match="selftest.cl"):
        cl_device.build("selftest", {})


def test_every_build_gets_the_shared_constants_and_may_not_redefine_them(cl_device):
    """The constants of satsweep/opencl/constants.py reach every build as -D definitions, as
    float32 literals: wta.cl's WTA_BIG is the host's np.float32(WTA_BIG), and a source built
    without them stops at common.h's #error. A build's own defines may not set them."""
    from satsweep.opencl.constants import SHARED_DEFINES, WTA_BIG

    opts = sdev._options({"SCALE": 1.0})
    for name, value in SHARED_DEFINES.items():
        assert f"-D{name}={sdev._define_value(value)}" in opts
    assert sdev._define_value(-1.0e30) == "(-1e+30f)" and sdev._define_value(3) == "3"
    # selftest with SCALE = WTA_BIG: the float32 literal the kernels read.
    prg = cl_device.build("selftest", {"SCALE": "WTA_BIG"})
    assert np.float32(_scale_of(cl_device, prg)) == np.float32(WTA_BIG)
    with pytest.raises(KernelBuildError, match="selftest.cl: WTA_BIG: shared constant"):
        cl_device.build("selftest", {"SCALE": 1.0, "WTA_BIG": 1.0})
    text = (sdev.kernel_dir() / "selftest.cl").read_text()
    bare = cl.Program(cl_device.context, text)
    with pytest.raises(cl.Error, match="constants.py"):
        bare.build(options=["-I", str(sdev.kernel_dir()), "-DSCALE=1.0f"])


def _scale_of(device, prg) -> float:
    """Run selftest's scale_add on ones and read back the scale the program was built with."""
    n = 8
    mf = cl.mem_flags
    a_buf = cl.Buffer(device.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ones(n, np.float32))
    out_buf = cl.Buffer(device.context, mf.WRITE_ONLY, 4 * n)
    prg.scale_add(device.queue, (n,), None, a_buf, out_buf, np.int32(n))
    out = np.empty(n, np.float32)
    cl.enqueue_copy(device.queue, out, out_buf)
    return float(out[0])


def test_prebuilt_programs_are_built_once_and_returned_by_build(cl_device, monkeypatch):
    """Requests built in the background come back from build (each its own defines), each
    (source, defines) compiled once however often it is requested."""
    device = sdev.Device(cl_device.info)  # a fresh program cache, not the session's
    compiled = []
    real = sdev.Device._compile

    def spy(self, source, defines):
        compiled.append((source, dict(defines or {})))
        return real(self, source, defines)

    monkeypatch.setattr(sdev.Device, "_compile", spy)
    requests = [("selftest", {"SCALE": 1.5}), ("selftest", {"SCALE": 2.5}), ("selftest", {"SCALE": 1.5})]
    device.prebuild(requests)
    b = device.build("selftest", {"SCALE": 2.5})
    a = device.build("selftest", {"SCALE": 1.5})
    assert (_scale_of(device, a), _scale_of(device, b)) == (1.5, 2.5)
    assert device.build("selftest", {"SCALE": 1.5}) is a
    device.prebuild(requests)  # all built: nothing more to do
    device.build("selftest", {"SCALE": 3.5})  # not requested: built in the foreground
    assert compiled == [("selftest", {"SCALE": 1.5}), ("selftest", {"SCALE": 2.5}),
                        ("selftest", {"SCALE": 3.5})]


def test_build_totals_count_each_compiled_program_once(cl_device):
    """build_totals counts what this Device compiled, foreground and background, and not what
    its cache served (a run's report gives the difference over the run)."""
    device = sdev.Device(cl_device.info)
    assert device.build_totals() == (0, 0.0)
    device.build("selftest", {"SCALE": 1.5})
    one, seconds = device.build_totals()
    assert one == 1 and seconds > 0.0
    device.build("selftest", {"SCALE": 1.5})  # from the cache
    assert device.build_totals() == (1, seconds)
    device.prebuild([("selftest", {"SCALE": 2.5})])
    device.build("selftest", {"SCALE": 2.5})  # waits for the background build
    two, more = device.build_totals()
    assert two == 2 and more > seconds


def test_a_prebuild_failure_is_raised_by_build_naming_the_file(cl_device):
    device = sdev.Device(cl_device.info)
    device.prebuild([("selftest", {"SCALE": "no_such_identifier"}), ("no_such_stage", None)])
    with pytest.raises(KernelBuildError, match="selftest.cl: build failed"):
        device.build("selftest", {"SCALE": "no_such_identifier"})
    with pytest.raises(KernelBuildError, match="no_such_stage.cl: kernel source does not exist"):
        device.build("no_such_stage")


def test_missing_source_is_a_named_build_error(cl_device):
    with pytest.raises(KernelBuildError, match="does not exist"):
        cl_device.build("no_such_stage")


def test_kernel_dir_holds_common_header():
    assert (sdev.kernel_dir() / "common.h").is_file()


def test_cli_devices_lists_and_selects(capsys):
    assert cli.main(["devices"]) == 0
    out = capsys.readouterr().out
    assert "selected:" in out and "builds kernels" in out


def test_cli_devices_bad_spec_exits_2(capsys):
    assert cli.main(["devices", "--device", "9:9"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("satsweep: error:") and "9:9" in err
