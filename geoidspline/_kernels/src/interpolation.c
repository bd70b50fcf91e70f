/* Kernels of spline quasi-interpolation (geoidspline/_kernels/interpolation.py calls them
 * through ctypes): the prefilter along one axis, lattice lookups, lattice directions. */
#include "gs_common.h"

/* Output points are cut into chunks of at least this many, at most GS_CHUNKS_MAX chunks:
 * each chunk is a task of gs_parallel_for. The result does not depend on the cut. */
#define GS_CHUNK_MIN 65536
#define GS_CHUNKS_MAX 64

static int64_t chunk_count(int64_t n)
{
    int64_t c = n / GS_CHUNK_MIN;
    return c < 1 ? 1 : (c > GS_CHUNKS_MAX ? GS_CHUNKS_MAX : c);
}

typedef struct {
    const int64_t *in_keys;
    const double *in_values;
    const int64_t *out_keys;
    int64_t nin, n, step, ntaps, nchunk;
    const double *taps;
    double *out;
} filter_job;

static void filter_task(void *ctx, int64_t c)
{
    const filter_job *J = ctx;
    int64_t lo = J->n * c / J->nchunk, hi = J->n * (c + 1) / J->nchunk, half = (J->ntaps - 1) / 2;
    for (int64_t m = lo; m < hi; ++m)
        J->out[m] = 0.0;
    if (hi <= lo)
        return;
    for (int64_t t = 0; t < J->ntaps; ++t) {
        int64_t shift = (t - half) * J->step;
        /* one binary search a chunk, then a merge walk of two sorted arrays */
        int64_t p = gs_lower_bound(J->in_keys, J->nin, J->out_keys[lo] + shift);
        double w = J->taps[t];
        for (int64_t m = lo; m < hi; ++m) {
            int64_t target = J->out_keys[m] + shift;
            while (J->in_keys[p] < target)
                ++p;
            J->out[m] += w * J->in_values[p];
        }
    }
}

GS_EXPORT void gs_filter_axis(const int64_t *in_keys, const double *in_values, int64_t nin, const int64_t *out_keys,
                              int64_t n, int64_t step, const double *taps, int64_t ntaps, double *out, int64_t nthreads)
{
    filter_job J = {in_keys, in_values, out_keys, nin, n, step, ntaps, chunk_count(n), taps, out};
    gs_parallel_for((int)nthreads, J.nchunk, filter_task, &J);
}

/* Weights of the 6-point Lagrange interpolant on nodes -2..3 at t in [0, 1). */
static void lagrange6(double t, double *w)
{
    for (int j = 0; j < 6; ++j) {
        double xj = j - 2.0, v = 1.0;
        for (int k = 0; k < 6; ++k)
            if (k != j)
                v *= (t - (k - 2.0)) / (xj - (k - 2.0));
        w[j] = v;
    }
}

typedef struct {
    const double *grid;
    int64_t ncol;
    double lat0, dlat, lon0, dlon;
    int64_t first_row;
    const double *latitude, *longitude;
    double *out;
    int64_t n, nchunk;
} lookup_job;

static void lookup_task(void *ctx, int64_t c)
{
    const lookup_job *J = ctx;
    double w_lat[6], w_lon[6];
    for (int64_t p = J->n * c / J->nchunk; p < J->n * (c + 1) / J->nchunk; ++p) {
        /* the row position on the whole lattice, then in the grid held: an exact
         * integer shift, so a band of rows gives the whole lattice's bits */
        double y = (J->latitude[p] - J->lat0) / J->dlat - (double)J->first_row;
        int64_t i = (int64_t)floor(y);
        lagrange6(y - (double)i, w_lat);
        double lon = J->longitude[p] - (J->lon0 + 2.0 * J->dlon);
        lon = lon - 360.0 * floor(lon / 360.0);
        double x = lon / J->dlon + 2.0;
        int64_t j = (int64_t)floor(x);
        lagrange6(x - (double)j, w_lon);
        double acc = 0.0;
        for (int a = 0; a < 6; ++a) {
            const double *row = J->grid + (i - 2 + a) * J->ncol + (j - 2);
            double r = 0.0;
            for (int b = 0; b < 6; ++b)
                r += w_lon[b] * row[b];
            acc += w_lat[a] * r;
        }
        J->out[p] = acc;
    }
}

GS_EXPORT void gs_lattice_lookup(const double *grid, int64_t ncol, double lat0, double dlat, int64_t first_row,
                                 double lon0, double dlon, const double *latitude, const double *longitude, int64_t n,
                                 double *out, int64_t nthreads)
{
    lookup_job J = {grid, ncol, lat0, dlat, lon0, dlon, first_row, latitude, longitude, out, n, chunk_count(n)};
    gs_parallel_for((int)nthreads, J.nchunk, lookup_task, &J);
}

typedef struct {
    const int64_t *keys;
    int64_t key_offset, key_bits;
    double position_offset, h;
    double *latitude, *longitude;
    int64_t n, nchunk;
} directions_job;

static void directions_task(void *ctx, int64_t c)
{
    const directions_job *J = ctx;
    int64_t mask = (((int64_t)1) << J->key_bits) - 1;
    const double degrees = 180.0 / 3.141592653589793; /* math.degrees: x * (180 / pi) */
    for (int64_t p = J->n * c / J->nchunk; p < J->n * (c + 1) / J->nchunk; ++p) {
        int64_t key = J->keys[p];
        double x = (double)(((key >> (2 * J->key_bits)) & mask) - J->key_offset) + J->position_offset;
        double y = (double)(((key >> J->key_bits) & mask) - J->key_offset) + J->position_offset;
        double z = (double)((key & mask) - J->key_offset) + J->position_offset;
        J->latitude[p] = atan2(z * J->h, hypot(x * J->h, y * J->h)) * degrees;
        J->longitude[p] = atan2(y * J->h, x * J->h) * degrees;
    }
}

GS_EXPORT void gs_key_directions(const int64_t *keys, int64_t n, int64_t key_offset, int64_t key_bits,
                                 double position_offset, double h, double *latitude, double *longitude,
                                 int64_t nthreads)
{
    directions_job J = {keys, key_offset, key_bits, position_offset, h, latitude, longitude, n, chunk_count(n)};
    gs_parallel_for((int)nthreads, J.nchunk, directions_task, &J);
}
