"""Numeric kernels: fully normalised associated Legendre functions and Legendre sums.

No validation here (that is :mod:`geoidspline.sources.harmonics.synthesis`'s job); callers pass
well-formed float64 arrays.

Convention: 4π ("geodesy") normalisation without the Condon-Shortley phase,
∫₋₁¹ P̄nm(t)² dt = 2(2 − δm0), P̄00 = 1, P̄11 = √3 u, with t = sin ψ = cos θ and
u = cos ψ = sin θ (ψ geocentric latitude, θ colatitude).

Recursion (standard forward column recursion, Holmes & Featherstone 2002, J. Geodesy
76:279-299, eqs. 11-13):

    P̄mm   = u √((2m+1)/(2m)) P̄m-1,m-1            (m ≥ 2)
    P̄m+1,m = √(2m+3) t P̄mm
    P̄nm   = a_nm t P̄n-1,m − b_nm P̄n-2,m,
    a_nm = √((2n−1)(2n+1)/((n−m)(n+m))),
    b_nm = √((2n+1)(n+m−1)(n−m−1)/((n−m)(n+m)(2n−3))).

Near the poles the sectoral values u^m·(...) underflow long before degree 2190 (at
ψ = 89°, u^2000 ≈ 1e-3500). The recursion therefore runs on "X-numbers" (Fukushima
2012, J. Geodesy 86:271-285): a double mantissa times BIG^ix with BIG = 2^960, so the
exponent range is unlimited. Within each column, once the values are back in the
ordinary double range (ix = 0) they stay there (they grow until the oscillatory zone,
then stay O(1)), so the rest of the column runs in plain doubles. Values that are still
below 2^-480 when a sum is formed contribute nothing measurable and are dropped.

The recursion and sums are C (``src/legendre.c``); the tables and the FFT fold are numpy.
"""

from __future__ import annotations

import numpy as np

from ._clib import F64, I64, PTR, c_in, c_out, function, ptr, threads

__all__ = [
    "recursion_tables",
    "plm_bar",
    "column_sums",
    "row_sums",
    "point_sums",
    "fold_to_circle",
]


def recursion_tables(nmax: int):
    """Order-major recursion coefficients AT[m, n] = a_nm, BT[m, n] = b_nm (n ≥ m + 1),
    with the sectoral factors on the diagonal: AT[m, m] = √((2m+1)/(2m)) (m ≥ 2) and
    AT[0, 1] = √3 doubling as P̄11/u. Memory: 2·8·(nmax+1)² bytes (77 MB at 2190).

    Built from square roots of integers, a = √(2n+1)/(√(n−m)√(n+m))·√(2n−1) etc.: near
    the poles the column recursion is ill-conditioned (its two solutions nearly coincide),
    and this form keeps the errors of the zonal columns at 89.9° about ten times smaller
    than one square root of the exact ratio (measured against 40-digit mpmath).
    """
    size = nmax + 1
    sq = np.sqrt(np.arange(2 * size + 4, dtype=np.float64))
    n = np.arange(size)[None, :]
    m = np.arange(size)[:, None]
    AT = np.zeros((size, size))
    BT = np.zeros((size, size))
    nn, mm = np.broadcast_arrays(n, m)
    sel = nn >= mm + 1
    ns, ms = nn[sel], mm[sel]
    f = sq[2 * ns + 1] / (sq[ns - ms] * sq[ns + ms])
    AT[sel] = f * sq[2 * ns - 1]
    sel2 = nn >= mm + 2
    ns, ms = nn[sel2], mm[sel2]
    f = sq[2 * ns + 1] / (sq[ns - ms] * sq[ns + ms])
    BT[sel2] = f * sq[ns + ms - 1] * sq[ns - ms - 1] / sq[2 * ns - 3]
    k = np.arange(2, size)
    AT[k, k] = sq[2 * k + 1] / sq[2 * k]
    return AT, BT


_plm_bar = function("gs_plm_bar", I64, F64, F64, PTR, PTR, I64, PTR, I64)
_column_sums = function("gs_column_sums", I64, F64, F64, F64, PTR, PTR, I64, PTR, PTR, I64, I64, PTR, PTR, I64, PTR,
                        PTR, PTR)
_row_sums = function("gs_row_sums", I64, PTR, PTR, PTR, I64, PTR, I64, PTR, I64, PTR, PTR, I64, I64, PTR, PTR, I64,
                     PTR, PTR, I64, I64, restype=I64)
_point_sums = function("gs_point_sums", I64, PTR, PTR, PTR, PTR, I64, PTR, I64, PTR, I64, PTR, PTR, I64, I64, PTR, PTR,
                       I64, PTR, I64, restype=I64)


def _sets(radial, CT, ST, AT, BT):
    """The coefficient sets and tables as the C kernels take them (no copy when they are)."""
    return (c_in(radial, np.bool_), c_in(CT, np.float64), c_in(ST, np.float64), c_in(AT, np.float64),
            c_in(BT, np.float64))


def plm_bar(nmax, t, u, AT, BT, out):
    """Fill ``out[n, m]`` (shape ≥ (nmax+1, nmax+1)) with P̄nm(t), u = √(1 − t²) ≥ 0,
    using the same recursion and tables (:func:`recursion_tables`) as :func:`column_sums`.
    Entries with m > n are left untouched. C: ``src/legendre.c``.
    """
    AT, BT = c_in(AT, np.float64), c_in(BT, np.float64)
    c_out(out, np.float64)
    _plm_bar(nmax, t, u, ptr(AT), ptr(BT), AT.shape[1], ptr(out), out.shape[1])
    return out


def column_sums(nmax, t, u, q, scale, radial, CT, ST, AT, BT, A, B, w):
    """Legendre sums of one latitude, for every order m.

    A[m] = Σ_k Σ_{n=m}^{nmax} w_k(n) CT[k, m, n] P̄nm(t) and likewise B with ST, where
    w_k(n) = scale[k]·q^n if radial[k] else scale[k]; K = CT.shape[0] is 1 or 2.
    ``CT``/``ST`` are order-major (k, m, n) so the inner loop over n is contiguous;
    ``AT``/``BT`` are :func:`recursion_tables`. ``w`` is scratch of shape (K, nmax+1).
    A and B (length ≥ nmax+1) are overwritten.
    """
    radial, CT, ST, AT, BT = _sets(radial, CT, ST, AT, BT)
    scale = c_in(scale, np.float64)
    for array in (A, B, w):
        c_out(array, np.float64)
    _column_sums(nmax, t, u, q, ptr(scale), ptr(radial), CT.shape[0], ptr(CT), ptr(ST), CT.shape[1], CT.shape[2],
                 ptr(AT), ptr(BT), AT.shape[1], ptr(A), ptr(B), ptr(w))


def row_sums(nmax, t, u, q, scale, radial, CT, ST, AT, BT, A, B):
    """:func:`column_sums` for many latitudes: row i uses t[i], u[i], q[i], scale[i, :]
    and writes A[i, :], B[i, :]. Rows in parallel (:func:`~._clib.threads`); each row's
    values do not depend on the thread count."""
    radial, CT, ST, AT, BT = _sets(radial, CT, ST, AT, BT)
    t, u, q, scale = (c_in(a, np.float64) for a in (t, u, q, scale))
    c_out(A, np.float64)
    c_out(B, np.float64)
    if _row_sums(nmax, ptr(t), ptr(u), ptr(q), t.shape[0], ptr(scale), scale.shape[1], ptr(radial), CT.shape[0],
                 ptr(CT), ptr(ST), CT.shape[1], CT.shape[2], ptr(AT), ptr(BT), AT.shape[1], ptr(A), ptr(B),
                 A.shape[1], threads()) != 0:
        raise MemoryError("no memory for the scratch of the Legendre sums")


def point_sums(nmax, t, u, q, lam, scale, radial, CT, ST, AT, BT, out):
    """Full synthesis at scattered points: out[i] = Σ_m A_m cos mλ_i + B_m sin mλ_i with
    A, B the :func:`column_sums` of point i (λ in radians). Points with NaN t get NaN.
    Points in parallel (:func:`~._clib.threads`), independent of the thread count."""
    radial, CT, ST, AT, BT = _sets(radial, CT, ST, AT, BT)
    t, u, q, lam, scale = (c_in(a, np.float64) for a in (t, u, q, lam, scale))
    c_out(out, np.float64)
    if _point_sums(nmax, ptr(t), ptr(u), ptr(q), ptr(lam), t.shape[0], ptr(scale), scale.shape[1], ptr(radial),
                   CT.shape[0], ptr(CT), ptr(ST), CT.shape[1], CT.shape[2], ptr(AT), ptr(BT), AT.shape[1], ptr(out),
                   threads()) != 0:
        raise MemoryError("no memory for the scratch of the Legendre sums")


def fold_to_circle(A: np.ndarray, B: np.ndarray, L: int) -> np.ndarray:
    """Values of Σ_m A_m cos mλ + B_m sin mλ at λ_j = 2πj/L, j = 0..L-1, for each row.

    ``A``, ``B``: shape (rows, M+1). Orders m ≥ L/2 alias onto lower frequencies on an
    L-point circle; they are folded exactly before a real inverse FFT (NumPy pocketfft).
    Returns shape (rows, L).
    """
    rows, mcount = A.shape
    half = L // 2
    Y = np.zeros((rows, half + 1), dtype=np.complex128)
    c = A - 1j * B  # Re(c e^{imλ}) = A cos mλ + B sin mλ
    m = np.arange(mcount)
    k = m % L
    mirrored = k > half
    kk = np.where(mirrored, L - k, k)
    weight = np.where((kk == 0) | ((L % 2 == 0) & (kk == half)), float(L), L / 2.0)
    for idx in range(mcount):  # few hundred to a few thousand orders: cheap column ops
        col = c[:, idx] if not mirrored[idx] else np.conj(c[:, idx])
        Y[:, kk[idx]] += weight[idx] * col
    return np.fft.irfft(Y, n=L, axis=1)
