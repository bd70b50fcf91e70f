"""Tensor-product B-splines on uniform grids in R³ (thesis ch. 3).

- :mod:`.keys`: integer positions packed in int64 keys, and set operations on them;
- :mod:`.basis`: the cardinal B-spline's weights and its two-scale (refinement) relation
  (the one implementation: the query index folds with it, the hierarchical basis refines with it);
- :mod:`.level`: :class:`~.level.LevelSpline`, one level's sparse coefficients;
- :mod:`.evaluate`: numpy evaluation of a sum of levels;
- :mod:`.domain`: the domain Ω, the cells of a level that meet the sphere (§3.2);
- :mod:`.index`: the compiled, folded brick index large batches are evaluated with.
"""
