/* Coverage lookups of large batches: is each point's source cell free of no-data nodes.
 * The same rule, step for step, as NodataLattice.cells_have_data in
 * geoidspline/sphere/coverage.py (numpy, used for small batches). */
#include "gs_common.h"

typedef struct {
    const double *latitude, *longitude;
    double south, north, west, span, lat0, dlat, lon0, dlon;
    int64_t nlat, nlon, periodic;
    const uint8_t *cell_ok;
    double edge_tol;
    uint8_t *out;
    int64_t n, chunk;
} coverage_job;

static void coverage_task(void *ctx, int64_t task)
{
    const coverage_job *J = ctx;
    int64_t columns = J->periodic ? J->nlon : J->nlon - 1;
    int64_t lo = task * J->chunk, hi = lo + J->chunk < J->n ? lo + J->chunk : J->n;
    for (int64_t p = lo; p < hi; ++p) {
        double la = J->latitude[p], lon = J->longitude[p];
        if (!(la >= J->south && la <= J->north) || (J->span < 360.0 && !(gs_pymod(lon - J->west, 360.0) <= J->span))) {
            J->out[p] = 0;
            continue;
        }
        double fi = (la - J->lat0) / J->dlat;
        int ok = fi >= -J->edge_tol && fi <= J->nlat - 1 + J->edge_tol; /* false for NaN */
        double offset = gs_pymod(lon - J->lon0, 360.0);
        double fj = offset / J->dlon;
        if (J->periodic) {
            ok = ok && fj <= J->nlon;
        } else {
            if (offset > 360.0 - J->edge_tol * J->dlon) /* just west of lon0: round-off */
                fj = 0.0;
            ok = ok && fj <= J->nlon - 1 + J->edge_tol;
        }
        if (!ok) {
            J->out[p] = 0;
            continue;
        }
        double fc = fi < 0.0 ? 0.0 : fi;
        if (fc > J->nlat - 2.0)
            fc = J->nlat - 2.0;
        int64_t i = (int64_t)fc;
        int64_t j = (int64_t)fj;
        if (J->periodic) {
            j = j % J->nlon;
        } else {
            j = j < 0 ? 0 : (j > columns - 1 ? columns - 1 : j);
        }
        J->out[p] = J->cell_ok[i * columns + j];
    }
}

GS_EXPORT void gs_cells_have_data(const double *latitude, const double *longitude, int64_t n, double south,
                                  double north, double west, double span, double lat0, double dlat, double lon0,
                                  double dlon, int64_t nlat, int64_t nlon, int64_t periodic, const uint8_t *cell_ok,
                                  double edge_tol, uint8_t *out, int64_t nthreads)
{
    coverage_job J = {latitude, longitude, south, north, west, span, lat0, dlat, lon0, dlon,
                      nlat, nlon, periodic, cell_ok, edge_tol, out, n, 65536};
    gs_parallel_for((int)nthreads, (n + J.chunk - 1) / J.chunk, coverage_task, &J);
}
