/* Shared pieces of geoidspline's compiled kernels: key packing, binary search, Python's
 * float modulo, cardinal B-spline weights and the thread fan-out (gs_parallel.c).
 *
 * Conventions are those of geoidspline/_kernels/__init__.py: a level is a uniform grid of
 * spacing h; B-spline k of order n is prod_d B_n(x_d/h - k_d); coefficient indices are packed
 * into one int64 key, GS_KEY_BITS bits an axis, offset by GS_KEY_OFFSET (layout.py).
 *
 * Floating point: compiled with -ffp-contract=off and without -ffast-math, so every sum is
 * evaluated in the order written (the values are reproducible across builds and threads).
 */
#ifndef GS_COMMON_H
#define GS_COMMON_H

#include <math.h>
#include <stdint.h>
#include <stddef.h>

#define GS_KEY_BITS 21
#define GS_KEY_OFFSET (((int64_t)1) << (GS_KEY_BITS - 1))
#define GS_KEY_MASK ((((int64_t)1) << GS_KEY_BITS) - 1)

#define GS_EXPORT __attribute__((visibility("default")))
#define GS_INLINE static inline __attribute__((always_inline))

GS_INLINE int64_t gs_pack(int64_t i, int64_t j, int64_t k)
{
    return ((i + GS_KEY_OFFSET) << (2 * GS_KEY_BITS)) | ((j + GS_KEY_OFFSET) << GS_KEY_BITS) | (k + GS_KEY_OFFSET);
}

/* First position in sorted keys[0..n) whose key is >= value (n if none). */
GS_INLINE int64_t gs_lower_bound(const int64_t *keys, int64_t n, int64_t value)
{
    int64_t lo = 0, hi = n;
    while (lo < hi) {
        int64_t mid = (lo + hi) >> 1;
        if (keys[mid] < value)
            lo = mid + 1;
        else
            hi = mid;
    }
    return lo;
}

/* Python's float a % b (the result takes the sign of b), as numpy and numba compute it. */
GS_INLINE double gs_pymod(double a, double b)
{
    double mod = fmod(a, b);
    if (mod != 0.0) {
        if ((b < 0.0) != (mod < 0.0))
            mod += b;
    } else {
        mod = copysign(0.0, b);
    }
    return mod;
}

/* The weights w[d * ld + j] (d = 0..nderiv <= 2, derivatives with respect to x/h) of the
 * order B-splines touching a point at t in [0, 1) of its cell: j weighs B-spline
 * k = a - order + 1 + j. Closed forms for the values of orders 4 and 6, the uniform-knot
 * de Boor recursion otherwise and for derivatives: work[q][j] = ((t+q-1-j) work[q-1][j-1]
 * + (1+j-t) work[q-1][j]) / (q-1), B_q' = B_{q-1}(x) - B_{q-1}(x-1). Inline, so a caller
 * with a constant order gets its own specialisation. order <= GS_MAX_ORDER. */
#define GS_MAX_ORDER 16
/* The closed forms of the order-4 and order-6 weights (values, nderiv 0) for t of type T:
 * double, or a GCC vector of doubles (query.c computes the three axes of a point in one
 * vector, lane by lane the same operations, so the same bits). */
#define GS_WEIGHTS4(T, t, w0, w1, w2, w3)                                                                             \
    do {                                                                                                              \
        T s_ = 1.0 - (t), t2_ = (t) * (t), t3_ = t2_ * (t);                                                           \
        w0 = s_ * s_ * s_ / 6.0;                                                                                      \
        w1 = (3.0 * t3_ - 6.0 * t2_ + 4.0) / 6.0;                                                                     \
        w2 = (-3.0 * t3_ + 3.0 * t2_ + 3.0 * (t) + 1.0) / 6.0;                                                        \
        w3 = t3_ / 6.0;                                                                                               \
    } while (0)
#define GS_WEIGHTS6(T, t, w0, w1, w2, w3, w4, w5)                                                                     \
    do {                                                                                                              \
        T s_ = 1.0 - (t), t2_ = (t) * (t), t3_ = t2_ * (t), t4_ = t2_ * t2_, t5_ = t4_ * (t);                         \
        const double c_ = 1.0 / 120.0;                                                                                \
        w0 = s_ * s_ * s_ * s_ * s_ * c_;                                                                             \
        w1 = (26.0 - 50.0 * (t) + 20.0 * t2_ + 20.0 * t3_ - 20.0 * t4_ + 5.0 * t5_) * c_;                             \
        w2 = (66.0 - 60.0 * t2_ + 30.0 * t4_ - 10.0 * t5_) * c_;                                                      \
        w3 = (26.0 + 50.0 * (t) + 20.0 * t2_ - 20.0 * t3_ - 20.0 * t4_ + 10.0 * t5_) * c_;                            \
        w4 = (1.0 + 5.0 * (t) + 10.0 * t2_ + 10.0 * t3_ + 5.0 * t4_ - 5.0 * t5_) * c_;                                \
        w5 = t5_ * c_;                                                                                                \
    } while (0)
GS_INLINE void gs_weights(double t, const int order, const int nderiv, double *w, const int64_t ld)
{
    if (order == 4) {
        double s = 1.0 - t, t2 = t * t; /* the derivatives' */
        GS_WEIGHTS4(double, t, w[0], w[1], w[2], w[3]);
        if (nderiv >= 1) {
            w[ld + 0] = -0.5 * s * s;
            w[ld + 1] = 1.5 * t2 - 2.0 * t;
            w[ld + 2] = -1.5 * t2 + t + 0.5;
            w[ld + 3] = 0.5 * t2;
        }
        if (nderiv >= 2) {
            w[2 * ld + 0] = s;
            w[2 * ld + 1] = 3.0 * t - 2.0;
            w[2 * ld + 2] = 1.0 - 3.0 * t;
            w[2 * ld + 3] = t;
        }
        return;
    }
    /* work[q][j]: the order-q weights, up to the order needed */
    int top = order == 6 ? (nderiv >= 1 ? 5 : 0) : order;
    double work[GS_MAX_ORDER + 1][GS_MAX_ORDER + 1];
    if (top > 0) {
        work[1][0] = 1.0;
        for (int q = 2; q <= top; ++q)
            for (int j = 0; j < q; ++j) {
                double left = j >= 1 ? work[q - 1][j - 1] : 0.0;
                double right = j <= q - 2 ? work[q - 1][j] : 0.0;
                work[q][j] = ((t + q - 1 - j) * left + (1 + j - t) * right) / (q - 1);
            }
    }
    if (order == 6) {
        GS_WEIGHTS6(double, t, w[0], w[1], w[2], w[3], w[4], w[5]);
    } else {
        for (int j = 0; j < order; ++j)
            w[j] = work[order][j];
    }
    if (nderiv >= 1) {
        int q = order - 1;
        for (int j = 0; j < order; ++j) {
            double left = j >= 1 ? work[q][j - 1] : 0.0;
            double right = j <= q - 1 ? work[q][j] : 0.0;
            w[ld + j] = left - right;
        }
    }
    if (nderiv >= 2) {
        int q = order - 2;
        for (int j = 0; j < order; ++j) {
            double a = j >= 2 ? work[q][j - 2] : 0.0;
            double b = (j >= 1 && j - 1 <= q - 1) ? work[q][j - 1] : 0.0;
            double c = j <= q - 1 ? work[q][j] : 0.0;
            w[2 * ld + j] = a - 2.0 * b + c;
        }
    }
}


/* Run fn(ctx, task) for task = 0..ntasks-1 on up to nthreads threads (the caller's thread
 * among them), tasks handed out one at a time from a shared counter; returns when all are
 * done. Threads are started per call and joined, so no state survives a call (fork-safe).
 * (gs_parallel.c) */
typedef void (*gs_task_fn)(void *ctx, int64_t task);
void gs_parallel_for(int nthreads, int64_t ntasks, gs_task_fn fn, void *ctx);

#endif
