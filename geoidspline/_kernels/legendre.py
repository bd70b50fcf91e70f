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
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = [
    "recursion_tables",
    "plm_bar",
    "column_sums",
    "row_sums",
    "point_sums",
    "fold_to_circle",
]

BIG = 2.0**960
BIGI = 2.0**-960
BIGS = 2.0**480
BIGSI = 2.0**-480


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


@numba.njit(cache=True, inline="always")
def _xnorm(x, ix):
    # keep |x| in [2^-480, 2^480) with one step: every multiplier used below changes
    # the magnitude by far less than 2^480
    w = abs(x)
    if w >= BIGS:
        return x * BIGI, ix + 1
    if w < BIGSI:
        return x * BIG, ix - 1
    return x, ix


@numba.njit(cache=True, inline="always")
def _xlsum2(f, x, ix, g, y, iy):
    # f·X + g·Y for X-numbers X = (x, ix), Y = (y, iy)
    d = ix - iy
    if d == 0:
        z = f * x + g * y
        iz = ix
    elif d == 1:
        z = f * x + g * (y * BIGI)
        iz = ix
    elif d == -1:
        z = g * y + f * (x * BIGI)
        iz = iy
    elif d > 1:
        z = f * x
        iz = ix
    else:
        z = g * y
        iz = iy
    return _xnorm(z, iz)


@numba.njit(cache=True, inline="always")
def _x2f(x, ix):
    if ix == 0:
        return x
    if ix == -1:
        return x * BIGI
    if ix < -1:
        return 0.0
    return x * BIG  # never reached: |P̄nm| ≤ √(2(2n+1))


@numba.njit(cache=True)
def plm_bar(nmax, t, u, AT, BT, out):
    """Fill ``out[n, m]`` (shape ≥ (nmax+1, nmax+1)) with P̄nm(t), u = √(1 − t²) ≥ 0,
    using the same recursion and tables (:func:`recursion_tables`) as :func:`column_sums`.
    Entries with m > n are left untouched.
    """
    smx = 1.0  # sectoral P̄mm as X-number
    smi = 0
    for m in range(nmax + 1):
        if m == 1:
            smx, smi = _xnorm(AT[0, 1] * u, 0)
        elif m >= 2:
            smx, smi = _xnorm(smx * AT[m, m] * u, smi)
        out[m, m] = _x2f(smx, smi)
        if m == nmax:
            break
        p1x, p1i = smx, smi
        px, pi = _xnorm(AT[m, m + 1] * t * p1x, p1i)
        out[m + 1, m] = _x2f(px, pi)
        n = m + 2
        while n <= nmax and (pi != 0 or p1i != 0):
            qx, qi = _xlsum2(AT[m, n] * t, px, pi, -BT[m, n], p1x, p1i)
            p1x, p1i = px, pi
            px, pi = qx, qi
            out[n, m] = _x2f(px, pi)
            n += 1
        p = px
        pp = p1x
        while n <= nmax:
            r = AT[m, n] * t * p - BT[m, n] * pp
            pp = p
            p = r
            out[n, m] = p
            n += 1
    return out


@numba.njit(cache=True, inline="always")
def _accumulate(K, w, CT, ST, m, n, p, sa, sb):
    for k in range(K):
        wk = w[k, n] * p
        sa += wk * CT[k, m, n]
        sb += wk * ST[k, m, n]
    return sa, sb


@numba.njit(cache=True)
def column_sums(nmax, t, u, q, scale, radial, CT, ST, AT, BT, A, B, w):
    """Legendre sums of one latitude, for every order m.

    A[m] = Σ_k Σ_{n=m}^{nmax} w_k(n) CT[k, m, n] P̄nm(t) and likewise B with ST, where
    w_k(n) = scale[k]·q^n if radial[k] else scale[k]; K = CT.shape[0] is 1 or 2.
    ``CT``/``ST`` are order-major (k, m, n) so the inner loop over n is contiguous;
    ``AT``/``BT`` are :func:`recursion_tables`. ``w`` is scratch of shape (K, nmax+1).
    A and B (length ≥ nmax+1) are overwritten.
    """
    K = CT.shape[0]
    for k in range(K):
        if radial[k]:
            qn = scale[k]
            for n in range(nmax + 1):
                w[k, n] = qn
                qn *= q
        else:
            for n in range(nmax + 1):
                w[k, n] = scale[k]
    for m in range(nmax + 1):
        A[m] = 0.0
        B[m] = 0.0
    smx = 1.0
    smi = 0
    for m in range(nmax + 1):
        if m == 1:
            if u == 0.0:
                break  # at the pole every P̄nm with m ≥ 1 vanishes
            smx, smi = _xnorm(AT[0, 1] * u, 0)  # √3 u
        elif m >= 2:
            smx, smi = _xnorm(smx * AT[m, m] * u, smi)
            if smx == 0.0:
                break
        sa = 0.0
        sb = 0.0
        if smi == 0:
            sa, sb = _accumulate(K, w, CT, ST, m, m, smx, sa, sb)
        if m < nmax:
            p1x, p1i = smx, smi
            px, pi = _xnorm(AT[m, m + 1] * t * p1x, p1i)
            if pi == 0:
                sa, sb = _accumulate(K, w, CT, ST, m, m + 1, px, sa, sb)
            n = m + 2
            # X-number phase: values below 2^-480 are carried but not summed
            while n <= nmax and (pi != 0 or p1i != 0):
                qx, qi = _xlsum2(AT[m, n] * t, px, pi, -BT[m, n], p1x, p1i)
                p1x, p1i = px, pi
                px, pi = qx, qi
                if pi == 0:
                    sa, sb = _accumulate(K, w, CT, ST, m, n, px, sa, sb)
                n += 1
            # plain double phase (most of the work); two specialised loops for K = 1, 2
            p = px
            pp = p1x
            if K == 1:
                while n <= nmax:
                    r = AT[m, n] * t * p - BT[m, n] * pp
                    pp = p
                    p = r
                    wk = w[0, n] * p
                    sa += wk * CT[0, m, n]
                    sb += wk * ST[0, m, n]
                    n += 1
            else:
                while n <= nmax:
                    r = AT[m, n] * t * p - BT[m, n] * pp
                    pp = p
                    p = r
                    w0 = w[0, n] * p
                    w1 = w[1, n] * p
                    sa += w0 * CT[0, m, n] + w1 * CT[1, m, n]
                    sb += w0 * ST[0, m, n] + w1 * ST[1, m, n]
                    n += 1
        A[m] = sa
        B[m] = sb


@numba.njit(cache=True)
def row_sums(nmax, t, u, q, scale, radial, CT, ST, AT, BT, A, B):
    """:func:`column_sums` for many latitudes: row i uses t[i], u[i], q[i], scale[i, :]
    and writes A[i, :], B[i, :]."""
    K = CT.shape[0]
    w = np.empty((K, nmax + 1))
    for i in range(t.shape[0]):
        column_sums(nmax, t[i], u[i], q[i], scale[i], radial, CT, ST, AT, BT, A[i], B[i], w)


@numba.njit(cache=True)
def point_sums(nmax, t, u, q, lam, scale, radial, CT, ST, AT, BT, out):
    """Full synthesis at scattered points: out[i] = Σ_m A_m cos mλ_i + B_m sin mλ_i with
    A, B the :func:`column_sums` of point i (λ in radians). Points with NaN t get NaN."""
    K = CT.shape[0]
    w = np.empty((K, nmax + 1))
    A = np.empty(nmax + 1)
    B = np.empty(nmax + 1)
    for i in range(t.shape[0]):
        if math.isnan(t[i]) or math.isnan(lam[i]):
            out[i] = math.nan
            continue
        column_sums(nmax, t[i], u[i], q[i], scale[i], radial, CT, ST, AT, BT, A, B, w)
        total = 0.0
        lam_i = lam[i]
        for m in range(nmax, 0, -1):  # small terms first
            ml = m * lam_i
            total += A[m] * math.cos(ml) + B[m] * math.sin(ml)
        out[i] = total + A[0]


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
