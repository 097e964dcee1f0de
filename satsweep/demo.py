"""``satsweep demo``: the built-in example, end to end on a synthetic scene with exact truth.

It generates a small seeded town seen by two or more pushbroom satellites (``satsweep.synth``),
reconstructs it from the images and their RPCs alone (``satsweep.pipeline.reconstruct``: the
pipeline estimates its own cameras), and evaluates the DSM against the scene's truth with the
IARPA MVS3DM protocol (``satsweep.products.evaluate``).
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
from pathlib import Path

from satsweep.config import PipelineConfig
from satsweep.geometry.altitude import AltitudeRange
from satsweep.options import Options
from satsweep.pipeline.outputs import ReconstructResult
from satsweep.pipeline.run import reconstruct


@dataclasses.dataclass(frozen=True)
class DemoOptions(Options):
    seed: int = 0  # scene seed
    n_views: int = 2  # satellite views of the scene
    size_px: int = 512  # image side in pixels (0.5 m ground sample distance): a 190 m AOI
    bias_px: float = 0.0  # max pointing bias injected per view (pixels); the pipeline corrects it
    alt_margin_m: float = 5.0  # margin added around the scene's true altitude range

    def check(self) -> None:
        self._require(self.n_views >= 2, "n_views", "need at least two views")
        self._require(64 <= self.size_px <= 2048, "size_px", "must be in [64, 2048]")
        self._require(0 <= self.bias_px <= 10, "bias_px", "must be in [0, 10] pixels")
        self._require(self.alt_margin_m >= 0, "alt_margin_m", "must be >= 0")


def run_demo(out_dir: str | os.PathLike | None = None, *, options: DemoOptions = DemoOptions(),
             config: PipelineConfig = PipelineConfig(), overwrite: bool = False,
             verbose: bool = True) -> tuple[Path, ReconstructResult]:
    """Generate the scene in ``out_dir/scene``, reconstruct it into ``out_dir/reconstruction``.

    ``out_dir`` None: a new folder under the system's temporary directory. Returns the folder
    and the reconstruction result (its ``evaluation`` holds the metrics against the truth).
    """
    from satsweep.pipeline.outputs import OutputFolder
    from satsweep.synth.scene import SynthOptions, generate_scene

    if out_dir is None:
        out_dir = Path(tempfile.mkdtemp(prefix="satsweep-demo-"))
    else:
        out_dir = Path(out_dir)
        OutputFolder.check(out_dir, overwrite=overwrite)
    scene = generate_scene(
        out_dir / "scene",
        SynthOptions(seed=options.seed, n_views=options.n_views, size_px=options.size_px,
                     gsd_m=0.5, bias_px=options.bias_px),
        overwrite=overwrite,
    )
    lo, hi = scene.alt_range
    alt = AltitudeRange(lo - options.alt_margin_m, hi + options.alt_margin_m)
    result = reconstruct([v.image for v in scene.views], scene.aoi, out_dir / "reconstruction",
                         alt_range=alt, config=config, overwrite=overwrite,
                         truth=scene.truth_dsm, verbose=verbose, command="demo")
    return out_dir, result
