"""OpenCL C sources of satsweep's kernels (``*.cl`` with the shared ``common.h``).

This folder is shipped inside the wheel as the package ``satsweep.kernels``; it holds no Python
code. ``satsweep.device.kernel_dir()`` locates it, and ``Device.build`` compiles a source with
this folder on the include path and the stage's sizes as ``-D`` constants.
"""
