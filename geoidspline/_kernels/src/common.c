/* The B-spline weights for Python callers (gs_common.h holds the one definition). */
#include "gs_common.h"

GS_EXPORT void gs_bspline_weights_into(double t, int64_t order, int64_t nderiv, double *out, int64_t ld)
{
    gs_weights(t, (int)order, (int)nderiv, out, ld);
}
