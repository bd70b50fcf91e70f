"""Answering queries from a fitted spline.

- :mod:`.index`: the compiled, folded brick index for large batches;
- :mod:`.derived`: deflection of the vertical, height conversion, per-tile error bounds;
- :mod:`.crs`: input coordinates in any CRS PROJ knows;
- :mod:`.export`: a store sampled on a grid (GTX, netCDF, GeoTIFF);
- :mod:`.validation`: a store against the exact synthesis of a harmonic model.
"""
