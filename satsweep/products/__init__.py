"""Products: from height maps to the DSM, orthophoto, point cloud, quick looks and evaluation.

- ``grid``: the DSM grid (UTM, north up) and its GeoTIFF.
- ``points``: height maps -> ENU points -> UTM points over each pixel's footprint.
- ``fusion``: cross-check between views, rasterisation, fusion, hole filling.
- ``ortho``: the true orthophoto's values; ``ply``: the point cloud file.
- ``quicklook``: PNG renderings; ``evaluate``: scores against a truth DSM.
"""
