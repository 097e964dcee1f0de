"""The satsweep exception family.

Every error that a user can cause (bad file, bad option, missing device) is a ``SatsweepError``
subclass with a one-line message that names the file or the option and what is wrong with it. The
command line turns any of them into that line on stderr and exit code 2; anything else is a bug.
"""

from __future__ import annotations

import os


class SatsweepError(Exception):
    """Base class of every error satsweep raises on purpose."""

    exit_code = 2


class InputError(SatsweepError):
    """An input file (image, RPC, AOI, DEM, config) is missing, unreadable or malformed."""

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path is not None else problem)


class RPCError(InputError):
    """An RPC is missing from an image, or an RPC file lacks keys or holds non-numeric values."""


class ImageFormatError(InputError):
    """A file that should be an image is truncated, not a TIFF, or of an unsupported layout."""


class AOIError(SatsweepError):
    """The area of interest or the altitude range is invalid, or an image does not see it."""


class OptionsError(SatsweepError):
    """An option has an invalid value, or a config file names an unknown key."""


class LocalizationError(SatsweepError):
    """RPC inverse localization did not converge."""


class DeviceError(SatsweepError):
    """No usable OpenCL device, a requested device is missing, or a device cannot build kernels."""


class KernelBuildError(DeviceError):
    """An OpenCL program failed to compile on the chosen device."""


class CameraError(SatsweepError):
    """A camera approximation or adjustment cannot be computed from the given data."""


class OutputExistsError(SatsweepError):
    """An output folder is not empty and --overwrite was not given."""


class RetiredOptionWarning(FutureWarning):
    """A configuration file gives an option that satsweep no longer reads (an older run's
    config.toml): the file still loads, the key is ignored, and the warning says what replaced
    it. The command line prints it as a ``satsweep: warning:`` line."""
