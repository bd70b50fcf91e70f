"""Compiled kernels, by stage, free of validation: C (``src/``, built at install, loaded
by :mod:`._clib`); nothing is compiled at run time.

- :mod:`.layout`: the packed key layout (plain integers);
- :mod:`.codec`: the store codec's radial prediction (format-3 tiles);
- :mod:`.common`: the B-spline weights (for Python callers and tests);
- :mod:`.fitting`: the domain test and the normal equations of least squares;
- :mod:`.interpolation`: the quasi-interpolant's lattice lookups and prefilter;
- :mod:`.query`: the brick index and the evaluation of batches;
- :mod:`.legendre`: associated Legendre functions and sums for harmonic synthesis;
- :mod:`.array_cache`: numpy's array memory reused within a scope (a band's fit).

Conventions shared by every kernel:

- A level is a uniform grid of spacing ``h`` in R³ (unit sphere units). Cell ``a``
  (an integer triple) is ``[a h, (a+1) h)``; B-spline ``k`` of order ``n`` is the
  tensor product ``Π_d B_n(x_d / h - k_d)`` of the cardinal B-spline on ``[0, n)``,
  so it is non-zero on cells ``k .. k + n - 1`` and a point in cell ``a`` is touched
  by ``k = a - n + 1 .. a`` on each axis.
- Coefficient indices are packed into one int64 key (:mod:`.layout`; numpy helpers in
  :mod:`geoidspline.bspline.keys`).

Callers pass well-formed contiguous arrays; the validated APIs live in the packages
named after each stage. Importing this package imports nothing: the submodules load the
compiled library, which a one-point query needs only to decode format-3 tiles (:mod:`.codec`).
"""
