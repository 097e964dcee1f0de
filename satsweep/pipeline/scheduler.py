"""The areas of a run (the AOI in one piece, or its tiles) as tile tasks, gathered into a mosaic.

Tiles come from ``satsweep.pipeline.tiling``; each is a task (``satsweep.pipeline.cluster``)
that runs in this process or on Dask workers and writes its results into the run's
finished-tiles folder. Each tile takes the images that see it (a large AOI need not lie in every
image); one seen by fewer than two is left without heights. A task answers:

- ``split``: its cameras are too far from the RPCs: its 2 x 2 parts become tasks;
- ``wait``: its views match too poorly for their own bundle adjustment. A pointing error is a
  translation of the whole image, so once every other task has finished it runs again with,
  per view, the median of the corrections of all the tiles that could adjust themselves: an
  explicit dependency on a fixed set of tiles, so that its result does not depend on which
  tiles happened to finish first;
- ``failed``: its data defeated it (no matches, no valid pixels): reported, left empty;
- ``done``: its rasters, cloud and cameras are in its folder.

The mosaic lists the finished areas in a fixed order (``TileTask.order``: the order one process
taking the tiles in turn finishes them), whatever order the workers finish them in, so that the
cloud and the report do not depend on the number of workers.
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from satsweep.errors import InputError
from satsweep.pipeline.area import median_shifts
from satsweep.pipeline.cluster import (
    RunSettings,
    TileOutcome,
    TileTask,
    load_outcome,
    reset_folder,
    settings_fingerprint,
    task_fingerprint,
    task_folder,
)
from satsweep.pipeline.mosaic import AreaPiece, load_piece

if TYPE_CHECKING:  # pragma: no cover
    from satsweep.geometry.aoi import AOI
    from satsweep.io.sources import ImageSource
    from satsweep.pipeline.report import RunReport
    from satsweep.pipeline.tiling import Tile
    from satsweep.products.grid import DSMGrid


@dataclasses.dataclass(frozen=True, eq=False)
class FinishedArea:
    """A finished area: its tile, its task's outcome and its folder of results."""

    tile: "Tile"
    outcome: TileOutcome
    folder: Path

    @property
    def piece(self) -> AreaPiece:
        return load_piece(self.folder)

    @property
    def cameras_file(self) -> Path:
        return self.folder / "cameras.json"


@dataclasses.dataclass(eq=False)
class Mosaic:
    """What the areas of a run made: their folders of results (each area's core cells of the
    DSM, confidence and orthophoto rasters, see ``satsweep.pipeline.mosaic``, its cloud piece and
    cameras) and their figures, in the outputs' order."""

    grid: "DSMGrid"
    done: list[FinishedArea]
    splits: list[dict[str, Any]]  # the areas cut again: cells, camera error, parts
    unseen: list[dict[str, Any]]  # the tiles seen by fewer than two images
    failed: list[dict[str, Any]]  # the tiles their data defeated: cells, images, reason
    outcomes: list[TileOutcome]  # every task's, reused or computed
    seen_shares: dict[str, float] = dataclasses.field(default_factory=dict)  # per image, the
    # share of the AOI it sees (``aoi_seen_shares``)
    computed_outcomes: list[TileOutcome] = dataclasses.field(default_factory=list)  # this run's
    reused: int = 0  # tasks whose results an earlier run had finished (--resume)
    computed: int = 0  # tasks run by this run
    retries: int = 0  # task starts beyond the first (a worker died mid-tile)

    @property
    def pieces(self) -> list[AreaPiece]:
        return [area.piece for area in self.done]

    @property
    def tiled(self) -> bool:
        """More than one area, or part of the AOI left unseen or failed."""
        return len(self.done) > 1 or bool(self.unseen) or bool(self.failed)


def reconstruct_areas(sources: Sequence["ImageSource"], aoi: "AOI", grid: "DSMGrid",
                      tiles: list["Tile"], settings: RunSettings, runner, cache: str | os.PathLike,
                      rep: "RunReport") -> Mosaic:
    """Every area of ``tiles`` (cut again where their cameras need it) into a ``Mosaic`` on
    ``grid``: each a task of ``runner``, its results in its folder of ``cache`` (reused when an
    earlier run finished the same task there)."""
    from satsweep.pipeline.tiling import MIN_TILE_M, can_split, split_tile

    r = settings.config.reconstruct
    whole = (0, grid.height, 0, grid.width)
    common = settings_fingerprint(settings)
    sources = tuple(sources)
    ready: list[tuple[TileTask, TileOutcome]] = []  # reused from the cache, not yet handled
    mosaic = Mosaic(grid=grid, done=[], splits=[], unseen=[], failed=[], outcomes=[])
    finished: list[tuple[tuple, FinishedArea]] = []
    splits, unseen, failed, waiting = [], [], [], []
    several = len(tiles) > 1

    def submit(tile: "Tile", path: tuple[int, ...], *, phase: int = 0, borrowed=None,
               seeing=None) -> None:
        is_whole = tile.core == whole
        split_above = r.tile_max_error_px if can_split(tile, grid, MIN_TILE_M) else 0.0
        may_wait = phase == 0 and (several or not is_whole)
        fingerprint = task_fingerprint(common, sources, tile, whole=is_whole, phase=phase,
                                       split_above_px=split_above, may_wait=may_wait,
                                       borrowed=borrowed, seeing=seeing)
        folder = task_folder(cache, fingerprint)
        task = TileTask(path=path, phase=phase, tile=tile, grid=grid, whole=is_whole,
                        sources=sources, settings=settings, split_above_px=split_above,
                        borrowed_shifts=borrowed, seeing=seeing, may_wait=may_wait,
                        folder=os.fspath(Path(folder).absolute()), fingerprint=fingerprint)
        outcome = load_outcome(folder)
        if outcome is not None:
            ready.append((task, outcome))
            mosaic.reused += 1
            return
        reset_folder(folder)
        runner.submit(task)

    for k, tile in enumerate(tiles):
        submit(tile, (k,))
    t_start = time.perf_counter()
    while True:
        if ready:
            task, outcome = ready.pop(0)
            computed = False
        elif runner.pending:
            task, outcome = runner.next_done()
            computed = True
            mosaic.computed += 1
            mosaic.retries += max(0, outcome.attempts - 1)
            mosaic.computed_outcomes.append(outcome)
        elif waiting:
            # Every other task has finished: the corrections of the tiles that adjusted
            # themselves are known, whatever order they finished in.
            for task, outcome in sorted(waiting, key=lambda item: item[0].order):
                borrowed = _borrowed(finished, outcome.images)
                submit(task.tile, task.path, phase=1, borrowed=borrowed,
                       seeing=tuple(outcome.images))
            waiting = []
            continue
        else:
            break
        mosaic.outcomes.append(outcome)
        _merge_report(rep, outcome, printed=computed and runner.kind == "in-process")
        if computed:
            _log_progress(rep, task, outcome, mosaic, runner, t_start)
        if outcome.kind == "error":
            raise outcome.exception()
        if outcome.kind == "done":
            finished.append((task.order, FinishedArea(tile=task.tile, outcome=outcome,
                                                      folder=Path(task.folder))))
        elif outcome.kind == "wait":
            waiting.append((task, outcome))
        elif outcome.kind == "split":  # the cameras are too far from the RPCs: cut it again
            parts = split_tile(task.tile, aoi, grid, overlap_m=r.tile_overlap_m,
                               min_m=MIN_TILE_M)
            rep.log(f"cameras up to {outcome.max_error_px:.3f} px from the RPCs over cells "
                    f"{task.tile.core} (more than tile_max_error_px = {r.tile_max_error_px:g}): "
                    f"{len(parts)} tiles")
            splits.append((task.order, {"core_cells": list(task.tile.core),
                                        "max_error_px": outcome.max_error_px,
                                        "into": len(parts)}))
            several = True
            for j, part in enumerate(parts):
                submit(part, task.path + (j,))
        elif outcome.kind == "unseen":
            unseen.append((task.order, {"core_cells": list(task.tile.core),
                                        "images": [os.path.basename(p) for p in outcome.images]}))
        elif outcome.kind == "failed":
            failed.append((task.order, outcome))
    mosaic.done = [area for _, area in sorted(finished, key=lambda item: item[0])]
    mosaic.splits = [entry for _, entry in sorted(splits, key=lambda item: item[0])]
    mosaic.unseen = [entry for _, entry in sorted(unseen, key=lambda item: item[0])]
    if mosaic.unseen:  # one line for them all: a large AOI may have hundreds
        cells = sum((c[1] - c[0]) * (c[3] - c[2]) for c in (e["core_cells"] for e in mosaic.unseen))
        rep.warn(f"{len(mosaic.unseen)} tile(s), {100 * cells / (grid.width * grid.height):.1f}% "
                 "of the AOI, are seen by fewer than two images: left without heights (report: "
                 "tiling.unseen)")
    # One line per image for the whole AOI (not one per tile at an image's edge, nor one per
    # area swept again or cut), from the areas' shares.
    from satsweep.io.views import PARTIAL_AOI_WARN_FRACTION

    mosaic.seen_shares = aoi_seen_shares(mosaic.outcomes, [s.path for s in sources])
    for path, share in mosaic.seen_shares.items():
        if share < PARTIAL_AOI_WARN_FRACTION:
            rep.warn(f"{path}: the image sees only about {100 * share:.0f}% of the AOI")
    failed.sort(key=lambda item: item[0])
    mosaic.failed = [{"core_cells": list(o.core), "images": [os.path.basename(p) for p in o.images],
                      "reason": o.reason} for _, o in failed]
    if not mosaic.done:
        if failed:
            raise failed[0][1].exception()
        raise InputError(None, f"no tile of the AOI is seen by two of the images "
                               f"({', '.join(s.name for s in sources)})")
    return mosaic


def aoi_seen_shares(outcomes: Sequence[TileOutcome], images: Sequence[str]) -> dict[str, float]:
    """Per image of ``images``, the share of the AOI it sees: the mean over the tiles that were
    done or unseen (the others were cut again, retried, or their data failed them) of the share
    of each tile it sees (``TileOutcome.seen_shares``; 0 where it does not see the tile),
    weighted by the tile's cells, rounded to 1e-4."""
    final = [o for o in outcomes if o.kind in ("done", "unseen")]
    cells = [(o.core[1] - o.core[0]) * (o.core[3] - o.core[2]) for o in final]
    total = sum(cells)
    if total == 0:
        return {}
    return {path: round(sum(n * o.seen_shares.get(path, 0.0) for n, o in zip(cells, final))
                        / total, 4) for path in images}


def _borrowed(finished: list[tuple[tuple, FinishedArea]], images: Sequence[str]):
    """Per image of ``images``, the median of the corrections of the finished tiles that
    adjusted themselves (None when an image has none)."""
    shifts: dict[str, list] = {path: [] for path in images}
    for _, area in sorted(finished, key=lambda item: item[0]):
        o = area.outcome
        for path, shift in zip(o.images, o.shifts or []):
            if path in shifts and shift is not None:
                shifts[path].append(shift)
    if not all(shifts[path] for path in images):
        return None
    return tuple(tuple(float(v) for v in s) for s in median_shifts([shifts[p] for p in images]))


def _merge_report(rep: "RunReport", outcome: TileOutcome, *, printed: bool) -> None:
    """A task's stage timings (added up), peak memory per stage (the highest) and warnings
    (printed unless they were as they came) into the run's report."""
    data = outcome.report or {}
    timings = rep.data["timings_s"]
    for name, seconds in data.get("timings_s", {}).items():
        timings[name] = timings.get(name, 0.0) + seconds
    peaks = rep.data["peak_memory_mb"]
    for name, mb in data.get("peak_memory_mb", {}).items():
        peaks[name] = max(peaks.get(name, 0.0), mb)
    for warning in data.get("warnings", []):
        if printed:
            rep.data["warnings"].append(warning)
        else:
            rep.warn(warning["message"], doubtful=warning["doubtful"])


def _log_progress(rep: "RunReport", task: TileTask, outcome: TileOutcome, mosaic: Mosaic,
                  runner, t_start: float) -> None:
    """A progress line for a computed task: the tasks finished, the time left at this pace."""
    if task.whole:
        return
    done = mosaic.computed
    pending = runner.pending
    spent = time.perf_counter() - t_start
    left = f", about {spent / done * pending:.0f} s left" if pending else ""
    retried = (f"; ran {outcome.attempts} times (a worker died)" if outcome.attempts > 1
               else "")
    rep.log(f"tiles: {done} of {done + pending} done (cells {task.tile.core}: {outcome.kind}"
            f"{retried}); {spent:.0f} s so far{left}")
