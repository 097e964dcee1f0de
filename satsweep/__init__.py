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

from .errors import SatsweepError  # noqa: E402

# name -> module that defines it
_API = {
    "reconstruct": "pipeline",
    "ReconstructResult": "pipeline",
    "PipelineConfig": "config",
    "ReconstructOptions": "config",
    "run_demo": "demo",
    "AOI": "aoi",
    "AltitudeRange": "aoi",
    "parse_aoi": "aoi",
    "RPCModel": "rpc",
    "ENUFrame": "geo",
    "build_cameras": "camera",
    "CameraSet": "camera",
    "adjust_principal_points": "bundle",
    "sweep_views": "sweep",
    "PlaneSweep": "sweep",
    "generate_scene": "synth",
    "SynthOptions": "synth",
    "evaluate_dsm": "evaluate",
    "open_device": "device",
    "list_devices": "device",
}

__all__ = ["__version__", "SatsweepError", *_API]


def __getattr__(name: str) -> Any:
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'satsweep' has no attribute {name!r}")
    return getattr(importlib.import_module(f".{module}", __name__), name)


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from .aoi import AOI, AltitudeRange, parse_aoi
    from .bundle import adjust_principal_points
    from .camera import CameraSet, build_cameras
    from .config import PipelineConfig, ReconstructOptions
    from .demo import run_demo
    from .device import list_devices, open_device
    from .evaluate import evaluate_dsm
    from .geo import ENUFrame
    from .pipeline import ReconstructResult, reconstruct
    from .rpc import RPCModel
    from .sweep import PlaneSweep, sweep_views
    from .synth import SynthOptions, generate_scene
