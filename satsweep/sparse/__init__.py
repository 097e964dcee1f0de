"""Sparse reconstruction: tie points between the views, and what they are used for.

- ``options``: the ``[sparse]`` options; ``features``: SIFT keypoints and descriptors;
  ``matching``: verified pairwise matches; ``tracks``: tracks and their sub-pixel registration;
  ``triangulation``: points from tracks and cameras.
- ``bundle``: adjustment of the principal points (RPC pointing errors are image translations).
- ``tiepoints``: the altitude range of a scene from tie points triangulated with the RPCs.
"""
