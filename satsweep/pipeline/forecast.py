"""The OpenCL programs an area's sweep will build, forecast from its cameras so that they
build in the background meanwhile.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from satsweep.config import PipelineConfig
from satsweep.dense.tiled import coarse_pass_planes, mrf_sweep_options, mrf_sweep_wants_wta
from satsweep.errors import SatsweepError
from satsweep.pipeline.sweeps import (
    area_mrf_options,
    area_sweep_options,
    reference_gsd,
    reference_options,
)


def program_forecast(device, cameras, u_range: tuple[float, float], config: PipelineConfig, *,
                     similarity: np.ndarray | None = None,
                     similarity_source: np.ndarray | None = None,
                     leaf_season: Sequence[float | None] | None = None) -> list:
    """The (source, defines) of the programs that the sweep stage will build, forecast from the
    cameras before adjustment (for ``Device.prebuild``): the view selection and the plane counts
    of those cameras, skew-corrected as the skew stage will do. The selection takes the views'
    ``similarity`` and ``leaf_season`` as ``select_views`` does: on a stack of several dates
    they choose the references and their sources (and so each sweep's source count and plane
    count); the similarity known before the images are compared is enough
    (``similarity.known_similarity``: the metadata's or the tie points'). Adjusting the
    principal points moves every plane's homography by the same translation, which leaves the
    plane spacing, and so the plane count, as it is. A wrong forecast costs only background
    time. [] where the forecast itself fails (the sweep stage then meets the error and reports
    it)."""
    from satsweep.dense.median import median_program, radius_px
    from satsweep.dense.planes import plane_heights
    from satsweep.dense.selection import select_views
    from satsweep.dense.sgm import SGM_MAX_LABELS, sgm_program_requests
    from satsweep.dense.sweep import PlaneSweep
    from satsweep.geometry.parallax import reparametrise
    from satsweep.geometry.skew import skew_corrected_camera

    try:
        cams = [skew_corrected_camera(v.camera)[0] if config.reconstruct.skew_correct else v.camera
                for v in cameras.views]
        projections = [reparametrise(cam, d=v.projection.d, zbar=v.projection.zbar)
                       for cam, v in zip(cams, cameras.views)]
        selection = select_views(cams, mid_height=0.5 * (u_range[0] + u_range[1]),
                                 options=config.views, similarity=similarity,
                                 similarity_source=similarity_source, leaf_season=leaf_season)
        n_refs = len(selection.references)
        area_mrf = area_mrf_options(config, n_refs)
        area_sweep = area_sweep_options(config, n_refs)
        method = area_mrf.method
        requests = []
        for r in selection.references:
            srcs = list(selection.sources[r])
            gsd = reference_gsd(cams[r].P, u_range)
            sweep, mrf = reference_options(config, area_sweep, area_mrf, n_refs, gsd)
            if mrf.median_radius_m > 0.0:
                requests.append(median_program(radius_px(mrf.median_radius_m, gsd)))
            if method == "none":
                engine, wta = PlaneSweep(device, sweep), True
            else:
                engine = PlaneSweep(device, mrf_sweep_options(sweep, mrf))
                wta = mrf_sweep_wants_wta(sweep, mrf)
            requests += [q for q in engine.program_requests(len(srcs), wta=wta) if q is not None]
            if method == "sgm":
                shape = (cams[r].height, cams[r].width)
                heights = plane_heights(projections[r], [projections[s] for s in srcs], u_range,
                                        sweep.step_px, ref_shape=shape)
                # A coarse-to-fine search's windows are refined by the full search's program
                # (sgm_refine builds SGM for every plane); its coarse pass has its own planes.
                counts = [heights.size]
                n_coarse = coarse_pass_planes(sweep, mrf, shape, heights.size)
                if n_coarse:
                    counts.append(n_coarse)
                for n in counts:
                    if n <= SGM_MAX_LABELS:
                        requests += sgm_program_requests(device, mrf, n)
        return requests
    except SatsweepError:  # raised again, where it belongs, by the stage that meets it
        return []
