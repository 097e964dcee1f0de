"""OpenCL C sources of satsweep's kernels (``*.cl`` with the shared ``common.h``).

This folder is shipped inside the wheel as the package ``satsweep.kernels``; it holds no Python
code. ``satsweep.opencl.device.kernel_dir()`` locates it, and ``Device.build`` compiles a source
with this folder on the include path, the stage's sizes as ``-D`` constants and the constants
shared with the host (``satsweep.opencl.constants``) as ``-D`` constants too.
"""
