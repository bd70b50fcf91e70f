"""Answering queries from any fitted spline (through ``undulation``/``evaluate_points``).

- :mod:`.batch`: the batch engine: CSV rows in, values out, in chunks;
- :mod:`.derived`: deflection of the vertical, height conversion;
- :mod:`.crs`: input coordinates in any CRS PROJ knows;
- :mod:`.plot`: maps of a store.

A store sampled on a grid (GTX, netCDF, GeoTIFF) and a store against a harmonic model
compose a query with a source: :mod:`geoidspline.api.export`, :mod:`geoidspline.api.validation`.
"""
