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
# The hidden staging folder a run writes its outputs into before moving them in place
# (satsweep.pipeline.outputs.OutputFolder), and the file in it that names the process owning it.
STAGING_PREFIX = ".satsweep-partial-"
STAGING_OWNER = "owner.pid"
# The hidden folder of a run's finished tiles (satsweep.pipeline.cluster): kept when a run fails
# or is interrupted so that ``--resume`` reuses them, cleared by a run without ``--resume``,
# removed by a run that succeeds. It holds the STAGING_OWNER file of the run using it.
RESUME_CACHE = ".satsweep-tiles"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    except OSError:
        return False
    return True


def stale_staging(path: str | os.PathLike) -> list[str]:
    """The staging folders in ``path`` left by runs that are no longer running (killed, or
    crashed before cleaning up): their owner process is gone, or they name none."""
    path = os.fspath(path)
    stale = []
    try:
        entries = os.listdir(path)
    except OSError:
        return []
    for name in entries:
        full = os.path.join(path, name)
        if not (name.startswith(STAGING_PREFIX) and os.path.isdir(full)):
            continue
        try:
            with open(os.path.join(full, STAGING_OWNER), encoding="ascii") as fh:
                pid = int(fh.read().strip())
        except (OSError, ValueError):
            pid = None
        if pid is None or not _pid_alive(pid):
            stale.append(full)
    return stale


def cache_owner(path: str | os.PathLike) -> int | None:
    """The process id of the live run that uses the finished-tiles folder ``RESUME_CACHE`` in
    the output folder ``path``; None when there is no such folder or its run is gone."""
    try:
        with open(os.path.join(os.fspath(path), RESUME_CACHE, STAGING_OWNER),
                  encoding="ascii") as fh:
            pid = int(fh.read().strip())
    except (OSError, ValueError):
        return None
    return pid if pid != os.getpid() and _pid_alive(pid) else None


def check_output_dir(path: str | os.PathLike, *, overwrite: bool) -> None:
    """Refuse an output folder that is a file, a non-empty folder without ``overwrite``, or one
    whose finished tiles another live run is using. Staging folders left by runs that were
    killed, and the finished tiles of an interrupted run (``RESUME_CACHE``), do not count as
    content.

    Called before anything is computed, so that a refused run writes nothing."""
    from satsweep.errors import OutputExistsError

    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isdir(path):
        raise OptionsError(f"output folder {path}: exists and is not a folder")
    owner = cache_owner(path) if os.path.isdir(path) else None
    if owner is not None:
        raise OutputExistsError(f"output folder {path} is being written by another satsweep "
                                f"run (process {owner})")
    if os.path.isdir(path) and not overwrite:
        stale = {os.path.basename(p) for p in stale_staging(path)} | {RESUME_CACHE}
        try:
            content = [e for e in os.listdir(path) if e not in stale]
        except OSError as exc:
            raise OptionsError(f"output folder {path}: cannot be listed "
                               f"({exc.strerror or exc})") from None
        if content:
            raise OutputExistsError(f"output folder {path} is not empty (pass --overwrite, or "
                                    "overwrite=True in the API, to write into it)")


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
