"""Tests of satsweep.sparse.graph: which pairs of views the sparse stage matches.

References: the geometry of the synthetic pinhole cameras of tests.synthetic_cameras (a camera
700 km up offset by (a, b) x 700 km looks at the origin along (a, b, 1), so the horizontal
displacement of its line of sight per metre of height is (a, b) and two cameras' base-to-height
ratio is the distance between their offsets), and a plain-Python breadth-first search for the
connectivity of the selected pairs.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from satsweep.errors import OptionsError
from satsweep.sparse import graph
from satsweep.sparse.options import SparseOptions
from tests.synthetic_cameras import satellite_camera

# The lines of sight of the synthetic cameras pass through the origin exactly; at 700 km their
# directions change by ~1e-6 over the 1 m step of ground_parallax: B/H agrees to 1e-4.
BH_TOL = 1e-4


def _connected(n: int, pairs) -> bool:
    """Breadth-first search from view 0 over the pairs (an independent check of the forest)."""
    nbrs = {v: set() for v in range(n)}
    for i, j in pairs:
        nbrs[i].add(j)
        nbrs[j].add(i)
    seen, todo = {0}, [0]
    while todo:
        for w in nbrs[todo.pop()] - seen:
            seen.add(w)
            todo.append(w)
    return len(seen) == n


def _candidates(n: int, seed: int):
    rng = np.random.default_rng(seed)
    out = []
    for i, j in itertools.combinations(range(n), 2):
        out.append(graph.PairCandidate(i=i, j=j, overlap=1.0, base_to_height=0.3, probe=0,
                                       score=float(rng.uniform(0.1, 10.0))))
    return out


@pytest.mark.parametrize("n,neighbours", [(5, 1), (12, 2), (20, 3), (40, 3)])
def test_selection_links_every_view_and_grows_linearly(n, neighbours):
    cands = _candidates(n, seed=n)
    pairs = graph.select_pairs(n, cands, neighbours)
    assert _connected(n, pairs)
    assert len(pairs) <= neighbours * n  # linear in the views, not n (n - 1) / 2
    deg = np.zeros(n, int)
    for i, j in pairs:
        deg[i] += 1
        deg[j] += 1
    assert deg.min() >= neighbours
    # each view's best candidate is always matched
    for v in range(n):
        best = max((c for c in cands if v in (c.i, c.j)), key=lambda c: c.score)
        assert (best.i, best.j) in pairs


def test_few_views_match_every_pair():
    cands = _candidates(4, seed=1)
    assert graph.select_pairs(4, cands, neighbours=3) == tuple(itertools.combinations(range(4), 2))


def test_excluded_views_take_no_part():
    cands = _candidates(6, seed=2)
    pairs = graph.select_pairs(6, cands, neighbours=2, exclude=[3])
    assert all(3 not in p for p in pairs)
    assert _connected(5, [(i - (i > 3), j - (j > 3)) for i, j in pairs])


def test_base_to_height_and_overlap_from_the_cameras():
    """B/H is the distance between the cameras' offsets; a camera that sees another part of the
    ground shares no AOI with the others and is no candidate."""
    offsets = [(0.0, 0.0), (0.2, 0.0), (0.0, -0.35), (0.1, 0.1)]
    cams = [satellite_camera(a, b) for a, b in offsets]
    # a fifth camera looking 3 km east of the origin: its 1000 px (500 m) image misses the AOI
    far = satellite_camera(0.0, 0.0)
    far_P = far.P @ np.array([[1, 0, 0, -3000.0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    cams.append(type(far)(K=far.K, R=far.R, t=far.t, P=far_P, width=far.width, height=far.height))
    e, n = np.meshgrid(np.linspace(-100, 100, 9), np.linspace(-100, 100, 9))
    samples = np.column_stack([e.ravel(), n.ravel(), np.zeros(e.size)])[None]
    rng = np.random.default_rng(0)
    feats = [(rng.uniform(0, 1000, (50, 2)), rng.normal(0, 50, (50, 128)).astype(np.float32))
             for _ in cams]
    g = graph.build_pair_graph(cams, feats, SparseOptions(pair_neighbours=2, pair_probe_features=0),
                               samples=samples)
    assert {(c.i, c.j) for c in g.candidates} == set(itertools.combinations(range(4), 2))
    for c in g.candidates:
        expected = np.hypot(*(np.subtract(offsets[c.i], offsets[c.j])))
        assert abs(c.base_to_height - expected) < BH_TOL
        assert c.overlap == 1.0
    # samples at several heights: a pair's overlap is that of the height both views see best
    # (3 km up, the 500 m footprints of views 0.35 x 700 km apart share nothing)
    everything = SparseOptions(pair_probe_features=0, pair_min_overlap=0.0)
    high = samples + [0.0, 0.0, 3000.0]
    up = {(c.i, c.j): c.overlap
          for c in graph.build_pair_graph(cams[:4], feats[:4], everything, samples=high).candidates}
    assert min(up.values(), default=0.0) < 1.0
    both = graph.build_pair_graph(cams[:4], feats[:4], everything,
                                  samples=np.concatenate([high, samples]))
    assert all(c.overlap == 1.0 for c in both.candidates)
    # with a preferred band of 0.15 .. 0.3, (0, 1) at B/H 0.2 counts fully, (0, 3) at 0.14 and
    # (1, 2) at 0.40 a quarter
    lo_hi = SparseOptions(pair_bh_range=(0.15, 0.3), pair_probe_features=0)
    g2 = graph.build_pair_graph(cams[:4], feats[:4], lo_hi, samples=samples)
    score = {(c.i, c.j): c.score for c in g2.candidates}
    assert score[(0, 1)] == 1.0 and score[(0, 3)] == score[(1, 2)] == graph._BH_PENALTY


def test_repair_offers_the_next_candidates():
    cands = sorted(_candidates(6, seed=3), key=lambda c: -c.score)
    g = graph.PairGraph(n_views=6, candidates=tuple(cands), selected=((0, 1),))
    extra = graph.repair_pairs(g, matched={(0, 1), (0, 2)}, loose=[2], per_view=2)
    mine = [(c.i, c.j) for c in cands if 2 in (c.i, c.j) and (c.i, c.j) != (0, 2)]
    assert extra == mine[:2]


@pytest.mark.parametrize("field,value", [("pair_neighbours", 0), ("pair_min_overlap", 1.5),
                                         ("pair_bh_range", (0.5, 0.1)), ("pair_probe_features", 5),
                                         ("pair_repair", -1)])
def test_graph_options_name_the_bad_field(field, value):
    with pytest.raises(OptionsError, match=field):
        SparseOptions(**{field: value})


def test_probes_grow_linearly_with_the_views():
    """With 16 views every pair is a candidate (120), but each view probes only its best few by
    geometry: at most 3 x pair_neighbours per view, and every view probes some."""
    n = 16
    angles = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    cams = [satellite_camera(0.2 * np.cos(a), 0.2 * np.sin(a)) for a in angles]
    rng = np.random.default_rng(1)
    feats = [(rng.uniform(0, 1000, (60, 2)), rng.normal(0, 50, (60, 128)).astype(np.float32))
             for _ in cams]
    options = SparseOptions(pair_neighbours=2, pair_probe_features=50)
    g = graph.build_pair_graph(cams, feats, options)
    probed = [c for c in g.candidates if c.probe >= 0]
    per_view = graph._PROBES_PER_NEIGHBOUR * options.pair_neighbours
    assert len(g.candidates) == n * (n - 1) // 2 and len(probed) <= per_view * n
    count = np.bincount([v for c in probed for v in (c.i, c.j)], minlength=n)
    assert count.min() >= per_view
    assert _connected(n, g.selected)
