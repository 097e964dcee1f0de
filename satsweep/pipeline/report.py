"""Run reports and progress: every run records its settings, device, per-stage timings and
results, and long stages show progress on stderr.

``RunReport`` is a plain container that the pipeline fills; ``RunReport.stage(name)`` is a context
manager that times a stage and prints a progress line when it starts and ends. ``Progress`` prints
fractional progress of a long loop at most every ``interval_s`` seconds.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import logging
import math
import platform
import sys
import time
from typing import Any, Callable, Iterator, TextIO

import numpy as np

from satsweep import __version__


def _jsonable(value: Any) -> Any:
    """Convert numpy scalars/arrays and tuples for json.dumps; NaN/inf become None."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def to_json(data: Any) -> str:
    return json.dumps(_jsonable(data), indent=2, allow_nan=False)


class Progress:
    """Prints ``[stage] label: k/n (p%)`` lines to ``stream``, at most every ``interval_s``."""

    def __init__(self, stage: str, total: int, *, stream: TextIO | None = None,
                 interval_s: float = 2.0, enabled: bool = True):
        self.stage = stage
        self.total = max(int(total), 1)
        self.stream = stream if stream is not None else sys.stderr
        self.interval_s = interval_s
        self.enabled = enabled
        self._last = -math.inf
        self.done = 0

    def update(self, done: int, label: str = "") -> None:
        self.done = done
        now = time.monotonic()
        if not self.enabled or (now - self._last < self.interval_s and done < self.total):
            return
        self._last = now
        pct = 100.0 * done / self.total
        text = f"[{self.stage}] {label + ': ' if label else ''}{done}/{self.total} ({pct:.0f}%)"
        print(text, file=self.stream, flush=True)

    def callback(self, label: str = "") -> Callable[[int, int], None]:
        """A ``(done, total)`` callback for stage functions that report their own progress."""

        def cb(done: int, total: int) -> None:
            self.total = max(int(total), 1)
            self.update(done, label)

        return cb


def peak_memory_bytes() -> int | None:
    """This process's peak resident memory so far (bytes): its high-water mark, which only grows;
    None where the platform does not report it.

    On Linux it is the VmHWM of /proc/self/status: getrusage's ru_maxrss would carry over the
    high-water mark of the process that started this one (Linux keeps it across fork and exec),
    so a satsweep run from a large Python process would report that process's peak. Elsewhere
    it is getrusage's ru_maxrss; None without a ``resource`` module (Windows).
    """
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024  # kB
    except (OSError, ValueError, IndexError):
        pass
    try:
        import resource  # noqa: PLC0415
    except ImportError:
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # The BSDs report kibibytes, macOS bytes.
    return int(peak) if sys.platform == "darwin" else int(peak) * 1024


class RunReport:
    """What a run did: settings, device, timings per stage, and each stage's figures.

    ``peak_memory_mb`` holds the process's peak resident memory (MiB) at the end of each stage
    (of its last entry, for a stage entered several times) and of the run ("total"): a high-water
    mark, so the stage where it rises is the one that set the peak.
    """

    def __init__(self, command: str, *, verbose: bool = True, stream: TextIO | None = None,
                 where: str = ""):
        self.data: dict[str, Any] = {
            "satsweep_version": __version__,
            "command": command,
            "started_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "host": {"python": platform.python_version(), "machine": platform.machine(),
                     "system": platform.system()},
            "settings": {},
            "device": None,
            "timings_s": {},
            "peak_memory_mb": {},
            "warnings": [],
        }
        self.verbose = verbose
        self.stream = stream if stream is not None else sys.stderr
        self.where = where  # put before each warning (a tile's: which cells it is about)
        self._t0 = time.perf_counter()

    def log(self, message: str) -> None:
        """A progress line (not printed when the run is quiet)."""
        if self.verbose:
            print(message, file=self.stream, flush=True)

    def warn(self, message: str, *, doubtful: bool = False) -> None:
        """A warning: always printed, and kept in the report's ``warnings``. ``doubtful``: the
        warning says the result itself may be wrong (``satsweep reconstruct --strict`` then
        exits non-zero). A warning already given (the same words: another tile, or an area swept
        again over a widened altitude range) is not repeated. The report's ``where`` comes
        first."""
        entry = {"message": self.where + message, "doubtful": bool(doubtful)}
        if entry in self.data["warnings"]:
            return
        self.data["warnings"].append(entry)
        print(f"warning: {entry['message']}", file=self.stream, flush=True)

    @property
    def doubtful(self) -> bool:
        """Whether a warning said the result may be wrong."""
        return any(w["doubtful"] for w in self.data["warnings"])

    @contextlib.contextmanager
    def capturing_warnings(self) -> Iterator[None]:
        """While inside: the warnings that satsweep's modules log (``logging``, logger
        ``satsweep.*``) become this report's warnings instead of going to the root logger."""
        report = self

        class _Handler(logging.Handler):
            def emit(self, record: logging.LogRecord) -> None:
                report.warn(record.getMessage())

        logger = logging.getLogger("satsweep")
        handler = _Handler(level=logging.WARNING)
        logger.addHandler(handler)
        propagate, logger.propagate = logger.propagate, False
        try:
            yield
        finally:
            logger.removeHandler(handler)
            logger.propagate = propagate

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time a stage; timings of a stage entered several times add up."""
        self.log(f"[{name}] ...")
        t = time.perf_counter()
        try:
            yield
        finally:
            dt = time.perf_counter() - t
            self.data["timings_s"][name] = self.data["timings_s"].get(name, 0.0) + dt
            self._record_peak(name)
            self.log(f"[{name}] done in {dt:.2f} s")

    def move_time(self, source: str, target: str, seconds: float) -> None:
        """Move ``seconds`` of stage ``source``'s time to stage ``target``: for work of one stage
        done, and timed, inside another's block (the MRF inside the tiled sweep)."""
        timings = self.data["timings_s"]
        moved = min(max(float(seconds), 0.0), timings.get(source, 0.0))
        timings[source] = timings.get(source, 0.0) - moved
        timings[target] = timings.get(target, 0.0) + moved
        self._record_peak(target)

    def progress(self, stage: str, total: int) -> Progress:
        return Progress(stage, total, stream=self.stream, enabled=self.verbose)

    def __setitem__(self, key: str, value: Any) -> None:
        self.data[key] = value

    def __getitem__(self, key: str) -> Any:
        return self.data[key]

    def _record_peak(self, name: str) -> None:
        peak = peak_memory_bytes()
        if peak is not None:
            self.data["peak_memory_mb"][name] = round(peak / 2**20, 1)

    def finish(self) -> dict[str, Any]:
        self.data["timings_s"]["total"] = time.perf_counter() - self._t0
        self._record_peak("total")
        self.data["finished_utc"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
        return self.data

    def to_json(self) -> str:
        return to_json(self.data)
