"""Legendre sums of lattice rows by ducc0's spherical-harmonic transforms.

A lattice row of :class:`~.synthesis.GeoidSynthesis` needs, for every order m,
A_m = Σ_n w (a/r)^n C̄nm P̄nm(sin ψ) and B_m likewise with S̄nm, at the geocentric
latitude ψ and radius r of its ellipsoid points. ducc0's ``alm2leg`` computes
Σ_n a_nm λ_nm(θ) for many rings at once (vectorised over rings, symmetric ring pairs
together), but with one set of coefficients for all rings, while (a/r)^n differs from
ring to ring (the ellipsoid). So the rows are cut into bands of nearly equal radius and,
in each band, with δ = ln(a/r) = c + h s (s in [-1, 1]),

    (a/r)^n = e^{n c} e^{n h s} = e^{n c} Σ_j ε_j I_j(n h) T_j(s)        (ε_0 = 1, ε_j = 2)

(the Chebyshev expansion of the exponential, I_j the modified Bessel functions): term j
is one ``alm2leg`` of the coefficients times ε_j e^{n c} I_j(n h), weighted per row by
T_j(s). The number of terms of a band is the least whose truncation error is below
:data:`RADIAL_TOLERANCE_M` by a bound from the model's own coefficients:
|Σ_m (C̄ cos + S̄ sin) P̄nm| ≤ √((2n+1) Σ_m (C̄² + S̄²)) (Cauchy-Schwarz and the addition
theorem), and |Σ_{j>K} ε_j I_j T_j| ≤ 2 Σ_{j>K} I_j. The band width is chosen for the
least work (terms × rows, plus the coefficient scaling each term costs).

Sets without the radial factor (the ζ-to-N correction) need one ``alm2leg`` a band.
Numeric helper: no validation (the synthesis validates).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import special

from ...errors import ParameterError

__all__ = ["ShtRows", "RADIAL_TOLERANCE_M", "EXACT_ROW_COST"]

#: Bound on the truncation error of the radial expansion (metres): a hundredth of the
#: 0.01 mm that the lattices must agree with the exact synthesis to (the bound is a
#: worst case; the errors seen are far smaller).
RADIAL_TOLERANCE_M = 1e-7

_MAX_TERMS = 16  # Chebyshev terms a band may use
_TAIL = 24  # Bessel terms summed for the tail bound (they fall faster than geometrically)
#: What the exact synthesis of one row costs, in rows of ``alm2leg`` (measured at degree
#: 2190, one thread: 11.7 ms against 0.5 ms).
EXACT_ROW_COST = 20.0
#: What one term costs besides its rows, in rows of ``alm2leg``: scaling the coefficients
#: and the call's own set-up (measured at degree 2190, one thread: about 46 + 36 ms,
#: against about 0.5 ms a row).
_SCALE_COST_ROWS = 160.0


class ShtRows:
    """Row sums of order-major coefficient sets CT[k, m, n], ST[k, m, n] (the layout of
    GeoidSynthesis); ``radial[k]``: set k carries (a/r)^n."""

    def __init__(self, CT, ST, radial, nmax: int):
        try:  # fail at construction, not in the middle of a lattice
            import ducc0  # noqa: F401
        except ImportError:
            raise ParameterError("the lattice engine 'sht' needs ducc0: pip install 'geoidspline[sht]' "
                                 "(or use the default engine, 'exact')") from None

        self.nmax = nmax
        size = nmax + 1
        m = np.arange(size)
        self.mval = m.astype(np.uint64)
        # ducc0's triangular layout, m-major: index of (n, m) = mstart[m] + n
        self.mstart = (m * (2 * nmax + 1 - m) // 2).astype(np.uint64)
        self.degree = np.concatenate([np.arange(k, size, dtype=np.int32) for k in range(size)])
        self.alm = [np.concatenate([CT[k, j, j:] + 1j * ST[k, j, j:] for j in range(size)]) for k in range(len(radial))]
        self.radial = np.asarray(radial, dtype=bool)
        # ducc0's λ_nm(θ) is P̄nm/√(4π) for m = 0 and (-1)^m P̄nm/√(8π) for m > 0
        self.factor = np.where(m == 0, math.sqrt(4 * math.pi), math.sqrt(8 * math.pi) * (-1.0) ** m)
        k0 = int(np.flatnonzero(self.radial)[0]) if self.radial.any() else None
        n = np.arange(size)
        power = np.zeros(size) if k0 is None else (CT[k0] ** 2 + ST[k0] ** 2).sum(axis=0)
        self.amplitude = np.sqrt((2 * n + 1) * power)  # bound of |degree n| per unit weight

    # ------------------------------------------------------------------ planning
    def _terms(self, h: float, c: float, weight: float) -> int | None:
        """Least number of Chebyshev terms K + 1 for a band of half-width h about c (in
        ln(a/r)) whose truncation error stays below the tolerance; None if none does."""
        if h == 0.0:
            return 1
        n = np.arange(self.nmax + 1)
        x = n * h
        j = np.arange(_MAX_TERMS + _TAIL)[:, None]
        tails = 2.0 * np.cumsum(special.iv(j, x[None, :])[::-1], axis=0)[::-1]  # tails[K] = 2 Σ_{j≥K} I_j
        scale = weight * self.amplitude * np.exp(n * c)
        bounds = tails[1:_MAX_TERMS + 1] @ scale  # bounds[K-1]: error with terms 0..K-1
        ok = np.flatnonzero(bounds <= RADIAL_TOLERANCE_M)
        return int(ok[0]) + 1 if ok.size else None

    @staticmethod
    def cost(bands) -> float:
        """The work of a plan, in rows of ``alm2leg`` (compare :data:`EXACT_ROW_COST`)."""
        return sum(terms * (_SCALE_COST_ROWS + rows.size) for rows, _, _, terms in bands)

    def plan(self, log_q, weight):
        """Bands [(row indices, c, h, terms)] covering every row, by ln(a/r) (rows of the
        same radius together, north and south alike); ``weight[i]``: row i's factor."""
        order = np.argsort(log_q, kind="stable")
        d = log_q[order]
        span = float(d[-1] - d[0]) if d.size else 0.0
        wmax = float(np.max(weight)) if weight.size else 0.0
        worst = float(d[-1]) if d.size else 0.0
        best = None
        h = span / 2.0
        while True:
            terms = self._terms(h, worst, wmax)
            if terms is not None:
                starts = _greedy(d, 2.0 * h)
                cost = terms * (len(starts) * _SCALE_COST_ROWS + d.size)
                if best is None or cost < best[0]:
                    best = (cost, h, starts)
            if h == 0.0 or h < 1e-9:
                break
            h = h / 2.0 if h > 1e-8 else 0.0
        starts = best[2]
        bands = []
        for a, b in zip(starts, list(starts[1:]) + [d.size]):
            rows = order[a:b]
            lo, hi = float(d[a]), float(d[b - 1])
            c, hb = (lo + hi) / 2.0, (hi - lo) / 2.0
            wb = float(np.max(weight[rows]))
            bands.append((rows, c, hb, self._terms(hb, c, wb) if self.radial.any() else 1))
        return bands

    # ------------------------------------------------------------------ sums
    def _leg(self, alm, theta, nthreads):
        import ducc0

        leg = ducc0.sht.experimental.alm2leg(
            alm=alm[None, :], lmax=self.nmax, theta=theta, spin=0, mval=self.mval, mstart=self.mstart,
            nthreads=nthreads,
        )
        return leg[0]

    def band_sums(self, theta, log_q, scale, band, nthreads: int = 1):
        """A, B (rows of the band × orders) for one band of :meth:`plan`: the rows'
        Σ_k scale[:, k] Σ_n (a/r)^n [C̄, S̄]_k P̄nm (no (a/r)^n where not radial[k])."""
        rows, c, h, terms = band
        th = np.ascontiguousarray(theta[rows], dtype=np.float64)
        size = self.nmax + 1
        total = np.zeros((rows.size, size), dtype=np.complex128)
        n = np.arange(size, dtype=np.float64)
        for k, alm in enumerate(self.alm):
            if not self.radial[k]:
                total += scale[rows, k][:, None] * self._leg(alm, th, nthreads)
                continue
            s = (log_q[rows] - c) / h if h > 0 else np.zeros(rows.size)
            cheb = np.polynomial.chebyshev.chebvander(s, terms - 1)
            part = np.zeros((rows.size, size), dtype=np.complex128)
            scaled = np.empty_like(alm)
            for j in range(terms):
                weight = (1.0 if j == 0 else 2.0) * special.iv(j, n * h) * np.exp(n * c)
                np.multiply(alm, np.take(weight, self.degree), out=scaled)
                part += cheb[:, j][:, None] * self._leg(scaled, th, nthreads)
            total += scale[rows, k][:, None] * part
        total *= self.factor[None, :]
        return total.real, total.imag


#: Rows a band holds at most (its arrays: about 100 kB a row at degree 2190).
_MAX_BAND_ROWS = 512


def _greedy(d, width):
    """Starts of consecutive groups of sorted values ``d``, each within ``width``."""
    starts = []
    i = 0
    while i < d.size:
        starts.append(i)
        i = min(int(np.searchsorted(d, d[i] + width, side="right")), i + _MAX_BAND_ROWS)
    return starts
