"""satsweep: satellite multi-view stereo with an OpenCL plane sweep.

Images with RPC camera models and an area of interest go in; a DSM on a UTM grid (GeoTIFF), a
point cloud and a quality report come out. The host code is float64 numpy; the kernels in
``kernels/`` are float32 OpenCL and run on any GPU and on PoCL.

The public API (each name is imported from its stage module on first use)::

    from satsweep import reconstruct, PipelineConfig, parse_aoi, AltitudeRange
    result = reconstruct(["a.tif", "b.tif"], parse_aoi("55.648,-21.233,55.651,-21.230"), "out/",
                         alt_range=AltitudeRange(2290, 2420), config=PipelineConfig())
    print(result.report["dsm"], result.dsm_path)
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

from satsweep.errors import SatsweepError  # noqa: E402

# name -> module that defines it
_API = {
    "reconstruct": "pipeline.run",
    "ReconstructResult": "pipeline.outputs",
    "PipelineConfig": "config",
    "ReconstructOptions": "config",
    "run_demo": "demo",
    "AOI": "geometry.aoi",
    "AltitudeRange": "geometry.altitude",
    "parse_aoi": "geometry.aoi",
    "RPCModel": "geometry.rpc",
    "ENUFrame": "geometry.geodesy",
    "prepare_views": "pipeline.prepare",
    "PreparedViews": "pipeline.prepare",
    "build_cameras": "geometry.camera",
    "CameraSet": "geometry.camera",
    "adjust_principal_points": "sparse.bundle",
    "sweep_views": "dense.sweep",
    "PlaneSweep": "dense.sweep",
    "generate_scene": "synth.scene",
    "SynthOptions": "synth.scene",
    "evaluate_dsm": "products.evaluate",
    "open_device": "opencl.device",
    "list_devices": "opencl.device",
}

__all__ = ["__version__", "SatsweepError", *_API]


def __getattr__(name: str) -> Any:
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'satsweep' has no attribute {name!r}")
    return getattr(importlib.import_module(f".{module}", __name__), name)


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from satsweep.config import PipelineConfig, ReconstructOptions  # noqa: F401
    from satsweep.demo import run_demo  # noqa: F401
    from satsweep.dense.sweep import PlaneSweep, sweep_views  # noqa: F401
    from satsweep.geometry.altitude import AltitudeRange  # noqa: F401
    from satsweep.geometry.aoi import AOI, parse_aoi  # noqa: F401
    from satsweep.geometry.camera import CameraSet, build_cameras  # noqa: F401
    from satsweep.geometry.geodesy import ENUFrame  # noqa: F401
    from satsweep.geometry.rpc import RPCModel  # noqa: F401
    from satsweep.opencl.device import list_devices, open_device  # noqa: F401
    from satsweep.pipeline.outputs import ReconstructResult  # noqa: F401
    from satsweep.pipeline.prepare import PreparedViews, prepare_views  # noqa: F401
    from satsweep.pipeline.run import reconstruct  # noqa: F401
    from satsweep.products.evaluate import evaluate_dsm  # noqa: F401
    from satsweep.sparse.bundle import adjust_principal_points  # noqa: F401
    from satsweep.synth.scene import SynthOptions, generate_scene  # noqa: F401
