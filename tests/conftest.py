"""Shared test fixtures.

``cl_device``: every kernel test that takes this fixture runs once per usable OpenCL device on
the machine (PoCL in CI, the GPU too where one is present), as pyopencl's own ``ctx_factory``
does. With no usable device the tests fail with the reason; they are never skipped silently.
Set SATSWEEP_TEST_DEVICES to a comma-separated list of PLATFORM:DEVICE specs to restrict them.

``shared_data``: the folder ``../shared/data`` beside the checkout; tests that use it skip with a
clear reason when it is absent (user installs do not have it).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from satsweep import device as sdev

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("SATSWEEP_SHARED_DATA", REPO.parent / "shared" / "data"))


def _test_devices():
    devices = [d for d in sdev.list_devices(check_build=True) if d.can_build]
    wanted = os.environ.get("SATSWEEP_TEST_DEVICES")
    if wanted:
        specs = {s.strip() for s in wanted.split(",") if s.strip()}
        devices = [d for d in devices if d.spec in specs]
    return devices


def pytest_generate_tests(metafunc):
    if "cl_device" in metafunc.fixturenames:
        devices = _test_devices()
        if devices:
            metafunc.parametrize(
                "cl_device", devices, ids=[f"{d.spec}-{d.kind}" for d in devices], indirect=True
            )
        else:
            metafunc.parametrize("cl_device", [None], ids=["no-device"], indirect=True)


_OPENED: dict[str, sdev.Device] = {}


@pytest.fixture
def cl_device(request) -> sdev.Device:
    info = request.param
    if info is None:
        listing = sdev.list_devices(check_build=True)
        pytest.fail(
            "no usable OpenCL device for the kernel tests; "
            + sdev._describe(listing)
            + " (install Debian's pocl-opencl-icd)",
            pytrace=False,
        )
    # One context per device for the whole session: building programs is the slow part.
    dev = _OPENED.get(info.spec)
    if dev is None:
        dev = _OPENED[info.spec] = sdev.Device(info)
    return dev


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real-data folder {SHARED_DATA} is absent (it is not part of user installs)")
    return SHARED_DATA


@pytest.fixture
def pleiades_pair(shared_data) -> Path:
    d = shared_data / "pleiades_pair"
    if not (d / "img_01.tif").is_file():
        pytest.skip(f"{d}/img_01.tif is absent")
    return d
