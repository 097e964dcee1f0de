"""The run's output folder (staged, then committed) and the writers of its products."""

from __future__ import annotations

import dataclasses
import math
import os
import secrets
import shutil
from pathlib import Path

from satsweep.pipeline.report import RunReport, to_json


@dataclasses.dataclass(frozen=True)
class ReconstructResult:
    """A finished run: its output folder, the DSM's path, the report and the evaluation (None
    without a truth)."""

    out_dir: Path
    dsm_path: Path
    report: dict
    evaluation: dict | None


# The folder (in the output folder, or in each tile's) of the views' RPCs with their pointing
# corrections folded in.
RPC_DIR = "rpc"


# What a run may write into its output folder: with --overwrite, those of an earlier run that
# this run does not write again are removed, so that the folder holds one run's outputs.
PRODUCTS = ("dsm.tif", "confidence.tif", "ortho.tif", "count.tif", "interpolated.tif",
            "cloud.ply", "dsm.png", "cameras.json", "config.toml", "report.json", "evaluation",
            "tiles", "images", RPC_DIR)


# The intermediate files' folder inside the staging folder (OutputFolder.work).
WORK_DIR = ".work"


class OutputFolder:
    """Stage outputs in a hidden folder inside ``out_dir``; move them in place on ``commit``.

    ``out_dir`` may not exist (it is created, with its missing parents) or be empty; a non-empty
    one needs ``overwrite`` (then the outputs of an earlier run that this one does not write
    again are removed on ``commit``; other files are left alone). Staging folders left by killed
    runs are removed. ``abort`` removes the staging folder, and the folders this run created.

    The run's finished tiles go to ``cache`` (``out_dir/.satsweep-tiles``), beside the staging
    folder rather than in it: ``abort`` keeps them (with ``out_dir``) so that a run with
    ``resume`` reuses them; a run without ``resume`` starts by clearing them; ``commit`` removes
    them.
    """

    def __init__(self, out_dir: str | os.PathLike, *, overwrite: bool, resume: bool = False):
        from satsweep.errors import InputError
        from satsweep.io.atomic import RESUME_CACHE, STAGING_OWNER, STAGING_PREFIX, stale_staging

        self.out_dir = Path(out_dir)
        self.overwrite = overwrite
        self.resume = resume
        self.check(self.out_dir, overwrite=overwrite)
        # The topmost folder this run creates: removed again if the run fails.
        self.created_root = None
        for folder in [self.out_dir, *self.out_dir.absolute().parents]:
            if folder.exists():
                break
            self.created_root = folder
        self.staging: Path | None = None
        self.cache = self.out_dir / RESUME_CACHE
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            for stale in stale_staging(self.out_dir):
                shutil.rmtree(stale, ignore_errors=True)
            self._make_staging(STAGING_PREFIX)
            (self.staging / STAGING_OWNER).write_text(str(os.getpid()), encoding="ascii")
            if not resume:
                shutil.rmtree(self.cache, ignore_errors=True)
            self.cache.mkdir(exist_ok=True)
            (self.cache / STAGING_OWNER).write_text(str(os.getpid()), encoding="ascii")
        except OSError as exc:
            self._undo_init()
            raise InputError(self.out_dir, f"cannot write the output folder "
                                           f"({exc.strerror or exc})") from None
        except BaseException:
            # Ctrl-C, SIGTERM or SIGHUP while the folders are being made: the caller has no
            # object to abort, so nothing of them may be left.
            self._undo_init()
            raise

    def _make_staging(self, prefix: str) -> None:
        """Create the staging folder, its name known before it exists (``self.staging``), so
        that an interruption at any moment leaves nothing that ``_undo_init`` does not know."""
        while True:
            self.staging = self.out_dir / f"{prefix}{secrets.token_hex(4)}"
            try:
                self.staging.mkdir(mode=0o700)
                return
            except FileExistsError:
                continue

    def _undo_init(self) -> None:
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
        if not self.resume:
            shutil.rmtree(self.cache, ignore_errors=True)
        self._remove_created()

    @property
    def created(self) -> bool:
        """Whether this run created ``out_dir``."""
        return self.created_root is not None

    @staticmethod
    def check(out_dir: Path, *, overwrite: bool) -> None:
        """Refuse a path that is a file, or a non-empty folder without ``overwrite``."""
        from satsweep.io.atomic import check_output_dir

        check_output_dir(out_dir, overwrite=overwrite)

    def path(self, name: str) -> Path:
        p = self.staging / name
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    @property
    def work(self) -> Path:
        """A folder for the run's intermediate files (the areas' pieces, the bands on disk):
        inside the staging folder, never moved into ``out_dir``."""
        p = self.staging / WORK_DIR
        p.mkdir(exist_ok=True)
        return p

    def commit(self) -> list[Path]:
        """Move the staged outputs into ``out_dir``; return their final paths."""
        from satsweep.io.atomic import STAGING_OWNER

        (self.staging / STAGING_OWNER).unlink(missing_ok=True)
        shutil.rmtree(self.staging / WORK_DIR, ignore_errors=True)
        written = {p.relative_to(self.staging).parts[0] for p in self.staging.rglob("*")}
        if self.overwrite:  # an earlier run's outputs that this run does not replace
            for name in PRODUCTS:
                old = self.out_dir / name
                if name in written or not (old.exists() or old.is_symlink()):
                    continue
                if old.is_dir() and not old.is_symlink():
                    shutil.rmtree(old, ignore_errors=True)
                else:
                    old.unlink(missing_ok=True)
        moved = []
        for src in sorted(self.staging.rglob("*")):
            if src.is_file():
                dst = self.out_dir / src.relative_to(self.staging)
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.replace(src, dst)
                moved.append(dst)
        shutil.rmtree(self.staging, ignore_errors=True)
        shutil.rmtree(self.cache, ignore_errors=True)
        return moved

    def abort(self, *, keep_tiles: bool = False) -> int:
        """Remove the staging folder; with ``keep_tiles`` keep the finished tiles, if any, for
        ``--resume`` (and so ``out_dir``), else remove their folder and every folder this run
        created. Returns the number of finished tiles kept."""
        from satsweep.io.atomic import STAGING_OWNER
        from satsweep.pipeline.cluster import finished_entries

        shutil.rmtree(self.staging, ignore_errors=True)
        kept = finished_entries(self.cache) if keep_tiles else 0
        if kept:
            (self.cache / STAGING_OWNER).unlink(missing_ok=True)
        else:
            shutil.rmtree(self.cache, ignore_errors=True)
            self._remove_created()
        return kept

    def _remove_created(self) -> None:
        if self.created_root is not None:
            shutil.rmtree(self.created_root, ignore_errors=True)


# What each raster of the outputs holds: (file, description, unit, GDAL_NODATA, overviews'
# resampling). Heights are above the WGS84 ellipsoid (EPSG:4979), in metres.
RASTERS = {
    "dsm": ("dsm.tif", "height above the WGS84 ellipsoid (EPSG:4979)", "m", math.nan, "average"),
    "confidence": ("confidence.tif", "matching confidence in [0, 1] of the views that made the "
                   "cell's height (NaN: no measured height)",
                   None, math.nan, "average"),
    "ortho": ("ortho.tif", "true orthophoto: the images' value at each cell's highest point",
              None, math.nan, "average"),
    "interpolated": ("interpolated.tif", "0: measured height, 1: interpolated (a small hole "
                     "filled), 255: no height", None, 255, "nearest"),
    "count": ("count.tif", "reference views whose heights agree on the cell's (0: none)", None,
              None, "nearest"),
}
# The longest side (pixels) of the quick look's map.
QUICKLOOK_MAX_PX = 2048


def write_products(bands: dict, cloud, grid, out: OutputFolder) -> Path:
    """The rasters of ``bands`` (name -> ``RawBand`` on ``grid``; see ``RASTERS``) as tiled,
    compressed GeoTIFFs with overviews, the quick look and the cloud (a ``PLYWriter`` holding
    the points, or None) into the staging folder. Returns the DSM's staged path."""
    from satsweep.io.cog import write_cog
    from satsweep.pipeline.mosaic import decimated
    from satsweep.products.quicklook import height_png

    items = {"VERTICAL_REFERENCE": "WGS84 ellipsoid (EPSG:4979), metres",
             "SOFTWARE": "satsweep"}
    for name, band in bands.items():
        filename, description, units, nodata, resampling = RASTERS[name]
        write_cog(out.path(filename), band, epsg=grid.epsg, x_min=grid.x_min, y_max=grid.y_max,
                  resolution=grid.resolution, nodata=nodata, resampling=resampling,
                  description=description, units=units,
                  items=items if name == "dsm" else {"SOFTWARE": "satsweep"}, work_dir=out.work)
    height_png(out.path("dsm.png"), decimated(bands["dsm"], QUICKLOOK_MAX_PX),
               title="satsweep DSM (m above WGS84 ellipsoid)")
    if cloud is not None:
        cloud.commit()
    return out.path("dsm.tif")


def write_corrected_rpcs(folder: str | os.PathLike, sources, shifts) -> list[Path]:
    """Each view's RPC with its pointing correction folded into the offsets
    (``RPCModel.corrected``), as ``folder/<image stem>_RPC.TXT``: GDAL's sidecar format, which
    S2P (rpcm), ASP and GDAL read, so that other tools start from this run's adjustment.

    ``sources``: the views' ``ImageSource`` (``.path``, ``.rpc``); ``shifts``: per image path,
    its correction (col, row) px, as the run applied it (views without one are skipped). Two
    images of one stem in different folders get their index in ``sources`` as a prefix. The
    correction holds over the AOI it was measured on (a translation of the image there).
    """
    from satsweep.geometry.rpc_formats import write_rpc_txt

    folder = Path(folder)
    stems = [Path(s.path).stem for s in sources]
    written = []
    for k, (source, stem) in enumerate(zip(sources, stems)):
        shift = shifts.get(source.path)
        if shift is None:
            continue
        name = f"{stem}_RPC.TXT" if stems.count(stem) == 1 else f"{k:02d}_{stem}_RPC.TXT"
        folder.mkdir(parents=True, exist_ok=True)
        write_rpc_txt(folder / name, source.rpc.corrected(shift))
        written.append(folder / name)
    return written


def evaluate_products(dsm_path: Path, truth, out: OutputFolder, rep: RunReport) -> dict:
    """The "evaluate" stage: the staged DSM against ``truth`` (IARPA MVS3DM; under ``dfc`` the
    DFC2019 protocol's figures too, as published multi-date results give them), written to
    evaluation/ and to the report."""
    from satsweep.products.evaluate import EvaluateOptions, evaluate_dsm

    with rep.stage("evaluate"):
        evaluation = evaluate_dsm(dsm_path, truth, out_dir=out.path("evaluation"))
        evaluation["prediction"] = os.fspath(out.out_dir / dsm_path.name)  # its final name
        dfc = evaluate_dsm(dsm_path, truth, EvaluateOptions(protocol="dfc"))
        evaluation["dfc"] = {k: v for k, v in dfc.items() if k not in ("prediction", "truth")}
        out.path("evaluation/evaluation.json").write_text(to_json(evaluation) + "\n",
                                                          encoding="utf-8")
        rep["evaluation"] = evaluation
    return evaluation
