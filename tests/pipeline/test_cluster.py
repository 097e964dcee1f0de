"""Tiles as tasks (issue 28): on Dask workers the outputs are the same, bit for bit, as in one
process; a worker killed mid-tile has its tile rerun with the same result; an interrupted run
resumes from the tiles it finished; a tile its data defeats is reported and left empty."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio

from satsweep.config import PipelineConfig
from satsweep.errors import CameraError, InputError, OptionsError, OutputExistsError, RPCError
from satsweep.geometry.altitude import AltitudeRange
from satsweep.io.atomic import RESUME_CACHE, STAGING_OWNER, check_output_dir
from satsweep.pipeline import cluster
from satsweep.pipeline.cluster import (
    OUTCOME_FILE,
    START_MARK,
    RunSettings,
    TileOutcome,
    settings_fingerprint,
    task_fingerprint,
)
from satsweep.pipeline.outputs import OutputFolder
from satsweep.pipeline.run import reconstruct
from tests.pipeline.test_pipeline import _alt, _aoi_arg
from tools.digest_outputs import digests

# The small town (its AOI is 59 m square) in 2 x 2 tiles of 30 m with 16 m of context, as the
# tile tests of test_pipeline.py cut it; a fast camera fit.
TILED = {"camera": {"grid_size": [20, 20, 6]},
         "reconstruct": {"tile_m": 50.0, "tile_overlap_m": 16.0}}
N_TILES = 4
# How long a test waits for a run to reach the point where it is disturbed (a tile takes a few
# seconds on 2 cores; a worker's first tile also imports satsweep and builds the kernels).
WAIT_S = 120.0
# The products compared bit for bit (decoded rasters, cloud bytes: tools/digest_outputs.py).
PRODUCTS = {"dsm.tif", "confidence.tif", "ortho.tif", "count.tif", "cloud.ply"}


def _run(scene, out: Path, mapping: dict = TILED, **kwargs):
    return reconstruct([v.image for v in scene.views], scene.aoi, out, alt_range=_alt(scene),
                       config=PipelineConfig.from_mapping(mapping), verbose=False, **kwargs)


def _digests(out: Path) -> dict:
    found = digests(out)
    assert set(found) == PRODUCTS, found
    return found


def _with(mapping: dict, **reconstruct) -> dict:
    return {**mapping, "reconstruct": {**mapping["reconstruct"], **reconstruct}}


@pytest.fixture(scope="module")
def serial(small_town, tmp_path_factory):
    """The tiled run in this process (workers = 1): the reference of every other run here."""
    out = tmp_path_factory.mktemp("serial") / "out"
    result = _run(small_town, out, _with(TILED, workers=1))
    return out, _digests(out), result.report


def test_in_process_run_reports_its_tiles_and_leaves_no_tiles_behind(serial):
    out, _, report = serial
    ex = report["execution"]
    assert ex["mode"] == "in-process" and ex["workers"] == 1 and ex["dashboard"] is None
    assert (ex["tiles_reused"], ex["tiles_computed"], ex["retries"]) == (0, N_TILES, 0)
    assert len(report["aoi_tiles"]) == N_TILES
    assert not (out / RESUME_CACHE).exists()


def _worker_kill_watcher(cache: Path, killed: list[int]):
    """A thread that kills (SIGKILL) the first worker process seen starting a tile in ``cache``
    (its pid is in the tile's start mark; never this process's)."""
    stop = threading.Event()

    def watch():
        deadline = time.monotonic() + WAIT_S
        while not stop.is_set() and time.monotonic() < deadline:
            for mark in cache.glob(f"*/{START_MARK}*"):
                pid = int(mark.name[len(START_MARK):].split("-")[0])
                if pid != os.getpid():
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
                    return
            time.sleep(0.05)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread, stop


def test_two_workers_and_a_killed_worker_give_the_same_outputs(small_town, serial, tmp_path):
    """On a local cluster of 2 workers the DSM, confidence, orthophoto and cloud are those of the
    run in one process, bit for bit, though one worker was killed (SIGKILL) while it ran a tile:
    the scheduler ran that tile again on a worker, and the report counts the rerun."""
    _, reference, _ = serial
    out = tmp_path / "out"
    killed: list[int] = []
    thread, stop = _worker_kill_watcher(out / RESUME_CACHE, killed)
    try:
        result = _run(small_town, out, _with(TILED, workers=2))
    finally:
        stop.set()
        thread.join()
    assert killed, "no worker was seen running a tile"
    ex = result.report["execution"]
    assert ex["mode"] == "local cluster" and ex["workers"] == 2
    assert ex["dashboard"] is None or ex["dashboard"].startswith("http")
    assert ex["worker_memory_limit_mb"] >= cluster.WORKER_MEMORY_FLOOR_BYTES / 2**20
    assert ex["tiles_computed"] == N_TILES and ex["retries"] >= 1
    assert killed[0] not in {int(k.split(":")[1]) for k in ex["worker_peak_memory_mb"]}
    assert _digests(out) == reference


@pytest.mark.slow
def test_a_running_scheduler_gives_the_same_outputs(small_town, serial, tmp_path, monkeypatch):
    """SATSWEEP_SCHEDULER (as --scheduler) attaches the run to a running cluster (here a local
    one standing in for dask-jobqueue's): the same outputs, bit for bit."""
    from distributed import Client, LocalCluster

    _, reference, _ = serial
    out = tmp_path / "out"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as local, Client(local) as client:
        monkeypatch.setenv(cluster.SCHEDULER_ENV, local.scheduler_address)
        result = _run(small_town, out)
        pids = set(client.run(os.getpid).values())
    ex = result.report["execution"]
    assert ex["mode"] == "scheduler" and ex["workers"] == 2
    assert ex["scheduler"] == local.scheduler_address
    assert {int(k.split(":")[1]) for k in ex["worker_peak_memory_mb"]} <= pids
    assert _digests(out) == reference


@pytest.mark.slow
def test_local_workers_and_a_killed_command_resumed_give_the_same_outputs(small_town, serial,
                                                                          tmp_path):
    """`satsweep reconstruct --workers 2` starts its own cluster; killed (SIGKILL, no clean-up)
    once a tile has finished, the same command with --resume computes only the tiles that had
    not finished, and the outputs are those of the run in one process, bit for bit."""
    _, reference, _ = serial
    out = tmp_path / "out"
    command = _tiled_command(small_town, tmp_path, out, "--workers", "2")
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        finished = _wait_for_finished_tiles(out / RESUME_CACHE, proc, 1)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the command and the workers it started
        proc.wait()
    assert 1 <= finished < N_TILES
    done = subprocess.run([*command, "--resume"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    ex = json.loads((out / "report.json").read_text())["execution"]
    assert ex["mode"] == "local cluster" and ex["workers"] == 2
    assert ex["tiles_reused"] >= finished and ex["tiles_reused"] + ex["tiles_computed"] == N_TILES
    assert _digests(out) == reference
    assert not (out / RESUME_CACHE).exists()


def _tiled_command(scene, tmp_path: Path, out: Path, *args: str, workers_line: str = "") -> list:
    """The ``satsweep reconstruct`` command line of ``scene`` in the tiles of ``TILED`` (written
    as a config file, with ``workers_line`` in its [reconstruct] table), ``args`` added."""
    config = tmp_path / "tiled.toml"
    config.write_text("[camera]\ngrid_size = [20, 20, 6]\n[reconstruct]\ntile_m = 50.0\n"
                      f"{workers_line}[reconstruct.advanced]\ntile_overlap_m = 16.0\n")
    alt = _alt(scene)
    return [sys.executable, "-m", "satsweep", "reconstruct", *[str(v.image) for v in scene.views],
            "--aoi", _aoi_arg(scene), "--alt-range", str(alt.min), str(alt.max), "--config",
            str(config), "--out", str(out), *args, "--quiet"]


def _wait_for_finished_tiles(cache: Path, proc, count: int) -> int:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline and proc.poll() is None:
        finished = len(list(cache.glob(f"*/{OUTCOME_FILE}")))
        if finished >= count:
            return finished
        time.sleep(0.05)
    raise AssertionError(f"no {count} finished tile(s) in {cache} (exit {proc.poll()})")


def test_a_killed_command_resumes_from_its_finished_tiles(small_town, serial, tmp_path):
    """In one process: the command killed (SIGKILL) once two tiles have finished; the same
    command with --resume reuses them, computes the others, and gives the same outputs."""
    _, reference, _ = serial
    out = tmp_path / "out"
    command = _tiled_command(small_town, tmp_path, out, workers_line="workers = 1\n")
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        _wait_for_finished_tiles(out / RESUME_CACHE, proc, 2)
    finally:
        proc.kill()
        proc.wait()
    finished = len(list((out / RESUME_CACHE).glob(f"*/{OUTCOME_FILE}")))
    assert 2 <= finished < N_TILES
    done = subprocess.run([*command, "--resume"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    report = json.loads((out / "report.json").read_text())
    ex = report["execution"]
    assert (ex["tiles_reused"], ex["tiles_computed"]) == (finished, N_TILES - finished)
    assert _digests(out) == reference
    assert not (out / RESUME_CACHE).exists()
    assert {p.name for p in out.iterdir()} >= {"dsm.tif", "report.json"}


def test_an_interrupted_run_keeps_its_tiles_and_says_so(small_town, tmp_path, monkeypatch,
                                                        capsys):
    """Ctrl-C during the third tile: the staging folder goes, the two finished tiles stay (and
    the output folder the run created), with a line saying how to reuse them; a run without
    resume starts afresh."""
    real = cluster._run_tile
    calls = []

    def interrupted(task, report, device):
        calls.append(task.tile.core)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(task, report, device)

    monkeypatch.setattr(cluster, "_run_tile", interrupted)
    out = tmp_path / "new" / "out"
    with pytest.raises(KeyboardInterrupt):
        _run(small_town, out, _with(TILED, workers=1))
    assert f"2 finished tile(s) kept in {out / RESUME_CACHE}" in capsys.readouterr().err
    assert {p.name for p in out.iterdir()} == {RESUME_CACHE}
    assert len(list((out / RESUME_CACHE).glob(f"*/{OUTCOME_FILE}"))) == 2
    assert not (out / RESUME_CACHE / STAGING_OWNER).exists()
    check_output_dir(out, overwrite=False)  # the kept tiles are no user content

    folder = OutputFolder(out, overwrite=False)  # without resume: the kept tiles are cleared
    assert [p.name for p in folder.cache.iterdir()] == [STAGING_OWNER]
    assert folder.abort(keep_tiles=True) == 0  # nothing finished: nothing kept
    assert not (out / RESUME_CACHE).exists()


def _fingerprint(scene, mapping: dict, **settings) -> str:
    from satsweep.io.sources import open_sources
    from satsweep.pipeline.tiling import Tile
    from satsweep.products.grid import DSMGrid

    grid = DSMGrid(epsg=32631, x_min=0.0, y_max=100.0, resolution=0.5, width=60, height=60)
    tile = Tile(core=(0, 30, 0, 30), window=(0, 46, 0, 46), grid=grid, aoi=scene.aoi)
    common = settings_fingerprint(RunSettings(config=PipelineConfig.from_mapping(mapping),
                                              **{"device": "cpu", "alt_range": _alt(scene),
                                                 **settings}))
    return task_fingerprint(common, open_sources([v.image for v in scene.views]), tile,
                            whole=False, phase=0, split_above_px=0.1, may_wait=True,
                            borrowed=None, seeing=None)


def test_fingerprints_follow_what_a_tile_computes_not_how_it_runs(small_town):
    base = _fingerprint(small_town, TILED)
    assert _fingerprint(small_town, TILED) == base
    for how in ({"workers": 3}, {"scheduler": "tcp://h:8786"}, {"worker_memory_gb": 9.0}):
        assert _fingerprint(small_town, _with(TILED, **how)) == base, how
    assert _fingerprint(small_town, {**TILED, "mrf": {"method": "none"}}) != base
    assert _fingerprint(small_town, _with(TILED, write_cloud=False)) != base
    assert _fingerprint(small_town, TILED, device="gpu") != base
    assert _fingerprint(small_town, TILED, alt_range=AltitudeRange(0.0, 300.0)) != base


def test_a_mask_added_beside_an_image_changes_the_fingerprint(small_town, tmp_path):
    """A mask changes what a tile computes (satsweep.io.masks) though the images do not."""
    import shutil
    from types import SimpleNamespace

    import tifffile

    from satsweep.io.masks import MASK_SUFFIX

    folder = tmp_path / "views"
    shutil.copytree(small_town.views[0].image.parent, folder)
    copy = SimpleNamespace(aoi=small_town.aoi, alt_range=small_town.alt_range,
                           views=[SimpleNamespace(image=folder / v.image.name)
                                  for v in small_town.views])
    base = _fingerprint(copy, TILED)
    shape = tifffile.TiffFile(copy.views[1].image).pages[0].shape[:2]
    mask = str(copy.views[1].image) + MASK_SUFFIX
    tifffile.imwrite(mask, np.full(shape, 255, np.uint8))
    assert _fingerprint(copy, TILED) != base


def test_a_tile_its_data_defeats_is_reported_and_left_empty(small_town, serial, tmp_path,
                                                            monkeypatch):
    """A tile whose views cannot be matched (a CameraError planted in the first tile) is tried
    once, reported under tiling.failed with a warning, and left without heights; the other
    tiles' measured heights are those of the run without the failure."""
    import satsweep.pipeline.area

    real = satsweep.pipeline.area.run_area
    calls = []

    def defeated(job, ctx):
        calls.append(job.grid)
        if len(calls) == 1:  # in one process the planned tiles run in turn: the first one
            raise CameraError("too few matches (planted by the test)")
        return real(job, ctx)

    ref_out, _, ref_report = serial
    first = ref_report["aoi_tiles"][0]["core_cells"]
    monkeypatch.setattr(satsweep.pipeline.area, "run_area", defeated)
    result = _run(small_town, tmp_path / "out", _with(TILED, workers=1))
    assert len(calls) == N_TILES  # the failed tile is not tried again
    (failed,) = result.report["tiling"]["failed"]
    assert failed["core_cells"] == first and "planted" in failed["reason"]
    assert any("planted" in w["message"] for w in result.report["warnings"])
    assert [t["core_cells"] for t in result.report["aoi_tiles"]] == \
        [t["core_cells"] for t in ref_report["aoi_tiles"][1:]]
    with rasterio.open(result.dsm_path) as a, rasterio.open(ref_out / "dsm.tif") as b, \
            rasterio.open(result.out_dir / "interpolated.tif") as c:
        dsm, ref, interpolated = a.read(1), b.read(1), c.read(1)
    r0, r1, c0, c1 = first
    assert np.isnan(dsm[r0:r1, c0:c1]).all()
    measured = interpolated == 0
    assert measured.any()
    np.testing.assert_array_equal(dsm[measured], ref[measured])


def test_errors_travel_back_as_data_and_are_raised_as_themselves():
    for exc in (InputError("/a/b.tif", "cannot read"), RPCError("/x_RPC.TXT", "no LINE_OFF"),
                CameraError("too few matches"), OptionsError("bad")):
        outcome = TileOutcome(kind="error", core=(0, 1, 0, 1), images=[],
                              error=cluster._error_record(exc))
        rebuilt = outcome.exception()
        assert type(rebuilt) is type(exc) and str(rebuilt) == str(exc)
    assert cluster.is_data_error(CameraError("x")) and cluster.is_data_error(InputError(None, "y"))
    assert not cluster.is_data_error(InputError("/f.tif", "unreadable"))


def test_a_folder_whose_tiles_a_live_run_uses_is_refused(tmp_path):
    out = tmp_path / "out"
    (out / RESUME_CACHE).mkdir(parents=True)
    (out / RESUME_CACHE / STAGING_OWNER).write_text(str(os.getppid()))  # a live process
    with pytest.raises(OutputExistsError, match="being written by another satsweep run"):
        check_output_dir(out, overwrite=True)
    (out / RESUME_CACHE / STAGING_OWNER).write_text("999999999")  # no such process
    check_output_dir(out, overwrite=False)


def test_the_command_line_sets_workers_scheduler_and_resume():
    from satsweep.cli import _pipeline_config, build_parser

    args = build_parser().parse_args(["reconstruct", "a.tif", "b.tif", "--aoi", "0,0,1,1",
                                      "--out", "o", "--workers", "3", "--scheduler",
                                      "tcp://head:8786", "--resume"])
    r = _pipeline_config(args).reconstruct
    assert (r.workers, r.scheduler, args.resume) == (3, "tcp://head:8786", True)
    with pytest.raises(OptionsError, match="workers"):
        PipelineConfig.from_mapping({"reconstruct": {"workers": -1}})
    with pytest.raises(OptionsError, match="worker_memory_gb"):
        PipelineConfig.from_mapping({"reconstruct": {"advanced": {"worker_memory_gb": -2.0}}})


def test_worker_memory_follows_the_tile_not_the_aoi():
    """The estimate grows with the largest tile's window and the views, not with the number of
    tiles (what a worker holds is one tile)."""
    from satsweep.pipeline.tiling import Tile
    from satsweep.products.grid import DSMGrid

    def tile(side: int) -> Tile:
        grid = DSMGrid(epsg=32631, x_min=0.0, y_max=0.0, resolution=0.5, width=side, height=side)
        return Tile(core=(0, side, 0, side), window=(0, side, 0, side), grid=grid, aoi=None)

    one = cluster.worker_memory_bytes([tile(1000)], 2)
    assert cluster.worker_memory_bytes([tile(1000)] * 400, 2) == one
    assert one == cluster.WORKER_BASE_BYTES + cluster.WORKER_BYTES_PER_CELL_VIEW * 2 * 1000**2
    assert cluster.worker_memory_bytes([tile(1000), tile(2000)], 2) > one


def test_borrowed_corrections_come_from_a_fixed_set_of_tiles():
    """A waiting tile borrows, per image, the median of the corrections of every finished tile
    that adjusted itself, whatever order they finished in; None when an image has none."""
    import itertools

    from satsweep.pipeline.scheduler import FinishedArea, _borrowed

    def area(k, images, shifts):
        outcome = TileOutcome(kind="done", core=(k, k + 1, 0, 1), images=images, shifts=shifts)
        return ((0, (k,)), FinishedArea(tile=None, outcome=outcome, folder=Path(".")))

    finished = [area(0, ["a", "b"], [[0.1, 0.2], [1.0, 2.0]]),
                area(1, ["a", "b"], [[0.3, 0.0], [1.5, 2.5]]),
                area(2, ["a", "b"], None),  # it borrowed: not one of the set
                area(3, ["b", "c"], [[1.2, 2.2], [5.0, 5.0]])]
    expected = ((0.2, 0.1), (1.2, 2.2))
    for order in itertools.permutations(finished):
        assert _borrowed(list(order), ["a", "b"]) == expected
    assert _borrowed(finished, ["c"]) == ((5.0, 5.0),)
    assert _borrowed(finished[:3], ["a", "c"]) is None
