"""seen_with_data: visible_at's rule with each source's data mask, against a plain loop."""

from __future__ import annotations

import numpy as np

from satsweep.dense.planes import seen_with_data, visible_at


def _homographies(n_planes: int, n_src: int, rng) -> np.ndarray:
    hom = np.zeros((n_planes, n_src, 3, 3))
    for p in range(n_planes):
        for s in range(n_src):
            hom[p, s] = np.array([[1.0, 0.02 * s, 3.0 * p - 5.0 + s],
                                  [0.01, 1.0, 2.0 * s - 4.0],
                                  [0.0, 1e-5 * p, 1.0]])
    return hom


def test_full_masks_give_visible_at_and_holes_are_not_seen():
    rng = np.random.default_rng(0)
    hom = _homographies(5, 2, rng)
    labels = rng.integers(0, 5, (20, 30))
    shapes = [(24, 33), (22, 35)]
    full = [np.ones(s, bool) for s in shapes]
    np.testing.assert_array_equal(seen_with_data(hom, labels, full),
                                  visible_at(hom, labels, shapes))
    masks = [rng.random(s) > 0.3 for s in shapes]
    got = seen_with_data(hom, labels, masks)
    for y in range(20):
        for x in range(30):
            expected = False
            for s, m in enumerate(masks):
                h = hom[labels[y, x], s]
                q = h @ np.array([x, y, 1.0])
                if q[2] <= 0:
                    continue
                u, v = q[0] / q[2], q[1] / q[2]
                rows, cols = m.shape
                if 0 <= u <= cols - 1 and 0 <= v <= rows - 1:
                    expected |= bool(m[int(np.floor(v + 0.5)), int(np.floor(u + 0.5))])
            assert got[y, x] == expected, (x, y)
