/* Kernels shared by fitting and queries (gs_common.h). */
#include "gs_common.h"

GS_EXPORT void gs_bspline_weights_into(double t, int64_t order, int64_t nderiv, double *out, int64_t ld)
{
    gs_weights(t, (int)order, (int)nderiv, out, ld);
}

GS_EXPORT int64_t gs_pack_key(int64_t i, int64_t j, int64_t k)
{
    return gs_pack(i, j, k);
}

GS_EXPORT int64_t gs_lower_bound_of(const int64_t *keys, int64_t n, int64_t value)
{
    return gs_lower_bound(keys, n, value);
}
