"""Hierarchies of levels (thesis ch. 5).

- :mod:`.ambient`: :class:`~.ambient.AmbientSpline`, the sum of levels S = Σ_ℓ S_ℓ, and
  its evaluation (numpy for small batches, the compiled index for large ones);
- :mod:`.overlays`: hierarchical overlays (§5.2), which B-splines each level adds;
- :mod:`.hierarchical`: linearly independent hierarchical B-splines (§5.3): up/down,
  Algorithms 1 and 2, and the least-squares matrices over all levels.
"""
