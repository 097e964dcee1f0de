"""Tile tasks, their finished results on disk, and where they run: here, or on Dask workers.

A tiled run is a set of tile tasks (``TileTask``): each does every stage of one tile, from the
images that see it to its rasters (``satsweep.pipeline.area.run_area``), and writes what it made
into its own folder of the output's finished-tiles folder (``out/.satsweep-tiles``): the core
cells' DSM, confidence and orthophoto (``satsweep.pipeline.mosaic.save_piece``), its cloud
(``save_cloud_piece``), its cameras (``cameras.json``) and, last, ``outcome.json``: a small
``TileOutcome`` (what happened, its report entry, its pointing corrections, its warnings and
timings) that is also what travels back to the run. The mosaic, the cloud and the report are
assembled from those files (``satsweep.pipeline.scheduler``); no raster goes through Dask.

Finished tiles are kept when a run fails or is interrupted: a task's folder is named by its
fingerprint (``task_fingerprint``: the tile, the images' paths, sizes and modification times,
their RPCs (a sidecar or --rpc-dir may change without the image), their masks' files (a mask
added or redrawn), every setting but those that
only say how tasks run, the device asked for, the altitude range or DEM, the borrowed
corrections), so a run with ``--resume`` reuses a folder whose ``outcome.json`` exists (written
last, atomically) and a changed setting recomputes.

Where the tasks run (``open_runner``):

- ``InProcessRunner``: one after the other in this process, on the run's one device. An AOI in
  one piece and ``[reconstruct] workers = 1`` (the default on a CPU device: one PoCL worker
  already uses every core) run so: a Dask cluster's start costs more than a small AOI's run.
- ``DaskRunner``: Dask distributed. ``workers`` > 1 starts a ``LocalCluster`` of that many worker
  processes (one thread each, one device context each: ``worker_device``), with a memory limit
  from the tile size (``worker_memory_bytes``); ``scheduler`` (or ``SATSWEEP_SCHEDULER``)
  attaches to a running cluster (dask-jobqueue on Slurm or PBS, Kubernetes), whose workers must
  see the images and the output folder at the same paths. A worker that dies mid-tile has its
  task rerun on another worker by Dask's scheduler (the task's folder is written again, its
  ``outcome.json`` last, so the result is the same); a tile that fails for a data reason (no
  matches, no valid pixels) returns a ``failed`` outcome and is not retried.

Both runners run the same function, ``run_tile_task``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import heapq
import io
import json
import logging
import os
import secrets
import shutil
import socket
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Sequence

import numpy as np

from satsweep.errors import (
    AOIError,
    CameraError,
    InputError,
    LocalizationError,
    OptionsError,
    SatsweepError,
)

if TYPE_CHECKING:  # pragma: no cover
    from satsweep.config import PipelineConfig
    from satsweep.geometry.altitude import AltitudeRange
    from satsweep.io.sources import ImageSource
    from satsweep.opencl.device import Device
    from satsweep.pipeline.report import RunReport
    from satsweep.pipeline.tiling import Tile
    from satsweep.products.grid import DSMGrid

# A tile's share seen by each image (``TileOutcome.seen_shares``) is measured on at most this
# many cell centres per side: 1/64 of a tile's side, finer than "about N%" needs.
SEEN_SAMPLES = 64

# The environment variable that names a running Dask scheduler (as --scheduler does).
SCHEDULER_ENV = "SATSWEEP_SCHEDULER"
# A finished task's record in its folder, written last; and the prefix of the files that mark
# each start of a task there (one per attempt: a second one means a worker died mid-tile).
OUTCOME_FILE = "outcome.json"
START_MARK = ".start-"
# The version of the folder layout: part of the fingerprint, so that folders of another layout
# are never reused (2: outcomes hold each image's share of the area, ``seen_shares``).
CACHE_LAYOUT = 2
# Seconds to wait for a running scheduler to answer (--scheduler).
SCHEDULER_TIMEOUT_S = 30.0
# Workers on a GPU device when none is asked for: two device contexts share the GPU, so that
# one tile's host stages (tie points, bundle adjustment, fusion) overlap another's kernels.
GPU_DEFAULT_WORKERS = 2

# A worker's memory for one tile: a fixed part (Python, numpy, OpenCV, the OpenCL runtime and
# its kernels) and a part per DSM cell of the tile's window (its context included) and view.
# Measured (docs/measurements.md, 2026-12-01): a worker's peak resident memory was 263-290 MiB
# for 3 views of 56,000-cell windows and 1189 MiB for 2 views of 1.04 million-cell windows
# (tools/bench_scale.py --workers); this estimate is above both (380 and 1297 MiB).
WORKER_BASE_BYTES = 300 * 2**20
WORKER_BYTES_PER_CELL_VIEW = 500
# The memory limit given to a local Dask worker is the estimate times this: Dask's nanny kills
# a worker at 95% of its limit, and an estimate is not a measurement of the next scene.
WORKER_MEMORY_SAFETY = 1.5
# ... and never less than this (bytes): below it the estimate is mostly the fixed part.
WORKER_MEMORY_FLOOR_BYTES = 2 * 2**30

# Errors a tile's own data can cause (no matches, no valid pixels, a view that does not see
# it): such a tile is reported and left empty. Any other error (a file, an option, the
# device) stops the run.
DATA_ERRORS = (CameraError, LocalizationError, AOIError)


class TileKilledError(OptionsError):
    """A tile killed every worker that ran it (out of memory, most likely). The run's finished
    tiles are kept (``resumable``): with more memory per worker, ``--resume`` reuses them."""

    resumable = True


def is_data_error(exc: BaseException) -> bool:
    """Whether ``exc`` comes from a tile's data rather than from a file, an option or a device:
    a tile failing so is left empty, not retried."""
    return isinstance(exc, DATA_ERRORS) or (type(exc) is InputError and exc.path is None)


# -- what a task needs and gives -----------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class RunSettings:
    """What every tile task of a run shares (picklable: it goes to the workers)."""

    config: "PipelineConfig"
    device: str  # the device spec every worker opens (resolved from SATSWEEP_DEVICE)
    alt_range: "AltitudeRange | None" = None  # --alt-range
    dem: str | None = None  # --dem
    verbose: bool = True  # stage lines printed live (in this process only)


@dataclasses.dataclass(frozen=True)
class TileTask:
    """One area to reconstruct (a tile, a part of a split tile, or the AOI in one piece)."""

    path: tuple[int, ...]  # the planned tile's index, then the part's index at each split
    phase: int  # 0: first try; 1: after the others, with their pointing corrections
    tile: "Tile"
    grid: "DSMGrid"  # the run's DSM grid
    whole: bool  # the AOI in one piece (every image sees it; errors stop the run)
    sources: tuple["ImageSource", ...]
    settings: RunSettings
    split_above_px: float  # Split when a camera is further than this from its RPC (0: never)
    borrowed_shifts: tuple[tuple[tuple[float, float], ...], ...] | None  # per view of `seeing`
    seeing: tuple[str, ...] | None  # phase 1: the paths of the images that see the tile
    may_wait: bool
    folder: str  # where the task writes its results (absolute)
    fingerprint: str

    @property
    def order(self) -> tuple:
        """The order of the run's areas in its outputs (the cloud, the report): planned tiles in
        turn, each split tile's parts in its place, the tiles that waited at the end; the order
        one process taking them in turn finishes them in."""
        return (self.phase, self.path)


@dataclasses.dataclass(frozen=True)
class TileOutcome:
    """What a task did, small enough to travel back through the scheduler; ``outcome.json``."""

    kind: str  # done | split | wait | unseen | failed | error
    core: tuple[int, int, int, int]
    images: list[str]  # the paths of the images that see the area
    names: list[str] = dataclasses.field(default_factory=list)  # done: the areas' image names
    entry: dict | None = None  # done: the area's report entry (AreaRecord.to_report)
    shifts: list[list[float] | None] | None = None  # done: its own pointing corrections per
    # image of ``images`` (None for an image left out for want of data)
    max_error_px: float | None = None  # split: its cameras' largest error against the RPCs
    reason: str | None = None  # wait, failed, error: why
    error: dict | None = None  # error: the SatsweepError to raise in the run
    bands: list[str] = dataclasses.field(default_factory=list)  # done: the rasters saved
    cloud_points: int = 0  # done: points in its cloud piece
    seen_shares: dict[str, float] = dataclasses.field(default_factory=dict)  # done and unseen:
    # per image that sees the area, the share of its core cells inside the image (at their
    # fused heights, else the middle of its altitude range; ``_seen_shares``)
    report: dict = dataclasses.field(default_factory=dict)  # timings_s, peak_memory_mb, warnings
    device: dict | None = None  # the device it ran on
    worker: dict = dataclasses.field(default_factory=dict)  # host, pid, peak_memory_mb
    attempts: int = 1  # starts of the task (a worker that died mid-tile made one more)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "TileOutcome":
        data = dict(data)
        data["core"] = tuple(data["core"])
        return cls(**data)

    def exception(self) -> SatsweepError:
        """The error of an ``error`` (or ``failed``) outcome, as raised in the task."""
        from satsweep import errors

        e = self.error or {}
        cls = getattr(errors, str(e.get("type")), None)
        if not (isinstance(cls, type) and issubclass(cls, SatsweepError)):
            cls = SatsweepError
        if issubclass(cls, InputError):
            return cls(e.get("path"), e.get("problem") or e.get("message", ""))
        return cls(e.get("message", ""))


def _error_record(exc: SatsweepError) -> dict:
    """A SatsweepError as plain data (some of them cannot be pickled and rebuilt as such)."""
    return {"type": type(exc).__name__, "message": str(exc), "path": getattr(exc, "path", None),
            "problem": getattr(exc, "problem", None)}


# -- fingerprints and the finished-tiles folder ----------------------------------------------------
def _file_stamp(path: str | os.PathLike | None) -> list | None:
    """A file's absolute path, size and modification time (ns): changed when it is replaced."""
    if path is None:
        return None
    full = os.path.abspath(os.fspath(path))
    try:
        st = os.stat(full)
    except OSError:
        return [full, None, None]
    return [full, st.st_size, st.st_mtime_ns]


def settings_fingerprint(settings: RunSettings) -> dict:
    """The part of every task's fingerprint that the run's settings give."""
    from satsweep import __version__
    from satsweep.config import ReconstructOptions

    config = settings.config.to_dict()
    config["reconstruct"] = {k: v for k, v in config["reconstruct"].items()
                             if k not in ReconstructOptions.EXECUTION and k != "device"}
    rng = settings.alt_range
    return {"layout": CACHE_LAYOUT, "version": __version__, "config": config,
            "device": settings.device, "dem": _file_stamp(settings.dem),
            "alt_range": None if rng is None else [rng.min, rng.max]}


def task_fingerprint(common: dict, sources: Sequence["ImageSource"], tile: "Tile", *, whole: bool,
                     phase: int, split_above_px: float, may_wait: bool, borrowed, seeing) -> str:
    """SHA-256 (hex) of everything a task's result depends on (see the module docstring)."""
    data = {**common, "images": [_file_stamp(s.path) for s in sources],
            "rpcs": [s.rpc.to_tag_values().tolist() for s in sources],
            "masks": [None if s.mask is None else [_file_stamp(s.mask.path), s.mask.page]
                      for s in sources],
            "tile": {**tile.to_dict(), "grid": dataclasses.asdict(tile.grid)}, "whole": whole,
            "phase": phase, "split_above_px": split_above_px, "may_wait": may_wait,
            "borrowed": borrowed, "seeing": seeing}
    text = json.dumps(data, sort_keys=True, default=_plain)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _plain(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (tuple, set)):
        return list(value)
    raise TypeError(f"cannot fingerprint {type(value).__name__}")


def task_folder(cache: str | os.PathLike, fingerprint: str) -> Path:
    """A task's folder in the finished-tiles folder."""
    return Path(cache) / fingerprint[:24]


def load_outcome(folder: str | os.PathLike) -> TileOutcome | None:
    """The outcome of a task finished in ``folder``; None when it did not finish there."""
    try:
        text = (Path(folder) / OUTCOME_FILE).read_text(encoding="utf-8")
        return TileOutcome.from_dict(json.loads(text))
    except (OSError, ValueError, TypeError):
        return None


def finished_entries(cache: str | os.PathLike) -> int:
    """How many finished tasks the finished-tiles folder holds."""
    try:
        return sum(1 for p in Path(cache).iterdir() if (p / OUTCOME_FILE).is_file())
    except OSError:
        return 0


def reset_folder(folder: str | os.PathLike) -> None:
    """Empty a task's folder before it is (re)computed: what an interrupted try left, and its
    start marks, go."""
    shutil.rmtree(folder, ignore_errors=True)


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


# -- the task ------------------------------------------------------------------------------------
_DEVICES: dict[str, "Device"] = {}


def worker_device(spec: str) -> "Device":
    """This process's device for ``spec``, opened once (a context cannot be pickled, so every
    worker opens its own); DeviceError when the spec cannot be honoured: never another one."""
    from satsweep.opencl.device import open_device

    device = _DEVICES.get(spec)
    if device is None:
        device = _DEVICES[spec] = open_device(spec)
    return device


@contextlib.contextmanager
def _warnings_to(report: "RunReport") -> Iterator[None]:
    """While inside: the warnings satsweep's modules log go to ``report`` only (in this process,
    the run's own report hands them over for the time of a task)."""
    logger = logging.getLogger("satsweep")
    saved = list(logger.handlers)
    for handler in saved:
        logger.removeHandler(handler)
    try:
        with report.capturing_warnings():
            yield
    finally:
        for handler in saved:
            logger.addHandler(handler)


def run_tile_task(task: TileTask, in_process: bool = False) -> TileOutcome:
    """Every stage of one tile, its results written into ``task.folder``; its ``TileOutcome``.

    The same function runs in the run's process (``in_process``: stage lines and warnings are
    printed as they come) and on Dask workers (they travel back in the outcome)."""
    from satsweep.pipeline.report import RunReport, peak_memory_bytes

    t0 = time.perf_counter()
    folder = Path(task.folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{START_MARK}{os.getpid()}-{secrets.token_hex(4)}").touch()
    verbose = in_process and task.settings.verbose
    report = RunReport("tile", verbose=verbose, stream=sys.stderr if in_process else io.StringIO(),
                       where="" if task.whole else f"cells {task.tile.core}: ")
    device = None
    with _warnings_to(report):
        try:
            device = worker_device(task.settings.device)
            outcome = _run_tile(task, report, device)
        except SatsweepError as exc:
            kind = "failed" if (not task.whole and is_data_error(exc)) else "error"
            if kind == "failed":
                report.warn(f"{exc}: left without heights")
            outcome = TileOutcome(kind=kind, core=task.tile.core,
                                  images=[s.path for s in task.sources], reason=str(exc),
                                  error=_error_record(exc))
    peak = peak_memory_bytes()
    attempts = sum(1 for p in folder.iterdir() if p.name.startswith(START_MARK))
    outcome = dataclasses.replace(
        outcome,
        report={k: report.data[k] for k in ("timings_s", "peak_memory_mb", "warnings")},
        device=None if device is None else device.info.as_dict(),
        worker={"host": socket.gethostname(), "pid": os.getpid(),
                "peak_memory_mb": None if peak is None else round(peak / 2**20, 1)},
        attempts=attempts, seconds=time.perf_counter() - t0)
    if outcome.kind != "error":  # an error stops the run: nothing to resume from
        _write_atomic(folder / OUTCOME_FILE, json.dumps(outcome.to_dict(), default=_plain))
    return outcome


def _run_tile(task: TileTask, report: "RunReport", device: "Device") -> TileOutcome:
    from satsweep.geometry.camera import write_cameras
    from satsweep.pipeline.altitude import prior_altitude_range
    from satsweep.pipeline.area import AreaJob, RunContext, Split, Wait, run_area, sources_seeing
    from satsweep.pipeline.mosaic import save_cloud_piece, save_piece
    from satsweep.pipeline.outputs import RPC_DIR, write_corrected_rpcs
    from satsweep.pipeline.report import to_json
    from satsweep.pipeline.tiling import sub_grid

    s, tile = task.settings, task.tile
    sources = list(task.sources)
    if not task.whole:
        prior = prior_altitude_range(sources, tile.aoi, alt_range=s.alt_range, dem=s.dem)
        sources = sources_seeing(sources, tile.aoi, prior)
        if len(sources) < 2:
            return TileOutcome(kind="unseen", core=tile.core, images=[x.path for x in sources],
                               seen_shares=_seen_shares(sources, tile, prior))
    seen = [x.path for x in sources]
    if task.seeing is not None and list(task.seeing) != seen:  # cannot happen: same inputs
        raise RuntimeError(f"cells {tile.core}: seen by {seen}, was {list(task.seeing)}")
    ctx = RunContext(device=device, config=s.config, report=report, alt_range=s.alt_range,
                     dem=s.dem)
    borrowed = (None if task.borrowed_shifts is None
                else {path: list(v) for path, v in zip(seen, task.borrowed_shifts)})
    job = AreaJob(sources=sources, aoi=tile.aoi, grid=tile.grid,
                  split_above_px=task.split_above_px, borrowed_shifts=borrowed,
                  may_wait=task.may_wait)
    result = run_area(job, ctx)
    if isinstance(result, Split):
        return TileOutcome(kind="split", core=tile.core, images=seen,
                           max_error_px=float(result.max_error_px))
    if isinstance(result, Wait):
        return TileOutcome(kind="wait", core=tile.core, images=seen, reason=result.reason)
    folder = Path(task.folder)
    rows, cols = tile.core_in_window
    area = result.rasters
    core = {"dsm": area.dsm[rows, cols], "confidence": area.confidence[rows, cols],
            "count": area.count[rows, cols]}
    if area.ortho is not None:
        core["ortho"] = area.ortho[rows, cols]
    save_piece(folder, tile.core, core)
    points = save_cloud_piece(folder, area.clouds,
                              None if task.whole else sub_grid(task.grid, *tile.core))
    write_cameras(folder, result.cameras)
    if result.shifts is not None:  # this area's own adjustment (not borrowed corrections)
        write_corrected_rpcs(folder / RPC_DIR, sources, result.shifts)
    return TileOutcome(kind="done", core=tile.core, images=seen, names=result.record.names,
                       entry=json.loads(to_json(result.record.to_report())),
                       shifts=(None if result.shifts is None
                               else [result.shifts.get(path) for path in seen]),
                       bands=list(core), cloud_points=points,
                       seen_shares=_seen_shares(sources, tile, result.record.altitude.range,
                                                core["dsm"]))


def _seen_shares(sources: Sequence["ImageSource"], tile: "Tile", alt_range: "AltitudeRange",
                 dsm: np.ndarray | None = None) -> dict[str, float]:
    """Per image, the share of the tile's core cells it sees: cell centres (at most
    SEEN_SAMPLES per side, evenly spread) at their height in ``dsm`` (the core's, where it has
    one) or else at the middle of ``alt_range``, projected by the image's RPC inside its
    pixels."""
    from satsweep.geometry.geodesy import utm_to_lonlat

    rows, cols = tile.core_in_window
    g = tile.grid
    r = np.linspace(rows.start + 0.5, rows.stop - 0.5, min(SEEN_SAMPLES, rows.stop - rows.start))
    c = np.linspace(cols.start + 0.5, cols.stop - 0.5, min(SEEN_SAMPLES, cols.stop - cols.start))
    x, y = np.meshgrid(g.x_min + c * g.resolution, g.y_max - r * g.resolution)
    lon, lat = utm_to_lonlat(x=x.ravel(), y=y.ravel(), epsg=g.epsg)
    alt = np.full(lon.shape, 0.5 * (alt_range.min + alt_range.max))
    if dsm is not None:  # the core's own heights at the sampled cells
        z = dsm[np.floor(r - rows.start).astype(int)[:, None],
                np.floor(c - cols.start).astype(int)[None, :]].ravel()
        alt = np.where(np.isfinite(z), z, alt)
    shares = {}
    for s in sources:
        col, row = s.rpc.projection(lon=lon, lat=lat, alt=alt)
        height, width = s.shape[0], s.shape[1]
        with np.errstate(invalid="ignore"):
            inside = (col >= -0.5) & (col <= width - 0.5) & (row >= -0.5) & (row <= height - 0.5)
        shares[s.path] = round(float(np.mean(inside)), 4)
    return shares


# -- runners ---------------------------------------------------------------------------------------
class InProcessRunner:
    """Tasks run one after the other in this process, in the order of the run's outputs."""

    kind = "in-process"

    def __init__(self, rep: "RunReport"):
        self.rep = rep
        self.workers = 1
        self.dashboard = None
        self.address = None
        self.memory_limit_bytes = None
        self._heap: list = []
        self._seq = 0

    @property
    def pending(self) -> int:
        return len(self._heap)

    def submit(self, task: TileTask) -> None:
        heapq.heappush(self._heap, (task.order, self._seq, task))
        self._seq += 1

    def next_done(self) -> tuple[TileTask, TileOutcome]:
        _, _, task = heapq.heappop(self._heap)
        if not task.whole:
            self.rep.log(f"tile: cells {task.tile.core} ({len(self._heap)} more queued)")
        return task, run_tile_task(task, in_process=True)

    def close(self) -> None:
        pass


class DaskRunner:
    """Tasks run on Dask workers: a ``LocalCluster`` started here, or a running cluster."""

    def __init__(self, rep: "RunReport", *, workers: int, address: str | None,
                 memory_limit_bytes: int | None):
        from distributed import Client, LocalCluster, as_completed

        self.rep = rep
        self.cluster = None
        if address is None:
            self.kind = "local cluster"
            # One thread per worker: a worker holds one device context and one tile at a time.
            self.cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                        memory_limit=memory_limit_bytes,
                                        dashboard_address=":0", silence_logs=logging.ERROR)
            self.client = Client(self.cluster)
        else:
            self.kind = "scheduler"
            try:
                self.client = Client(address, timeout=SCHEDULER_TIMEOUT_S)
            except (OSError, TimeoutError, ValueError) as exc:
                raise OptionsError(f"--scheduler {address}: no Dask scheduler answers there "
                                   f"({exc})") from None
        info = self.client.scheduler_info()
        self.address = info.get("address")
        self.workers = len(info.get("workers", {}))
        self.memory_limit_bytes = memory_limit_bytes
        self.dashboard = (self.client.dashboard_link
                          if "dashboard" in info.get("services", {}) else None)
        self._done = as_completed()
        self._tasks: dict[str, TileTask] = {}

    @property
    def pending(self) -> int:
        return len(self._tasks)

    def submit(self, task: TileTask) -> None:
        # A key per task and output folder: two runs on one cluster never share a task.
        key = "satsweep-tile-" + hashlib.sha256(task.folder.encode("utf-8")).hexdigest()[:24]
        # Earlier areas of the outputs' order first (Dask runs higher priorities first).
        priority = -(task.phase * 10**6 + (task.path[0] if task.path else 0))
        future = self.client.submit(run_tile_task, task, key=key, pure=False,
                                    priority=priority, retries=0)
        self._tasks[future.key] = task
        self._done.add(future)

    def next_done(self) -> tuple[TileTask, TileOutcome]:
        from distributed import KilledWorker

        future = next(self._done)
        task = self._tasks.pop(future.key)
        try:
            outcome = future.result()
        except KilledWorker:
            raise TileKilledError(
                f"cells {task.tile.core}: the tile killed every worker that ran it (out of "
                "memory?): raise [reconstruct] worker_memory_gb or lower tile_m") from None
        finally:
            future.release()
        return task, outcome

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.client.close()
        if self.cluster is not None:
            with contextlib.suppress(Exception):
                self.cluster.close()


def resolve_device_spec(spec: str | None) -> str:
    """The device spec the run asks for: ``spec``, else SATSWEEP_DEVICE, else auto."""
    from satsweep.opencl.device import ENV_VAR

    return (spec or os.environ.get(ENV_VAR) or "auto").strip().lower()


def resolve_scheduler(address: str | None) -> str | None:
    """The scheduler to attach to: ``address``, else SATSWEEP_SCHEDULER, else None."""
    address = address or os.environ.get(SCHEDULER_ENV) or None
    return address.strip() if address else None


def default_workers(device_spec: str) -> int:
    """Workers when none are asked for: 1 on a CPU device (PoCL spreads every kernel over all
    the cores already, so a second worker would only share them), ``GPU_DEFAULT_WORKERS`` on a
    GPU (at most the CPU cores)."""
    from satsweep.opencl.device import select_device

    info = select_device(device_spec)
    if info.kind == "gpu":
        return max(1, min(GPU_DEFAULT_WORKERS, os.cpu_count() or 1))
    return 1


def worker_memory_bytes(tiles: Sequence["Tile"], views: int) -> int:
    """The estimate of a worker's peak memory for the largest of ``tiles`` (its window's
    cells, context included) seen by ``views`` images (see WORKER_BASE_BYTES)."""
    cells = max(t.grid.width * t.grid.height for t in tiles)
    return int(WORKER_BASE_BYTES + WORKER_BYTES_PER_CELL_VIEW * cells * views)


def open_runner(settings: RunSettings, tiles: Sequence["Tile"], views: int,
                rep: "RunReport") -> InProcessRunner | DaskRunner:
    """Where the run's tiles go (see the module docstring); the choice is logged and goes to
    the report's ``execution``."""
    r = settings.config.reconstruct
    address = resolve_scheduler(r.scheduler)
    estimate = worker_memory_bytes(tiles, views)
    if address is None:
        workers = r.workers or default_workers(settings.device)
        if workers <= 1 or len(tiles) <= 1:
            if workers > 1:
                rep.log(f"AOI in one piece: its tile runs in this process, not on {workers} "
                        "workers")
            return InProcessRunner(rep)
        limit = (int(r.worker_memory_gb * 2**30) if r.worker_memory_gb > 0 else
                 max(int(WORKER_MEMORY_SAFETY * estimate), WORKER_MEMORY_FLOOR_BYTES))
        total = _physical_memory_bytes()
        if total is not None and workers * limit > total:
            rep.warn(f"{workers} workers of {limit / 2**30:.1f} GiB each need more than this "
                     f"machine's {total / 2**30:.1f} GiB: use fewer workers or smaller tiles")
        runner = DaskRunner(rep, workers=workers, address=None, memory_limit_bytes=limit)
        rep.log(f"Dask: a local cluster of {runner.workers} workers, "
                f"{limit / 2**30:.1f} GiB each")
    else:
        runner = DaskRunner(rep, workers=0, address=address, memory_limit_bytes=None)
        rep.log(f"Dask: scheduler {runner.address} with {runner.workers} workers (each needs "
                f"about {estimate / 2**30:.1f} GiB per tile)")
        if runner.workers == 0:
            rep.log("Dask: no worker yet: the tiles wait for the cluster's workers")
    if runner.dashboard:
        rep.log(f"Dask dashboard: {runner.dashboard}")
    return runner


def _physical_memory_bytes() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def execution_summary(runner, *, reused: int, computed: int, retries: int,
                      outcomes: Sequence[TileOutcome]) -> dict:
    """The report's ``execution``: where the tiles ran, how many were reused from an earlier
    run (``--resume``) and computed, the reruns after a worker died, and the peak resident
    memory of each process that computed ``outcomes`` (host:pid; this one in process)."""
    peaks: dict[str, float] = {}
    for o in outcomes:
        w = o.worker or {}
        if w.get("peak_memory_mb") is not None:
            key = f"{w.get('host')}:{w.get('pid')}"
            peaks[key] = max(peaks.get(key, 0.0), w["peak_memory_mb"])
    limit = runner.memory_limit_bytes
    return {"mode": runner.kind, "workers": runner.workers, "scheduler": runner.address,
            "dashboard": runner.dashboard,
            "worker_memory_limit_mb": None if limit is None else round(limit / 2**20, 1),
            "tiles_reused": reused, "tiles_computed": computed, "retries": retries,
            "tile_seconds": sum(o.seconds for o in outcomes),
            "tile_seconds_max": max((o.seconds for o in outcomes), default=0.0),
            "worker_peak_memory_mb": dict(sorted(peaks.items())),
            "max_worker_peak_memory_mb": max(peaks.values()) if peaks else None}

