"""The whole pipeline's configuration: one frozen options object per stage, and its TOML form.

A TOML file holds one table per stage (``[reconstruct]``, ``[camera]``, ``[sparse]``,
``[bundle]``, ``[views]``, ``[sweep]``, ``[mrf]``, ``[dsm]``); each table's keys are that stage's
option fields. Unknown tables and unknown keys are errors naming the file. The command line
overrides the file, and the configuration actually used is written beside the outputs
(``config.toml``), so a run can be repeated exactly with ``--config DIR/config.toml``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import types
from typing import Any, Literal, Mapping

from satsweep.dense.mrf import MRFOptions
from satsweep.dense.selection import ViewSelectionOptions
from satsweep.dense.sweep import SweepOptions
from satsweep.errors import OptionsError
from satsweep.geometry.camera import CameraOptions
from satsweep.options import Options, dumps_toml, load_toml
from satsweep.pipeline.tiling import MIN_TILE_M
from satsweep.products.fusion import DSMOptions
from satsweep.sparse.bundle import BundleOptions
from satsweep.sparse.options import SparseOptions

# Most Dask worker processes a run may ask for (a typo such as 10000 is refused up front).
MAX_WORKERS = 1024


@dataclasses.dataclass(frozen=True)
class ReconstructOptions(Options):
    """Options of the orchestration itself (the stages have their own tables)."""

    device: str | None = None  # OpenCL device: auto, cpu, gpu or PLATFORM:DEVICE; unset: the
    # SATSWEEP_DEVICE environment variable, else auto
    adjust: Literal["auto", "on", "off"] = "auto"  # bundle adjustment of the principal points:
    # auto = with 3+ views, and with 2 views when their features match
    write_cloud: bool = True  # write cloud.ply (every reference view's points, UTM, grey colour)
    write_ortho: bool = True  # write ortho.tif, a true orthophoto on the DSM grid (image units)
    tile_m: float = 1000.0  # an AOI wider or taller than this (m) is reconstructed in tiles of
    # at most this side, each with its own cameras; 0: never
    warn_filled_below: float = 0.2  # a DSM with a smaller fraction of its cells filled gets a
    # warning that its result is doubtful
    max_aoi_km2: float = 2500.0  # an AOI larger than this (km2) is refused before any work
    max_dsm_cells: float = 4e9  # a DSM grid of more cells than this is refused before any work
    skew_correct: bool = True  # shear the images so that K has no skew before the sweep
    crop_margin_px: int = 32  # margin (px) kept around the AOI footprint in each image's crop
    tile_overlap_m: float = 50.0  # context (m) each tile is reconstructed with beyond its cells
    tile_max_error_px: float = 0.1  # an area whose cameras are further than this (px) from
    # their RPCs is cut again in 2 x 2, down to tiles of 50 m; 0: never
    workers: int = 0  # Dask worker processes for the tiles of a tiled AOI, each with its own
    # device context; 0: from the device (1 on a CPU device, in this process: one PoCL worker
    # already uses every core; 2 on a GPU); 1: in this process, without Dask
    scheduler: str | None = None  # address of a running Dask scheduler to run the tiles on
    # (tcp://HOST:8786; Slurm, PBS, Kubernetes clusters); unset: SATSWEEP_SCHEDULER, else local
    worker_memory_gb: float = 0.0  # memory limit (GiB) of each local Dask worker; 0: from the
    # tile size (satsweep.pipeline.cluster.worker_memory_bytes)

    ADVANCED = ("warn_filled_below", "max_aoi_km2", "max_dsm_cells", "skew_correct", "crop_margin_px",
                "tile_overlap_m", "tile_max_error_px", "worker_memory_gb")
    # The altitude range without --alt-range or --dem came from quantiles of tie points
    # triangulated with the raw RPCs until the sparse stage's adjusted tie points replaced them
    # everywhere (wrong matches among many views widened those quantiles by tens of metres).
    RETIRED = types.MappingProxyType({
        key: "the altitude range now comes from the sparse stage's adjusted tie points; "
             "[sparse] altitude_margin_below_m and altitude_margin_above_m set its margins"
        for key in ("tie_altitude_quantile", "tie_altitude_margin_m")})
    # How the tiles are run, not what they compute: left out of the finished tiles'
    # fingerprints, so that a run resumed with other workers reuses them.
    EXECUTION = ("workers", "scheduler", "worker_memory_gb")

    def check(self) -> None:
        self._require(self.device is None or bool(self.device.strip()), "device",
                      "must be auto|cpu|gpu|PLATFORM:DEVICE")
        self._require(0 <= self.crop_margin_px <= 4096, "crop_margin_px", "must be in [0, 4096]")
        self._require(self.tile_m == 0.0 or (math.isfinite(self.tile_m)
                                             and self.tile_m >= MIN_TILE_M),
                      "tile_m", f"must be 0 (no tiling) or at least {MIN_TILE_M:g} metres")
        self._require(math.isfinite(self.tile_overlap_m) and self.tile_overlap_m >= 0.0
                      and (self.tile_m == 0.0 or self.tile_overlap_m <= self.tile_m),
                      "tile_overlap_m", "must be a number of metres in [0, tile_m]")
        self._require(0.0 <= self.warn_filled_below <= 1.0, "warn_filled_below",
                      "must be a fraction in [0, 1]")
        self._require(math.isfinite(self.max_aoi_km2) and self.max_aoi_km2 > 0.0, "max_aoi_km2",
                      "must be a positive number of square kilometres")
        self._require(math.isfinite(self.max_dsm_cells) and self.max_dsm_cells >= 1.0,
                      "max_dsm_cells", "must be a number of cells >= 1")
        self._require(math.isfinite(self.tile_max_error_px) and self.tile_max_error_px >= 0.0,
                      "tile_max_error_px", "must be a number of pixels >= 0 (0: off)")
        self._require(0 <= self.workers <= MAX_WORKERS, "workers",
                      f"must be a number of worker processes in [0, {MAX_WORKERS}] (0: from the "
                      "device)")
        self._require(self.scheduler is None or bool(self.scheduler.strip()), "scheduler",
                      "must be a Dask scheduler address such as tcp://HOST:8786")
        self._require(math.isfinite(self.worker_memory_gb) and self.worker_memory_gb >= 0.0,
                      "worker_memory_gb", "must be a number of GiB >= 0 (0: from the tile size)")


# Written above every stage's advanced sub-table.
ADVANCED_HEADER = ("Tuning knobs: their defaults were measured (docs/measurements.md); change "
                   "them with a benchmark at hand.")

SECTIONS: dict[str, type[Options]] = {
    "reconstruct": ReconstructOptions,
    "camera": CameraOptions,
    "sparse": SparseOptions,
    "bundle": BundleOptions,
    "views": ViewSelectionOptions,
    "sweep": SweepOptions,
    "mrf": MRFOptions,
    "dsm": DSMOptions,
}


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """All stages' options. Every field has its stage's defaults."""

    reconstruct: ReconstructOptions = ReconstructOptions()
    camera: CameraOptions = CameraOptions()
    sparse: SparseOptions = SparseOptions()
    bundle: BundleOptions = BundleOptions()
    views: ViewSelectionOptions = ViewSelectionOptions()
    sweep: SweepOptions = SweepOptions()
    mrf: MRFOptions = MRFOptions()
    dsm: DSMOptions = DSMOptions()

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], *, source: str = "config") -> "PipelineConfig":
        unknown = sorted(set(data) - set(SECTIONS))
        if unknown:
            raise OptionsError(f"{source}: unknown table(s) [{'], ['.join(unknown)}] "
                               f"(known: {', '.join(SECTIONS)})")
        values = {}
        for name, table in data.items():
            if not isinstance(table, Mapping):
                raise OptionsError(f"{source}: '{name}' must be a table ([{name}])")
            values[name] = SECTIONS[name].from_mapping(table, source=f"{source} [{name}]")
        return cls(**values)

    @classmethod
    def from_toml(cls, path: str | os.PathLike) -> "PipelineConfig":
        return cls.from_mapping(load_toml(path), source=os.fspath(path))

    def override(self, section: str, **changes: Any) -> "PipelineConfig":
        """A copy with some fields of one section changed (None values are ignored)."""
        if section not in SECTIONS:
            raise OptionsError(f"no configuration section {section!r} (known: "
                               f"{', '.join(SECTIONS)})")
        changes = {k: v for k, v in changes.items() if v is not None}
        if not changes:
            return self
        return dataclasses.replace(self, **{section: getattr(self, section).replace(**changes)})

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return {name: getattr(self, name).to_dict() for name in SECTIONS}

    def to_toml(self, header: str = "satsweep configuration (as used by this run)",
                comments: bool = True) -> str:
        """TOML text of every option, one table per stage and the tuning knobs in its
        ``advanced`` sub-table; with ``comments`` each key is preceded by its field's comment in
        the source (what it means and its unit)."""
        tables = {name: getattr(self, name).to_tables() for name in SECTIONS}
        notes = {name: SECTIONS[name].field_comments() for name in SECTIONS} if comments else None
        headers = ({f"{name}.{options.ADVANCED_TABLE}": ADVANCED_HEADER
                    for name, options in SECTIONS.items()} if comments else None)
        return f"# {header}\n" + dumps_toml(tables, notes, headers)
