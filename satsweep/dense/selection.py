"""View selection: which views serve as references, and which sources each reference sweeps.

Geometry of a satellite pair seen from the AOI centre: for a view whose camera lies in the unit
direction ``v`` (ENU, from the AOI centre towards the camera), a point raised by ``dh`` metres
moves on the ground-projected image by ``dh * v_h / v_u`` (``v_h`` the horizontal part). The
base-to-height ratio of a pair is the length of the difference of those parallax vectors,
``|| v1_h / v1_u - v2_h / v2_u ||``: the disparity in ground metres per metre of height. A useful
stereo pair has B/H roughly between 0.1 (too little parallax, heights are noisy) and 0.5 (too much
occlusion and appearance change). The incidence angle of a view is the angle between ``v`` and
the vertical.

Rules (documented in the report):
- every view may be a reference (with 2 views, each is the reference once); at most
  ``max_references`` are kept, lowest incidence first;
- a reference's sources are the other views whose B/H with it lies in the useful range, ranked by
  closeness to ``target_b_over_h`` and then incidence; at most ``max_sources``;
- when no view lies in the useful range, the pair closest to it is used and a warning is recorded;
- footprint overlap (fraction of the reference crop that the source crop sees on the AOI's mid
  plane) must be at least ``min_overlap``;
- acquisition dates: when the metadata gives them, sources acquired closer in time rank first
  among equally good B/H (RPC files alone carry no date; satsweep's inputs then rank without it).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from satsweep.errors import CameraError
from satsweep.options import Options

# Below this base-to-height ratio a pair has no usable parallax (a metre of height moves a pixel
# of 0.5 m by less than 0.02 px): two images of one viewpoint, or a copy of one image.
MIN_STEREO_B_OVER_H = 0.01


@dataclasses.dataclass(frozen=True)
class ViewSelectionOptions(Options):
    """Options of the choice of reference views and of their sources."""

    max_references: int = 4  # reference views swept (each costs a sweep)
    max_sources: int = 3  # source views per reference
    min_b_over_h: float = 0.1  # least base-to-height ratio of a reference-source pair
    max_b_over_h: float = 0.5  # largest base-to-height ratio of a reference-source pair
    target_b_over_h: float = 0.25  # base-to-height ratio preferred when ranking sources
    min_overlap: float = 0.3  # least fraction of a reference crop that a source must see

    ADVANCED = ("min_b_over_h", "max_b_over_h", "target_b_over_h", "min_overlap")

    def check(self) -> None:
        self._require(0 <= self.min_b_over_h < self.max_b_over_h, "min_b_over_h",
                      "must be >= 0 and < max_b_over_h")
        self._require(self.target_b_over_h > 0, "target_b_over_h", "must be > 0")
        self._require(self.max_sources >= 1, "max_sources", "must be >= 1")
        self._require(self.max_references >= 1, "max_references", "must be >= 1")
        self._require(0 <= self.min_overlap <= 1, "min_overlap", "must be in [0, 1]")


@dataclasses.dataclass(frozen=True)
class ViewGeometry:
    """Per-view viewing geometry seen from the AOI centre."""

    direction: np.ndarray  # unit ENU vector from the AOI centre towards the camera
    incidence_deg: float  # angle between that direction and the vertical
    azimuth_deg: float  # clockwise from north, of the direction towards the camera


@dataclasses.dataclass(frozen=True)
class Selection:
    """The chosen references and sources, with the figures that justify them."""

    references: tuple[int, ...]
    sources: dict[int, tuple[int, ...]]
    b_over_h: np.ndarray  # (n, n) pairwise base-to-height ratios
    overlap: np.ndarray  # (n, n) fraction of view i's crop seen by view j
    geometry: tuple[ViewGeometry, ...]
    warnings: tuple[str, ...] = ()

    def to_dict(self, names: Sequence[str] | None = None) -> dict:
        n = len(self.geometry)
        names = list(names) if names is not None else [str(i) for i in range(n)]
        return {
            "views": [
                {"name": names[i], "incidence_deg": g.incidence_deg, "azimuth_deg": g.azimuth_deg}
                for i, g in enumerate(self.geometry)
            ],
            "pairs": [
                {"a": names[i], "b": names[j], "b_over_h": float(self.b_over_h[i, j]),
                 "overlap": float(min(self.overlap[i, j], self.overlap[j, i]))}
                for i in range(n) for j in range(i + 1, n)
            ],
            "references": [
                {"reference": names[r], "sources": [names[s] for s in self.sources[r]]}
                for r in self.references
            ],
            "warnings": list(self.warnings),
        }


def view_geometry(camera_center: np.ndarray, target: np.ndarray) -> ViewGeometry:
    """Direction, incidence and azimuth of a camera centre seen from ``target`` (ENU, metres)."""
    v = np.asarray(camera_center, float) - np.asarray(target, float)
    v = v / np.linalg.norm(v)
    incidence = float(np.degrees(np.arccos(np.clip(v[2], -1.0, 1.0))))
    azimuth = float(np.degrees(np.arctan2(v[0], v[1])) % 360.0)
    return ViewGeometry(direction=v, incidence_deg=incidence, azimuth_deg=azimuth)


def b_over_h(g1: ViewGeometry, g2: ViewGeometry) -> float:
    """Base-to-height ratio of two views: length of the difference of their parallax vectors."""
    p1 = g1.direction[:2] / g1.direction[2]
    p2 = g2.direction[:2] / g2.direction[2]
    return float(np.linalg.norm(p1 - p2))


def crop_overlap(cam_i, cam_j, mid_height: float, samples: int = 21) -> float:
    """Fraction of view i's crop whose pixels, lifted to the plane u = mid_height, land in view j.

    Both cameras are 3x4 ENU->pixel matrices (``.P``, ``.width``, ``.height``)."""
    xs = np.linspace(0, cam_i.width - 1, samples)
    ys = np.linspace(0, cam_i.height - 1, samples)
    x, y = np.meshgrid(xs, ys)
    P = cam_i.P
    # Solve P @ [e, n, h, 1] ~ [x, y, 1] for (e, n): two linear equations per pixel.
    a = P[0, :2][None, :] - x.reshape(-1, 1) * P[2, :2][None, :]
    b = P[1, :2][None, :] - y.reshape(-1, 1) * P[2, :2][None, :]
    rhs0 = x.reshape(-1) * (P[2, 2] * mid_height + P[2, 3]) - (P[0, 2] * mid_height + P[0, 3])
    rhs1 = y.reshape(-1) * (P[2, 2] * mid_height + P[2, 3]) - (P[1, 2] * mid_height + P[1, 3])
    A = np.stack([a, b], axis=1)  # (N, 2, 2)
    en = np.linalg.solve(A, np.stack([rhs0, rhs1], axis=1)[..., None])[..., 0]
    X = np.concatenate([en, np.full((en.shape[0], 1), mid_height), np.ones((en.shape[0], 1))], 1)
    q = X @ cam_j.P.T
    u, v = q[:, 0] / q[:, 2], q[:, 1] / q[:, 2]
    inside = (u >= -0.5) & (u <= cam_j.width - 0.5) & (v >= -0.5) & (v <= cam_j.height - 0.5)
    return float(inside.mean())


def select_views(cameras: Sequence, *, mid_height: float,
                 options: ViewSelectionOptions = ViewSelectionOptions(),
                 names: Sequence[str] | None = None) -> Selection:
    """Choose references and their sources from the approximated cameras (see module doc).

    ``cameras`` are objects with ``center`` (ENU, m), ``P``, ``width`` and ``height``;
    ``mid_height`` is the ENU height of the middle of the altitude range.
    """
    n = len(cameras)
    names = list(names) if names is not None else [f"view {i}" for i in range(n)]
    if n < 2:
        raise CameraError(f"view selection needs at least two views, got {n}")
    target = np.array([0.0, 0.0, mid_height])
    geometry = tuple(view_geometry(c.center, target) for c in cameras)
    bh = np.zeros((n, n))
    ov = np.eye(n)
    for i in range(n):
        for j in range(n):
            if i != j:
                bh[i, j] = b_over_h(geometry[i], geometry[j])
                ov[i, j] = crop_overlap(cameras[i], cameras[j], mid_height)
    o = options
    warnings: list[str] = []
    order = sorted(range(n), key=lambda i: geometry[i].incidence_deg)
    references: list[int] = []
    sources: dict[int, tuple[int, ...]] = {}
    for r in order:
        cands = [j for j in range(n) if j != r and ov[r, j] >= o.min_overlap]
        flat = [j for j in cands if bh[r, j] < MIN_STEREO_B_OVER_H]
        if flat:
            warnings.append(f"{names[r]}: no parallax with {', '.join(names[j] for j in flat)} "
                            f"(B/H below {MIN_STEREO_B_OVER_H}: the same viewpoint, or a copy of "
                            "the image)")
            cands = [j for j in cands if j not in flat]
        good = [j for j in cands if o.min_b_over_h <= bh[r, j] <= o.max_b_over_h]
        if not good and cands:
            best = min(cands, key=lambda j: _range_distance(bh[r, j], o))
            warnings.append(
                f"{names[r]}: no source with B/H in [{o.min_b_over_h}, {o.max_b_over_h}]; "
                f"using {names[best]} (B/H {bh[r, best]:.3f})"
            )
            good = [best]
        if not good:
            warnings.append(f"{names[r]}: no other view overlaps it by {o.min_overlap:.0%}; "
                            "not used as a reference")
            continue
        good.sort(key=lambda j: (abs(bh[r, j] - o.target_b_over_h), geometry[j].incidence_deg))
        sources[r] = tuple(good[: o.max_sources])
        references.append(r)
        if len(references) == o.max_references:
            break
    if not references:
        raise CameraError("no stereo pair among the views (" + "; ".join(warnings) + ")")
    return Selection(references=tuple(references), sources=sources, b_over_h=bh, overlap=ov,
                     geometry=geometry, warnings=tuple(warnings))


def _range_distance(value: float, o: ViewSelectionOptions) -> float:
    if value < o.min_b_over_h:
        return o.min_b_over_h - value
    if value > o.max_b_over_h:
        return value - o.max_b_over_h
    return 0.0
