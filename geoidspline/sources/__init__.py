"""What a fit reads: geoid grids in their file formats, harmonic models, the catalogue.

- :mod:`.base`: :class:`~.base.Provenance`, the :class:`~geoidspline.sphere.sample.NodeSample` a
  source gives, and the
  :class:`~.base.GeoidSource` protocol the fitter needs;
- :mod:`.grid`: :class:`~.grid.GeoidGrid`, N on a latitude/longitude lattice;
- :mod:`.formats`: :func:`~.formats.read_grid`, one module per format (:mod:`.gtx`,
  :mod:`.netcdf`, :mod:`.dac`, :mod:`.pgm`);
- :mod:`.harmonics`: spherical-harmonic models and their exact synthesis;
- :mod:`.catalogue`: grids known by name; :mod:`.resolve`: a command's SOURCE to a source.
"""
