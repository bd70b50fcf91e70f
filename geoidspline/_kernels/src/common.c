/* Kernels shared by fitting and queries (gs_common.h). */
#include <string.h>

#include "gs_common.h"

void gs_bspline_weights(double t, int order, int nderiv, double *out, int64_t ld)
{
    if (order == 4) {
        /* closed form of the cubic case */
        double s = 1.0 - t, t2 = t * t, t3 = t2 * t;
        out[0] = s * s * s / 6.0;
        out[1] = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0;
        out[2] = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0;
        out[3] = t3 / 6.0;
        if (nderiv >= 1) {
            out[ld + 0] = -0.5 * s * s;
            out[ld + 1] = 1.5 * t2 - 2.0 * t;
            out[ld + 2] = -1.5 * t2 + t + 0.5;
            out[ld + 3] = 0.5 * t2;
        }
        if (nderiv >= 2) {
            out[2 * ld + 0] = s;
            out[2 * ld + 1] = 3.0 * t - 2.0;
            out[2 * ld + 2] = 1.0 - 3.0 * t;
            out[2 * ld + 3] = t;
        }
        return;
    }
    /* uniform-knot de Boor recursion: work[q][j] = ((t+q-1-j) work[q-1][j-1]
     * + (1+j-t) work[q-1][j]) / (q-1); B_q' = B_{q-1}(x) - B_{q-1}(x-1) */
    double work[GS_MAX_ORDER + 1][GS_MAX_ORDER + 1];
    memset(work, 0, sizeof(work));
    work[1][0] = 1.0;
    for (int q = 2; q <= order; ++q)
        for (int j = 0; j < q; ++j) {
            double left = j >= 1 ? work[q - 1][j - 1] : 0.0;
            double right = j <= q - 2 ? work[q - 1][j] : 0.0;
            work[q][j] = ((t + q - 1 - j) * left + (1 + j - t) * right) / (q - 1);
        }
    for (int j = 0; j < order; ++j)
        out[j] = work[order][j];
    if (nderiv >= 1) {
        int q = order - 1;
        for (int j = 0; j < order; ++j) {
            double left = j >= 1 ? work[q][j - 1] : 0.0;
            double right = j <= q - 1 ? work[q][j] : 0.0;
            out[ld + j] = left - right;
        }
    }
    if (nderiv >= 2) {
        int q = order - 2;
        for (int j = 0; j < order; ++j) {
            double a = j >= 2 ? work[q][j - 2] : 0.0;
            double b = (j >= 1 && j - 1 <= q - 1) ? work[q][j - 1] : 0.0;
            double c = j <= q - 1 ? work[q][j] : 0.0;
            out[2 * ld + j] = a - 2.0 * b + c;
        }
    }
}

GS_EXPORT void gs_bspline_weights_into(double t, int64_t order, int64_t nderiv, double *out, int64_t ld)
{
    gs_bspline_weights(t, (int)order, (int)nderiv, out, ld);
}

GS_EXPORT int64_t gs_pack_key(int64_t i, int64_t j, int64_t k)
{
    return gs_pack(i, j, k);
}

GS_EXPORT int64_t gs_lower_bound_of(const int64_t *keys, int64_t n, int64_t value)
{
    return gs_lower_bound(keys, n, value);
}
