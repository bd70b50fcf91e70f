"""Package data of geoidspline: ``catalogue.toml``, the geoid grids known by name.

Installed as ``geoidspline.grids``; read through :mod:`geoidspline.catalogue`.
"""
