"""Input and output files: images and GeoTIFFs, the views' crops of the AOI, atomic writes.

- ``images``: reading (windows of) TIFF images, tonemapping.
- ``geotiff``: reading and writing north-up GeoTIFFs (DSMs, DEMs).
- ``atomic``: output folders and files written under a temporary name, then renamed.
- ``views``: each image cropped to the footprint of the AOI cube, with its RPC carried along.
- ``metadata``: acquisition date-time, sun and satellite angles from TIFF tags and sidecars.
"""
