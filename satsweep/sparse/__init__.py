"""Sparse reconstruction: tie points between the views, and what they are used for.

- ``stage``: the sparse stage, one pass over the views cropped at a prior altitude range:
  per-view pointing corrections (of any size), the views that can be used (the others dropped
  with the reason), the altitude range of the adjusted tie points, the pair graph and figures
  (:func:`stage.sparse_stage` -> :class:`stage.SparseResult`).
- ``options``: the ``[sparse]`` options; ``features``: SIFT keypoints and descriptors;
  ``graph``: which pairs of views are matched; ``matching``: verified pairwise matches;
  ``tracks``: tracks and their sub-pixel registration; ``triangulation``: points from tracks
  and cameras.
- ``bundle``: the coarse and the fine adjustment of the principal points (RPC pointing errors
  are image translations); ``adjust_principal_points`` for cameras already fitted.
- ``surface_ties``: the corrections refined on tie points of a first DSM's surface (the
  pipeline's second pass where the sparse stage's tie points leave them uncertain).
- ``tiepoints``: altitude ranges from tie points: the sparse stage's adjusted ones, and the
  older RPC triangulation of every pair's matches.
"""
