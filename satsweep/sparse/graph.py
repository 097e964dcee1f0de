"""The pair graph of the sparse stage: which pairs of views are matched.

Matching every pair of V views costs V (V - 1) / 2 pair matchings; a stack of 19 views spent
most of its sparse stage there. Only a chosen graph of pairs is matched instead, whose size grows
linearly with V:

1. *Candidates*: the pairs whose views see a common part of the AOI. The AOI box is sampled
   (``_COVERAGE_SAMPLES`` per side, at the bottom, middle and top of the altitude range) and
   projected by each view's camera; a pair's *overlap* is the largest fraction of one
   altitude's samples inside both crops. Pairs below ``pair_min_overlap`` are no candidates.
2. *Score* of a candidate: overlap x geometry x appearance. Geometry: the pair's base-to-height
   ratio (B/H, the horizontal distance between the two lines of sight through a ground point per
   metre of height, from the cameras) inside ``pair_bh_range`` counts 1, outside
   ``_BH_PENALTY`` (too small: the heights are poorly triangulated; too large: the views differ
   too much for SIFT). Appearance: the verified matches between the ``pair_probe_features``
   strongest features of the two views (:func:`probe_matches`), plus one; views of different
   seasons, lighting or places match less there than in the full matching. Each view probes
   only its best candidates by geometry (a few times ``pair_neighbours``), so that the probes
   too grow linearly with the views; the pairs not probed count as if they had no match.
3. *Selection* (:func:`select_pairs`): a maximum spanning forest of the candidates by score
   (every view that has a candidate is linked to the others by the best pairs available), then
   the best pairs until each view has ``pair_neighbours`` of them: about pair_neighbours / 2
   pairs per view. With V <= pair_neighbours + 1 that is every candidate pair. A view matched with several others is tied in two dimensions (one pair only ties the
   component of its pointing error across the epipolar lines; the other component is the height
   of the pair's points), and the tracks that chain through the graph tie it further.

The matching stage repairs the graph (:func:`repair_pairs`): a view that its pairs fail to tie to
the largest group of views is matched with its next candidates before it is dropped.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import numpy as np

from satsweep.sparse.matching import match_pair
from satsweep.sparse.options import SparseOptions

# AOI samples per side for the views' coverage (12 x 12 = 144 samples: overlaps to ~1%).
_COVERAGE_SAMPLES = 12
# Score factor of a pair whose B/H lies outside pair_bh_range: such pairs are still matched when
# they are the best a view has, but the in-range pairs come first.
_BH_PENALTY = 0.25
# Each view probes (appearance) at most this many times pair_neighbours of its candidates, the
# best by geometry: probing every pair would grow with the square of the views (190 probes of
# 20 views took 1.2 s of CPU, against 15 s for the whole stage).
_PROBES_PER_NEIGHBOUR = 3


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
def aoi_samples(frame: Any, aoi: Any, altitudes: Sequence[float],
                n: int = _COVERAGE_SAMPLES) -> np.ndarray:
    """(A, n * n, 3) ENU points (m) of a regular grid over the AOI box at each of the A
    ``altitudes`` (m above the ellipsoid)."""
    lon = np.linspace(aoi.lon_min, aoi.lon_max, n)
    lat = np.linspace(aoi.lat_min, aoi.lat_max, n)
    lon, lat = np.meshgrid(lon, lat)
    out = []
    for altitude in altitudes:
        e, nn, u = frame.from_geodetic(lon=lon.ravel(), lat=lat.ravel(),
                                       alt=np.full(lon.size, float(altitude)))
        out.append(np.column_stack([e, nn, u]))
    return np.stack(out)


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
    """The pairs to match: a maximum spanning forest of the candidates by score (Kruskal; it
    holds each view's best candidate), then, by decreasing score, the pairs of two views that
    both have fewer than ``neighbours`` pairs, then for each view still short of them its best
    remaining candidates. Views in ``exclude`` take no part. Sorted (i, j).

    Each view gets ``neighbours`` pairs (or all its candidates) and the total stays near
    ``neighbours / 2`` pairs per view: with 3, 8 pairs for 5 views, 16 for 10, 31 for 20 (each
    view's 3 best regardless of the others' would make 9, 19 and 37-40, for corrections no
    better on tools/bench_ba.py's stacks: at most 0.031 px against 0.028)."""
    out = set()
    skip = set(exclude)
    cands = sorted((c for c in candidates if c.i not in skip and c.j not in skip),
                   key=lambda c: (-c.score, c.i, c.j))
    parent = list(range(n_views))
    degree = np.zeros(n_views, dtype=np.int64)

    def add(c: PairCandidate) -> None:
        out.add((c.i, c.j))
        degree[c.i] += 1
        degree[c.j] += 1

    for c in cands:
        a, b = _find(parent, c.i), _find(parent, c.j)
        if a != b:
            parent[max(a, b)] = min(a, b)
            add(c)
    for c in cands:  # pairs that neither view has enough of
        if (c.i, c.j) not in out and degree[c.i] < neighbours and degree[c.j] < neighbours:
            add(c)
    for c in cands:  # views still short: their best remaining candidates
        if (c.i, c.j) not in out and (degree[c.i] < neighbours or degree[c.j] < neighbours):
            add(c)
    return tuple(sorted(out))


def _pairs_to_probe(geometry: Sequence[tuple[int, int, float, float, float]],
                    options: SparseOptions) -> list[tuple[int, int]]:
    """The candidate pairs whose appearance is probed: each view's best by geometry, at most
    ``_PROBES_PER_NEIGHBOUR * pair_neighbours`` of them (ties, as when every view sees the whole
    AOI within the B/H band, go to the B/H nearest the band's geometric middle)."""
    lo, hi = options.pair_bh_range
    middle = math.sqrt(max(lo, 1e-3) * hi)
    per_view = _PROBES_PER_NEIGHBOUR * options.pair_neighbours
    ranked = sorted(geometry, key=lambda g: (-g[4], abs(math.log(max(g[3], 1e-6) / middle)),
                                             g[0], g[1]))
    count: dict[int, int] = {}
    out = []
    for i, j, *_ in ranked:
        if count.get(i, 0) < per_view or count.get(j, 0) < per_view:
            out.append((i, j))
            count[i] = count.get(i, 0) + 1
            count[j] = count.get(j, 0) + 1
    return out


def build_pair_graph(cameras: Sequence[Any], features: Sequence[tuple[np.ndarray, np.ndarray]],
                     options: SparseOptions, *, samples: np.ndarray | None = None,
                     exclude: Sequence[int] = (),
                     thresholds: dict[tuple[int, int], float] | None = None) -> PairGraph:
    """Candidates, scores and the selected pairs of the views (see the module docstring).

    ``cameras``: per view, anything with ``P``, ``width``, ``height`` (the crops' cameras);
    ``features``: per view ``(xy, descriptors)``, strongest first; ``samples``: (A, S, 3) ENU
    points of the AOI at A altitudes (:func:`aoi_samples`; a pair's overlap is the largest
    fraction of the samples of one altitude that both views see: where the scene lies in the
    altitude range is not known yet), or None for views known to be crops of one AOI (every pair
    overlaps fully, and B/H is taken where view 0's centre sees the plane u = 0); ``exclude``:
    views left out (no features); ``thresholds``: per pair the verification threshold (px) of
    the probe, default ``options.ransac_threshold_px``.
    """
    V = len(cameras)
    skip = set(exclude)
    if samples is not None:
        samples = np.asarray(samples, np.float64).reshape(-1, samples.shape[-2], 3)
        seen = np.stack([coverage(cameras, level) for level in samples], axis=1)  # (V, A, S)
        centre = samples[len(samples) // 2].mean(axis=0)
    else:
        from satsweep.geometry.camera import _backproject

        seen = np.array([[[c is not None]] for c in cameras])
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
            overlap = float((seen[i] & seen[j]).mean(axis=-1).max())
            if overlap >= options.pair_min_overlap and overlap > 0.0:
                pairs.append((i, j, overlap))
    lo, hi = options.pair_bh_range
    geometry = []
    for i, j, overlap in pairs:
        bh = float(np.hypot(*(parallax[i] - parallax[j])))
        factor = 1.0 if lo <= bh <= hi else _BH_PENALTY
        geometry.append((i, j, overlap, bh, overlap * factor))
    probe = {}
    everything = V - len(skip) <= options.pair_neighbours + 1
    if options.pair_probe_features > 0 and not everything:
        probe = probe_matches(features, cameras, _pairs_to_probe(geometry, options), options,
                              thresholds or {})
    candidates = []
    for i, j, overlap, bh, geo in geometry:
        p = probe.get((i, j), -1)
        candidates.append(PairCandidate(i=i, j=j, overlap=overlap, base_to_height=bh, probe=p,
                                        score=geo * (max(p, 0) + 1)))
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
