/* Kernels of harmonic synthesis (geoidspline/_kernels/legendre.py calls them through
 * ctypes): fully normalised associated Legendre functions and Legendre sums by the
 * forward column recursion on X-numbers (Fukushima 2012); legendre.py states the
 * convention and the recursion. Arithmetic in the order of the numba kernels it replaces. */
#include <stdlib.h>

#include "gs_common.h"

#define BIG 0x1p960
#define BIGI 0x1p-960
#define BIGS 0x1p480
#define BIGSI 0x1p-480

/* An X-number x BIG^i. */
typedef struct {
    double x;
    int64_t i;
} xnum;

/* keep |x| in [2^-480, 2^480) with one step: every multiplier used below changes the
 * magnitude by far less than 2^480 */
GS_INLINE xnum xnorm(double x, int64_t ix)
{
    double w = fabs(x);
    if (w >= BIGS)
        return (xnum){x * BIGI, ix + 1};
    if (w < BIGSI)
        return (xnum){x * BIG, ix - 1};
    return (xnum){x, ix};
}

/* f X + g Y */
GS_INLINE xnum xlsum2(double f, xnum X, double g, xnum Y)
{
    int64_t d = X.i - Y.i;
    if (d == 0)
        return xnorm(f * X.x + g * Y.x, X.i);
    if (d == 1)
        return xnorm(f * X.x + g * (Y.x * BIGI), X.i);
    if (d == -1)
        return xnorm(g * Y.x + f * (X.x * BIGI), Y.i);
    if (d > 1)
        return xnorm(f * X.x, X.i);
    return xnorm(g * Y.x, Y.i);
}

GS_INLINE double x2f(xnum X)
{
    if (X.i == 0)
        return X.x;
    if (X.i == -1)
        return X.x * BIGI;
    if (X.i < -1)
        return 0.0;
    return X.x * BIG; /* never reached: |P̄nm| <= sqrt(2(2n+1)) */
}

/* out[n * ldo + m] = P̄nm(t) for m <= n <= nmax; AT, BT (recursion_tables) have rows of lda. */
GS_EXPORT void gs_plm_bar(int64_t nmax, double t, double u, const double *AT, const double *BT, int64_t lda,
                          double *out, int64_t ldo)
{
#define A_(m, n) AT[(m) * lda + (n)]
#define B_(m, n) BT[(m) * lda + (n)]
    xnum sm = {1.0, 0}; /* sectoral P̄mm */
    for (int64_t m = 0; m <= nmax; ++m) {
        if (m == 1)
            sm = xnorm(A_(0, 1) * u, 0);
        else if (m >= 2)
            sm = xnorm(sm.x * A_(m, m) * u, sm.i);
        out[m * ldo + m] = x2f(sm);
        if (m == nmax)
            break;
        xnum p1 = sm;
        xnum p = xnorm(A_(m, m + 1) * t * p1.x, p1.i);
        out[(m + 1) * ldo + m] = x2f(p);
        int64_t n = m + 2;
        while (n <= nmax && (p.i != 0 || p1.i != 0)) {
            xnum q = xlsum2(A_(m, n) * t, p, -B_(m, n), p1);
            p1 = p;
            p = q;
            out[n * ldo + m] = x2f(p);
            ++n;
        }
        double pd = p.x, pp = p1.x;
        while (n <= nmax) {
            double r = A_(m, n) * t * pd - B_(m, n) * pp;
            pp = pd;
            pd = r;
            out[n * ldo + m] = pd;
            ++n;
        }
    }
}

/* The coefficient sets CT, ST (K, ctm, ctn) and the recursion tables of every sum. */
typedef struct {
    int64_t nmax, K, ctm, ctn, lda;
    const uint8_t *radial;
    const double *CT, *ST, *AT, *BT;
} sums_setup;

/* Legendre sums of one latitude (legendre.column_sums): A[m], B[m] for m = 0..nmax;
 * w is scratch of K (nmax + 1). */
static void column_sums(const sums_setup *S, double t, double u, double q, const double *scale, double *A,
                        double *B, double *w)
{
    int64_t nmax = S->nmax, K = S->K, ctm = S->ctm, ctn = S->ctn, lda = S->lda;
    const double *AT = S->AT, *BT = S->BT;
#define C_(k, m, n) S->CT[((k) * ctm + (m)) * ctn + (n)]
#define S_(k, m, n) S->ST[((k) * ctm + (m)) * ctn + (n)]
#define W_(k, n) w[(k) * (nmax + 1) + (n)]
    for (int64_t k = 0; k < K; ++k) {
        if (S->radial[k]) {
            double qn = scale[k];
            for (int64_t n = 0; n <= nmax; ++n) {
                W_(k, n) = qn;
                qn *= q;
            }
        } else {
            for (int64_t n = 0; n <= nmax; ++n)
                W_(k, n) = scale[k];
        }
    }
    for (int64_t m = 0; m <= nmax; ++m) {
        A[m] = 0.0;
        B[m] = 0.0;
    }
    xnum sm = {1.0, 0};
    for (int64_t m = 0; m <= nmax; ++m) {
        if (m == 1) {
            if (u == 0.0)
                break; /* at the pole every P̄nm with m >= 1 vanishes */
            sm = xnorm(A_(0, 1) * u, 0);
        } else if (m >= 2) {
            sm = xnorm(sm.x * A_(m, m) * u, sm.i);
            if (sm.x == 0.0)
                break;
        }
        double sa = 0.0, sb = 0.0;
#define ACCUMULATE(nn, pv)                          \
    for (int64_t k = 0; k < K; ++k) {               \
        double wk = W_(k, nn) * (pv);               \
        sa += wk * C_(k, m, nn);                    \
        sb += wk * S_(k, m, nn);                    \
    }
        if (sm.i == 0)
            ACCUMULATE(m, sm.x)
        if (m < nmax) {
            xnum p1 = sm;
            xnum p = xnorm(A_(m, m + 1) * t * p1.x, p1.i);
            if (p.i == 0)
                ACCUMULATE(m + 1, p.x)
            int64_t n = m + 2;
            /* X-number phase: values below 2^-480 are carried but not summed */
            while (n <= nmax && (p.i != 0 || p1.i != 0)) {
                xnum qx = xlsum2(A_(m, n) * t, p, -B_(m, n), p1);
                p1 = p;
                p = qx;
                if (p.i == 0)
                    ACCUMULATE(n, p.x)
                ++n;
            }
            /* plain double phase (most of the work); two specialised loops for K = 1, 2 */
            double pd = p.x, pp = p1.x;
            if (K == 1) {
                for (; n <= nmax; ++n) {
                    double r = A_(m, n) * t * pd - B_(m, n) * pp;
                    pp = pd;
                    pd = r;
                    double wk = W_(0, n) * pd;
                    sa += wk * C_(0, m, n);
                    sb += wk * S_(0, m, n);
                }
            } else {
                for (; n <= nmax; ++n) {
                    double r = A_(m, n) * t * pd - B_(m, n) * pp;
                    pp = pd;
                    pd = r;
                    double w0 = W_(0, n) * pd, w1 = W_(1, n) * pd;
                    sa += w0 * C_(0, m, n) + w1 * C_(1, m, n);
                    sb += w0 * S_(0, m, n) + w1 * S_(1, m, n);
                }
            }
        }
        A[m] = sa;
        B[m] = sb;
    }
#undef ACCUMULATE
#undef W_
#undef S_
#undef C_
}

GS_EXPORT void gs_column_sums(int64_t nmax, double t, double u, double q, const double *scale, const uint8_t *radial,
                              int64_t K, const double *CT, const double *ST, int64_t ctm, int64_t ctn,
                              const double *AT, const double *BT, int64_t lda, double *A, double *B, double *w)
{
    sums_setup S = {nmax, K, ctm, ctn, lda, radial, CT, ST, AT, BT};
    column_sums(&S, t, u, q, scale, A, B, w);
}

/* Many latitudes (row_sums) or scattered points (point_sums): one task a row or point. */
typedef struct {
    sums_setup S;
    const double *t, *u, *q, *lam, *scale;
    int64_t lds, ldab;
    double *A, *B, *out;
    int failed;
} rows_job;

static void row_task(void *ctx, int64_t i)
{
    rows_job *J = ctx;
    double *w = malloc(sizeof(double) * (size_t)(J->S.K * (J->S.nmax + 1)));
    if (w == NULL) {
        __atomic_store_n(&J->failed, 1, __ATOMIC_RELAXED);
        return;
    }
    column_sums(&J->S, J->t[i], J->u[i], J->q[i], J->scale + i * J->lds, J->A + i * J->ldab, J->B + i * J->ldab, w);
    free(w);
}

/* Returns 0, or -1 when out of memory. */
GS_EXPORT int64_t gs_row_sums(int64_t nmax, const double *t, const double *u, const double *q, int64_t rows,
                              const double *scale, int64_t lds, const uint8_t *radial, int64_t K, const double *CT,
                              const double *ST, int64_t ctm, int64_t ctn, const double *AT, const double *BT,
                              int64_t lda, double *A, double *B, int64_t ldab, int64_t nthreads)
{
    rows_job J = {{nmax, K, ctm, ctn, lda, radial, CT, ST, AT, BT}, t, u, q, NULL, scale, lds, ldab, A, B, NULL, 0};
    gs_parallel_for((int)nthreads, rows, row_task, &J);
    return J.failed ? -1 : 0;
}

static void point_task(void *ctx, int64_t i)
{
    rows_job *J = ctx;
    int64_t nmax = J->S.nmax;
    if (isnan(J->t[i]) || isnan(J->lam[i])) {
        J->out[i] = NAN;
        return;
    }
    double *w = malloc(sizeof(double) * (size_t)((J->S.K + 2) * (nmax + 1)));
    if (w == NULL) {
        __atomic_store_n(&J->failed, 1, __ATOMIC_RELAXED);
        return;
    }
    double *A = w + J->S.K * (nmax + 1), *B = A + (nmax + 1);
    column_sums(&J->S, J->t[i], J->u[i], J->q[i], J->scale + i * J->lds, A, B, w);
    double total = 0.0, lam = J->lam[i];
    for (int64_t m = nmax; m > 0; --m) { /* small terms first */
        double ml = (double)m * lam;
        total += A[m] * cos(ml) + B[m] * sin(ml);
    }
    J->out[i] = total + A[0];
    free(w);
}

/* Returns 0, or -1 when out of memory. */
GS_EXPORT int64_t gs_point_sums(int64_t nmax, const double *t, const double *u, const double *q, const double *lam,
                                int64_t points, const double *scale, int64_t lds, const uint8_t *radial, int64_t K,
                                const double *CT, const double *ST, int64_t ctm, int64_t ctn, const double *AT,
                                const double *BT, int64_t lda, double *out, int64_t nthreads)
{
    rows_job J = {{nmax, K, ctm, ctn, lda, radial, CT, ST, AT, BT}, t, u, q, lam, scale, lds, 0, NULL, NULL, out, 0};
    gs_parallel_for((int)nthreads, points, point_task, &J);
    return J.failed ? -1 : 0;
}
