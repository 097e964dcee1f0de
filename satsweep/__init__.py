"""satsweep: satellite multi-view stereo with an OpenCL plane sweep.

Images with RPC camera models and an area of interest go in; a DSM on a UTM grid (GeoTIFF), a
point cloud and a quality report come out. The host code is float64 numpy; the kernels in
``kernels/`` are float32 OpenCL and run on any GPU and on PoCL.
"""

__version__ = "0.1.0"

from .errors import SatsweepError  # noqa: E402,F401
