"""Output folders and atomic files: every file is written under a temporary name in its
destination folder and renamed on success, so a failed run never leaves a half-written output.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from typing import Iterator

from satsweep.errors import OptionsError


# -- atomic outputs ----------------------------------------------------------------------------
def check_output_dir(path: str | os.PathLike, *, overwrite: bool) -> None:
    """Refuse an output folder that is a file, or a non-empty folder without ``overwrite``.

    Called before anything is computed, so that a refused run writes nothing."""
    from satsweep.errors import OutputExistsError

    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isdir(path):
        raise OptionsError(f"--out {path}: exists and is not a folder")
    if os.path.isdir(path) and os.listdir(path) and not overwrite:
        raise OutputExistsError(f"--out {path}: folder is not empty (pass --overwrite to write into it)")


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary path beside ``path``; rename it to ``path`` on success, remove it on error.

    The temporary name keeps the extension (``.NAME.RANDOM.tmp.tif``) and lives in the same folder,
    so the final ``os.replace`` is atomic on POSIX file systems.
    """
    path = os.fspath(path)
    folder, name = os.path.split(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise OptionsError(f"{path}: output folder {folder} does not exist")
    stem, ext = os.path.splitext(name)
    tmp = os.path.join(folder, f".{stem}.{secrets.token_hex(6)}.tmp{ext}")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


@contextlib.contextmanager
def _maybe_atomic(path: str | os.PathLike, atomic: bool) -> Iterator[str]:
    if atomic:
        with atomic_output(path) as tmp:
            yield tmp
    else:
        yield os.fspath(path)
