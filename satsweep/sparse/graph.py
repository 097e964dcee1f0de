"""The pair graph of the sparse stage: which pairs of views are matched.

Matching every pair of V views costs V (V - 1) / 2 pair matchings; a stack of 19 views spent
most of its sparse stage there. Only a chosen graph of pairs is matched instead, whose size grows
linearly with V:

1. *Candidates*: the pairs whose views see a common part of the AOI. The AOI box is sampled
   (``_COVERAGE_SAMPLES`` per side, at the middle of the altitude range) and projected by each
   view's camera; a pair's *overlap* is the fraction of samples inside both crops. Pairs below
   ``pair_min_overlap`` are no candidates.
2. *Score* of a candidate: overlap x geometry x appearance. Geometry: the pair's base-to-height
   ratio (B/H, the horizontal distance between the two lines of sight through a ground point per
   metre of height, from the cameras) inside ``pair_bh_range`` counts 1, outside
   ``_BH_PENALTY`` (too small: the heights are poorly triangulated; too large: the views differ
   too much for SIFT). Appearance: the verified matches between the ``pair_probe_features``
   strongest features of the two views (:func:`probe_matches`), plus one; views of different
   seasons, lighting or places match less there than in the full matching.
3. *Selection*: a maximum spanning forest of the candidates by score (every view that has a
   candidate is linked to the others by the best pairs available), plus each view's
   ``pair_neighbours`` best candidates. With V <= pair_neighbours + 1 that is every candidate
   pair. A view matched with several others is tied in two dimensions (one pair only ties the
   component of its pointing error across the epipolar lines; the other component is the height
   of the pair's points), and the tracks that chain through the graph tie it further.

The matching stage repairs the graph (:func:`repair_pairs`): a view that its pairs fail to tie to
the largest group of views is matched with its next candidates before it is dropped.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import numpy as np

from satsweep.sparse.matching import match_pair
from satsweep.sparse.options import SparseOptions

# AOI samples per side for the views' coverage (12 x 12 = 144 samples: overlaps to ~1%).
_COVERAGE_SAMPLES = 12
# Score factor of a pair whose B/H lies outside pair_bh_range: such pairs are still matched when
# they are the best a view has, but the in-range pairs come first.
_BH_PENALTY = 0.25


@dataclasses.dataclass(frozen=True)
class PairCandidate:
    """A pair of views that see a common part of the AOI, and what its score is made of."""

    i: int
    j: int
    overlap: float  # fraction of the AOI's samples seen by both views
    base_to_height: float  # horizontal parallax (m) per metre of height between the two views
    probe: int  # verified matches among the strongest features (-1: not probed)
    score: float  # overlap x B/H factor x (probe + 1)


@dataclasses.dataclass(frozen=True)
class PairGraph:
    """The candidates of a set of views and the pairs chosen among them to be matched."""

    n_views: int
    candidates: tuple[PairCandidate, ...]  # by decreasing score
    selected: tuple[tuple[int, int], ...]  # (i, j), i < j, chosen to be matched

    def candidate(self, i: int, j: int) -> PairCandidate | None:
        """The candidate of views i and j (either order), None when they share no AOI."""
        a, b = min(i, j), max(i, j)
        for c in self.candidates:
            if (c.i, c.j) == (a, b):
                return c
        return None

    def degree(self) -> np.ndarray:
        """Selected pairs per view, (V,) int."""
        deg = np.zeros(self.n_views, dtype=np.int64)
        for i, j in self.selected:
            deg[i] += 1
            deg[j] += 1
        return deg


# -- what the graph is made of -------------------------------------------------------------------
def aoi_samples(frame: Any, aoi: Any, altitude: float, n: int = _COVERAGE_SAMPLES) -> np.ndarray:
    """(n * n, 3) ENU points (m) of a regular grid over the AOI box at ``altitude`` (m)."""
    lon = np.linspace(aoi.lon_min, aoi.lon_max, n)
    lat = np.linspace(aoi.lat_min, aoi.lat_max, n)
    lon, lat = np.meshgrid(lon, lat)
    e, nn, u = frame.from_geodetic(lon=lon.ravel(), lat=lat.ravel(), alt=np.full(lon.size, altitude))
    return np.column_stack([e, nn, u])


def coverage(cameras: Sequence[Any], points: np.ndarray) -> np.ndarray:
    """(V, S) bool: sample s projects inside view v's image (cameras with ``P``, ``width``,
    ``height``; pixel (0, 0) is the centre of the first pixel; None: a view with no camera,
    which sees nothing)."""
    out = np.zeros((len(cameras), len(points)), dtype=bool)
    Xh = np.column_stack([points, np.ones(len(points))])
    for v, cam in enumerate(cameras):
        if cam is None:
            continue
        h = Xh @ np.asarray(cam.P, np.float64).T
        col, row = h[:, 0] / h[:, 2], h[:, 1] / h[:, 2]
        out[v] = ((h[:, 2] > 0) & (col >= -0.5) & (col <= cam.width - 0.5)
                  & (row >= -0.5) & (row <= cam.height - 0.5))
    return out


def ground_parallax(cameras: Sequence[Any], point: np.ndarray) -> np.ndarray:
    """(V, 2) horizontal displacement (m) per metre of height of each view's line of sight
    through the ENU ``point``: where the ray of the pixel that sees ``point`` crosses the
    horizontal planes one metre apart (NaN for a view without camera). Two views' B/H is the
    norm of their difference."""
    from satsweep.geometry.camera import _backproject

    out = np.full((len(cameras), 2), np.nan)
    p = np.append(np.asarray(point, np.float64), 1.0)
    for v, cam in enumerate(cameras):
        if cam is None:
            continue
        P = np.asarray(cam.P, np.float64)
        h = P @ p
        col, row = h[0] / h[2], h[1] / h[2]
        e0, n0 = _backproject(P, col, row, point[2])
        e1, n1 = _backproject(P, col, row, point[2] + 1.0)
        out[v] = [float(e1 - e0), float(n1 - n0)]
    return out


def probe_matches(features: Sequence[tuple[np.ndarray, np.ndarray]], cameras: Sequence[Any],
                  pairs: Sequence[tuple[int, int]], options: SparseOptions,
                  thresholds: dict[tuple[int, int], float]) -> dict[tuple[int, int], int]:
    """Verified matches between the ``options.pair_probe_features`` strongest features of each
    pair's views (features sorted strongest first, as :func:`detect_features` returns them):
    a cheap appearance similarity, about (probe / max_features)^2 of a full matching's cost."""
    from satsweep.sparse.matching import fundamental_from_cameras

    n = options.pair_probe_features
    out = {}
    for i, j in pairs:
        (xy_i, d_i), (xy_j, d_j) = features[i], features[j]
        F = (fundamental_from_cameras(cameras[i], cameras[j])
             if options.geometric_model == "cameras" else None)
        a, _ = match_pair(d_i[:n], d_j[:n], xy_i[:n], xy_j[:n], options, fundamental=F,
                          threshold_px=thresholds.get((i, j)))
        out[(i, j)] = int(a.size)
    return out


# -- the graph -----------------------------------------------------------------------------------
def _find(parent: list[int], v: int) -> int:
    while parent[v] != v:
        parent[v] = parent[parent[v]]
        v = parent[v]
    return v


def select_pairs(n_views: int, candidates: Sequence[PairCandidate], neighbours: int,
                 exclude: Sequence[int] = ()) -> tuple[tuple[int, int], ...]:
    """The pairs to match: a maximum spanning forest of the candidates by score (Kruskal) plus
    each view's ``neighbours`` best candidates; views in ``exclude`` take no part. Sorted (i, j)."""
    out = set()
    skip = set(exclude)
    cands = sorted((c for c in candidates if c.i not in skip and c.j not in skip),
                   key=lambda c: (-c.score, c.i, c.j))
    parent = list(range(n_views))
    for c in cands:
        a, b = _find(parent, c.i), _find(parent, c.j)
        if a != b:
            parent[max(a, b)] = min(a, b)
            out.add((c.i, c.j))
    taken = np.zeros(n_views, dtype=np.int64)
    for c in cands:  # by decreasing score: each view's best candidates first
        if taken[c.i] < neighbours or taken[c.j] < neighbours:
            out.add((c.i, c.j))
        taken[c.i] += 1
        taken[c.j] += 1
    return tuple(sorted(out))


def build_pair_graph(cameras: Sequence[Any], features: Sequence[tuple[np.ndarray, np.ndarray]],
                     options: SparseOptions, *, samples: np.ndarray | None = None,
                     exclude: Sequence[int] = (),
                     thresholds: dict[tuple[int, int], float] | None = None) -> PairGraph:
    """Candidates, scores and the selected pairs of the views (see the module docstring).

    ``cameras``: per view, anything with ``P``, ``width``, ``height`` (the crops' cameras);
    ``features``: per view ``(xy, descriptors)``, strongest first; ``samples``: ENU points of
    the AOI (:func:`aoi_samples`), or None for views known to be crops of one AOI (every pair
    overlaps fully, and B/H is taken where view 0's centre sees the plane u = 0); ``exclude``:
    views left out (no features); ``thresholds``: per pair the verification threshold (px) of
    the probe, default ``options.ransac_threshold_px``.
    """
    V = len(cameras)
    skip = set(exclude)
    if samples is not None:
        seen = coverage(cameras, samples)
        centre = samples.mean(axis=0)
    else:
        from satsweep.geometry.camera import _backproject

        seen = np.array([[c is not None] for c in cameras])
        c0 = next(c for c in cameras if c is not None)
        e, n = _backproject(np.asarray(c0.P, np.float64), (c0.width - 1) / 2.0,
                            (c0.height - 1) / 2.0, 0.0)
        centre = np.array([float(e), float(n), 0.0])
    parallax = ground_parallax(cameras, centre)
    pairs = []
    for i in range(V):
        for j in range(i + 1, V):
            if i in skip or j in skip:
                continue
            overlap = float((seen[i] & seen[j]).mean())
            if overlap >= options.pair_min_overlap and overlap > 0.0:
                pairs.append((i, j, overlap))
    probe = {}
    everything = V - len(skip) <= options.pair_neighbours + 1
    if options.pair_probe_features > 0 and not everything:
        probe = probe_matches(features, cameras, [(i, j) for i, j, _ in pairs], options,
                              thresholds or {})
    lo, hi = options.pair_bh_range
    candidates = []
    for i, j, overlap in pairs:
        bh = float(np.hypot(*(parallax[i] - parallax[j])))
        factor = 1.0 if lo <= bh <= hi else _BH_PENALTY
        p = probe.get((i, j), -1)
        candidates.append(PairCandidate(i=i, j=j, overlap=overlap, base_to_height=bh, probe=p,
                                        score=overlap * factor * (max(p, 0) + 1)))
    candidates.sort(key=lambda c: (-c.score, c.i, c.j))
    selected = select_pairs(V, candidates, options.pair_neighbours, exclude)
    return PairGraph(n_views=V, candidates=tuple(candidates), selected=selected)


def repair_pairs(graph: PairGraph, matched: set[tuple[int, int]], loose: Sequence[int],
                 per_view: int) -> list[tuple[int, int]]:
    """For each view in ``loose`` (not tied to the largest group), its ``per_view`` best
    candidates not yet ``matched``, best first: the pairs to try before dropping it."""
    out = []
    for v in loose:
        mine = [c for c in graph.candidates if v in (c.i, c.j) and (c.i, c.j) not in matched]
        for c in mine[:per_view]:
            if (c.i, c.j) not in out:
                out.append((c.i, c.j))
    return out
