/* Kernels of fitting (geoidspline/_kernels/fitting.py calls them through ctypes): the
 * domain test and the normal equations of least squares. */
#include <stdlib.h>

#include "gs_common.h"

/* out[s]: cell s (cells[3 s .. 3 s + 2]) of spacing h meets the sphere |x| = radius
 * (fitting.py says why the 1e-9 slack). */
GS_EXPORT void gs_cells_meet_sphere(const int64_t *cells, int64_t m, double h, double radius, uint8_t *out)
{
    double r2 = radius * radius;
    for (int64_t s = 0; s < m; ++s) {
        double near = 0.0, far = 0.0;
        for (int d = 0; d < 3; ++d) {
            double lo = (double)cells[3 * s + d] * h;
            double hi = lo + h;
            if (lo > 0.0)
                near += lo * lo;
            else if (hi < 0.0)
                near += hi * hi;
            double a = lo * lo, b = hi * hi;
            far += b > a ? b : a; /* Python's max(a, b) */
        }
        out[s] = near <= r2 * (1.0 + 1e-9) && r2 * (1.0 - 1e-9) <= far;
    }
}

/* Accumulates AᵀA into table (last - first, (2 order - 1)³), zeroed by the caller, indexed
 * by the relative position of the second B-spline, for the columns (second B-splines)
 * first <= c2 < last of keys (n), and Aᵀb into rhs (n, zeroed) for the same columns: one
 * call per slice of the columns bounds the table. Sites in order, so every entry is summed
 * in the order of the sites. Returns 0, or -1 when out of memory. */
GS_EXPORT int64_t gs_normal_table(const double *points, const double *values, int64_t m, double h, int64_t order,
                                  const int64_t *keys, int64_t n, int64_t first, int64_t last, double *table,
                                  double *rhs)
{
    int64_t span = 2 * order - 1, width = span * span * span, block = order * order * order;
    int64_t centre = ((order - 1) * span + (order - 1)) * span + (order - 1);
    double inv_h = 1.0 / h;
    int64_t *cols = malloc(sizeof(int64_t) * (size_t)block);
    int64_t *lin = malloc(sizeof(int64_t) * (size_t)block);
    double *vals = malloc(sizeof(double) * (size_t)block);
    double wx[GS_MAX_ORDER], wy[GS_MAX_ORDER], wz[GS_MAX_ORDER];
    if (cols == NULL || lin == NULL || vals == NULL) {
        free(cols), free(lin), free(vals);
        return -1;
    }
    for (int64_t s = 0; s < m; ++s) {
        double fx = points[3 * s] * inv_h, fy = points[3 * s + 1] * inv_h, fz = points[3 * s + 2] * inv_h;
        int64_t ax = (int64_t)floor(fx), ay = (int64_t)floor(fy), az = (int64_t)floor(fz);
        gs_weights(fx - (double)ax, (int)order, 0, wx, GS_MAX_ORDER);
        gs_weights(fy - (double)ay, (int)order, 0, wy, GS_MAX_ORDER);
        gs_weights(fz - (double)az, (int)order, 0, wz, GS_MAX_ORDER);
        int64_t found = 0, k0 = az - order + 1;
        for (int64_t p = 0; p < order; ++p) {
            int64_t i = ax - order + 1 + p;
            for (int64_t q = 0; q < order; ++q) {
                int64_t j = ay - order + 1 + q;
                int64_t base = gs_pack(i, j, k0);
                int64_t pos = gs_lower_bound(keys, n, base);
                while (pos < n && keys[pos] < base + order) {
                    int64_t r = keys[pos] - base;
                    cols[found] = pos;
                    vals[found] = wx[p] * wy[q] * wz[r];
                    lin[found] = (p * span + q) * span + r;
                    ++found;
                    ++pos;
                }
            }
        }
        /* keys[cols[e]] increase with e (lexicographic p, q, r), so the rows c1 <= c2 are
         * those of e1 <= e2; B-spline e1 sits at lin[e1] - lin[e2] + centre relative to e2 */
        double value = values[s];
        for (int64_t e2 = 0; e2 < found; ++e2) {
            int64_t c2 = cols[e2];
            if (c2 < first || c2 >= last)
                continue;
            double v2 = vals[e2];
            double *row = table + (c2 - first) * width + (centre - lin[e2]);
            rhs[c2] += v2 * value;
            for (int64_t e1 = 0; e1 <= e2; ++e1)
                row[lin[e1]] += vals[e1] * v2;
        }
    }
    free(cols), free(lin), free(vals);
    return 0;
}

/* Compresses the table of the columns first <= c < last into CSC (indptr last - first + 1,
 * indices into keys (n) and data of as many entries as the table has non-zero values):
 * column c holds rows c1 <= c; offsets in lexicographic order are increasing key deltas,
 * hence increasing row positions. */
GS_EXPORT void gs_normal_compress(const double *table, const int64_t *keys, int64_t n, int64_t first, int64_t last,
                                  int64_t order, int64_t *indptr, int32_t *indices, double *data)
{
    int64_t span = 2 * order - 1, width = span * span * span, at = 0;
    indptr[0] = 0;
    for (int64_t c = first; c < last; ++c) {
        const double *row = table + (c - first) * width;
        for (int64_t off = 0; off < width; ++off) {
            double v = row[off];
            if (v != 0.0) {
                int64_t dr = off % span - (order - 1);
                int64_t dq = (off / span) % span - (order - 1);
                int64_t dp = off / (span * span) - (order - 1);
                int64_t target = keys[c] + dp * (((int64_t)1) << (2 * GS_KEY_BITS)) + dq * (((int64_t)1) << GS_KEY_BITS)
                                 + dr;
                indices[at] = (int32_t)gs_lower_bound(keys, n, target);
                data[at] = v;
                ++at;
            }
        }
        indptr[c - first + 1] = at;
    }
}

/* sum_k a[k] b[k], k < n, accumulated in double in four partial sums: independent chains
 * the compiler can keep in flight. One body for both types of a: double rows of the
 * factorisation (dot4) and the float rows of the stored factors (dot4_float). */
#define GS_DOT4(NAME, A_TYPE)                                                                    \
    GS_INLINE double NAME(const A_TYPE *a, const double *b, int64_t n)                           \
    {                                                                                            \
        double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;                                           \
        int64_t k = 0;                                                                           \
        for (; k + 4 <= n; k += 4) {                                                             \
            s0 += (double)a[k] * b[k];                                                           \
            s1 += (double)a[k + 1] * b[k + 1];                                                   \
            s2 += (double)a[k + 2] * b[k + 2];                                                   \
            s3 += (double)a[k + 3] * b[k + 3];                                                   \
        }                                                                                        \
        for (; k < n; ++k)                                                                       \
            s0 += (double)a[k] * b[k];                                                           \
        return (s0 + s1) + (s2 + s3);                                                            \
    }
GS_DOT4(dot4, double)
GS_DOT4(dot4_float, float)

/* Additive Schwarz preconditioner z = Σ_b R_bᵀ (L_b L_bᵀ)⁻¹ R_b r (z zeroed by the caller):
 * block b holds the indices index[block_at[b] .. block_at[b + 1]) (m of them) and its
 * Cholesky factor L_b packed by rows (row i: L[i][0..i]) at factors[factor_at[b] ..],
 * m (m + 1) / 2 values in float (half the memory; the solves accumulate in double, the
 * preconditioner need not be exact); work holds the largest m. */
GS_EXPORT void gs_schwarz_apply(int64_t blocks, const int64_t *block_at, const int64_t *index,
                                const int64_t *factor_at, const float *factors, const double *r, double *z,
                                double *work)
{
    for (int64_t b = 0; b < blocks; ++b) {
        const int64_t *idx = index + block_at[b];
        int64_t m = block_at[b + 1] - block_at[b];
        const float *l = factors + factor_at[b];
        /* L y = r: row i of L is contiguous */
        for (int64_t i = 0; i < m; ++i) {
            const float *row = l + i * (i + 1) / 2;
            work[i] = (r[idx[i]] - dot4_float(row, work, i)) / (double)row[i];
        }
        /* Lᵀ z = y, by rows of L from the last: z_i final, then taken out of the rows above */
        for (int64_t i = m - 1; i >= 0; --i) {
            const float *row = l + i * (i + 1) / 2;
            double zi = work[i] / (double)row[i];
            work[i] = zi;
            for (int64_t k = 0; k < i; ++k)
                work[k] -= (double)row[k] * zi;
        }
        for (int64_t i = 0; i < m; ++i)
            z[idx[i]] += work[i];
    }
}

/* Cholesky factor L (packed by rows: row i is L[i][0..i], at i (i + 1) / 2) of the
 * symmetric positive definite m x m matrix whose lower triangle is that of lower (row-major;
 * the upper triangle is not read), plus shift on the diagonal. One thread: the blocks of a
 * preconditioner are small and many. Returns 0, or i + 1 when the pivot of row i is not
 * positive. */
GS_EXPORT int64_t gs_cholesky_packed(const double *lower, int64_t m, double shift, double *packed)
{
    for (int64_t i = 0; i < m; ++i) {
        double *li = packed + i * (i + 1) / 2;
        for (int64_t j = 0; j <= i; ++j) {
            const double *lj = packed + j * (j + 1) / 2;
            double s = lower[i * m + j] + (i == j ? shift : 0.0) - dot4(li, lj, j);
            if (j < i) {
                li[j] = s / lj[j];
            } else {
                if (!(s > 0.0))
                    return i + 1;
                li[i] = sqrt(s);
            }
        }
    }
    return 0;
}
