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
  ``max_references`` are kept, lowest incidence first; beyond ``BUDGET_FREE_REFERENCES`` of
  them, only as many as keep the references' crops within ``reference_megapixels`` (each
  reference costs a sweep of its crop: small crops take more references, large ones fewer);
- a reference's sources are the other views whose B/H with it lies in the useful range, ranked by
  closeness to ``target_b_over_h`` and then incidence; at most ``max_sources``;
- when no view lies in the useful range, the pair closest to it is used and a warning is recorded;
- footprint overlap (fraction of the reference crop that the source crop sees on the AOI's mid
  plane) must be at least ``min_overlap``;
- appearance: sources are ranked by their distance to ``target_b_over_h`` (relative to it)
  plus ``similarity_weight`` times (1 - their appearance similarity with the reference, from the
  acquisition metadata or measured from the images: ``satsweep.dense.similarity``); sources
  whose metadata make them less similar than ``min_similarity`` are left out when the reference
  keeps a better one, unless the metadata say that every source is of another date
  (``CLOSE_SIMILARITY``); a similarity measured from tie points or images only ranks (its
  scale is the stack's own: the best pair 1);
- references are taken by incidence plus ``REFERENCE_DISSIMILARITY_DEG`` times (1 - the mean
  similarity of its best sources): a view that sees the AOI steeply but only from other dates
  comes after one that has sources of its own date;
- side coverage: each side of the buildings (north, east, south, west) that some view sees is
  seen by at least ``side_coverage`` references where the slots allow: the last references are
  taken from the best views on the sides still missing (references all looking from one side
  leave the ground in front of every wall facing the other way hidden from all of them, and
  the fusion fills it with roof heights);
- season: where the metadata date the views (``similarity.leaf_season``: how fully deciduous
  trees are in leaf on that date at the AOI's latitude; without dates, optionally estimated
  from the images' colour, ``leaf_from_colour``), at least ``leaf_on_references`` of
  the references are views of dates in leaf where the stack has such views (views part in leaf
  counting for their part; the side coverage keeps its slots), and a source's rank adds
  ``leaf_state_weight`` times its difference in leaf state from the reference. The DSM holds
  the canopy's top (the highest point of a cell, an airborne lidar's first return); a leafless
  crown shows the ground through its branches, and references all of winter dates put the
  crowns at the ground's height (an issue-form stack of 19 views on 19 dates whose 8 lowest-
  cost references were all of dates from October to April: crowns 4.6 m too low on average).
Without similarity (all 1) and dates, the rules reduce to B/H and incidence alone.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import numpy as np

from satsweep.errors import CameraError
from satsweep.options import Options

# Below this base-to-height ratio a pair has no usable parallax (a metre of height moves a pixel
# of 0.5 m by less than 0.02 px): two images of one viewpoint, or a copy of one image.
MIN_STEREO_B_OVER_H = 0.01
# Degrees of incidence that a reference's dissimilarity to its sources (1 - mean similarity)
# weighs when the references are ordered: a reference whose sources are all of other dates
# counts as 30 degrees more oblique.
REFERENCE_DISSIMILARITY_DEG = 30.0
# Metadata similarity from which a source counts as taken in the reference's conditions: its pass
# (1), or a sun within about 7 degrees in the same season (similarity.metadata_similarity). When
# the metadata say that no source is, min_similarity leaves none out: all are of other dates, and
# the lowest costs of several (the sweep's n_best_sources) outvote the shadows and seasons of
# each better than one or two sources do. One view per date (tools/bench_multidate.py --dates
# 10, seeds 0-5): 85.35 -> 87.27% within 1 m, DFC MAE 1.511 -> 1.493 m; held-out seeds 6-9
# 81.72 -> 83.67%, 1.749 -> 1.567 m; 10 of 20 views (v20 seeds 0-3) 83.95 -> 85.83%; the
# 10-view stacks of passes (seeds 0-5) 92.13 -> 92.18%, their 5-view subsets 71.05 -> 76.83%.
# Not applied to similarities measured from tie points or images, whose values do not tell a
# pass from a date of like conditions (a pass's pairs score 0.52-1.0, other dates' up to 0.83).
# Nor is min_similarity: such a similarity is each pair's tie points over the stack's best
# pair's, so on a stack without metadata it left most references one or two sources (those of
# their pass, or the few most alike), and a reference whose one source failed somewhere left
# holes or blunders there. Ranking only, the issue-form stacks generated without metadata
# (docs/measurements.md, twenty-sixth session), DFC MAE m, seeds 7, 8, 11-18: 0.861 1.503
# 1.206 0.854 1.169 0.885 0.995 1.425 1.810 0.928 -> 0.713 0.910 1.220 0.774 1.255 0.862 0.939
# 1.415 0.438 0.850 (mean 1.164 -> 0.938). It costs the small grey stacks of passes of two
# views (tools/bench_multidate.py v10 --no-metadata, seeds 0-5), whose references' own pass
# serves them well: within 1 m 94.8 92.2 93.3 96.0 90.5 95.0 -> 94.6 91.1 92.8 95.8 89.5 92.5%,
# DFC MAE mean 0.590 -> 0.627 m; keeping two sources at least instead: 93.17% there (from
# 93.63) but the issue-form stacks lose most of the gain (17 / 8 / 13: 0.546 / 1.088 / 1.159).
CLOSE_SIMILARITY = 0.9
# A view sees the side of the buildings that faces azimuth a (the wall, and the ground in front
# of it) when its own azimuth (towards the camera) lies within this angle of a; a view within
# NADIR_DEG of the vertical sees every side (a 10 m wall hides under 1 m of ground from it).
# An issue-form stack (seed 9: 17 views, 0.3 m, 8 references) whose lowest-incidence views all
# look from the west (azimuths 241-334): DFC MAE / within 1 m 1.076 m / 88.18% with no such
# rule, 0.999 / 89.18 with side_coverage = 1 (one reference from the east), 0.984 / 91.18 with
# 2 (three); seed 12: 0.867 / 88.16 with 0 and 1, 0.834 / 90.02 with 2; seed 13 1.1545 /
# 90.42, 1.1543 / 90.36, 1.1585 / 90.41; v20 seed 3 (tools/bench_multidate.py, 20 views)
# 94.3 / 0.745 -> 94.2 / 0.726 with 2. Seeds 7, 8, 11, bench_multidate v10 (passes and one
# view per date) and v20 seeds 0-5 otherwise: unchanged (docs/measurements.md).
SIDE_HALF_ANGLE_DEG = 60.0
NADIR_DEG = 6.0
SIDES_DEG = (0.0, 90.0, 180.0, 270.0)
# A view's date counts as in leaf from this similarity.leaf_season on (late May to mid October
# in the northern temperate zone).
LEAF_ON_SEASON = 0.75
# References that ``reference_megapixels`` never takes away (fewer only where max_references
# asks for fewer). Each reference is a sweep of its crop, so the sweep stage's time grows with
# the references' pixels; a 19-view stack of 850 px views at 0.3 m (the issue-form stacks,
# crops of about 0.54 Mpx) takes 12 references within 10 Mpx, views of 1000 px at 0.5 m (1 Mpx)
# 10, one of 1700 px views (crops of about 2.6 Mpx) 8.
# Issue-form stacks, seeds 11-20, DFC MAE 8 -> 12 references: mean 0.884 -> 0.834 m (8 of 10
# lower), within 1 m higher on all ten, 22-29 s -> 28-38 s (docs/measurements.md, fifty-sixth
# session); 10-view stacks of 384 px at 0.5 m (all 10 references): mean 0.542 -> 0.538 m;
# 20 views of 384 px, seeds 0-1: 1.020 / 0.882 -> 1.019 / 0.849 m. Held-out issue-form seeds
# 23-28 (fifty-seventh session): 0.954 -> 0.939 m without the free-space check's voters, 0.972
# -> 0.976 m with them (fusion.VISIBILITY_VOTER_CONFIDENCE).
BUDGET_FREE_REFERENCES = 8


@dataclasses.dataclass(frozen=True)
class ViewSelectionOptions(Options):
    """Options of the choice of reference views and of their sources."""

    max_references: int = 12  # reference views swept at most (each costs a sweep)
    reference_megapixels: float = 10.0  # beyond BUDGET_FREE_REFERENCES (8) references, only
    # as many as keep the references' crops within this many megapixels in all (the median
    # crop's pixels each); 0: max_references alone
    max_sources: int = 4  # source views per reference
    min_b_over_h: float = 0.1  # least base-to-height ratio of a reference-source pair
    max_b_over_h: float = 0.5  # largest base-to-height ratio of a reference-source pair
    target_b_over_h: float = 0.25  # base-to-height ratio preferred when ranking sources
    min_overlap: float = 0.3  # least fraction of a reference crop that a source must see
    similarity_weight: float = 2.0  # weight of a source's dissimilarity (1 - similarity) against
    # its relative distance to target_b_over_h when sources are ranked
    min_similarity: float = 0.2  # sources whose metadata make them less similar than this
    # are left out when the reference keeps another (a similarity measured from tie points or
    # images only ranks them)
    side_coverage: int = 2  # references wanted that see each side of the buildings (north,
    # east, south, west: the views looking from within 60 degrees of it, and those within 6
    # degrees of nadir), where some view does; 0: no such rule
    leaf_on_references: float = 0.5  # share of the references (rounded up) taken from views
    # of dates in leaf (similarity.leaf_season >= LEAF_ON_SEASON, from the metadata's date and
    # the AOI's latitude, or from colour: leaf_from_colour) where the stack has such views:
    # the DSM holds the canopy's top, which leafless crowns do not show; 0: no such rule
    leaf_state_weight: float = 1.0  # weight of the difference in leaf state between a
    # reference and a source (|leaf_season difference|, 0 where either is unknown) in the
    # source's rank, beside similarity_weight x (1 - similarity)
    leaf_from_colour: bool = True  # where no view's metadata give a date and every image has
    # colour, the leaf state of the two rules above is estimated from the images' greenest
    # pixels (similarity.leaf_state_from_vegetation; measured in docs/measurements.md,
    # twenty-sixth session); false: unknown without dates

    ADVANCED = ("reference_megapixels", "min_b_over_h", "max_b_over_h", "target_b_over_h",
                "min_overlap", "similarity_weight", "min_similarity", "side_coverage",
                "leaf_on_references", "leaf_state_weight", "leaf_from_colour")

    def check(self) -> None:
        self._require(0 <= self.min_b_over_h < self.max_b_over_h, "min_b_over_h",
                      "must be >= 0 and < max_b_over_h")
        self._require(self.target_b_over_h > 0, "target_b_over_h", "must be > 0")
        self._require(self.max_sources >= 1, "max_sources", "must be >= 1")
        self._require(self.max_references >= 1, "max_references", "must be >= 1")
        self._require(math.isfinite(self.reference_megapixels) and self.reference_megapixels >= 0,
                      "reference_megapixels", "must be >= 0 megapixels (0: no such limit)")
        self._require(0 <= self.min_overlap <= 1, "min_overlap", "must be in [0, 1]")
        self._require(0 <= self.similarity_weight <= 100, "similarity_weight",
                      "must be in [0, 100]")
        self._require(0 <= self.min_similarity <= 1, "min_similarity", "must be in [0, 1]")
        self._require(self.side_coverage >= 0, "side_coverage", "must be >= 0 (0: no such rule)")
        self._require(math.isfinite(self.leaf_on_references)
                      and 0 <= self.leaf_on_references <= 1, "leaf_on_references",
                      "must be a share in [0, 1] (0: no such rule)")
        self._require(math.isfinite(self.leaf_state_weight)
                      and 0 <= self.leaf_state_weight <= 100, "leaf_state_weight",
                      "must be in [0, 100] (0: no such rule)")


@dataclasses.dataclass(frozen=True)
class ViewGeometry:
    """Per-view viewing geometry seen from the AOI centre."""

    direction: np.ndarray  # unit ENU vector from the AOI centre towards the camera
    incidence_deg: float  # angle between that direction and the vertical
    azimuth_deg: float  # clockwise from north, of the direction towards the camera


# The rules of ``select_views``, as report.json states them.
RULES = [
    "references: lowest incidence plus 30 degrees x (1 - mean similarity of their best sources) "
    f"first, at most max_references; beyond {BUDGET_FREE_REFERENCES}, only as many as keep "
    "their crops (the median crop's pixels each) within reference_megapixels",
    f"side coverage: the last references come from the best views of the sides (N, E, S, W; "
    f"azimuth within {SIDE_HALF_ANGLE_DEG:g} degrees, or incidence under {NADIR_DEG:g}) that "
    "some view sees and fewer than side_coverage references do",
    "sources: overlap >= min_overlap and B/H in [min_b_over_h, max_b_over_h] (else the closest "
    "pair, with a warning), no pair under B/H 0.01",
    "sources ranked by |B/H - target_b_over_h| / target_b_over_h + similarity_weight x "
    "(1 - similarity), then incidence; those whose metadata similarity is under min_similarity "
    "dropped if a better one remains (a similarity from tie points or images only ranks), "
    "unless the metadata say that every source is of another date (similarity under "
    f"{CLOSE_SIMILARITY:g} to all: then none is); at most max_sources",
    "season: at least leaf_on_references of the references are views of dates in leaf "
    f"(leaf_season >= {LEAF_ON_SEASON:g}; views part in leaf count for their part) where there "
    "are such views (the side coverage keeps its slots); sources' rank adds leaf_state_weight "
    "x their difference in leaf state from the reference; leaf_season from the metadata's date and "
    "the AOI's latitude, or where no view is dated and every image has colour (leaf_from_colour) "
    "from the share of each view's pixels as green as the stack's canopy, scaled from the "
    "pale views' median share (0) to the green views' (1) (unknown: no preference)",
    "similarity: from the acquisition metadata when both views have it (1 within one pass, else "
    "sun-direction and season terms), else from the sparse stage's tie points (each pair's "
    "matches among the strongest features over the stack's largest), else measured (gradient "
    "ZNCC on the AOI's mid plane)",
]


@dataclasses.dataclass(frozen=True)
class Selection:
    """The chosen references and sources, with the figures that justify them."""

    references: tuple[int, ...]
    sources: dict[int, tuple[int, ...]]
    b_over_h: np.ndarray  # (n, n) pairwise base-to-height ratios
    overlap: np.ndarray  # (n, n) fraction of view i's crop seen by view j
    geometry: tuple[ViewGeometry, ...]
    warnings: tuple[str, ...] = ()
    similarity: np.ndarray | None = None  # (n, n) appearance similarity; None: not known
    similarity_source: np.ndarray | None = None  # (n, n) where each pair's came from:
    # "metadata", "tie points" or "images" (satsweep.dense.similarity)
    leaf_season: tuple[float | None, ...] | None = None  # per view, how fully its date's
    # trees are in leaf (None: unknown date)
    leaf_season_from: str | None = None  # where leaf_season came from: "metadata" (the
    # dates) or "colour" (similarity.leaf_state_from_vegetation); None: unknown
    reference_limit: int | None = None  # the most references the options allowed for these
    # crops (reference_limit); None: not known

    def to_dict(self, names: Sequence[str] | None = None) -> dict:
        n = len(self.geometry)
        names = list(names) if names is not None else [str(i) for i in range(n)]
        return {
            "views": [
                {"name": names[i], "incidence_deg": g.incidence_deg, "azimuth_deg": g.azimuth_deg,
                 "leaf_season": None if self.leaf_season is None else self.leaf_season[i]}
                for i, g in enumerate(self.geometry)
            ],
            "leaf_season_from": self.leaf_season_from,
            "reference_limit": self.reference_limit,
            "pairs": [
                {"a": names[i], "b": names[j], "b_over_h": float(self.b_over_h[i, j]),
                 "overlap": float(min(self.overlap[i, j], self.overlap[j, i]))}
                for i in range(n) for j in range(i + 1, n)
            ],
            "references": [
                {"reference": names[r], "sources": [names[s] for s in self.sources[r]]}
                for r in self.references
            ],
            "similarity": (None if self.similarity is None else [
                {"a": names[i], "b": names[j], "similarity": float(self.similarity[i, j]),
                 "from": ("images" if self.similarity_source is None
                          else str(self.similarity_source[i, j]))}
                for i in range(n) for j in range(i + 1, n)]),
            "rules": RULES,
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
                 names: Sequence[str] | None = None, similarity: np.ndarray | None = None,
                 similarity_source: np.ndarray | None = None,
                 leaf_season: Sequence[float | None] | None = None,
                 leaf_season_from: str | None = None) -> Selection:
    """Choose references and their sources from the approximated cameras (see module doc).

    ``cameras`` are objects with ``center`` (ENU, m), ``P``, ``width`` and ``height``;
    ``mid_height`` is the ENU height of the middle of the altitude range; ``similarity`` the
    (n, n) appearance similarity of the views (``satsweep.dense.similarity``; None: all alike);
    ``leaf_season`` per view how fully its date's trees are in leaf (``similarity.leaf_season``;
    None, or None for a view: unknown, no preference), ``leaf_season_from`` where it came from
    (reported).
    """
    n = len(cameras)
    names = list(names) if names is not None else [f"view {i}" for i in range(n)]
    if n < 2:
        raise CameraError(f"view selection needs at least two views, got {n}")
    sim = np.ones((n, n)) if similarity is None else np.asarray(similarity, float)
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
    # Leaf state per view (None / NaN: unknown date).
    seasons = None if leaf_season is None else tuple(
        None if v is None else float(v) for v in leaf_season)
    leaf = np.array([np.nan if v is None else v for v in (seasons or (None,) * n)], float)
    leaf_gap = np.nan_to_num(np.abs(leaf[:, None] - leaf[None, :]), nan=0.0)
    in_leaf = leaf >= LEAF_ON_SEASON  # False where unknown

    def in_range(r: int, j: int) -> bool:
        return (j != r and ov[r, j] >= o.min_overlap
                and o.min_b_over_h <= bh[r, j] <= o.max_b_over_h)

    def source_cost(r: int, j: int) -> tuple[float, float]:
        return (abs(bh[r, j] - o.target_b_over_h) / o.target_b_over_h
                + o.similarity_weight * (1.0 - sim[r, j]) + o.leaf_state_weight * leaf_gap[r, j],
                geometry[j].incidence_deg)

    def reference_cost(r: int) -> float:
        cands = sorted((sim[r, j] for j in range(n) if in_range(r, j)), reverse=True)
        best = cands[:o.max_sources] or [1.0]
        return (geometry[r].incidence_deg
                + REFERENCE_DISSIMILARITY_DEG * (1.0 - float(np.mean(best))))

    def all_other_dates(r: int, sources: Sequence[int]) -> bool:
        """Whether the metadata say that none of ``sources`` shares the reference's conditions
        (see CLOSE_SIMILARITY)."""
        if similarity_source is None or not sources:
            return False
        return all(similarity_source[r, j] == "metadata" and sim[r, j] < CLOSE_SIMILARITY
                   for j in sources)

    def measured(r: int, j: int) -> bool:
        """Whether the pair's similarity was measured (tie points, images), not given by the
        metadata: its values are relative to the stack's best pair, not a date's likeness,
        so min_similarity does not apply (see CLOSE_SIMILARITY's comment)."""
        return similarity_source is not None and similarity_source[r, j] != "metadata"

    warnings: list[str] = []
    quiet: list[str] = []  # what explains a failure but is normal in a stack (repeat orbits)
    remaining = sorted(range(n), key=lambda r: (reference_cost(r), geometry[r].incidence_deg))
    sees = np.array([[g.incidence_deg < NADIR_DEG
                      or abs((g.azimuth_deg - side + 180.0) % 360.0 - 180.0) <= SIDE_HALF_ANGLE_DEG
                      for side in SIDES_DEG] for g in geometry])
    references: list[int] = []
    sources: dict[int, tuple[int, ...]] = {}
    limit = reference_limit(o, [c.width * c.height for c in cameras])
    leaf_on_wanted = math.ceil(o.leaf_on_references * min(limit, n))
    while remaining and len(references) < limit:
        r = remaining[0]
        slots = limit - len(references)
        # Season: once the slots left are no more than the references still wanted from dates
        # in leaf, the next one must be such a view (one that sees a side still wanted first),
        # unless the side coverage below needs the slot (then a view in leaf of such a side
        # if there is one, when one is due): a side that no reference sees leaves holes, not
        # just lower crowns.
        leaf_left = [j for j in remaining if in_leaf[j]]
        # References of dates part in leaf count for their part (a May date for 0.66).
        leaf_missing = leaf_on_wanted - float(np.nansum(leaf[references]))
        leaf_on = bool(leaf_left) and math.ceil(leaf_missing) >= slots
        # Side coverage: once the references left to take are no more than the views still
        # wanted on the sides that some remaining view sees, the next one must see such a side
        # (the best of those by the order above); references all on one side leave the ground
        # behind every wall facing away hidden from all of them (filled with roof heights).
        wanted = np.maximum(o.side_coverage - sees[references].sum(axis=0), 0)
        wanted = wanted * sees[remaining].any(axis=0)
        if wanted.sum() >= slots:
            side = [j for j in remaining if (sees[j] & (wanted > 0)).any()]
            r = next((j for j in side if in_leaf[j] and leaf_on), side[0] if side else r)
        elif leaf_on:
            r = next((j for j in leaf_left if (sees[j] & (wanted > 0)).any()), leaf_left[0])
        remaining.remove(r)
        cands = [j for j in range(n) if j != r and ov[r, j] >= o.min_overlap]
        flat = [j for j in cands if bh[r, j] < MIN_STEREO_B_OVER_H]
        # One viewpoint on another date (a repeat orbit, as real stacks hold): left out as a
        # source, not worth a warning; one that looks alike (or unknown) may be a copy.
        copies = [j for j in flat if similarity is None or sim[r, j] >= CLOSE_SIMILARITY]
        repeats = [j for j in flat if j not in copies]
        for group, said, why in ((copies, warnings, "the same viewpoint, or a copy of the image"),
                                 (repeats, quiet, "the same viewpoint on another date")):
            if group:
                said.append(f"{names[r]}: no parallax with {', '.join(names[j] for j in group)} "
                            f"(B/H below {MIN_STEREO_B_OVER_H}: {why})")
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
        good.sort(key=lambda j: source_cost(r, j))
        if not all_other_dates(r, good):
            similar = [j for j in good if sim[r, j] >= o.min_similarity or measured(r, j)]
            good = similar or good[:1]
        sources[r] = tuple(good[: o.max_sources])
        references.append(r)
    if not references:
        raise CameraError("no stereo pair among the views (" + "; ".join(warnings + quiet) + ")")
    return Selection(references=tuple(references), sources=sources, b_over_h=bh, overlap=ov,
                     geometry=geometry, warnings=tuple(warnings),
                     similarity=None if similarity is None else sim,
                     similarity_source=similarity_source, leaf_season=seasons,
                     leaf_season_from=None if seasons is None else leaf_season_from,
                     reference_limit=limit)


def reference_limit(options: ViewSelectionOptions, crop_pixels: Sequence[int]) -> int:
    """The most references ``options`` allow for views of ``crop_pixels`` pixels each:
    ``max_references``, but beyond BUDGET_FREE_REFERENCES only as many as keep that many crops
    of the median's pixels within ``reference_megapixels`` (0: no such limit)."""
    limit = options.max_references
    if options.reference_megapixels > 0 and len(crop_pixels):
        each = max(float(np.median(crop_pixels)), 1.0) / 1e6
        fit = int(options.reference_megapixels / each)
        limit = min(limit, max(BUDGET_FREE_REFERENCES, fit))
    return limit


def _range_distance(value: float, o: ViewSelectionOptions) -> float:
    if value < o.min_b_over_h:
        return o.min_b_over_h - value
    if value > o.max_b_over_h:
        return value - o.max_b_over_h
    return 0.0
