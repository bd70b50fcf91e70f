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

/* Cardinal B-spline values (and derivatives d = 1..nderiv, with respect to x/h) of the
 * order B-splines touching a point at t in [0, 1) of its cell: out[d * ld + j] weights
 * B-spline k = a - order + 1 + j. order <= GS_MAX_ORDER. (common.c) */
#define GS_MAX_ORDER 16
void gs_bspline_weights(double t, int order, int nderiv, double *out, int64_t ld);

/* Run fn(ctx, task) for task = 0..ntasks-1 on up to nthreads threads (the caller's thread
 * among them), tasks handed out one at a time from a shared counter; returns when all are
 * done. Threads are started per call and joined, so no state survives a call (fork-safe).
 * (gs_parallel.c) */
typedef void (*gs_task_fn)(void *ctx, int64_t task);
void gs_parallel_for(int nthreads, int64_t ntasks, gs_task_fn fn, void *ctx);

#endif
