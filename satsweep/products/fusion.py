"""From per-view height maps to a DSM on a UTM grid: cross-check, rasterisation, fusion.

Stages (host code, float64 numpy, vectorised):

1. ``cross_check_heights`` keeps only the pixels whose 3D point another reference view's height
   map confirms (the points themselves: :mod:`satsweep.products.points`).
2. ``rasterise_max``: points to cells of the grid (:mod:`satsweep.products.grid`), highest point
   per cell (a DSM is the top surface: a roof point beats a wall point falling in the same cell);
   ``rasterise_quantile_cells`` for views of several pixels per cell (``DSMOptions.view_raster``).
3. ``fuse_dsms``: per cell, median of the per-reference-view DSMs after discarding values farther
   than ``outlier_m`` from their first median (a consistency filter across views).
4. ``fill_small_holes``: optional; fills holes of a few cells (those at the border too, by
   default) and returns how many cells it filled, so the caller reports it.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Callable, Hashable, Literal, Sequence

import numpy as np

from satsweep.errors import OptionsError
from satsweep.io.images import VEGETATION_INDEX_MIN
from satsweep.options import Options
from satsweep.products.grid import DSMGrid
from satsweep.products.points import Points, points_to_utm, project_points, solve_ground_en
from satsweep.threads import map_in_threads

# Threads of the free-space check and the cross-check (a view each: numpy's projections and
# comparisons release the GIL; the same masks as one thread). A 19-view stack of 1700^2 px at
# 0.3 m (8 references of 2 Mpx) on 2 cores: the DSM stage 24.4-26.3 -> 21.4-23.9 s, its own
# peak 2.6 -> 3.0-3.2 GB (each thread holds a view's points and their projections), so two
# whatever the cores; the run's peak (the sweep's, 5.1 GiB) and the Pleiades pair's are as before.
FUSION_THREADS_MAX = 2

# fuse_dsms works on row blocks of at most this many values (views x cells): ~64 MB per float64
# temporary, whatever the DSM size.
FUSE_BLOCK_VALUES = 8_000_000
# With this many reference height maps or more, [dsm] fusion = "auto" takes the consensus. Two
# references are one pair seen both ways, which the per-pixel cross-check already compares;
# on tools/bench_e2e.py's 3-view towns (seeds 0-1) the consensus of 3 gave 90.8% / 88.7%
# within 1 m against the cross-check's 91.0% / 88.9% (medians 0.158 / 0.180 m against
# 0.158 / 0.179 m).
CONSENSUS_MIN_REFERENCES = 4
# The default of [dsm] consensus_min_share: a cell whose largest agreeing group holds fewer than
# half of the reference heights there (the views that see it scatter: shadows of other dates,
# alleys between tall buildings that few views see to the ground) is left to the hole filling
# (the lowest of the hole's rim, the ground beside a wall). On six multi-date stacks at 0.3 m
# (17-19 views, 8 references) DFC MAE 1.156 -> 1.120 m (lower on 5, within 1 m as high or higher
# on all 6); 10-view stacks at 0.5 m (seeds 0-5, passes and one view per date): within 1 m 92.66
# -> 92.69% and 88.08 -> 88.09%, MAE 0.699 -> 0.699 and 1.390 -> 1.384 m. Requiring 3 agreeing
# views instead: MAE 1.075 m on the 0.3 m stacks but one 0.5 m stack 3.1 points lower within 1 m
# (docs/measurements.md).
CONSENSUS_MIN_SHARE = 0.5
# A view with at least this many pixel centres per cell it fills (the mean) is rasterised by a high
# quantile of its points in each cell (VIEW_RASTER_QUANTILE) rather than their highest ([dsm]
# view_raster = auto). With about one pixel per cell (0.5 m pixels on 0.5 m cells) the highest of
# the footprint sub-samples reaching a cell is the surface's top there, as the truth's highest point
# per cell; with several (0.3 m pixels: about 2.8 per cell) it is the most fattened or wrong of
# them. Nine synthetic multi-date stacks at 0.3 m (docs/measurements.md): DFC MAE 1.224 -> 1.091 m
# on average (lower on 8 of 9), within 1 m 89.06 -> 89.00%; the median instead: 1.055 m but 88.75%,
# and one stack 0.27 m worse. At 0.5 m either loses (v10 seeds 0-5, median: 92.66 -> 91.55% within
# 1 m; upper quartile 92.04%).
DENSE_CENTRES_PER_CELL = 2.0
# The quantile of a dense view's points that makes its height in a cell: the
# ``floor(q (n - 1) + 0.5)``-th of n values in ascending order. 0.3 m pixels on 0.5 m cells with
# 2 x 2 sub-samples a pixel (``subsamples``) put about 11 points in a cell: 0.85 takes the second
# highest of 11, the upper quartile (0.75, before the sixtieth session) the third. Issue-form
# stacks (19 views at 0.3 m), the DSM stage replayed on their runs' height maps: DFC MAE 0.7952
# -> 0.7882 m on seeds 11-20 and 23-57 (lower on 30 of 45), 0.8425 -> 0.8386 m on seeds 58-98
# (held out: lower on 23 of 41); 0.8 and 0.9 0.7905 and 0.7909 m, 0.625 0.8301 m and 0.5 0.8668 m
# (higher on 36 and 38 of 45), the highest 0.8040 m (higher on 23).
VIEW_RASTER_QUANTILE = 0.85
# A pixel of a height map lies on the high side of a step when one of its 8 neighbours is more
# than this many metres lower (``step_edge_pixels``): where edges and facades matched at the
# roof's height put their points in the air. On the 0.3 m issue-form stacks 11-17% of each
# reference map's points lie more than 1 m above the highest surface within 0.3 m, 88-94% of
# them on such a step's high side or a pixel from it, with confidences of 0.02-0.11 (quartiles;
# the other points 0.31-0.86). Leaving out a dense view's step pixels under
# dsm.edge_min_confidence = 0.15, DFC MAE m on six such stacks (seeds 7, 8, 9, 11, 12, 13):
# 0.931 0.875 0.984 1.510 0.834 1.159 -> 0.938 0.760 0.840 1.456 0.733 1.221 (mean 1.049 ->
# 0.991), within 1 m 90.23% against 90.05% on average; dropping every pixel under that
# confidence opened roofs (seed 13: 1.305 m); 0.5 m views (the highest point per cell) are left
# alone: there it lost on 4 of 6 v10 stacks (docs/measurements.md).
EDGE_STEP_M = 2.0
# Vertical co-registration of the reference views' rasters before the consensus ([dsm]
# coregister): each raster's offset to a first consensus is the median of their differences
# over the cells where that consensus is flat (a slope under COREGISTER_FLAT_M per cell: no
# edge, wall or crown) and the two agree within COREGISTER_WINDOW_M; fewer than
# COREGISTER_MIN_CELLS such cells leave the raster as it is. Each reference map carries its own
# few decimetres of height offset (the pointing left after the adjustment, along its pair's
# epipolar lines: on v10 seed 0 the maps' offsets to the truth spread over 0.33 m), which blurs
# the consensus. Measured on the v10 stacks (seeds 0-5; offsets found within +-0.30 m) and the
# issue-form 0.3 m stacks (seeds 7-13): medians lower on 10 of 12 (0.114 -> 0.098 m on v10
# seed 0), within 1 m as high or higher on 11 of 12, DFC MAE as low or lower on all 12.
COREGISTER_FLAT_M = 0.2
COREGISTER_WINDOW_M = 2.0
COREGISTER_MIN_CELLS = 100
# The free-space check's slack ([dsm] visibility_slack_px, visibility_slack_confidence): view j
# sees past a point of view k when its height at the point's pixel lies below the point; each
# view's occlusion edges are off by about a pixel (a tree crown narrower by a cell in one map
# than in another, a roof's edge rounded either way), so at a crown's rim the views that erode
# it "see past" the points of the views that do not, and the check removed the rim that the
# consensus needed (v10 seed 2: the crowns' outermost cells 56% more than 1 m off after the
# fusion, against 38% in its best same-date pair, which runs no such check). With the slack, j
# sees past a point only where its heights at the pixel and its neighbours within the slack all
# lie below it. A facade matched at its roof's height (a point in the air beside a wall, a
# pixel or more from the roof's edge in the other views) is matched with low confidence
# (0.02-0.11 on the 0.3 m stacks, EDGE_STEP_M above) and keeps the strict test,
# the nearest pixel; the slack alone, for every pixel, let those facades stand (v10 seed 1: DFC
# MAE 0.860 -> 1.040 m, the ground beside walls more than 1 m off 40 -> 51%). The far rule
# (visibility_far_m) reads the nearest pixel. v10 seeds 0-5 (docs/measurements.md, eighteenth
# session): within 1 m 93.27 -> 93.48% on average (higher on all six), DFC MAE 0.618 ->
# 0.604 m; confidences 0.2 / 0.5: 93.50 / 0.605 and 93.38 / 0.611; a 2-pixel slack 93.46 /
# 0.603; the issue-form 0.3 m stacks (seeds 7-13) DFC MAE 0.928 -> 0.925 m on average.
VISIBILITY_SLACK_PX = 1
VISIBILITY_SLACK_CONFIDENCE = 0.3
# The free-space check's voters ([dsm] visibility_voter_confidence): a view whose pixels are
# finer than the cells (fine_pixels) sees past a point only from its pixels whose matching
# confidence (SGM's margin between its two lowest minima) is at least this. A height of two
# near-equal minima is no evidence that the space above it is empty: a roof in another tower's
# moving shadow, matched low by the views of the dates that shadow it, outvoted the views that
# matched it (twelve references on issue-form seed 11: a 135-cell patch of a 39 m roof emptied
# and filled from the ground). Issue-form stacks (seeds 11-20, 12 references), DFC MAE mean
# 0.834 -> 0.805 m at 0.01 (lower on 8 of 10, seed 11 1.117 -> 1.045 m); at 0.02 0.799 m
# (seed 11 1.068), at 0.05 / 0.15 seeds 11 and 16 1.131 / 1.282 and 0.853 / 0.989 m
# (docs/measurements.md, fifty-sixth session). Views of pixels as wide as the cells vote as
# before: on the 0.5 m stacks of 10 views (v10 seeds 0-5) every view voting so at 0.02 took
# the mean 0.538 -> 0.556 m (seed 1 0.782 -> 0.874). Not confirmed on held-out stacks: issue-
# form seeds 23-32 (made after the choice) 0.880 -> 0.901 m, worse on 7 of 10; the 1700 px
# stack 1.003 -> 0.930 m; over those 21 stacks 0.864 -> 0.857 m (fifty-seventh session).
VISIBILITY_VOTER_CONFIDENCE = 0.01
MAX_VISIBILITY_SLACK_PX = 8
# Small raised objects' whole footprints ([dsm] small_object_area_m2): the DSM holds each
# cell's highest point (as the lidar truths do), and a pixel's sub-samples (+-0.25 px with 2 per
# side) stop short of its footprint's edges, so the cells a tree crown (or a truck, a shed) only
# overhangs take the ground beside it. Spreading every pixel's sub-samples to its footprint's
# edges carried the facades matched at the roof's height onto the ground beside buildings as
# well (docs/measurements.md, seventeenth session: v10 seed 1 DFC MAE 0.860 -> 1.163 m). Only
# the pixels of small raised regions of a view's height map spread: pixels at least
# SMALL_OBJECT_MIN_HEIGHT_M above the ground (the lowest of the map, smoothed by a
# SMALL_OBJECT_SMOOTH_PX median, within SMALL_OBJECT_GROUND_WINDOW_M), in 8-connected regions of
# at most small_object_area_m2; their sub-samples reach FOOTPRINT_EDGE_PX of the pixel's centre
# (just inside its edges). v10 seeds 0-5 (eighteenth session), with the free-space slack: within
# 1 m 93.48 -> 93.66% on average (higher on all six), DFC MAE 0.604 -> 0.588 m; the issue-form
# 0.3 m stacks 0.925 -> 0.924 m (docs/measurements.md).
SMALL_OBJECT_MIN_HEIGHT_M = 2.0
SMALL_OBJECT_GROUND_WINDOW_M = 20.0
SMALL_OBJECT_SMOOTH_PX = 5
FOOTPRINT_EDGE_PX = 0.49
# Crowns in the views rasterised by the quantile ([dsm] small_object_top): a crown's rim is a step,
# matched poorly where the leaves' fine texture differs between dates, so the edge rule
# (edge_min_confidence) dropped it, and the quantile of a rim cell's points is the ground's wherever
# fewer than 15% of them are the crown's (a quarter with the upper quartile, measured): the
# issue-form 0.3 m stack seed 11 (19 dates) had its crowns' outer cells (within 0.75 m of the rim)
# 4.7 m too low (median) and 74% more than 1 m too low. Keeping the small raised objects' step
# pixels and giving each cell the highest of their points, issue-form stacks (19 views, 0.3 m;
# docs/measurements.md) DFC MAE m, seeds 11 13 14 15 16 17 18: 1.117 1.112 0.834 1.024 1.190 0.457
# 0.837 -> 1.090 1.080 0.764 1.029 1.162 0.454 0.826 (mean 0.939 -> 0.915), crowns within 1 m higher
# on all seven; the step pixels kept alone: 1.103 and 1.178 m on seeds 11 and 16. Views of a pixel
# per cell (their highest point per cell already) are left as they were.
SMALL_OBJECT_TOP = True
# Crowns that join larger raised regions ([dsm] green_top): a clump of crowns, or a crown against
# a wall, is one raised region of more than small_object_area_m2, so small_object_top left its
# rims to the edge rule. On 15 issue-form stacks (the DSM stage replayed, the error by the truth's
# class, the ground far from objects as zero) the crowns' inner cells were 1.2-4.7 m too low on
# average (medians 0.4-3.1 m), their rim cells 1.0-2.5 m, the roofs' inner cells' medians within
# 0.05 m; with no edge rule at all (edge_min_confidence 0) seeds 11-20, 23-57 went 0.7881 ->
# 0.7931 m, lower by up to 0.14 m on some stacks, higher by as much on others. Where the views
# have colour, the pixels of raised regions of any area that the reference image shows as
# vegetation (green_raised_pixels) count as the small objects' do. DFC MAE mean, issue-form
# stacks (docs/measurements.md, sixty-first session): seeds 11-20, 23-57 0.7881 -> 0.7662 m
# (lower on 27, higher on 17; over 1 m 8 -> 6), held-out seeds 58-104 0.8379 -> 0.8295 m (23 /
# 22), the 1700 px stack 0.907 -> 0.832 m; by class (seeds 11-20, 23-32, before the opening
# below) the crowns' cells better on all 20 and the ground beside buildings worse on all 20.
GREEN_TOP = True
# Green raised pixels count only where they fill a square this wide (a morphological opening):
# a strip of grass along a wall that a reference matched at the roof's height is one or two
# pixels wide, a crown metres. 1 m (3 pixels of 0.3 m) against no opening: seeds 11-20, 23-57
# 0.7674 -> 0.7662 m (lower on 27, higher on 16), held-out seeds 58-104 0.8303 -> 0.8295 m (30 /
# 15), the 1700 px stack 0.821 -> 0.832 m; a 3-pixel cross instead of the square 0.7659 / 0.8294
# m, a 5-pixel disc (1.5 m) 0.7689 m on seeds 11-20, 23-57.
GREEN_TOP_MIN_WIDTH_M = 1.0
# Crowns' tops from the views of dates in leaf ([dsm] leaf_on_crowns): in winter a deciduous
# crown shows the ground through its branches, and the consensus of all dates puts a crown's
# cells between the two (issue-form seed 11: crowns 2.85 m too low on average). A cell takes the
# mean of the highest two leaf-on reference rasters (of two passes) that agree within the
# consensus tolerance, where that lies more than LEAF_TOP_RISE_M above the consensus (less: the
# consensus holds the crown already) and belongs to a small raised object (small_raised_pixels
# over the cells: not a roof; buildings keep their consensus). Issue-form stacks, DFC MAE m
# (twenty-fourth session): 11 1.075 -> 1.062, 13 1.089 -> 1.072, 16 1.160 -> 1.135, 14 0.758
# -> 0.741, seven others within 0.005 m; with any two dated views instead of those in leaf, the
# same mean but ground, roads and plazas raised on seeds 8, 9, 15 (docs/measurements.md).
LEAF_TOP_RISE_M = 1.0
# Crowns' empty cells ([dsm] crown_holes): where the views scatter on a crown (each date redraws
# its leaves; leafless dates see the ground) the consensus leaves the cell empty and the hole
# filling gives it its rim's lowest height, the ground's (issue-form seed 16: 1468 crown cells,
# 9 m too low, 12% of the error). Such a cell takes the highest pair of reference rasters of
# two passes that agree there, where that is a small raised object. Issue-form stacks, DFC MAE
# m (twenty-fourth session, after leaf_on_crowns): 16 1.135 -> 1.093, 13 1.072 -> 1.059, 11
# 1.062 -> 1.055, 18 0.828 -> 0.816, 8 0.845 -> 0.851, 9 0.949 -> 0.956, the others within
# 0.006 m (docs/measurements.md).

# Crowns' tops from colour ([dsm] green_crowns): a view whose image shows vegetation at a cell's
# highest point (satsweep.io.images.vegetation_index at least its VEGETATION_INDEX_MIN:
# leaves, and grass, which the rule tells from crowns by height) sees the crown there, not the
# ground through it; where at least GREEN_MIN_VIEWS such views put the cell on a small raised
# object of their own maps, the highest of their heights is the crown's top if it lies more than
# GREEN_TOP_RISE_M above the consensus. Issue-form stacks with colour (docs/measurements.md,
# twenty-fifth session), DFC MAE m, seeds 13 / 16: 1.058 / 1.082 -> 0.987 / 0.956; the others
# within 0.016 m either way (raising crowns moves the protocol's mean offset, which the
# too-high ground beside walls already pulls up). One such view was enough (13 / 16 0.945 /
# 0.910) but raised crowns' rims and grass beside them (8, 11, 15 worse by 0.018-0.055).
GREEN_TOP_RISE_M = 1.0
GREEN_MIN_VIEWS = 2
# Raised cells that few reference views agree on, in thin regions ([dsm] thin_raised_max_share).
# The floors of narrow gaps between tall buildings (alleys, courtyards, inner corners) are seen
# by few views, and the references match them at their walls' heights: on issue-form seed 34,
# of the reference pixels that see such a floor, 15% come within 1 m (12-71% per reference
# where all four of its sources see it too; 9% with the winner-take-all of unfiltered costs
# over every plane). The consensus there is a few views agreeing on a wall's height (a median
# of 5 of 12 on seeds 11, 25, 29 and 34, where correct roofs gather 9-10), and the gaps up to
# 3 m across hold 28-36% of the error of the issue-form stacks over 1 m (tools/diag_gaps.py).
# Such a cell, more than THIN_RAISED_RISE_M above the lowest consensus cell within
# THIN_RAISED_GROUND_M, is left to the hole filling (its rim's lowest: the gap's ground where it
# opens onto a street), unless it lies in a region of such cells and empty ones that holds a
# square THIN_RAISED_SIDE_M wide (a roof in a tower's shadow, speckled with holes, keeps its
# heights: without that, and with a rise of 2.5 m, seed 11 lost 0.35 m). Lower raised cells keep
# theirs (crowns and low roofs: with a rise of 2.5 m the 30 stacks below lost on 13, seed 20 by
# 0.14 m). Issue-form stacks (12 references), DFC MAE mean over seeds 11-20 / 23-32 / 33-42:
# 0.805 / 0.901 / 0.975 -> 0.812 / 0.837 / 0.912 m, lower on 20 of 30 (seven over 1 m before and
# after); seeds 43-52, made while choosing and after, 0.909 -> 0.839 m (lower on 5 of 10); the
# 1700 px stack (8 references) 0.930 -> 0.962 m; the 0.5 m stacks of 10 views (v10 seeds 0-5)
# 0.538 -> 0.535 m (docs/measurements.md, fifty-eighth session).
THIN_RAISED_RISE_M = 15.0
THIN_RAISED_GROUND_M = 15.0
THIN_RAISED_SIDE_M = 2.5
# Raised cells in a valley of the consensus's counts ([dsm] valley_min_share). A gap's floor
# matched at its walls' heights is agreed on by fewer views than the roofs on either side of it
# (a median of 5 of 12 against 9-10: THIN_RAISED_RISE_M's comment), whatever the width of the
# region of such cells. A cell raised as THIN_RAISED_RISE_M says whose count lies, along a row,
# a column or a diagonal, at least valley_min_share of the reference views (rounded up) under
# the highest count of the raised cells within VALLEY_REACH_M on each side is left to the hole
# filling too. Chosen on replays of the DSM stage over issue-form seeds 11-20 and 23-57 (12
# references, so 4 views: a reach of 1.5 / 2 / 2.5 / 3 m, 3-5 views, with or without a share
# limit or a square; docs/measurements.md, fifty-ninth session); DFC MAE mean 0.830 -> 0.795 m
# there, and on 25 held-out stacks made before the choice was tried on them (seeds 58-82)
# 0.854 -> 0.818 m, lower on 15 and higher on 10.
VALLEY_REACH_M = 2.0


@dataclasses.dataclass(frozen=True)
class DSMOptions(Options):
    """Options of the DSM stage (rasterisation, fusion across reference views, hole filling)."""

    resolution: float = 0.5  # DSM cell size (m, UTM)
    fill_max_hole_cells: int = 1000  # fill holes of at most this many cells; 0: none
    fill_border_holes: bool = True  # also fill the holes that touch the DSM's border (those of
    # fill_max_hole_cells cells at most)
    subsamples: int = 2  # points splatted per side of each reference pixel's footprint (1: its
    # centre only)
    cross_check_m: float = 2.0  # median fusion: a reference pixel is kept where another
    # reference view's height map agrees within this (m); 0: no check
    cross_check_views: int = 1  # how many other reference views must agree
    outlier_m: float = 2.0  # fusion: per-view heights farther than this (m) from the cell's
    # first median are dropped
    min_views: int = 1  # fusion: cells that fewer reference views fill are left empty
    fill_method: Literal["min", "supported_min", "median"] = "min"  # a filled hole's value: the
    # minimum of its rim, the lowest rim value that RIM_SUPPORT_SHARE of the rim (and two cells)
    # lie within RIM_SUPPORT_M above (one blunder on a rim does not set the hole), or the median
    fusion: Literal["auto", "median", "consensus"] = "auto"  # how the reference views' heights
    # make a cell's: consensus of agreeing views, or the median after the cross-check; auto =
    # consensus with CONSENSUS_MIN_REFERENCES reference views or more
    consensus_tolerance_m: float = 1.0  # consensus: heights within this (m) of each other agree
    consensus_min_views: int = 2  # consensus: cells fewer views agree on are left empty
    consensus_min_share: float = CONSENSUS_MIN_SHARE  # consensus: ... or fewer than this share
    # of the reference views with a height there (0.5: half of them, rounded up); 0: none
    coregister: bool = True  # consensus: each reference view's raster is first moved up or down
    # by its median offset to a first consensus on flat cells (COREGISTER_FLAT_M)
    visibility_check: bool = True  # consensus: drop the points that more reference views see
    # past (free space, by more than consensus_tolerance_m) than agree with (within it)
    visibility_far_m: float = 15.0  # ... or that views seeing more than this (m) past them are
    # half as many as agree with (facades at their roof's height); 0: no such rule
    visibility_leaf_on_far_m: float = 3.0  # ... and the views whose pixels are finer than the
    # cells (fine_pixels) and whose date is in leaf (similarity.leaf_season >= LEAF_ON_SEASON)
    # count as seeing far past from this (m) on: a wall's roof points in front of it are a
    # storey or more above the ground those views see there, leafless views see the ground
    # through crowns, and views of cell-wide pixels read the ground beside a roof's edge a pixel
    # off (docs/measurements.md); 0: no such rule
    visibility_bare_far_m: float = 3.0  # ... and so does every view whose pixels are finer
    # than the cells and whose height map was matched with a source of its own date (the
    # metadata's pass: the same shadows), whatever its season, from this (m) on, past the
    # points that their own view's image does not show green (vegetation_index under
    # VEGETATION_INDEX_MIN): only crowns are seen through, and only on leafless dates. A stack
    # without colour or without dates takes no part. Issue-form 0.3 m stacks with metadata:
    # DFC MAE lower on 10 of 12, mean over the nine 0.756 -> 0.738 m; without the same-date
    # condition the stacks of one view per date lost 0.05 m (docs/measurements.md); 0: none
    visibility_slack_px: int = VISIBILITY_SLACK_PX  # a view sees past a confident point only
    # where its heights within this many pixels of the point's pixel all lie below it
    # (occlusion edges a pixel off: crowns one view erodes); 0: the nearest pixel only
    visibility_slack_confidence: float = VISIBILITY_SLACK_CONFIDENCE  # ... confident: a
    # pixel's matching confidence at least this (facades matched at the roof's height are not)
    visibility_voter_confidence: float = VISIBILITY_VOTER_CONFIDENCE  # a view whose pixels are
    # finer than the cells sees past a point (or far past) only from its pixels of at least
    # this matching confidence (two near-equal cost minima are no evidence of free space); 0:
    # from every pixel
    small_object_area_m2: float = 150.0  # the pixels of a view's raised regions (2 m above the
    # ground around them) of at most this area splat to their footprints' edges: a crown's rim
    # reaches the cells it overhangs (SMALL_OBJECT_MIN_HEIGHT_M); 0: none (subsamples 1:
    # nothing to spread)
    small_object_top: bool = SMALL_OBJECT_TOP  # in a view rasterised by the quantile
    # (view_raster), the pixels of those small raised objects keep their step pixels
    # (edge_min_confidence) and each cell takes the highest of their points where that lies
    # above the quantile: a tree crown's top, as the truth's highest point per cell
    green_top: bool = GREEN_TOP  # with small_object_top (and small_object_area_m2 > 0), in
    # views of colour images, the pixels of raised regions of any area (a clump of crowns, a
    # crown against a wall) that the reference image shows as vegetation (VEGETATION_INDEX_MIN)
    # count as small objects' pixels there (green_raised_pixels)
    leaf_on_crowns: bool = True  # consensus: where two reference views of dates in leaf (the
    # metadata's date; of two passes) agree on a small raised object's top above the cell's
    # consensus height, the cell takes it (leafless crowns show the ground below them); views
    # without a date take no part (leaf_on_crown_tops)
    crown_holes: bool = True  # consensus: a cell no group agrees on, on a small raised object
    # that two reference views of different passes (the metadata's times) agree on, takes their
    # height rather than the hole filling's (its rim's lowest: the ground; crown_hole_tops)
    green_crowns: bool = True  # consensus: where two or more reference views of colour
    # images see vegetation (VEGETATION_INDEX_MIN) on a small raised object of their own maps
    # more than 1 m above the cell's consensus height, the cell takes the highest of those
    # views' heights (green_crown_tops); a stack with an image of one band takes no part
    consensus_min_distinct_views: int = 3  # consensus: the agreeing height maps must be matched
    # from at least this many distinct views in all (A against B and B against A are one pair;
    # at most the views there are)
    thin_raised_max_share: float = 0.25  # consensus: a cell more than THIN_RAISED_RISE_M above the
    # ground around it that at most this share of the reference views agree on, in a thin
    # region (no square of THIN_RAISED_SIDE_M fits in it with the empty cells around), is left
    # to the hole filling: the floors of narrow gaps between tall buildings, which the
    # references match at their walls' heights (THIN_RAISED_RISE_M's comment); 0: none
    valley_min_share: float = 0.33  # consensus: a cell raised as above whose views agreeing
    # lie, along a row, column or diagonal, at least this share of the reference views (rounded
    # up) under those of the raised cells within VALLEY_REACH_M on each side, is left to the
    # hole filling: a gap's floor matched at its walls' heights, with the roofs around it
    # agreed on by more views (VALLEY_REACH_M's comment); 0: none
    edge_min_confidence: float = 0.15  # a dense view's pixels (those view_raster = auto
    # rasterises by the quantile) on the high side of a height step (EDGE_STEP_M) are dropped
    # below this confidence: edges and facades matched at the roof's height; 0: none
    view_raster: Literal["auto", "max", "quantile"] = "auto"  # a reference view's height in a
    # cell: the highest of its points there, or their VIEW_RASTER_QUANTILE (0.85); auto = the
    # quantile where the view has 2 pixel centres per filled cell or more
    # (DENSE_CENTRES_PER_CELL: finer pixels than cells, as WorldView-3's 0.3 m on 0.5 m
    # cells), else the highest

    ADVANCED = ("subsamples", "cross_check_m", "cross_check_views", "outlier_m", "min_views",
                "fill_method", "fill_border_holes", "consensus_tolerance_m", "consensus_min_views",
                "consensus_min_share", "consensus_min_distinct_views", "thin_raised_max_share",
                "valley_min_share",
                "coregister",
                "visibility_check", "visibility_far_m", "visibility_leaf_on_far_m",
                "visibility_bare_far_m", "visibility_slack_px",
                "visibility_slack_confidence", "visibility_voter_confidence",
                "small_object_area_m2", "small_object_top", "green_top",
                "leaf_on_crowns", "crown_holes", "green_crowns",
                "view_raster", "edge_min_confidence")

    def check(self) -> None:
        self._require(math.isfinite(self.resolution) and self.resolution > 0.0, "resolution", "must be > 0 metres")
        self._require(1 <= self.subsamples <= 8, "subsamples", "must be 1..8")
        self._require(math.isfinite(self.cross_check_m) and self.cross_check_m >= 0.0, "cross_check_m",
                      "must be >= 0 metres (0 disables the check)")
        self._require(self.cross_check_views >= 1, "cross_check_views", "must be >= 1")
        self._require(math.isfinite(self.outlier_m) and self.outlier_m > 0.0, "outlier_m", "must be > 0 metres")
        self._require(self.min_views >= 1, "min_views", "must be >= 1")
        self._require(self.fill_max_hole_cells >= 0, "fill_max_hole_cells", "must be >= 0 (0 disables filling)")
        self._require(math.isfinite(self.edge_min_confidence)
                      and 0.0 <= self.edge_min_confidence <= 1.0, "edge_min_confidence",
                      "must be a confidence in [0, 1] (0: none dropped)")
        self._require(math.isfinite(self.visibility_far_m) and self.visibility_far_m >= 0.0,
                      "visibility_far_m", "must be >= 0 metres (0: no such rule)")
        self._require(math.isfinite(self.visibility_leaf_on_far_m)
                      and self.visibility_leaf_on_far_m >= 0.0, "visibility_leaf_on_far_m",
                      "must be >= 0 metres (0: no such rule)")
        self._require(math.isfinite(self.visibility_bare_far_m)
                      and self.visibility_bare_far_m >= 0.0, "visibility_bare_far_m",
                      "must be >= 0 metres (0: no such rule)")
        self._require(0 <= self.visibility_slack_px <= MAX_VISIBILITY_SLACK_PX,
                      "visibility_slack_px", f"must be 0..{MAX_VISIBILITY_SLACK_PX} pixels")
        self._require(math.isfinite(self.visibility_slack_confidence)
                      and 0.0 <= self.visibility_slack_confidence <= 1.0,
                      "visibility_slack_confidence", "must be a confidence in [0, 1]")
        self._require(math.isfinite(self.visibility_voter_confidence)
                      and 0.0 <= self.visibility_voter_confidence <= 1.0,
                      "visibility_voter_confidence", "must be a confidence in [0, 1] (0: every "
                      "pixel votes)")
        self._require(math.isfinite(self.small_object_area_m2) and self.small_object_area_m2 >= 0.0,
                      "small_object_area_m2", "must be >= 0 square metres (0: none)")
        self._require(math.isfinite(self.consensus_tolerance_m) and self.consensus_tolerance_m > 0,
                      "consensus_tolerance_m", "must be > 0 metres")
        self._require(self.consensus_min_views >= 1, "consensus_min_views", "must be >= 1")
        self._require(math.isfinite(self.consensus_min_share)
                      and 0.0 <= self.consensus_min_share <= 1.0, "consensus_min_share",
                      "must be a fraction in [0, 1] (0: no such rule)")
        self._require(math.isfinite(self.thin_raised_max_share)
                      and 0.0 <= self.thin_raised_max_share <= 1.0, "thin_raised_max_share",
                      "must be a fraction in [0, 1] (0: no such rule)")
        self._require(math.isfinite(self.valley_min_share)
                      and 0.0 <= self.valley_min_share <= 1.0, "valley_min_share",
                      "must be a fraction in [0, 1] (0: no such rule)")

    def view_raster_for(self, centre_cells: np.ndarray) -> str:
        """The rule (``"max"`` or ``"quantile"``) of a view's raster whose pixel centres
        fall in ``centre_cells`` (``flat_cells``, -1 outside the grid)."""
        if self.view_raster != "auto":
            return self.view_raster
        dense = centres_per_cell(centre_cells) >= DENSE_CENTRES_PER_CELL
        return "quantile" if dense else "max"

    def fusion_for(self, n_references: int) -> str:
        """The fusion an area with ``n_references`` reference height maps uses."""
        if self.fusion != "auto":
            return self.fusion
        return "consensus" if n_references >= CONSENSUS_MIN_REFERENCES else "median"


def cross_check_heights(heights: Sequence[np.ndarray], projections: Sequence[np.ndarray], *,
                        tolerance_m: float, min_agreeing: int = 1,
                        points: Sequence[tuple[np.ndarray, ...]] | None = None) -> list[np.ndarray]:
    """Consistency of the height maps of several reference views (a geometric cross-check).

    ``heights[k]``: (H_k, W_k) ENU up coordinate (m) of the surface seen at each pixel of
    reference view k, NaN where unknown; ``projections[k]``: that view's 3x4 ENU -> pixel matrix.
    Each known pixel of view k becomes its 3-D point (the pixel's ray at its height); the point is
    projected into every other view j, whose height at the nearest pixel (``floor(x + 0.5)``)
    must lie within ``tolerance_m`` of the point's height. A pixel is kept when at least
    ``min_agreeing`` other views confirm it (all the others when there are fewer): a wrong match
    (occlusion, low texture, fattened edge) rarely lands on the same 3-D point from another
    viewpoint. Returns one boolean mask per view (True = known and confirmed). With a single view
    nothing can be checked and its known pixels are returned as they are. ``points``: each
    view's ``height_map_to_enu(heights[k], isfinite(heights[k]), projections[k])``, when the
    caller has them already (they are then not solved again; the same masks).
    """
    if not (isinstance(min_agreeing, int) and min_agreeing >= 1):
        raise OptionsError(f"min_agreeing = {min_agreeing!r}: must be an integer >= 1")
    need = min(min_agreeing, len(heights) - 1)
    return _heights_seen_by_others(heights, projections, tolerance_m, points,
                                   "cross_check_heights",
                                   reduce=lambda known, agree, _past, _far: known & (agree >= need))


def visibility_check_heights(heights: Sequence[np.ndarray], projections: Sequence[np.ndarray], *,
                             tolerance_m: float, far_m: float = 0.0,
                             points: Sequence[tuple[np.ndarray, ...]] | None = None,
                             slack_px: int = 0,
                             confidences: Sequence[np.ndarray | None] | None = None,
                             slack_min_confidence: float = 0.0,
                             trusted_far_m: float = 0.0,
                             trusted_views: Sequence[bool] | None = None,
                             bare_far_m: float = 0.0,
                             bare_views: Sequence[bool] | None = None,
                             green: Sequence[np.ndarray | None] | None = None,
                             voter_min_confidence: float = 0.0,
                             voter_views: Sequence[bool] | None = None
                             ) -> list[np.ndarray]:
    """Free-space check of several reference views' height maps.

    Each known pixel of view k becomes its 3-D point, projected into every other view j. View j
    *sees past* the point when its own height at that pixel lies more than ``tolerance_m`` below
    it: its line of sight runs through the point to a surface behind it, so the point is empty
    space for j. It *agrees* when the heights are within ``tolerance_m``; a height above the
    point means the point is hidden from j (no evidence). A pixel is dropped when more views see
    past it than agree with it, or (``far_m`` > 0) when the views that see more than ``far_m``
    past it are at least half as many as those that agree. The errors this removes are those a
    consensus of views cannot: a facade matched at its roof's height puts roof points over the
    ground in front of the wall, and every view from that side makes the same mistake, while
    views from the other sides see the ground there; a tall building's facade is seen by
    several views from its side, and the few views that see the ground tens of metres below
    such a point outweigh them. Seeing past by a few metres is weaker evidence (trees of another
    season, roof edges that other views erode by a cell) and needs a majority. The views that
    ``trusted_views`` marks (None: none) count as seeing far past from ``trusted_far_m`` on
    (when > 0, and below ``far_m`` or without it): views whose pixels are finer than the cells
    and whose date is in leaf make neither of those mistakes. The views that ``bare_views``
    marks (None: none) count as seeing far past from ``bare_far_m`` on (when > 0) the points
    that ``green`` does not mark: per view k, None (every point marked) or a bool per point of
    ``points[k]`` (required with ``bare_far_m``), the points that k's image shows green. Only
    crowns are seen through, and only on leafless dates.

    The views that ``voter_views`` marks (None: none) see past a point, or far past it, only
    from their pixels whose confidence (``confidences[j]``; None: no pixel of j) is at least
    ``voter_min_confidence`` (when > 0): a height of two near-equal cost minima (a roof in
    another building's shadow of that date) is no evidence of empty space above it. Their
    heights still agree.

    With ``slack_px`` > 0, a pixel of view k whose confidence (``confidences[k]``, (H_k, W_k),
    None: no pixel of k counts as confident) is at least ``slack_min_confidence`` is seen past by
    j only where j's heights at the pixel and at its neighbours within ``slack_px`` pixels (a
    square) all lie more than ``tolerance_m`` below it: the views' occlusion edges are a pixel
    off each other (VISIBILITY_SLACK_PX). The far rule reads the nearest pixel. Arguments and
    returns otherwise as :func:`cross_check_heights`.
    """
    if not (math.isfinite(far_m) and far_m >= 0.0):
        raise OptionsError(f"far_m = {far_m!r}: must be >= 0 metres (0: no such rule)")
    if not (isinstance(slack_px, (int, np.integer)) and 0 <= slack_px <= MAX_VISIBILITY_SLACK_PX):
        raise OptionsError(f"slack_px = {slack_px!r}: must be an integer in "
                           f"0..{MAX_VISIBILITY_SLACK_PX}")
    if not (math.isfinite(slack_min_confidence) and 0.0 <= slack_min_confidence <= 1.0):
        raise OptionsError(f"slack_min_confidence = {slack_min_confidence!r}: must be a "
                           "confidence in [0, 1]")
    if not (math.isfinite(voter_min_confidence) and 0.0 <= voter_min_confidence <= 1.0):
        raise OptionsError(f"voter_min_confidence = {voter_min_confidence!r}: must be a "
                           "confidence in [0, 1]")
    if confidences is not None and len(confidences) != len(heights):
        raise ValueError(f"visibility_check_heights: {len(heights)} height maps, "
                         f"{len(confidences)} confidence maps")
    if voter_views is not None and len(voter_views) != len(heights):
        raise ValueError(f"visibility_check_heights: {len(heights)} height maps, "
                         f"{len(voter_views)} voter_views flags")
    for depth_name, depth, flags_name, flags in (
            ("trusted_far_m", trusted_far_m, "trusted_views", trusted_views),
            ("bare_far_m", bare_far_m, "bare_views", bare_views)):
        if not (math.isfinite(depth) and depth >= 0.0):
            raise OptionsError(f"{depth_name} = {depth!r}: must be >= 0 metres (0: no such "
                               "rule)")
        if flags is not None and len(flags) != len(heights):
            raise ValueError(f"visibility_check_heights: {len(heights)} height maps, "
                             f"{len(flags)} {flags_name} flags")
    use_bare = bare_far_m > 0.0 and bare_views is not None and any(bare_views)
    if use_bare and (points is None or green is None or len(green) != len(heights)):
        raise ValueError("visibility_check_heights: bare_far_m needs the points and a green "
                         "flag set (or None) per height map")
    # Per view, the depth past a point (m) from which it sees far past it, and past the other
    # views' points that are not green; None: never.
    far_from: list[float | None] = []
    far_bare: list[float | None] = []
    for k in range(len(heights)):
        depth = far_m if far_m > 0.0 else math.inf
        if trusted_far_m > 0.0 and trusted_views is not None and trusted_views[k]:
            depth = min(depth, trusted_far_m)
        bare = min(depth, bare_far_m) if use_bare and bare_views[k] else depth
        far_from.append(max(tolerance_m, depth) if math.isfinite(depth) else None)
        far_bare.append(max(tolerance_m, bare) if math.isfinite(bare) else None)
    if far_bare == far_from:
        use_bare = False
    not_green = None
    if use_bare:
        not_green = [None if g is None else ~np.asarray(g, dtype=bool) for g in green]
        for k, (g, pt) in enumerate(zip(not_green, points)):
            if g is not None and g.shape != np.shape(pt[2]):
                raise ValueError(f"visibility_check_heights: view {k}'s green flags are "
                                 f"{g.shape}, its points {np.shape(pt[2])}")
    slack = None
    if slack_px > 0 and confidences is not None:
        slack = [None if c is None else np.asarray(c, np.float64) >= slack_min_confidence
                 for c in confidences]
    # Per view, the pixels from which it may see past (None: all of them).
    voters = None
    if voter_min_confidence > 0.0 and voter_views is not None and any(voter_views):
        voters = []
        for j, (flag, h) in enumerate(zip(voter_views, heights)):
            c = None if confidences is None else confidences[j]
            if not flag or c is None:  # all its pixels, or none of them without confidences
                voters.append(None if not flag else np.zeros(np.size(h), bool))
                continue
            if np.shape(c) != np.shape(h):
                raise ValueError(f"visibility_check_heights: view {j}'s confidence map is "
                                 f"{np.shape(c)}, its height map {np.shape(h)}")
            voters.append((np.asarray(c, np.float64) >= voter_min_confidence).ravel())
    # A view that never sees far past adds nothing to ``far``: 2 far <= agree always holds.
    return _heights_seen_by_others(
        heights, projections, tolerance_m, points, "visibility_check_heights", voters=voters,
        far_from=far_from, slack_px=slack_px, slack=slack,
        far_bare=far_bare if use_bare else None, bare_points=not_green,
        reduce=lambda known, agree, past, far: known & (past <= agree) & (2 * far <= agree))


def _max_within(values: np.ndarray, radius_px: int) -> np.ndarray:
    """The highest of ``values`` (float64) within ``radius_px`` pixels (a square) of each pixel,
    those outside the array ignored: OpenCV's dilation, as dense.coarse's plane windows."""
    import cv2  # noqa: PLC0415

    kernel = np.ones((2 * radius_px + 1, 2 * radius_px + 1), np.uint8)
    return cv2.dilate(np.asarray(values, np.float64), kernel, borderType=cv2.BORDER_REPLICATE)


def _min_within(values: np.ndarray, radius_px: int) -> np.ndarray:
    """The lowest of ``values`` within ``radius_px`` pixels of each pixel: ``_max_within``'s
    erosion."""
    import cv2  # noqa: PLC0415

    kernel = np.ones((2 * radius_px + 1, 2 * radius_px + 1), np.uint8)
    return cv2.erode(np.asarray(values, np.float64), kernel, borderType=cv2.BORDER_REPLICATE)


def _highest_within(height: np.ndarray, radius_px: int) -> np.ndarray:
    """(H, W): the highest known value of ``height`` within ``radius_px`` pixels (a square) of
    each pixel, NaN where none is known."""
    known = np.isfinite(height)
    out = _max_within(np.where(known, height, -np.inf), radius_px)
    out[np.isneginf(out)] = np.nan
    return out


# Points per block of _heights_seen_by_others' comparisons, whose temporaries then stay in the
# CPU's cache: 1700 px seed 22's eight maps (captured), 2.8-3.5 s in one block, 2.2-2.4 s so.
SEEN_BLOCK = 1 << 16


def _heights_seen_by_others(heights, projections, tolerance_m: float, points, caller: str,
                            far_from: Sequence[float | None] | None = None, slack_px: int = 0,
                            slack=None, *,
                            reduce: Callable[..., np.ndarray],
                            voters: Sequence[np.ndarray | None] | None = None,
                            far_bare: Sequence[float | None] | None = None,
                            bare_points: Sequence[np.ndarray | None] | None = None
                            ) -> list[np.ndarray]:
    """Per view k, ``reduce(known, agree, past, far)`` of its (H_k, W_k) maps: its known pixels,
    and at each how many other views' heights at the pixel's 3-D point lie within ``tolerance_m``
    of its height (agree), more than that below it (past), or more than ``far_from[j]`` below it
    (far; a view j whose ``far_from`` is None, or all without it, never counts); zeros where
    unknown, and everywhere with a single view. With ``far_bare`` (per view j, as
    ``far_from``), the points that ``bare_points[k]`` marks (a bool per point of
    ``points[k]``; None: none) count far from ``far_bare[j]`` instead. ``slack``
    (per view, an (H_k, W_k) bool map or None) marks the pixels whose "past" reads the highest of
    the other view's heights within ``slack_px`` pixels instead of the nearest one. The views run
    in up to FUSION_THREADS_MAX threads (each view's maps depend on the others' heights only: the
    sequential loop's results). ``voters`` (per view j, a flat bool per pixel or None: all)
    marks the pixels of j that may count as past or far. See :func:`cross_check_heights` for
    the other arguments."""
    maps = [np.ascontiguousarray(h, dtype=np.float64) for h in heights]
    if len(maps) != len(projections):
        raise ValueError(f"{caller}: {len(maps)} height maps, {len(projections)} projections")
    if not (math.isfinite(tolerance_m) and tolerance_m > 0.0):
        raise OptionsError(f"tolerance_m = {tolerance_m!r}: must be > 0 metres")
    if points is not None and len(points) != len(maps):
        raise ValueError(f"{caller}: {len(maps)} height maps, {len(points)} point sets")
    use_slack = slack is not None and slack_px > 0 and any(m is not None for m in slack)
    if use_slack:
        for k, (h, s) in enumerate(zip(maps, slack)):
            if s is not None and s.shape != h.shape:
                raise ValueError(f"{caller}: view {k}'s confidence map is {s.shape}, its "
                                 f"height map {h.shape}")
    highest = [_highest_within(h, slack_px) for h in maps] if use_slack else None

    def one(k: int) -> np.ndarray:
        h, P = maps[k], projections[k]
        known = np.isfinite(h)
        agree_map = np.zeros(h.shape, dtype=np.int32)
        past_map = np.zeros(h.shape, dtype=np.int32)
        far_map = np.zeros(h.shape, dtype=np.int32)
        if len(maps) < 2:  # nothing to check against
            return reduce(known, agree_map, past_map, far_map)
        if points is None:
            rows, cols = np.nonzero(known)
            u = h[rows, cols]
            e, n = solve_ground_en(P, col=cols.astype(np.float64), row=rows.astype(np.float64),
                                   u=u)
        else:
            e, n, u, pixel = points[k]
            rows, cols = np.divmod(pixel, h.shape[1])
        slack_k = slack[k][rows, cols] if use_slack and slack[k] is not None else None
        bare_k = None if far_bare is None or bare_points is None else bare_points[k]
        agree = np.zeros(u.size, dtype=np.int64)
        past = np.zeros(u.size, dtype=np.int64)
        far = np.zeros(u.size, dtype=np.int64)
        for j, (hj, Pj) in enumerate(zip(maps, projections)):
            if j == k:
                continue
            flat_j = hj.ravel()
            high_j = highest[j].ravel() if slack_k is not None else None
            far_j = None if far_from is None else far_from[j]
            # The depth of each point (bare_k) where j's differs for the bare points.
            bare_j = None if bare_k is None or far_bare[j] == far_j else far_bare[j]
            for start in range(0, u.size, SEEN_BLOCK):
                b = slice(start, start + SEEN_BLOCK)
                ub = u[b]
                col, row = project_points(Pj, e=e[b], n=n[b], u=ub)
                with np.errstate(invalid="ignore"):
                    ic = np.floor(col + 0.5)
                    ir = np.floor(row + 0.5)
                    inside = (ic >= 0) & (ic < hj.shape[1]) & (ir >= 0) & (ir < hj.shape[0])
                    # Every point reads a height: a point outside j's map reads its first
                    # pixel, then NaN, which no comparison below counts (no gather and scatter
                    # of the points inside).
                    at = np.where(inside, ir * hj.shape[1] + ic, 0.0).astype(np.int64)
                other = np.where(inside, flat_j[at], np.nan)
                below = other
                if slack_k is not None:
                    below = np.where(slack_k[b] & inside, high_j[at], other)
                # Whether j's pixel may see past (its points outside read pixel 0: NaN there).
                vote = True if voters is None or voters[j] is None else voters[j][at]
                with np.errstate(invalid="ignore"):
                    agree[b] += np.abs(other - ub) <= tolerance_m
                    past[b] += (below < ub - tolerance_m) & vote
                    if bare_j is not None:
                        depth = np.where(bare_k[b], bare_j,
                                         math.inf if far_j is None else far_j)
                        far[b] += (other < ub - depth) & vote
                    elif far_j is not None:
                        far[b] += (other < ub - far_j) & vote
        agree_map[rows, cols] = agree
        past_map[rows, cols] = past
        far_map[rows, cols] = far
        return reduce(known, agree_map, past_map, far_map)

    return map_in_threads(one, range(len(maps)), max_threads=FUSION_THREADS_MAX, name="fusion")


# -- rasterisation -----------------------------------------------------------------------------
def rasterise_max(points_x, points_y, values, grid: DSMGrid) -> np.ndarray:
    """Highest value per grid cell: (grid.height, grid.width) float32, NaN where no point fell.

    ``points_x``/``points_y``: map coordinates (metres, the grid's CRS); a point belongs to the
    cell whose half-open square ``[x0, x0 + res) x (y1 - res, y1]`` holds it (so a point on a cell
    boundary goes to the cell east / south of it). Points outside the grid and non-finite values
    are ignored. The maximum is taken in float64, then rounded to float32.
    """
    x = np.asarray(points_x, np.float64).ravel()
    y = np.asarray(points_y, np.float64).ravel()
    if x.size != y.size:
        raise ValueError(f"rasterise_max: lengths differ ({x.size}, {y.size})")
    return rasterise_max_cells(flat_cells(x, y, grid), values, grid)


def flat_cells(points_x, points_y, grid: DSMGrid) -> np.ndarray:
    """Row-major index of the grid cell of each point (``rasterise_max``'s rule), -1 outside."""
    i, j = grid.cell_of(x=np.ravel(points_x), y=np.ravel(points_y))
    inside = (i >= 0) & (i < grid.height) & (j >= 0) & (j < grid.width)
    return np.where(inside, i * grid.width + j, -1).astype(np.int64)


def _points_in_grid(cells: np.ndarray, values, caller: str) -> tuple[np.ndarray, np.ndarray]:
    """The cells (``flat_cells``) and values of the points with a finite value inside the grid."""
    c = np.asarray(cells, np.int64).ravel()
    z = np.asarray(values, np.float64).ravel()
    if c.size != z.size:
        raise ValueError(f"{caller}: lengths differ ({c.size} cells, {z.size} values)")
    ok = np.isfinite(z) & (c >= 0)
    return c[ok], z[ok]


def rasterise_max_cells(cells: np.ndarray, values, grid: DSMGrid) -> np.ndarray:
    """``rasterise_max`` of points whose cells (``flat_cells``) are already known: several value
    sets over the same points (heights, confidences) share them."""
    c, z = _points_in_grid(cells, values, "rasterise_max")
    out = np.full(grid.width * grid.height, -np.inf)
    np.maximum.at(out, c, z)
    out[np.isneginf(out)] = np.nan
    return out.reshape(grid.shape).astype(np.float32)


def rasterise_quantile_cells(cells: np.ndarray, values, grid: DSMGrid,
                             quantile: float = VIEW_RASTER_QUANTILE) -> np.ndarray:
    """Per cell, the ``floor(quantile (n - 1) + 0.5)``-th of the ``n`` values of its points in
    ascending order (0: the lowest, 1: the highest), NaN where none; arguments as
    ``rasterise_max_cells``."""
    if not 0.0 <= quantile <= 1.0:
        raise ValueError(f"rasterise_quantile_cells: quantile = {quantile!r}, must be in [0, 1]")
    c, z = _points_in_grid(cells, values, "rasterise_quantile_cells")
    out = np.full(grid.width * grid.height, np.nan, np.float32)
    if c.size:
        # One sort of 64-bit keys, each point's cell above its value's float32 order (the
        # raster is float32, and rounding keeps the order: the same cell values as sorting the
        # float64 values; a fifth of the time of a lexsort of the pairs). A height map's pixels
        # come in runs of cells (its rows cross the grid), which the stable sort (timsort)
        # merges: the same keys in the same order, in about a quarter of the default's time.
        key = (c.astype(np.uint64) << np.uint64(32)) | _float32_order(z)
        key.sort(kind="stable")
        c = (key >> np.uint64(32)).astype(np.int64)
        starts = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
        counts = np.diff(np.r_[starts, c.size])
        pick = key[starts + np.floor(quantile * (counts - 1) + 0.5).astype(np.int64)]
        out[c[starts]] = _float32_of_order(pick & np.uint64(0xFFFFFFFF))
    return out.reshape(grid.shape)


def _float32_order(values: np.ndarray) -> np.ndarray:
    """uint64 keys in [0, 2^32) whose order is that of ``values`` rounded to float32 (finite):
    the float32 bits with the sign bit set for positive numbers and every bit flipped for
    negative ones."""
    bits = np.asarray(values, np.float32).view(np.uint32)
    negative = bits >= np.uint32(0x80000000)
    return np.where(negative, ~bits, bits | np.uint32(0x80000000)).astype(np.uint64)


def _float32_of_order(keys: np.ndarray) -> np.ndarray:
    """The float32 values of ``_float32_order``'s keys."""
    k = keys.astype(np.uint32)
    positive = k >= np.uint32(0x80000000)
    return np.where(positive, k & np.uint32(0x7FFFFFFF), ~k).view(np.float32)


def _check_gsd(caller: str, gsd_m: float) -> None:
    """A map's pixel size must be a positive, finite number of metres."""
    if not (math.isfinite(gsd_m) and gsd_m > 0.0):
        raise ValueError(f"{caller}: gsd_m = {gsd_m!r} must be > 0 metres")


def raised_pixels(height: np.ndarray, gsd_m: float, *,
                  min_height_m: float = SMALL_OBJECT_MIN_HEIGHT_M,
                  ground_window_m: float = SMALL_OBJECT_GROUND_WINDOW_M) -> np.ndarray:
    """(H, W) bool: the known pixels of a height map (NaN: unknown) more than ``min_height_m``
    above the ground under them: the lowest height within ``ground_window_m`` (a square, from a
    ``SMALL_OBJECT_SMOOTH_PX`` median of the map, which one pixel's blunder does not lower;
    pixels of ``gsd_m`` metres). Unknown pixels are neither ground nor raised."""
    import cv2  # noqa: PLC0415

    _check_gsd("raised_pixels", gsd_m)
    h = np.asarray(height, dtype=np.float64)
    known = np.isfinite(h)
    if not known.any():
        return known
    # The median in float32 (OpenCV's, edges replicated): metres to 1e-5 against a 2 m rule.
    smooth = cv2.medianBlur(np.ascontiguousarray(np.where(known, h, np.inf), dtype=np.float32),
                            SMALL_OBJECT_SMOOTH_PX).astype(np.float64)
    radius = max(1, int(round(0.5 * ground_window_m / gsd_m)))
    ground = _min_within(smooth, radius)
    with np.errstate(invalid="ignore"):
        return known & (h > ground + min_height_m)


def small_regions(raised: np.ndarray, gsd_m: float, max_area_m2: float) -> np.ndarray:
    """(H, W) bool: the pixels of ``raised`` (``raised_pixels``) whose 8-connected regions cover
    at most ``max_area_m2`` (pixels of ``gsd_m`` metres); none where ``max_area_m2`` <= 0."""
    import cv2  # noqa: PLC0415

    raised = np.asarray(raised, dtype=bool)
    if max_area_m2 <= 0.0 or not raised.any():
        return np.zeros(raised.shape, bool)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(raised.astype(np.uint8),
                                                           connectivity=8)
    small = stats[:, cv2.CC_STAT_AREA] * gsd_m * gsd_m <= max_area_m2
    small[0] = False  # the background
    return small[labels]


def small_raised_pixels(height: np.ndarray, gsd_m: float, max_area_m2: float, *,
                        min_height_m: float = SMALL_OBJECT_MIN_HEIGHT_M,
                        ground_window_m: float = SMALL_OBJECT_GROUND_WINDOW_M) -> np.ndarray:
    """(H, W) bool: the pixels of a height map (NaN: unknown) that belong to small raised
    objects (tree crowns, vehicles, sheds) rather than buildings; a box on a roof is
    part of its building's region.

    The pixels ``raised_pixels`` gives (more than ``min_height_m`` above the ground within
    ``ground_window_m``) in 8-connected regions of at most ``max_area_m2`` (``small_regions``;
    pixels of ``gsd_m`` metres).
    """
    _check_gsd("small_raised_pixels", gsd_m)
    if max_area_m2 <= 0.0:
        return np.zeros(np.shape(height), bool)
    raised = raised_pixels(height, gsd_m, min_height_m=min_height_m,
                           ground_window_m=ground_window_m)
    return small_regions(raised, gsd_m, max_area_m2)


def green_raised_pixels(height: np.ndarray, vegetation: np.ndarray, gsd_m: float, *,
                        raised: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool: the pixels of a height map (NaN: unknown) raised as ``raised_pixels``
    says (SMALL_OBJECT_MIN_HEIGHT_M above the ground around them; ``raised``: that mask of this
    map, already computed), in regions of any area, whose
    ``vegetation`` index (``satsweep.io.images.vegetation_index`` in the same pixels) is at
    least VEGETATION_INDEX_MIN: crowns, also where they join a building's or each other's
    region (``[dsm] green_top``). Grass on the ground is not raised; strips of such pixels
    narrower than GREEN_TOP_MIN_WIDTH_M (grass beside a wall matched at its roof's height) are
    left out by a morphological opening."""
    _check_gsd("green_raised_pixels", gsd_m)  # the opening's width too, with raised given
    h = np.asarray(height)
    veg = np.asarray(vegetation)
    for name, given in (("vegetation", veg), ("raised", raised)):
        if given is not None and np.shape(given) != h.shape:
            raise ValueError(f"green_raised_pixels: {name} {np.shape(given)} and height "
                             f"{h.shape} differ in shape")
    import cv2  # noqa: PLC0415

    with np.errstate(invalid="ignore"):
        green = veg >= VEGETATION_INDEX_MIN
    if not green.any():
        return green
    green &= raised_pixels(h, gsd_m) if raised is None else np.asarray(raised, dtype=bool)
    # Opened by a square GREEN_TOP_MIN_WIDTH_M wide (odd pixels, 3 at least).
    side = 2 * int(0.5 * GREEN_TOP_MIN_WIDTH_M / gsd_m) + 1
    kernel = np.ones((max(3, side),) * 2, np.uint8)
    return cv2.morphologyEx(green.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)


def rasterise_dense_view_cells(cells: np.ndarray, values, grid: DSMGrid,
                               top: np.ndarray | None = None) -> np.ndarray:
    """A dense view's raster (``view_raster`` "quantile"): per cell the VIEW_RASTER_QUANTILE
    of its points, or the highest of its points that ``top`` marks (per
    point: those of small raised objects, ``small_raised_pixels``) where that is higher; NaN
    where no point fell. Arguments as ``rasterise_max_cells``."""
    out = rasterise_quantile_cells(cells, values, grid)
    if top is None:
        return out
    top = np.asarray(top, bool).ravel()
    c = np.asarray(cells, np.int64).ravel()
    if top.size != c.size:
        raise ValueError(f"rasterise_dense_view_cells: lengths differ ({c.size} cells, "
                         f"{top.size} top flags)")
    highest = rasterise_max_cells(c[top], np.asarray(values, np.float64).ravel()[top], grid)
    return np.fmax(out, highest)


def dropped_edge_pixels(height: np.ndarray, confidence: np.ndarray, min_confidence: float,
                        keep: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool: the pixels of a dense view's height map that its raster leaves out
    (``DSMOptions.edge_min_confidence``): on the high side of a step (``step_edge_pixels``) and
    matched with a confidence under ``min_confidence``, except those ``keep`` marks (the small
    raised objects' pixels with ``small_object_top``, and green raised ones with ``green_top``:
    a crown's rim is a step too)."""
    drop = step_edge_pixels(height) & (np.asarray(confidence) < min_confidence)
    if keep is not None:
        drop &= ~np.asarray(keep, bool)
    return drop


def step_edge_pixels(height: np.ndarray, step_m: float = EDGE_STEP_M) -> np.ndarray:
    """(H, W) bool: the known pixels of a height map (NaN unknown) with a known 8-neighbour
    more than ``step_m`` lower: the high side of its steps (a roof's rim, or a facade or ground
    pixel matched at the roof's height beside it)."""
    h = np.asarray(height, dtype=np.float64)
    known = np.isfinite(h)
    lowest = _min_within(np.where(known, h, np.inf), 1)
    with np.errstate(invalid="ignore"):
        return known & (h - lowest > step_m)


def fine_pixels(gsd_m: float, resolution_m: float) -> bool:
    """Whether a view of ``gsd_m`` metres per pixel has pixels finer than DSM cells of
    ``resolution_m``: DENSE_CENTRES_PER_CELL pixel footprints or more per cell (0.3 m pixels on
    0.5 m cells: 2.8), as ``DSMOptions.view_raster_for`` counts them on a view's points."""
    if not (math.isfinite(gsd_m) and gsd_m > 0.0 and math.isfinite(resolution_m)
            and resolution_m > 0.0):
        raise ValueError(f"fine_pixels: gsd_m = {gsd_m!r}, resolution_m = {resolution_m!r}: "
                         "must be > 0 metres")
    return (resolution_m / gsd_m) ** 2 >= DENSE_CENTRES_PER_CELL


def centres_per_cell(cells: np.ndarray) -> float:
    """Mean number of points per cell over the cells that hold one (``flat_cells``; -1
    outside), 0 when none does."""
    c = np.asarray(cells, np.int64).ravel()
    c = c[c >= 0]
    # The cells held, counted by a bincount (np.unique took 40 times as long on 2 M points).
    return float(c.size / np.count_nonzero(np.bincount(c))) if c.size else 0.0


def rasterise_points(points: Points, grid: DSMGrid) -> np.ndarray:
    """DSM of one point set on ``grid``: ``points_to_utm`` then ``rasterise_max`` of the heights."""
    x, y, z = points_to_utm(points, grid.epsg)
    return rasterise_max(x, y, z, grid)


# -- fusion ------------------------------------------------------------------------------------
def _nanmedian_first_axis(stack: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median over axis 0 ignoring NaN (NaN where all are NaN) and the count of finite values.

    Sorting puts NaN last, so the finite values of each cell are the first ``k`` of its column and
    the median is the mean of entries ``(k - 1) // 2`` and ``k // 2``.
    """
    s = np.sort(stack, axis=0)
    k = np.count_nonzero(np.isfinite(stack), axis=0)
    lo = np.take_along_axis(s, np.maximum((k - 1) // 2, 0)[None], axis=0)[0]
    hi = np.take_along_axis(s, np.maximum(k // 2 - (k == 0), 0)[None], axis=0)[0]
    med = 0.5 * (lo.astype(np.float64) + hi.astype(np.float64))
    med[k == 0] = np.nan
    return med, k


def fuse_dsms(
    dsms: Sequence[np.ndarray], *, outlier_m: float = 2.0, min_views: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Robust per-cell fusion of per-reference-view DSMs on the same grid.

    For each cell: m0 = median of the finite values; values with ``|v - m0| > outlier_m`` are
    discarded; the result is the median of the rest (NaN when fewer than ``min_views`` remain).
    With two views that disagree by more than ``2 * outlier_m`` both are discarded: neither can be
    trusted. Returns (fused float32, count of values kept per cell as int32).
    """
    if not dsms:
        raise ValueError("fuse_dsms needs at least one DSM")
    if not (math.isfinite(outlier_m) and outlier_m > 0.0):
        raise OptionsError(f"outlier_m = {outlier_m!r}: must be > 0 metres")
    shape = np.asarray(dsms[0]).shape
    if len(shape) != 2:
        raise ValueError(f"fuse_dsms needs 2D rasters, got shape {shape}")
    for k, d in enumerate(dsms):
        if np.asarray(d).shape != shape:
            raise ValueError(f"fuse_dsms: DSM {k} has shape {np.asarray(d).shape}, DSM 0 has {shape}")
    fused = np.full(shape, np.nan, dtype=np.float32)
    count = np.zeros(shape, dtype=np.int32)
    # Row blocks bound the temporary memory to about FUSE_BLOCK_VALUES float64 values per copy.
    rows_per_block = max(1, FUSE_BLOCK_VALUES // max(1, len(dsms) * int(np.prod(shape[1:], dtype=np.int64))))
    for r0 in range(0, shape[0], rows_per_block):
        block = slice(r0, r0 + rows_per_block)
        stack = np.stack([np.asarray(d)[block].astype(np.float64) for d in dsms])
        stack[~np.isfinite(stack)] = np.nan
        m0, _ = _nanmedian_first_axis(stack)
        with np.errstate(invalid="ignore"):
            far = np.abs(stack - m0[None]) > outlier_m
        stack[far] = np.nan
        f, k = _nanmedian_first_axis(stack)
        low = k < min_views
        f[low] = np.nan
        k[low] = 0
        fused[block] = f
        count[block] = k
    return fused, count


def consensus_dsms(dsms: Sequence[np.ndarray], *, tolerance_m: float, min_views: int,
                   view_sets: Sequence[Sequence[int]] | None = None,
                   min_distinct_views: int = 0,
                   min_share: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-cell consensus of per-reference-view DSMs on the same grid.

    For each cell the views' heights are sorted and the widest group of them that fits in a
    window of ``2 * tolerance_m`` is found (on a tie, the lowest such group: edge fattening smears
    roof heights onto the ground beside buildings, never the other way); the cell's height is
    the median of that group, its count the group's size. A cell where fewer than
    ``min_views`` views agree is left empty: one view's blunder (a shadow matched tens of
    metres off, a car that moved) is never a height on its own. With
    ``view_sets`` (per DSM, the views its height map was matched from: its reference and
    sources, indices < 64), the group must also draw on at least ``min_distinct_views`` views
    in all: two height maps of one pair seen both ways (A against B, B against A) share their
    errors and are one measurement, not two. With ``min_share`` the group must also hold at
    least that fraction of the heights the cell has (0.5: half of them, rounded up): where the
    views that see a cell scatter into small groups, none of them is its height (the cell is
    left empty, for the hole filling). Returns (fused float32, agreeing views per cell as
    uint8, (V, H, W) bool: which view is in the group).
    """
    if not dsms:
        raise ValueError("consensus_dsms needs at least one DSM")
    if not (math.isfinite(tolerance_m) and tolerance_m > 0.0):
        raise OptionsError(f"tolerance_m = {tolerance_m!r}: must be > 0 metres")
    if not (math.isfinite(min_share) and 0.0 <= min_share <= 1.0):
        raise OptionsError(f"min_share = {min_share!r}: must be a fraction in [0, 1]")
    shape = np.asarray(dsms[0]).shape
    n = len(dsms)
    fused = np.full(shape, np.nan, dtype=np.float32)
    count = np.zeros(shape, dtype=np.uint8)
    members = np.zeros((n,) + tuple(shape), dtype=bool)
    width = 2.0 * float(tolerance_m)
    rows_per_block = max(1, FUSE_BLOCK_VALUES // max(1, n * n * int(shape[1])))
    for r0 in range(0, shape[0], rows_per_block):
        block = slice(r0, r0 + rows_per_block)
        stack = np.stack([np.asarray(d)[block].astype(np.float64) for d in dsms])
        stack[~np.isfinite(stack)] = np.nan
        s = np.sort(stack, axis=0)  # NaN last
        with np.errstate(invalid="ignore"):
            # size[i]: the values from s[i] up to s[i] + width (sorted: a contiguous run).
            size = ((s[None, :] >= s[:, None]) & (s[None, :] <= s[:, None] + width)).sum(axis=1)
        size[~np.isfinite(s)] = 0
        # The widest window; among equally wide ones the lowest (the first start index):
        # edge fattening puts roof heights beside a building, so on a tie the ground wins
        # (multi-date seeds 0 and 1, 10 views: DFC MAE 2.60 m against 3.06 m for the highest).
        best = np.argmax(size, axis=0)
        c = np.take_along_axis(size, best[None], axis=0)[0]
        lo = np.take_along_axis(s, best[None], axis=0)[0]
        mid_lo = np.take_along_axis(s, np.minimum(best + (c - 1) // 2, n - 1)[None], axis=0)[0]
        mid_hi = np.take_along_axis(s, np.minimum(best + c // 2, n - 1)[None], axis=0)[0]
        ok = (c >= max(int(min_views), 1)) & (c >= min_share * np.isfinite(s).sum(axis=0))
        with np.errstate(invalid="ignore"):
            inside = (stack >= lo[None]) & (stack <= lo[None] + width) & ok[None]
        if view_sets is not None and min_distinct_views > 0:
            ok &= _distinct_views(inside, view_sets) >= min_distinct_views
            inside &= ok[None]
        f = np.where(ok, 0.5 * (mid_lo + mid_hi), np.nan)
        fused[block] = f
        count[block] = np.where(ok, c, 0).astype(np.uint8)
        members[:, block] = inside
    return fused, count, members


def _raised_cells(f: np.ndarray, finite: np.ndarray, resolution_m: float) -> np.ndarray:
    """(H, W) bool: the cells of ``f`` (``finite``: those with a height) more than
    THIN_RAISED_RISE_M above the lowest within THIN_RAISED_GROUND_M."""
    radius = int(round(THIN_RAISED_GROUND_M / resolution_m))
    ground = _min_within(np.where(finite, f, np.inf), radius)
    with np.errstate(invalid="ignore"):
        return finite & (f - ground > THIN_RAISED_RISE_M)


def thin_raised_minority(fused: np.ndarray, count: np.ndarray, n_views: int, *,
                         max_share: float, resolution_m: float) -> np.ndarray:
    """(H, W) bool: the consensus cells (``fused``, NaN: empty; ``count``: the views agreeing
    there, of ``n_views`` reference views) to leave to the hole filling: more than
    THIN_RAISED_RISE_M above the lowest cell within THIN_RAISED_GROUND_M, agreed on by at most
    ``max_share`` of the views (rounded down; none below one view), and outside every square of
    THIN_RAISED_SIDE_M that such cells and empty ones fill (see THIN_RAISED_RISE_M)."""
    from scipy.ndimage import binary_opening

    if not (math.isfinite(max_share) and 0.0 <= max_share <= 1.0):
        raise OptionsError(f"max_share = {max_share!r}: must be a fraction in [0, 1]")
    f = np.asarray(fused, dtype=np.float64)
    finite = np.isfinite(f)
    limit = math.floor(max_share * n_views + 1e-9)
    if limit < 1 or not finite.any():
        return np.zeros(f.shape, dtype=bool)
    few = _raised_cells(f, finite, resolution_m) & (np.asarray(count) <= limit)
    side = max(1, int(round(THIN_RAISED_SIDE_M / resolution_m)))
    wide = binary_opening(few | ~finite, structure=np.ones((side, side), dtype=bool))
    return few & ~wide


def _max_along(values: np.ndarray, dy: int, dx: int, reach: int) -> np.ndarray:
    """(H, W): per cell, the largest of ``values`` (integers, -1: none) at the cells 1..``reach``
    steps of (``dy``, ``dx``) away; -1 where all of them lie outside the grid."""
    h, w = values.shape
    out = np.full(values.shape, -1, dtype=np.int32)
    for k in range(1, reach + 1):
        oy, ox = dy * k, dx * k
        if abs(oy) >= h or abs(ox) >= w:
            break
        dst = out[max(0, -oy):h - max(0, oy), max(0, -ox):w - max(0, ox)]
        np.maximum(dst, values[max(0, oy):h - max(0, -oy), max(0, ox):w - max(0, -ox)], out=dst)
    return out


def raised_count_valleys(fused: np.ndarray, count: np.ndarray, n_views: int, *,
                         min_share: float, resolution_m: float) -> np.ndarray:
    """(H, W) bool: the consensus cells (``fused``, NaN: empty; ``count``: the views agreeing
    there, of ``n_views`` reference views) more than THIN_RAISED_RISE_M above the lowest cell
    within THIN_RAISED_GROUND_M whose count lies at least ``min_share`` of the views (rounded
    up; none below one view) under the highest count of such raised cells within
    VALLEY_REACH_M on both sides along a row, a column or a diagonal (see VALLEY_REACH_M)."""
    if not (math.isfinite(min_share) and 0.0 <= min_share <= 1.0):
        raise OptionsError(f"min_share = {min_share!r}: must be a fraction in [0, 1]")
    f = np.asarray(fused, dtype=np.float64)
    finite = np.isfinite(f)
    if min_share == 0.0 or not finite.any():
        return np.zeros(f.shape, dtype=bool)
    drop = max(1, math.ceil(min_share * n_views - 1e-9))
    raised = _raised_cells(f, finite, resolution_m)
    c = np.asarray(count).astype(np.int32)
    flanks = np.where(raised, c, -1).astype(np.int32)
    reach = max(1, int(round(VALLEY_REACH_M / resolution_m)))
    valley = np.zeros(f.shape, dtype=bool)
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        lower_side = np.minimum(_max_along(flanks, dy, dx, reach),
                                _max_along(flanks, -dy, -dx, reach))
        valley |= lower_side >= c + drop
    return raised & valley


def vertical_offsets(dsms: Sequence[np.ndarray], reference: np.ndarray) -> np.ndarray:
    """Per DSM of ``dsms`` (on ``reference``'s grid), its median height offset to ``reference``
    over the cells where ``reference`` is flat (its central differences under COREGISTER_FLAT_M
    per cell) and the two lie within COREGISTER_WINDOW_M of each other; 0 where fewer than
    COREGISTER_MIN_CELLS such cells. Subtract them to co-register the DSMs vertically."""
    ref = np.asarray(reference, np.float64)
    gy, gx = np.gradient(ref)  # NaN next to a cell without height: not flat
    with np.errstate(invalid="ignore"):
        flat = np.hypot(gx, gy) < COREGISTER_FLAT_M
    out = np.zeros(len(dsms))
    for k, d in enumerate(dsms):
        e = np.asarray(d, np.float64) - ref
        with np.errstate(invalid="ignore"):
            ok = flat & (np.abs(e) < COREGISTER_WINDOW_M)
        if ok.sum() >= COREGISTER_MIN_CELLS:
            out[k] = float(np.median(e[ok]))
    return out


def _distinct_views(inside: np.ndarray, view_sets: Sequence[Sequence[int]]) -> np.ndarray:
    """Per cell, the number of distinct views in the view sets of the DSMs ``inside`` marks."""
    bits = np.array([sum(1 << int(v) for v in set(vs)) for vs in view_sets], dtype=np.uint64)
    union = np.zeros(inside.shape[1:], dtype=np.uint64)
    for k, b in enumerate(bits):
        union |= np.where(inside[k], b, np.uint64(0))
    count = np.zeros(union.shape, dtype=np.int64)
    while union.any():  # popcount, one bit at a time (a few dozen views at most)
        count += (union & np.uint64(1)).astype(np.int64)
        union >>= np.uint64(1)
    return count


def _highest_agreeing_pair(rasters: Sequence[np.ndarray], passes: Sequence[Hashable | None],
                           tolerance_m: float, shape: tuple[int, ...]) -> np.ndarray:
    """Per cell, the mean of the highest pair of ``rasters`` of two different known ``passes``
    within ``tolerance_m`` of each other (NaN where no such pair)."""
    best = np.full(shape, np.nan)
    heights = [np.asarray(r, dtype=np.float64) for r in rasters]
    for i, j in itertools.combinations(range(len(rasters)), 2):
        if passes[i] is None or passes[j] is None or passes[i] == passes[j]:
            continue
        a, b = heights[i], heights[j]
        with np.errstate(invalid="ignore"):
            pair = np.where(np.abs(a - b) <= tolerance_m, 0.5 * (a + b), np.nan)
        best = np.fmax(best, pair)
    return best


def leaf_on_crown_tops(fused: np.ndarray, rasters: Sequence[np.ndarray],
                       passes: Sequence[Hashable | None], *, tolerance_m: float,
                       resolution_m: float, max_area_m2: float) -> tuple[np.ndarray, np.ndarray]:
    """Crowns' tops from the reference views of dates in leaf (``LEAF_TOP_RISE_M``).

    ``rasters``: those views' rasters (the consensus's grid), ``passes`` each one's acquisition
    pass (``similarity.acquisition_passes``; None: unknown, the view takes no part). A cell's
    candidate is the mean of the highest pair of rasters of different passes within
    ``tolerance_m`` of each other; the cell takes it where it lies more than
    ``LEAF_TOP_RISE_M`` above ``fused`` (a known height) and is part of a small raised object
    (``small_raised_pixels`` of the candidates over the fused cells, regions of at most
    ``max_area_m2``). Returns (a float32 copy of ``fused``, (H, W) bool: the cells raised)."""
    f = np.asarray(fused, dtype=np.float32)
    best = _highest_agreeing_pair(rasters, passes, tolerance_m, f.shape)
    with np.errstate(invalid="ignore"):
        raised = np.isfinite(best) & np.isfinite(f) & (best > f + LEAF_TOP_RISE_M)
    if raised.any():
        top = np.where(np.isfinite(best), best, f)
        raised &= small_raised_pixels(top, resolution_m, max_area_m2)
    return np.where(raised, best, f).astype(np.float32), raised


def crown_hole_tops(fused: np.ndarray, rasters: Sequence[np.ndarray],
                    passes: Sequence[Hashable | None], *, tolerance_m: float,
                    resolution_m: float, max_area_m2: float) -> tuple[np.ndarray, np.ndarray]:
    """Empty cells of the consensus on small raised objects (``[dsm] crown_holes``).

    ``rasters``: every reference view's (the consensus's grid), ``passes`` each one's acquisition
    pass (``similarity.acquisition_passes``; None: unknown, the view takes no part). A cell that
    ``fused`` leaves empty takes the mean of the highest pair of rasters of different passes
    within ``tolerance_m`` of each other where that is part of a small raised object
    (``small_raised_pixels`` of the fused cells with those pairs in its empty ones, regions of
    at most ``max_area_m2``): the hole filling would give it its rim's lowest height, the
    ground's. Returns (a float32 copy of ``fused``, (H, W) bool: the cells filled)."""
    f = np.asarray(fused, dtype=np.float32)
    empty = ~np.isfinite(f)
    best = _highest_agreeing_pair(rasters, passes, tolerance_m, f.shape)
    filled = empty & np.isfinite(best)
    if filled.any():
        filled &= small_raised_pixels(np.where(empty, best, f), resolution_m, max_area_m2)
    return np.where(filled, best, f).astype(np.float32), filled


def green_crown_tops(fused: np.ndarray, rasters: Sequence[np.ndarray],
                     vegetation: Sequence[np.ndarray], *, resolution_m: float,
                     max_area_m2: float) -> tuple[np.ndarray, np.ndarray]:
    """Crowns' tops from the reference views that see leaves there (``[dsm] green_crowns``).

    ``rasters``: the reference views' heights (the consensus's grid), ``vegetation`` each one's
    vegetation index at its highest point per cell (``satsweep.io.images.vegetation_index``,
    NaN: none). A view speaks for a cell where its index there is at least
    VEGETATION_INDEX_MIN and the cell is part of a small raised object of its own raster
    (``small_raised_pixels``, regions of at most ``max_area_m2``: a crown, not a lawn, nor
    grass beside a building matched at its roof's height, which joins the roof's region). A
    cell that at least GREEN_MIN_VIEWS views speak for takes the highest of their heights where
    that lies more than GREEN_TOP_RISE_M above ``fused`` (or ``fused`` is empty) and
    SMALL_OBJECT_MIN_HEIGHT_M above the ground around it (``raised_pixels`` over the fused
    cells with those heights). Returns (a float32 copy of ``fused``, (H, W)
    bool: the cells raised)."""
    if len(rasters) != len(vegetation):
        raise ValueError(f"green_crown_tops: {len(rasters)} rasters but {len(vegetation)} "
                         "vegetation rasters")
    f = np.asarray(fused, dtype=np.float32)
    best = np.full(f.shape, np.nan)
    speaking = np.zeros(f.shape, np.int64)
    for r, v in zip(rasters, vegetation):
        h = np.asarray(r, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            green = (np.asarray(v) >= VEGETATION_INDEX_MIN) & np.isfinite(h)
        if green.any():
            green &= small_raised_pixels(h, resolution_m, max_area_m2)
        speaking += green
        best = np.fmax(best, np.where(green, h, np.nan))
    with np.errstate(invalid="ignore"):
        raised = ((speaking >= GREEN_MIN_VIEWS)
                  & (~np.isfinite(f) | (best > f + GREEN_TOP_RISE_M)))
    if raised.any():
        raised &= raised_pixels(np.where(raised, best, f), resolution_m)
    return np.where(raised, best, f).astype(np.float32), raised


# -- hole filling ------------------------------------------------------------------------------
# "supported_min" hole filling: a rim value counts when at least this share of the hole's rim (and
# at least RIM_SUPPORT_CELLS rim cells) lie within RIM_SUPPORT_M above it; the hole takes the
# lowest such value (the rim's minimum when none does). A hole beside a wall has ground on a
# good part of its rim; one blunder deep below the ground (a shadow matched at the floor of a
# widened altitude range) set a whole hole's value under "min": one view per date seed 9, 1220
# cells filled 10-40 m under the ground from 85 such rim cells (docs/measurements.md).
RIM_SUPPORT_SHARE = 0.1
RIM_SUPPORT_CELLS = 2
RIM_SUPPORT_M = 1.0


def fill_small_holes(
    dsm: np.ndarray, *, max_hole_cells: int,
    method: Literal["min", "supported_min", "median"] = "min",
    border_holes: bool = True,
) -> tuple[np.ndarray, int]:
    """Fill no-data holes of at most ``max_hole_cells`` 4-connected cells.

    A hole is a 4-connected set of NaN cells; with ``border_holes=False`` only those that do not
    touch the raster border (a gap at the border is not known to be closed). Each hole gets one
    value from its rim (the valid cells 4-adjacent to it, inside the raster, counted once per
    side they touch it): the minimum by default, because small holes in satellite DSMs are
    mostly ground occluded by a wall, i.e. the lower side; the lowest value that
    RIM_SUPPORT_SHARE of the rim lie within RIM_SUPPORT_M above (``supported_min``: one blunder
    does not set the hole); or the median. Returns (filled float32 copy, number of cells
    filled), which the caller must report.
    """
    import cv2

    # float32 throughout (a copy): the fill values are the rim's own float32 values (min) or
    # their mean rounded to float32 on assignment (median), as the float32 result needs anyway;
    # a float64 copy would double the memory of a large AOI's grid.
    a = np.array(dsm, dtype=np.float32)
    if a.ndim != 2:
        raise ValueError(f"fill_small_holes needs a 2D array, got shape {a.shape}")
    if not (isinstance(max_hole_cells, int) and max_hole_cells >= 0):
        raise OptionsError(f"max_hole_cells = {max_hole_cells!r}: must be an integer >= 0")
    if method not in ("min", "supported_min", "median"):
        raise OptionsError(f"fill method = {method!r}: must be 'min', 'supported_min' or "
                           "'median'")
    hole = ~np.isfinite(a)
    if max_hole_cells == 0 or not hole.any() or hole.all():
        return a, 0
    n, labels = cv2.connectedComponents(hole.astype(np.uint8), connectivity=4, ltype=cv2.CV_32S)
    n -= 1  # label 0 is the background (the valid cells)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    eligible = (sizes <= max_hole_cells)
    eligible[0] = False
    if not border_holes:
        eligible[border] = False
    if not eligible[1:].any():
        return a, 0
    # Rim pairs (hole label, rim value) from the four neighbour directions.
    pair_labels, pair_values = [], []
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        lab = labels[max(dy, 0):a.shape[0] + min(dy, 0), max(dx, 0):a.shape[1] + min(dx, 0)]
        nb = a[max(-dy, 0):a.shape[0] + min(-dy, 0), max(-dx, 0):a.shape[1] + min(-dx, 0)]
        sel = (lab > 0) & np.isfinite(nb)
        pair_labels.append(lab[sel])
        pair_values.append(nb[sel])
    pl = np.concatenate(pair_labels)
    pv = np.concatenate(pair_values).astype(np.float64)
    keep = eligible[pl]
    pl, pv = pl[keep], pv[keep]
    fill = np.full(n + 1, np.nan)
    if method in ("min", "supported_min"):
        fill_min = np.full(n + 1, np.inf)
        np.minimum.at(fill_min, pl, pv)
        if method == "supported_min" and pv.size:
            supported = _supported_minimum(pl, pv, n + 1)
            fill_min = np.where(np.isfinite(supported), supported, fill_min)
        fill = np.where(np.isfinite(fill_min), fill_min, np.nan)
    else:
        order = np.lexsort((pv, pl))
        pl, pv = pl[order], pv[order]
        starts = np.searchsorted(pl, np.arange(n + 1), side="left")
        ends = np.searchsorted(pl, np.arange(n + 1), side="right")
        cnt = ends - starts
        has = cnt > 0
        lo_idx = starts + np.maximum(cnt - 1, 0) // 2
        hi_idx = starts + cnt // 2
        lo_idx = np.minimum(lo_idx, max(pv.size - 1, 0))
        hi_idx = np.minimum(hi_idx, max(pv.size - 1, 0))
        if pv.size:
            fill[has] = 0.5 * (pv[lo_idx[has]] + pv[hi_idx[has]])
    target = eligible[labels] & np.isfinite(fill[labels])
    a[target] = fill[labels[target]]
    return a, int(np.count_nonzero(target))


def _supported_minimum(labels: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Per hole label 0 .. n - 1, the lowest of its rim ``values`` that at least
    max(RIM_SUPPORT_CELLS, RIM_SUPPORT_SHARE of its rim) rim values lie within RIM_SUPPORT_M
    above (itself included); +inf where none does."""
    order = np.lexsort((values, labels))
    lab, val = labels[order], values[order]
    rim = np.bincount(lab, minlength=n)
    need = np.maximum(RIM_SUPPORT_CELLS, np.ceil(RIM_SUPPORT_SHARE * rim))
    # One sorted key for all labels (each label's values in increasing order, the labels apart
    # by more than RIM_SUPPORT_M): how many of its label's values lie in [v, v + RIM_SUPPORT_M].
    key = val - val.min()
    key = key + lab * (float(key.max()) + RIM_SUPPORT_M + 1.0)
    above = np.searchsorted(key, key + RIM_SUPPORT_M, side="right") - np.arange(key.size)
    ok = above >= need[lab]
    out = np.full(n, np.inf)
    np.minimum.at(out, lab[ok], val[ok])
    return out
