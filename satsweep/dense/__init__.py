"""Dense matching: from cameras and images to one height map per reference view.

- ``selection``: which views are references and which are their sources.
- ``planes``: the planes swept (their spacing) and their homographies.
- ``sweep``: the OpenCL plane sweep (census cost, guided filter, winner-take-all): a
  ``HeightMap``, or the ``CostVolume`` of ``volume`` (host or device, one type for every layout).
- ``mrf``: refinement of a ``CostVolume`` by an MRF: ``sgm`` (OpenCL) or ``graphcut`` (host).
- ``coarse``: the plane windows of a coarse-to-fine search.
- ``tiled``: sweep and MRF of a whole reference, tile by tile under a memory budget.
"""
