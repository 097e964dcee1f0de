"""Geometry: RPC models and their file formats, geodesy (ECEF, ENU, UTM), the area of interest
and its altitude range, and the perspective cameras that approximate the RPCs over it.

- ``rpc``: the RPC model (projection, localization); ``rpc_formats``: its file formats.
- ``geodesy``: WGS84 ECEF / geodetic / ENU / UTM conversions.
- ``aoi``: the area of interest; ``altitude``: the altitude range swept over it.
- ``camera``: RPC -> K [R | t] over the AOI cube; ``skew``: skew correction;
  ``parallax``: the 4x4 plane-plus-parallax matrices and plane-induced homographies.
"""
