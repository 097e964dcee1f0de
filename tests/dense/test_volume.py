"""The CostVolume type (satsweep/dense/volume.py): its layouts, dimensions and checks."""

from __future__ import annotations

import numpy as np
import pytest

from satsweep.dense.volume import CostVolume
from satsweep.errors import InputError


def test_host_volume_dims_and_windows():
    data = np.zeros((7, 4, 5), np.float32)
    v = CostVolume(data)
    assert v.dims == (7, 4, 5) and v.n_labels == 7 and v.shape == (4, 5) and not v.on_device
    with v:  # a host volume has nothing to free
        pass
    base = np.arange(20).reshape(4, 5)
    windowed = CostVolume(data, label_base=base, label_count=np.full((4, 5), 3))
    assert windowed.label_base.dtype == np.int32 and windowed.label_count.dtype == np.int32


@pytest.mark.parametrize("kwargs, match", [
    ({"layout": "pixel_major"}, "host volume is plane-major"),
    ({"layout": "slices"}, "layout"),
    ({"label_count": np.ones((4, 5), int)}, "label_count: needs label_base"),
    ({"label_base": np.zeros((5, 4), int)}, "label_base: expected integers of shape"),
    ({"label_base": -np.ones((4, 5), int)}, "planes must be >= 0"),
    ({"label_base": np.zeros((4, 5), int), "label_count": np.full((4, 5), 8)}, "outside 1..7"),
    ({"label_base": np.zeros((4, 5), int), "label_count": np.zeros((4, 5), int)}, "outside"),
    ({"label_offset": np.zeros((4, 5), np.uint64)}, "only a ragged volume"),
])
def test_bad_host_volumes_are_input_errors(kwargs, match):
    with pytest.raises(InputError, match=match):
        CostVolume(np.zeros((7, 4, 5), np.float32), **kwargs)


def test_device_layouts(cl_device):
    import pyopencl.array as cla

    q = cl_device.queue
    with CostVolume(cla.zeros(q, (4, 5, 7), np.float32), "pixel_major") as pm:
        assert pm.on_device and pm.dims == (7, 4, 5)
    count = np.array([[1, 2], [3, 4]])
    offset = np.array([[0, 1], [3, 6]], np.uint64)
    with CostVolume(cla.zeros(q, (10,), np.float32), "ragged", label_base=np.zeros((2, 2), int),
                    label_count=count, label_offset=offset) as ragged:
        assert ragged.dims == (4, 2, 2)
        with pytest.raises(InputError, match="reach float 11"):
            CostVolume(ragged.data, "ragged", label_base=np.zeros((2, 2), int),
                       label_count=count, label_offset=offset + np.uint64(1))
        with pytest.raises(InputError, match="needs label_base, label_count and label_offset"):
            CostVolume(ragged.data, "ragged")
    with pytest.raises(InputError, match="float32"):
        CostVolume(cla.zeros(q, (4, 5, 7), np.float64))
