"""The run's output folder (staged, then committed) and the writers of its products."""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from satsweep.pipeline.report import RunReport, to_json


@dataclasses.dataclass(frozen=True)
class ReconstructResult:
    """A finished run: its output folder, the DSM's path, the report and the evaluation (None
    without a truth)."""

    out_dir: Path
    dsm_path: Path
    report: dict
    evaluation: dict | None


class OutputFolder:
    """Stage outputs in a hidden folder inside ``out_dir``; move them in place on ``commit``.

    ``out_dir`` may not exist (it is created) or be empty; a non-empty one needs ``overwrite``
    (then only the files this run writes are replaced). ``abort`` removes the staging folder, and
    ``out_dir`` too when this run created it.
    """

    def __init__(self, out_dir: str | os.PathLike, *, overwrite: bool):
        self.out_dir = Path(out_dir)
        self.check(self.out_dir, overwrite=overwrite)
        self.created = not self.out_dir.exists()
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.staging = Path(tempfile.mkdtemp(prefix=".satsweep-partial-", dir=self.out_dir))

    @staticmethod
    def check(out_dir: Path, *, overwrite: bool) -> None:
        """Refuse a path that is a file, or a non-empty folder without ``overwrite``."""
        from satsweep.io.atomic import check_output_dir

        check_output_dir(out_dir, overwrite=overwrite)

    def path(self, name: str) -> Path:
        p = self.staging / name
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def commit(self) -> list[Path]:
        moved = []
        for src in sorted(self.staging.rglob("*")):
            if src.is_file():
                dst = self.out_dir / src.relative_to(self.staging)
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.replace(src, dst)
                moved.append(dst)
        shutil.rmtree(self.staging, ignore_errors=True)
        return moved

    def abort(self) -> None:
        shutil.rmtree(self.staging, ignore_errors=True)
        if self.created:
            shutil.rmtree(self.out_dir, ignore_errors=True)


def write_products(fused, conf, ortho, cloud, grid, rep: RunReport, out: OutputFolder, truth):
    """The "outputs" stage's rasters (``ortho`` None: none) and cloud (a ``PLYWriter`` holding
    the points, or None), then the evaluation against ``truth`` if given. Returns (the DSM's
    path in the staging folder, the evaluation or None)."""
    from satsweep.io.geotiff import write_geotiff
    from satsweep.products.grid import write_dsm_geotiff
    from satsweep.products.quicklook import height_png

    with rep.stage("outputs"):
        dsm_path = out.path("dsm.tif")
        write_dsm_geotiff(dsm_path, fused.astype(np.float32), grid)
        write_geotiff(out.path("confidence.tif"), conf.astype(np.float32), epsg=grid.epsg,
                      x_min=grid.x_min, y_max=grid.y_max, resolution=grid.resolution)
        if ortho is not None:
            write_geotiff(out.path("ortho.tif"), ortho.astype(np.float32), epsg=grid.epsg,
                          x_min=grid.x_min, y_max=grid.y_max, resolution=grid.resolution)
        height_png(out.path("dsm.png"), fused, title="satsweep DSM (m above WGS84 ellipsoid)")
        if cloud is not None:
            cloud.commit()
    evaluation = None
    if truth is not None:
        from satsweep.products.evaluate import evaluate_dsm

        with rep.stage("evaluate"):
            evaluation = evaluate_dsm(dsm_path, truth, out_dir=out.path("evaluation"))
            evaluation["prediction"] = os.fspath(out.out_dir / dsm_path.name)  # its final name
            out.path("evaluation/evaluation.json").write_text(to_json(evaluation) + "\n",
                                                              encoding="utf-8")
            rep["evaluation"] = evaluation
    return dsm_path, evaluation
