"""Synthetic cost volumes with exact truth for the MRF tests and benchmarks: a textured plane
and a plain roof, with noise, as a sweep would give them.
"""

from __future__ import annotations

import dataclasses

import numpy as np


# ---------------------------------------------------------------------------------------------
# synthetic cost volumes with known truth (tests and benchmarks)
# ---------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class SyntheticVolume:
    """A synthetic filtered cost volume with its true labels (see ``synthetic_roof_volume``)."""

    cost: np.ndarray  # (L, H, W) float32, in [0, cost_scale]
    guide: np.ndarray  # (H, W) float32 in [0, 1]
    heights: np.ndarray  # (L,) plane heights, metres
    truth_labels: np.ndarray  # (H, W) int64 true plane index
    roof: np.ndarray  # (H, W) bool, the weakly textured region
    cost_scale: float

    @property
    def truth_height(self) -> np.ndarray:
        return self.heights[self.truth_labels]


def synthetic_roof_volume(shape: tuple[int, int] = (64, 80), n_labels: int = 40, *,
                          seed: int = 0, cost_scale: float = 62.0, spacing_m: float = 0.5,
                          roof_contrast: float = 0.02, texture_contrast: float = 0.6,
                          noise: float = 0.05) -> SyntheticVolume:
    """A cost volume of a textured, gently undulating terrain with a large flat roof.

    The roof covers the central 60 % x 62 % of the image at a constant plane (70 % of the range);
    the terrain elsewhere varies smoothly over a quarter of the range. The cost of plane k at a
    pixel of true plane t is ``cost_scale * (0.5 - c/2 + c * min(|k - t| / 3, 1) + N(0, noise))``
    clipped to [0, cost_scale], with c = ``texture_contrast`` on the terrain and the much smaller
    ``roof_contrast`` on the roof, where the noise hides the minimum from a winner-take-all (as
    on a plain roof, whose census costs are nearly flat). The guide is uniform noise in [0, 1] on
    the terrain and nearly constant (0.6 +- 0.01) on the roof. Planes are ``spacing_m`` apart.
    """
    rng = np.random.default_rng(seed)
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    base = 0.3 * n_labels
    amp = 0.125 * n_labels
    truth = np.rint(base + amp * (0.55 * np.sin(xx / (0.11 * w)) + 0.45 * np.cos(yy / (0.17 * h))))
    truth = np.clip(truth, 1, n_labels - 2).astype(np.int64)
    roof = ((yy >= int(0.2 * h)) & (yy < int(0.8 * h)) & (xx >= int(0.2 * w))
            & (xx < int(0.82 * w)))
    truth[roof] = int(0.7 * n_labels)
    guide = rng.uniform(0.0, 1.0, (h, w))
    guide[roof] = 0.6 + rng.uniform(-0.01, 0.01, int(roof.sum()))
    k = np.arange(n_labels)[:, None, None]
    shape_k = np.minimum(np.abs(k - truth[None]) / 3.0, 1.0)
    contrast = np.where(roof, roof_contrast, texture_contrast)[None]
    cost = cost_scale * (0.5 - 0.5 * contrast + contrast * shape_k
                         + rng.normal(0.0, noise, (n_labels, h, w)))
    cost = np.clip(cost, 0.0, cost_scale).astype(np.float32)
    heights = 100.0 + spacing_m * np.arange(n_labels)
    return SyntheticVolume(cost=cost, guide=guide.astype(np.float32), heights=heights,
                           truth_labels=truth, roof=roof, cost_scale=float(cost_scale))
