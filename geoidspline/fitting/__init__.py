"""Fitting a geoid source with ambient B-splines (thesis §3-5).

- :mod:`.parameters`: :class:`~.parameters.FitParameters`, numerical only;
- :mod:`.sites`: data nodes and the rays through them (the radial extension, §3.1);
- :mod:`.least_squares`: one level's least squares, block by block (§4.3);
- :mod:`.interpolation`: quasi-interpolation of an exact source (no solves);
- :mod:`.executors`: where blocks are solved (this process, a pool, dask): never persisted;
- :mod:`.driver`: level after level until the tolerance holds (§5.2);
- :mod:`.hierarchical`: one least-squares fit over the hierarchical basis, refined until
  the tolerance holds (§5.3, ``refinement="hierarchical"``);
- :mod:`.hierarchical_interpolation`: the hierarchical quasi-interpolant of an exact
  source over that basis, no solve (§5.3.1, with ``method="interpolation"``);
- :mod:`.result`: what a fit returns (either way);
- :mod:`.check_points`: where a fit is measured besides its sites.
"""
