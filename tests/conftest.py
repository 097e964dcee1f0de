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

from satsweep.opencl import device as sdev

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


# The small synthetic town that the pipeline, sweep and tie-point tests share: two views of a
# 192 px town at 0.5 m (96 m square), base-to-height about 0.2, no pointing bias.
SMALL_TOWN = dict(seed=3, n_views=2, size_px=192, gsd_m=0.5)


@pytest.fixture(scope="session")
def synthetic_scene(tmp_path_factory):
    """A factory of synthetic scenes (``satsweep.synth``), each generated once per session: the
    tests that ask for the same options share its files (which no test may change)."""
    from satsweep.synth.scene import SynthOptions, generate_scene

    cache = {}

    def make(**options):
        key = tuple(sorted(options.items()))
        if key not in cache:
            cache[key] = generate_scene(tmp_path_factory.mktemp("scene") / "scene",
                                        SynthOptions(**options))
        return cache[key]

    return make


@pytest.fixture(scope="session")
def small_town(synthetic_scene):
    """``SMALL_TOWN``: the shared two-view town."""
    return synthetic_scene(**SMALL_TOWN)
