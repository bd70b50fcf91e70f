/* Kernels of queries: the brick index, its evaluation and batches of latitude/longitude
 * (geoidspline/_kernels/query.py calls them through ctypes; conventions in gs_common.h).
 *
 * A spline's query tables travel as one gs_spline record (query.py's Spline mirrors it).
 * Evaluation is written once, with the spline order and the number of derivatives as
 * parameters of always-inline functions; the callers switch on them with constants
 * (order 4, 6 or any), so the compiler emits one specialised loop per case from one
 * definition. The hot loops are built twice (x86-64-v3 and baseline, chosen at load time
 * by the CPU) when the compiler can: both give the same bits, as -ffp-contract=off keeps
 * every product and sum as written and no sum is reassociated.
 */
#include <stdlib.h>
#include <string.h>

#include "gs_common.h"

/* Python's build flags add -fwrapv (defined signed overflow); it keeps GCC from folding
 * the index arithmetic of the evaluation loops and cost 15 % of a batch's time (2 mm
 * store). Nothing here relies on signed overflow. */
#pragma GCC optimize("no-wrapv")
/* vectors passed between always-inline functions: no ABI is involved */
#pragma GCC diagnostic ignored "-Wpsabi"

#define BRICK_BITS 4
#define BRICK_MASK ((1 << BRICK_BITS) - 1)
#define COL_KBITS 5 /* a column entry: run offset << COL_SHIFT | first local k << COL_KBITS | length */
#define COL_SHIFT (2 * COL_KBITS)
#define COL_KMASK ((1 << COL_KBITS) - 1)
#define PRESENCE_CELL 0.125
#define PRESENCE_SIDE 20
#define HASH_MULT 0x9E3779B97F4A7C15ULL
#define CHUNK 4096 /* points per task of the evaluation loops */

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && !defined(GS_NO_CLONES)
#define GS_HOT __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define GS_HOT
#endif

/* The query tables of one spline (geoidspline.bspline.index.BrickIndex); levels coarse to
 * fine. Mirrored field for field by query.py's Spline. */
typedef struct {
    int64_t order, nlev, side;
    const double *inv_hs, *band_lo2, *band_hi2; /* per level: 1/h, band |x|^2 bounds */
    const uint8_t *presence;                    /* (nlev, PRESENCE_SIDE^3) */
    const int64_t *slots;                       /* (capacity, 2): brick key, brick index */
    const int64_t *slot_start, *slot_mask;      /* per level */
    const int64_t *fold_base, *own_base;        /* per brick: first value of its table */
    const int32_t *fold_cols, *own_cols;        /* (bricks, side, side) column entries */
    const double *values;
    /* (bricks, side, side) per column: run offset - first k; int32, or int16 with quantised
     * values (qwidth != 0: column_offset; a brick holds at most side^3 < 2^15 values) */
    const void *fold_offs, *own_offs;
    const uint16_t *fold_full, *own_full;       /* (bricks, S, S) per cell column: bit lz = all columns full */
    /* Quantised tables (qwidth 2 or 4; values then unused): the coefficient at value
     * position v of brick b is (double)(qbase[b] + qvalues[v]) * value_step, bitwise what
     * a store's decoder gives (codec.py: int32 q times the step); qvalues int16 (qwidth 2)
     * or int32 (4, qbase 0): 2 or 4 bytes a value, not 8. With qwidth 2 a brick whose
     * values span more than 65,535 steps holds them as int32 (qbase QBASE_WIDE, as 0),
     * two int16 slots each: the bases (fold_base, own_base) count qwidth-byte slots. */
    const void *qvalues;
    const int32_t *qbase; /* per brick */
    double value_step;
    int64_t qwidth; /* 0: float64 values */
    /* per brick: the values of its folded table (float64 tables beyond the caches: the
     * batches' bricks ahead are prefetched, see prefetch_bricks), else NULL */
    const int64_t *fold_size;
} gs_spline;

#define QBASE_WIDE INT32_MIN /* qbase of a brick of int32 values in an int16 table */

/* ---- the brick hash --------------------------------------------------------------- */

GS_INLINE int64_t hash_slot(int64_t key, int64_t mask)
{
    return (int64_t)((((uint64_t)key * HASH_MULT) >> 32) & (uint64_t)mask);
}

/* Open-addressing table (linear probing) from key to its position: slots (capacity, 2),
 * capacity a power of two > n; a probe reads one 16-byte slot. */
GS_EXPORT void gs_build_hash(const int64_t *keys, int64_t n, int64_t *slots, int64_t capacity)
{
    int64_t mask = capacity - 1;
    for (int64_t s = 0; s < 2 * capacity; ++s)
        slots[s] = -1;
    for (int64_t pos = 0; pos < n; ++pos) {
        int64_t s = hash_slot(keys[pos], mask);
        while (slots[2 * s] != -1)
            s = (s + 1) & mask;
        slots[2 * s] = keys[pos];
        slots[2 * s + 1] = pos;
    }
}

GS_INLINE int64_t hash_find(const int64_t *slots, int64_t mask, int64_t key)
{
    int64_t s = hash_slot(key, mask);
    for (;;) {
        int64_t k = slots[2 * s];
        if (k == key)
            return slots[2 * s + 1];
        if (k == -1)
            return -1;
        s = (s + 1) & mask;
    }
}

/* Whether level lev may have a brick at the point (0: it has none there); outside the
 * presence map's cube [-1.25, 1.25)^3 the hash probe decides. */
GS_INLINE int present(const gs_spline *S, int64_t lev, double x, double y, double z)
{
    double fi = floor(x / PRESENCE_CELL) + PRESENCE_SIDE / 2;
    double fj = floor(y / PRESENCE_CELL) + PRESENCE_SIDE / 2;
    double fk = floor(z / PRESENCE_CELL) + PRESENCE_SIDE / 2;
    if (!(fi >= 0.0 && fj >= 0.0 && fk >= 0.0 && fi < PRESENCE_SIDE && fj < PRESENCE_SIDE && fk < PRESENCE_SIDE))
        return 1;
    int64_t i = (int64_t)fi, j = (int64_t)fj, k = (int64_t)fk;
    return S->presence[((lev * PRESENCE_SIDE + i) * PRESENCE_SIDE + j) * PRESENCE_SIDE + k] != 0;
}

/* ---- evaluation ------------------------------------------------------------------- */

/* Lanes: order doubles (one per z index r) held in vector registers, 4 to a vector, then
 * a pair, then one; GCC's vector extensions, so every lane is its own scalar sum (the
 * same bits in the baseline and x86-64-v3 builds). When order % 4 == 2 (order 6), the
 * pair is the top half of a last vector of 4 lanes overlapping the one before (lanes
 * order - 4 .. order - 1): each column is then two loads of 4 and the y weight's
 * broadcast serves both (lanes order - 4, order - 3 are summed twice, their second sum
 * unused). */
typedef double gs_v4 __attribute__((vector_size(32)));
typedef double gs_v2 __attribute__((vector_size(16)));
typedef struct {
    gs_v4 v[GS_MAX_ORDER / 4];
    gs_v4 over; /* LANE_OVER: lanes order - 4 .. order - 1 */
    gs_v2 pair;
    double one;
} lanes;

#define LANE_V(order) ((order) / 4)
#define LANE_OVER(order) (((order) % 4) == 2 && (order) > 4)
#define LANE_PAIR(order) (((order) % 4) >= 2 && !LANE_OVER(order))
#define LANE_ONE(order) (((order) % 2) == 1)

GS_INLINE void lanes_zero(const int order, lanes *a)
{
    for (int k = 0; k < LANE_V(order); ++k)
        a->v[k] = (gs_v4){0.0, 0.0, 0.0, 0.0};
    a->over = (gs_v4){0.0, 0.0, 0.0, 0.0};
    a->pair = (gs_v2){0.0, 0.0};
    a->one = 0.0;
}

/* a += w c for c order contiguous doubles */
GS_INLINE void lanes_axpy(const int order, lanes *a, double w, const double *c)
{
    for (int k = 0; k < LANE_V(order); ++k) {
        gs_v4 x;
        memcpy(&x, c + 4 * k, sizeof x);
        a->v[k] += w * x;
    }
    if (LANE_OVER(order)) {
        gs_v4 x;
        memcpy(&x, c + order - 4, sizeof x);
        a->over += w * x;
    }
    if (LANE_PAIR(order)) {
        gs_v2 x;
        memcpy(&x, c + 4 * LANE_V(order), sizeof x);
        a->pair += w * x;
    }
    if (LANE_ONE(order))
        a->one += w * c[order - 1];
}

/* Coefficient i of a quantised table's values qv (quant: 2 int16, 4 int32): (double)(qb +
 * q) * step, the decoder's product (gs_spline). */
GS_INLINE double dequantised_at(const int quant, const void *qv, int64_t i, int32_t qb, double step)
{
    int32_t q = quant == 2 ? (int32_t)((const int16_t *)qv)[i] : ((const int32_t *)qv)[i];
    return (double)(qb + q) * step;
}

/* The integers q of order coefficients of a quantised table (quant 2: int16, 4: int32)
 * at qv + at, as doubles in lanes (laid out as lanes_axpy reads a column; exact: |q| <
 * 2**31): the full-column sums add w q, and table_sum scales the sum by the step and adds
 * the brick's base once (see there), instead of (qb + q) step per coefficient. Converted
 * in vector registers (a column converted into memory and loaded back as vectors waits
 * on store forwarding: 3 times slower).
 *
 * int16 q is widened to int64 lanes by the build chosen at run time (sx, see GS_SX): 0
 * (the target clones) a broadcast and two shifts (GCC 12 widens int16 vectors one lane
 * at a time through general registers), 1 (AVX2) one vpmovsxwq from memory; then the
 * magic-number conversion: q + the bits of 1.5 2**52 is the bit pattern of the double
 * 1.5 2**52 + q (its mantissa field 2**51 + q does not carry), minus 1.5 2**52 exactly q.
 * 2 (AVX-512DQ): vpmovsxwq, then vcvtqq2pd. Every build gives the same doubles. */
typedef int32_t gs_i32x4 __attribute__((vector_size(16)));
typedef int32_t gs_i32x2 __attribute__((vector_size(8)));
typedef int64_t gs_i64x4 __attribute__((vector_size(32)));
typedef int64_t gs_i64x2 __attribute__((vector_size(16)));
typedef uint64_t gs_u64x4 __attribute__((vector_size(32)));
typedef uint64_t gs_u64x2 __attribute__((vector_size(16)));
#define DEQUANT_MAGIC 6755399441055744.0           /* 1.5 2**52 */
#define DEQUANT_MAGIC_BITS 0x4338000000000000LL    /* its bits */

/* The widening instructions in the hot loop: vpmovsxwq (AVX2) and vcvtqq2pd (AVX-512DQ),
 * which GCC emits only from intrinsics or asm, and neither compiles in the baseline clone
 * of a target_clones function. So the quantised table sums are built twice more as
 * functions for those instruction sets (GS_QUANTISED_SUMS, sx = 1 and 2, the asm), chosen
 * at run time by what the CPU has (gs_sx_level). The asm is in branches on a constant
 * that the baseline builds fold away, which needs optimisation: an -O0 build
 * (__OPTIMIZE__ undefined) has the target clones only. */
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && defined(__OPTIMIZE__)
#define GS_SX 1
#else
#define GS_SX 0
#endif
typedef uint64_t gs_u64_alias __attribute__((may_alias));

GS_INLINE gs_v4 widened4(const int quant, const int sx, const void *qv, int64_t at)
{
    if (quant == 2) {
        gs_i64x4 q;
#if GS_SX
        if (sx) {
            __asm__("vpmovsxwq %1, %0" : "=x"(q) : "m"(*(const gs_u64_alias *)((const int16_t *)qv + at)));
            if (sx == 2) {
                gs_v4 d;
                __asm__("vcvtqq2pd %1, %0" : "=x"(d) : "x"(q));
                return d;
            }
            return (gs_v4)(q + DEQUANT_MAGIC_BITS) - DEQUANT_MAGIC;
        }
#endif
        /* the 4 int16 in every lane, each lane's own moved to the top and shifted back
         * down with its sign (vpbroadcastq, vpsllvq, vpsraq) */
        uint64_t x;
        memcpy(&x, (const int16_t *)qv + at, sizeof x);
        const gs_u64x4 up = {48, 32, 16, 0};
        q = (gs_i64x4)((gs_u64x4){x, x, x, x} << up) >> 48;
        return (gs_v4)(q + DEQUANT_MAGIC_BITS) - DEQUANT_MAGIC;
    }
    gs_i32x4 q; /* int32: their own conversion (vcvtdq2pd) */
    memcpy(&q, (const int32_t *)qv + at, sizeof q);
    return __builtin_convertvector(q, gs_v4);
}

GS_INLINE void lanes_widened(const int order, const int quant, const int sx, const void *qv, int64_t at, lanes *c)
{
    for (int k = 0; k < LANE_V(order); ++k)
        c->v[k] = widened4(quant, sx, qv, at + 4 * k);
    if (LANE_OVER(order))
        c->over = widened4(quant, sx, qv, at + order - 4);
    if (LANE_PAIR(order)) {
        if (quant == 2) {
            uint32_t x;
            memcpy(&x, (const int16_t *)qv + at + 4 * LANE_V(order), sizeof x);
            const gs_u64x2 up = {48, 32};
            gs_i64x2 q = (gs_i64x2)((gs_u64x2){x, x} << up) >> 48;
            c->pair = (gs_v2)(q + DEQUANT_MAGIC_BITS) - DEQUANT_MAGIC;
        } else {
            gs_i32x2 q;
            memcpy(&q, (const int32_t *)qv + at + 4 * LANE_V(order), sizeof q);
            c->pair = __builtin_convertvector(q, gs_v2);
        }
    }
    if (LANE_ONE(order))
        c->one = quant == 2 ? (double)((const int16_t *)qv)[at + order - 1] : (double)((const int32_t *)qv)[at + order - 1];
}

/* a += w b */
GS_INLINE void lanes_add(const int order, lanes *a, double w, const lanes *b)
{
    for (int k = 0; k < LANE_V(order); ++k)
        a->v[k] += w * b->v[k];
    if (LANE_OVER(order))
        a->over += w * b->over;
    if (LANE_PAIR(order))
        a->pair += w * b->pair;
    if (LANE_ONE(order))
        a->one += w * b->one;
}

/* sum_r w[r ws] a[r], r in order (ws: the weights' stride) */
GS_INLINE double lanes_dot(const int order, const lanes *a, const double *w, const int ws)
{
    double s = 0.0;
    for (int k = 0; k < LANE_V(order); ++k)
        for (int j = 0; j < 4; ++j)
            s += w[(4 * k + j) * ws] * a->v[k][j];
    if (LANE_OVER(order)) {
        s += w[(order - 2) * ws] * a->over[2];
        s += w[(order - 1) * ws] * a->over[3];
    }
    if (LANE_PAIR(order)) {
        s += w[4 * LANE_V(order) * ws] * a->pair[0];
        s += w[(4 * LANE_V(order) + 1) * ws] * a->pair[1];
    }
    if (LANE_ONE(order))
        s += w[(order - 1) * ws] * a->one;
    return s;
}

/* order coefficients of a quantised table from qv + at into pad */
GS_INLINE const double *dequantised(const int order, const int quant, const void *qv, int64_t at, int32_t qb,
                                    double step, double *pad)
{
    for (int r = 0; r < order; ++r)
        pad[r] = dequantised_at(quant, qv, at + r, qb, step);
    return pad;
}

/* The bytes of a quantised spline's column offsets (2: int16; before 2026-12-06 int32, 4):
 * benchmarks/query_ab.py gives older libraries int32 ones. */
GS_EXPORT int64_t gs_quantised_offs_width(void)
{
    return 2;
}

/* Entry i of a table's column offsets (gs_spline's *_offs): int16 with quantised values
 * (quant), else int32: a point's order rows of offsets, side apart, span half the bytes
 * and about half the cache lines (tables beyond the caches: benchmarks/README.md). */
GS_INLINE int64_t column_offset(const int quant, const void *offs, int64_t i)
{
    return quant ? (int64_t)((const int16_t *)offs)[i] : (int64_t)((const int32_t *)offs)[i];
}

/* The first of the order coefficients k = lz .. lz + order - 1 of column entry packed
 * (a run of length coefficients from local k0 at values + run offset), or pad filled with
 * them and zeros where the run does not reach; NULL when the column is empty. quant: the
 * table is quantised (qv, qb, step; see gs_spline), the coefficients always go to pad. */
GS_INLINE const double *column_run(const int order, const int quant, const double *values, const void *qv,
                                   int32_t qb, double step, int32_t packed, int64_t lz, double *pad)
{
    int64_t length = packed & COL_KMASK;
    if (length == 0)
        return NULL;
    int64_t start = lz - ((packed >> COL_KBITS) & COL_KMASK);
    int64_t offset = (int64_t)(packed >> COL_SHIFT) + start;
    if (start >= 0 && start + order <= length)
        return quant ? dequantised(order, quant, qv, offset, qb, step, pad) : values + offset;
    for (int r = 0; r < order; ++r)
        pad[r] = (start + r >= 0 && start + r < length)
                     ? (quant ? dequantised_at(quant, qv, offset + r, qb, step) : values[offset + r])
                     : 0.0;
    return pad;
}

/* Add one brick table's spline (and derivatives) at a point into result.
 *
 * The table's column (p, q) is a run of coefficients along z. Sums go per z lane r,
 * separably: B_p[r] = sum_q wy_q c_pqr, A[r] = sum_p wx_p B_p[r], then value = sum_r
 * wz_r A[r] (and the same with derivative weights): a column is order contiguous doubles
 * added into vector lanes, rows p are independent chains (short add latencies).
 *
 * full (a constant): the point's cell column has its bit lz set in the table's full map,
 * so every one of the order^2 columns holds k = lz .. lz + order - 1 and the column
 * (p, q) starts at values + offs[p][q] + lz: no decoding and no branch per column (most
 * points: a folded table covers its band whole). Otherwise each column is decoded from
 * its entry (column_run), an empty one skipped, one cut by the run's end read through a
 * zero-padded copy. Both add the same products in the same order (the same bits).
 *
 * Quantised tables (quant): the decoding path sums the decoder's coefficients (qb + q)
 * step, bitwise as the float64 tables; the full-column path sums w q and adds qb step
 * once (the weights sum to 1, to 0 for derivatives): per coefficient a conversion
 * instead of an addition, a conversion and a product (benchmarks/README.md); the two
 * differ by a few units in the last place of the largest coefficient (below 1e-13 m for
 * a geoid's +-110 m; tests/test_query_index.py). */
GS_INLINE void table_sum(const gs_spline *S, const int order, const int nderiv, const int full, const int quant,
                         const int sx, const double *wx, const double *wy, const double *wz, const int ws, int64_t base,
                         const int32_t *cols, const void *offs,
                         int64_t brick, int64_t lx, int64_t ly, int64_t lz, double inv_h, double *result)
{
    const int64_t side = (1 << BRICK_BITS) + order - 1;
    const int64_t col_at = (brick * side + lx) * side + ly;
    /* quant (a constant): the table's values are quantised, width 2 (int16) or 4 (int32)
     * bytes (see gs_spline: this brick's own, a wide brick of an int16 table int32); else
     * float64 */
    int width = quant ? (int)S->qwidth : 0;
    int32_t qb = width ? S->qbase[brick] : 0;
    const void *qv = width ? (const void *)((const char *)S->qvalues + S->qwidth * base) : NULL;
    if (quant && qb == QBASE_WIDE) {
        width = 4;
        qb = 0;
    }
    const double *values = width ? NULL : S->values + base;
    const double *values_lz = width ? NULL : values + lz;
    /* the column address as one register plus the column's offset (a load's base and
     * index): without this GCC adds base + lz to each offset, one more instruction a column */
    if (!width)
        __asm__("" : "+r"(values_lz));
    const double step = S->value_step;
    /* A per derivative (x, y): 00 value; 10 01 first; 20 02 11 second */
    lanes a00, a10, a01, a20, a02, a11;
    double pad[GS_MAX_ORDER];
    lanes_zero(order, &a00);
    if (nderiv >= 1) {
        lanes_zero(order, &a10);
        lanes_zero(order, &a01);
    }
    if (nderiv >= 2) {
        lanes_zero(order, &a20);
        lanes_zero(order, &a02);
        lanes_zero(order, &a11);
    }
    for (int p = 0; p < order; ++p) {
        lanes b0, b1, b2; /* B_p with the y weights of derivative 0, 1, 2 */
        lanes_zero(order, &b0);
        if (nderiv >= 1)
            lanes_zero(order, &b1);
        if (nderiv >= 2)
            lanes_zero(order, &b2);
        for (int q = 0; q < order; ++q) {
            const double *c;
            if (full && quant) {
                lanes col;
                lanes_zero(order, &col); /* the lanes it does not fill (unread: for the compiler) */
                lanes_widened(order, width, sx, qv, lz + column_offset(1, offs, col_at + p * side + q), &col);
                lanes_add(order, &b0, wy[q * ws], &col);
                if (nderiv >= 1)
                    lanes_add(order, &b1, wy[(order + q) * ws], &col);
                if (nderiv >= 2)
                    lanes_add(order, &b2, wy[(2 * order + q) * ws], &col);
                continue;
            }
            if (full) {
                c = values_lz + column_offset(quant, offs, col_at + p * side + q);
            } else {
                c = column_run(order, width, values, qv, qb, step, cols[col_at + p * side + q], lz, pad);
                if (c == NULL)
                    continue;
            }
            lanes_axpy(order, &b0, wy[q * ws], c);
            if (nderiv >= 1)
                lanes_axpy(order, &b1, wy[(order + q) * ws], c);
            if (nderiv >= 2)
                lanes_axpy(order, &b2, wy[(2 * order + q) * ws], c);
        }
        lanes_add(order, &a00, wx[p * ws], &b0);
        if (nderiv >= 1) {
            lanes_add(order, &a10, wx[(order + p) * ws], &b0);
            lanes_add(order, &a01, wx[p * ws], &b1);
        }
        if (nderiv >= 2) {
            lanes_add(order, &a20, wx[(2 * order + p) * ws], &b0);
            lanes_add(order, &a02, wx[p * ws], &b2);
            lanes_add(order, &a11, wx[(order + p) * ws], &b1);
        }
    }
    /* quantised full columns summed w q: times the step, plus the brick's base once (qb
     * step times the weights' sum, 1; the derivative weights sum to 0); scale 1 folds away */
    const double scale = full && quant ? step : 1.0;
    const double value = lanes_dot(order, &a00, wz, ws);
    result[0] += full && quant ? value * step + (double)qb * step : value;
    if (nderiv >= 1) {
        const double ih = inv_h * scale;
        result[1] += lanes_dot(order, &a10, wz, ws) * ih;
        result[2] += lanes_dot(order, &a01, wz, ws) * ih;
        result[3] += lanes_dot(order, &a00, wz + order * ws, ws) * ih;
    }
    if (nderiv >= 2) {
        const double ih2 = inv_h * inv_h * scale;
        result[4] += lanes_dot(order, &a20, wz, ws) * ih2;
        result[5] += lanes_dot(order, &a02, wz, ws) * ih2;
        result[6] += lanes_dot(order, &a00, wz + 2 * order * ws, ws) * ih2;
        result[7] += lanes_dot(order, &a11, wz, ws) * ih2;
        result[8] += lanes_dot(order, &a10, wz + order * ws, ws) * ih2;
        result[9] += lanes_dot(order, &a01, wz + order * ws, ws) * ih2;
    }
}

/* One brick table at a point: the full-column sum where the table's full map allows it,
 * the decoding one otherwise (quant: from quantised values). */
GS_INLINE void table_sums(const gs_spline *S, const int order, const int nderiv, const int quant, const int sx,
                          const double *wx, const double *wy, const double *wz, const int ws, int64_t base,
                          const int32_t *cols, const void *offs, const uint16_t *full, int64_t brick, int64_t lx,
                          int64_t ly, int64_t lz, double inv_h, double *result)
{
    if ((full[(brick << (2 * BRICK_BITS)) + (lx << BRICK_BITS) + ly] >> lz) & 1)
        table_sum(S, order, nderiv, 1, quant, sx, wx, wy, wz, ws, base, cols, offs, brick, lx, ly, lz, inv_h, result);
    else
        table_sum(S, order, nderiv, 0, quant, sx, wx, wy, wz, ws, base, cols, offs, brick, lx, ly, lz, inv_h, result);
}

/* table_sums of quantised tables, one function per (order, nderiv) that the callers call
 * (inlined into each of them, like the float64 one, it tripled the kernels' compile
 * time); order 0: any order, given as order_. Each three times with GS_SX: the target
 * clones, an AVX2 function (name_sx1: vpmovsxwq) and an AVX-512DQ one (name_sx2:
 * vcvtqq2pd), chosen by brick_sum (see widened4). */
#define GS_QUANTISED_SUMS_AS(o, d, name, attributes, sx)                                                              \
    attributes static void name(const gs_spline *S, int order_, const double *wx, const double *wy, const double *wz, \
                                int ws, int64_t base, const int32_t *cols, const void *offs, const uint16_t *full,    \
                                int64_t brick, int64_t lx, int64_t ly, int64_t lz, double inv_h, double *result)      \
    {                                                                                                                 \
        table_sums(S, (o) ? (o) : order_, d, 1, sx, wx, wy, wz, ws, base, cols, offs, full, brick, lx, ly, lz, inv_h, \
                   result);                                                                                           \
    }
#if GS_SX
#define GS_QUANTISED_SUMS(o, d)                                                                                       \
    GS_QUANTISED_SUMS_AS(o, d, quantised_sums_##o##_##d, GS_HOT, 0)                                                  \
    GS_QUANTISED_SUMS_AS(o, d, quantised_sums_##o##_##d##_sx1, __attribute__((target("avx2"))), 1)               \
    GS_QUANTISED_SUMS_AS(o, d, quantised_sums_##o##_##d##_sx2,                                                       \
                         __attribute__((target("avx2,avx512f,avx512dq,avx512vl"))), 2)
#else
#define GS_QUANTISED_SUMS(o, d) GS_QUANTISED_SUMS_AS(o, d, quantised_sums_##o##_##d, GS_HOT, 0)
#endif
GS_QUANTISED_SUMS(4, 0)
GS_QUANTISED_SUMS(4, 1)
GS_QUANTISED_SUMS(4, 2)
GS_QUANTISED_SUMS(6, 0)
GS_QUANTISED_SUMS(6, 1)
GS_QUANTISED_SUMS(6, 2)
GS_QUANTISED_SUMS(0, 0)
GS_QUANTISED_SUMS(0, 1)
GS_QUANTISED_SUMS(0, 2)

#if GS_SX
/* the widest build of the quantised sums this CPU runs (see widened4): 2 AVX-512DQ (and
 * VL), 1 AVX2, 0 the target clones */
static int cpu_sx_level(void)
{
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx512dq") && __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx2"))
        return 2;
    return __builtin_cpu_supports("avx2") ? 1 : 0;
}

/* the build the quantised sums run as, found when the library loads */
static int gs_sx_level;
__attribute__((constructor)) static void gs_sx_detect(void)
{
    gs_sx_level = cpu_sx_level();
}
#endif

/* Which build the quantised sums run as (widened4's sx: 0 the target clones, 1 AVX2, 2
 * AVX-512DQ): level >= 0 sets the widest allowed (as far as the CPU has it; tests compare
 * the builds), -1 only asks; returns the previous level (0 where no other is built). Not
 * thread-safe: call it between batches. */
GS_EXPORT int64_t gs_quantised_sums_level(int64_t level)
{
#if GS_SX
    int64_t previous = gs_sx_level, widest = cpu_sx_level();
    if (level >= 0)
        gs_sx_level = (int)(level < widest ? level : widest);
    return previous;
#else
    (void)level;
    return 0;
#endif
}

/* One brick table at a point (table_sums), from quantised values when the spline has them. */
GS_INLINE void brick_sum(const gs_spline *S, const int order, const int nderiv, const double *wx, const double *wy,
                         const double *wz, const int ws, int64_t base, const int32_t *cols, const void *offs,
                         const uint16_t *full, int64_t brick, int64_t lx, int64_t ly, int64_t lz, double inv_h,
                         double *result)
{
    if (!S->qwidth) {
        table_sums(S, order, nderiv, 0, 0, wx, wy, wz, ws, base, cols, offs, full, brick, lx, ly, lz, inv_h, result);
        return;
    }
#define GS_QUANTISED_CALL(o, d, suffix)                                                                               \
    quantised_sums_##o##_##d##suffix(S, order, wx, wy, wz, ws, base, cols, offs, full, brick, lx, ly, lz, inv_h, result)
#define GS_QUANTISED_CALLS(suffix)                                                                                    \
    do {                                                                                                              \
        if (order == 4) {                                                                                             \
            if (nderiv == 0) GS_QUANTISED_CALL(4, 0, suffix);                                                         \
            else if (nderiv == 1) GS_QUANTISED_CALL(4, 1, suffix);                                                    \
            else GS_QUANTISED_CALL(4, 2, suffix);                                                                     \
        } else if (order == 6) {                                                                                      \
            if (nderiv == 0) GS_QUANTISED_CALL(6, 0, suffix);                                                         \
            else if (nderiv == 1) GS_QUANTISED_CALL(6, 1, suffix);                                                    \
            else GS_QUANTISED_CALL(6, 2, suffix);                                                                     \
        } else {                                                                                                      \
            if (nderiv == 0) GS_QUANTISED_CALL(0, 0, suffix);                                                         \
            else if (nderiv == 1) GS_QUANTISED_CALL(0, 1, suffix);                                                    \
            else GS_QUANTISED_CALL(0, 2, suffix);                                                                     \
        }                                                                                                             \
    } while (0)
#if GS_SX
    if (gs_sx_level == 2) {
        GS_QUANTISED_CALLS(_sx2);
        return;
    }
    if (gs_sx_level == 1) {
        GS_QUANTISED_CALLS(_sx1);
        return;
    }
#endif
    GS_QUANTISED_CALLS();
#undef GS_QUANTISED_CALLS
#undef GS_QUANTISED_CALL
}

/* The cell (ax, ay, az) of the point (x, y, z) on level lev's lattice and t its position
 * in that cell (fractions of a spacing): point_sum and latlon_locate locate with these
 * same products, so a point's weights do not depend on which of them located it. */
GS_INLINE void lattice_cell(const gs_spline *S, int64_t lev, double x, double y, double z, int64_t cell[3],
                            double t[3])
{
    double inv_h = S->inv_hs[lev];
    double fx = x * inv_h, fy = y * inv_h, fz = z * inv_h;
    double flx = floor(fx), fly = floor(fy), flz = floor(fz);
    cell[0] = (int64_t)flx;
    cell[1] = (int64_t)fly;
    cell[2] = (int64_t)flz;
    t[0] = fx - flx;
    t[1] = fy - fly;
    t[2] = fz - flz;
}

/* The brick of level lev holding the point (x, y, z), or -1, and its cell and t
 * (lattice_cell). last_key and last_brick (per level) remember the last brick looked up. */
GS_INLINE int64_t brick_at(const gs_spline *S, int64_t lev, double x, double y, double z, int64_t cell[3],
                           double t[3], int64_t *last_key, int64_t *last_brick)
{
    lattice_cell(S, lev, x, y, z, cell, t);
    int64_t key = gs_pack(cell[0] >> BRICK_BITS, cell[1] >> BRICK_BITS, cell[2] >> BRICK_BITS);
    if (key == last_key[lev])
        return last_brick[lev];
    int64_t brick = present(S, lev, x, y, z) ? hash_find(S->slots + 2 * S->slot_start[lev], S->slot_mask[lev], key)
                                             : -1;
    last_key[lev] = key;
    last_brick[lev] = brick;
    return brick;
}

/* Add the spline (and derivatives) at a finite point into result (zeroed by the caller).
 *
 * From the finest level down, the first level with a brick at the point whose band holds
 * the point is evaluated from its folded table (which includes every coarser level) and
 * ends the sum; a level with a brick there but outside its band adds its own table and
 * the descent goes on; a level without a brick there has no B-spline touching the point.
 * last_key/last_brick (per level, per task) remember the last brick looked up: points
 * visited in a locality-preserving order mostly stay in the brick of the point before,
 * and then neither the presence map nor the hash table is read. */
GS_INLINE void point_sum(const gs_spline *S, const int order, const int nderiv, double x, double y, double z,
                         int64_t *last_key, int64_t *last_brick, double *result)
{
    double r2 = x * x + y * y + z * z;
    double wx[3 * GS_MAX_ORDER], wy[3 * GS_MAX_ORDER], wz[3 * GS_MAX_ORDER];
    int64_t cell[3];
    double t[3];
    for (int64_t lev = S->nlev - 1; lev >= 0; --lev) {
        int64_t brick = brick_at(S, lev, x, y, z, cell, t, last_key, last_brick);
        if (brick < 0)
            continue;
        double inv_h = S->inv_hs[lev];
        gs_weights(t[0], order, nderiv, wx, order);
        gs_weights(t[1], order, nderiv, wy, order);
        gs_weights(t[2], order, nderiv, wz, order);
        int64_t lx = cell[0] & BRICK_MASK, ly = cell[1] & BRICK_MASK, lz = cell[2] & BRICK_MASK;
        if (S->band_lo2[lev] <= r2 && r2 <= S->band_hi2[lev]) {
            brick_sum(S, order, nderiv, wx, wy, wz, 1, S->fold_base[brick], S->fold_cols, S->fold_offs, S->fold_full,
                      brick, lx, ly, lz, inv_h, result);
            break;
        }
        brick_sum(S, order, nderiv, wx, wy, wz, 1, S->own_base[brick], S->own_cols, S->own_offs, S->own_full, brick, lx,
                  ly, lz, inv_h, result);
    }
}

GS_INLINE void reset_cache(int64_t nlev, int64_t *last_key, int64_t *last_brick)
{
    for (int64_t l = 0; l < nlev; ++l)
        last_key[l] = last_brick[l] = -1; /* -1 is no packed key */
}

typedef struct {
    const gs_spline *S;
    const double *points;
    double *out;
    int64_t m, nderiv, width;
} points_job;

GS_INLINE void points_range(const points_job *J, const int order, const int nderiv, int64_t lo, int64_t hi)
{
    const gs_spline *S = J->S;
    int64_t last_key[S->nlev], last_brick[S->nlev];
    reset_cache(S->nlev, last_key, last_brick);
    for (int64_t s = lo; s < hi; ++s) {
        double x = J->points[3 * s], y = J->points[3 * s + 1], z = J->points[3 * s + 2];
        if (!(isfinite(x) && isfinite(y) && isfinite(z)))
            continue;
        double result[10] = {0.0};
        point_sum(S, order, nderiv, x, y, z, last_key, last_brick, result);
        for (int r = 0; r < J->width; ++r)
            J->out[s * J->width + r] += result[r];
    }
}

/* One definition, instantiated per (order, nderiv) by constant arguments. */
#define GS_DISPATCH(order, nderiv, call)                                                                              \
    do {                                                                                                              \
        if ((order) == 4) {                                                                                           \
            if ((nderiv) == 0) call(4, 0); else if ((nderiv) == 1) call(4, 1); else call(4, 2);                       \
        } else if ((order) == 6) {                                                                                    \
            if ((nderiv) == 0) call(6, 0); else if ((nderiv) == 1) call(6, 1); else call(6, 2);                       \
        } else {                                                                                                      \
            if ((nderiv) == 0) call((order), 0); else if ((nderiv) == 1) call((order), 1); else call((order), 2);     \
        }                                                                                                             \
    } while (0)

GS_HOT static void points_task(void *ctx, int64_t task)
{
    const points_job *J = ctx;
    int64_t lo = task * CHUNK, hi = lo + CHUNK < J->m ? lo + CHUNK : J->m;
    const int order = (int)J->S->order;
#define GS_POINTS(o, d) points_range(J, (o), (d), lo, hi)
    GS_DISPATCH(order, J->nderiv, GS_POINTS);
#undef GS_POINTS
}

/* The spline (and derivatives) at points (m, 3), added into out (m, width): width 1
 * (value), 4 (+ gradient) or 10 (+ Hessian xx yy zz xy xz yz) for nderiv 0, 1, 2.
 * Non-finite points are skipped. */
GS_EXPORT void gs_evaluate_bricks(const gs_spline *S, const double *points, int64_t m, int64_t nderiv, double *out,
                                  int64_t nthreads)
{
    points_job J = {S, points, out, m, nderiv, nderiv == 0 ? 1 : (nderiv == 1 ? 4 : 10)};
    gs_parallel_for((int)nthreads, (m + CHUNK - 1) / CHUNK, points_task, &J);
}

/* ---- visiting orders -------------------------------------------------------------- */

#define ORDER_BITS 6 /* query_order: 2**ORDER_BITS buckets an axis over [-1.25, 1.25) */

GS_INLINE int64_t spread3(int64_t v)
{
    v &= 0x3FF;
    v = (v | (v << 16)) & 0x30000FF;
    v = (v | (v << 8)) & 0x300F00F;
    v = (v | (v << 4)) & 0x30C30C3;
    v = (v | (v << 2)) & 0x9249249;
    return v;
}

GS_INLINE int64_t clamped_cell(double f, int64_t side)
{
    f = floor(f);
    return f < 0.0 ? 0 : (f > side - 1 ? side - 1 : (int64_t)f);
}

/* A stable visiting order of points (m, 3) in which neighbours follow each other: a
 * counting sort on the Morton index of a coarse grid (points outside it clamped, NaN
 * last). key: work array of m. */
GS_EXPORT void gs_query_order(const double *points, int64_t m, int64_t *key, int64_t *order)
{
    const int64_t side = 1 << ORDER_BITS, nbuckets = side * side * side;
    const double scale = side / 2.5;
    int64_t *counts = calloc((size_t)nbuckets + 1, sizeof(int64_t));
    for (int64_t s = 0; s < m; ++s) {
        double x = points[3 * s], y = points[3 * s + 1], z = points[3 * s + 2];
        int64_t b = nbuckets;
        if (isfinite(x) && isfinite(y) && isfinite(z)) {
            int64_t i = clamped_cell((x + 1.25) * scale, side);
            int64_t j = clamped_cell((y + 1.25) * scale, side);
            int64_t k = clamped_cell((z + 1.25) * scale, side);
            b = spread3(i) | (spread3(j) << 1) | (spread3(k) << 2);
        }
        key[s] = b;
        counts[b] += 1;
    }
    int64_t total = 0;
    for (int64_t b = 0; b <= nbuckets; ++b) {
        int64_t c = counts[b];
        counts[b] = total;
        total += c;
    }
    for (int64_t s = 0; s < m; ++s)
        order[counts[key[s]]++] = s;
    free(counts);
}

/* ---- latitude/longitude batches --------------------------------------------------- */

#define LL_LAT_BITS 10 /* the sort grid: 2**10 rows and 2**11 columns of 0.18 degrees */
#define LL_LON_BITS 11
#define LL_LOW_BITS 10 /* the sort's second pass: the low bits of the Morton code */
#define LL_BUCKETS (1 << (LL_LAT_BITS + LL_LON_BITS - LL_LOW_BITS)) /* of the first pass; one more for NaN */

/* Directions are computed 4 points at a time, one vector lane each (GCC's vector
 * extensions: one vector in the x86-64-v3 clone, two halves in the baseline one); a lane
 * does the operations a scalar would, in the same order, so the bits do not depend on the
 * lane or the build. */
typedef int64_t gs_i4 __attribute__((vector_size(32)));
typedef int32_t gs_w4 __attribute__((vector_size(16)));

GS_INLINE gs_v4 v4_splat(double a)
{
    return (gs_v4){a, a, a, a};
}

/* mask ? a : b per lane (mask lanes all ones or all zeros, as comparisons give) */
GS_INLINE gs_v4 v4_select(gs_i4 mask, gs_v4 a, gs_v4 b)
{
    return (gs_v4)((mask & (gs_i4)a) | (~mask & (gs_i4)b));
}

/* Whether any lane of a comparison's mask is set. */
GS_INLINE int v4_any(gs_i4 mask)
{
    return (mask[0] | mask[1] | mask[2] | mask[3]) != 0;
}

/* floor per lane, exactly floor() for every double (the sign of a zero included): round
 * to an integer by adding and removing 2**52 (towards zero from the side of x, where the
 * spacing of doubles is 1), one less where that rounded up. */
GS_INLINE gs_v4 v4_floor(gs_v4 x)
{
    const gs_v4 big = v4_splat(4503599627370496.0);
    const gs_i4 sign = {INT64_MIN, INT64_MIN, INT64_MIN, INT64_MIN};
    gs_v4 rounded = v4_select(x >= 0.0, (x + big) - big, (x - big) + big);
    gs_v4 whole = v4_select((x < -big) | (x > big), x, rounded); /* beyond 2**52 all are whole */
    gs_v4 t = v4_select(whole > x, whole - v4_splat(1.0), whole);
    return (gs_v4)(((gs_i4)t & ~sign) | ((gs_i4)x & sign)); /* floor(x) has the sign of x */
}

/* Angles in degrees (longitudes; latitudes on directions4's checked path) outside
 * [-180, 180) wrapped into it (lanes inside keep their bits; the division and floor only
 * when a lane needs them; a huge angle wraps inexactly). */
GS_INLINE gs_v4 wrapped_degrees4(gs_v4 degrees)
{
    gs_i4 outside = (degrees < -180.0) | (degrees >= 180.0);
    if (v4_any(outside))
        degrees = v4_select(outside, degrees - 360.0 * v4_floor((degrees + 180.0) / 360.0), degrees);
    return degrees;
}

/* sin and cos of n degrees, {sin, cos} in row n = 0 .. 180, each correctly rounded
 * (tests/test_query_index.py recomputes every row to 50 digits with Python's decimal) */
static const double gs_degree_sincos[181][2] = {
    {0x0.0p+0, 0x1.0000000000000p+0}, {0x1.1df0b2b89dd1ep-6, 0x1.ffec097f5af8ap-1}, /* 0-1 */
    {0x1.1de58c9f7dc27p-5, 0x1.ffb0278bf0567p-1}, {0x1.acbc748efc90ep-5, 0x1.ff4c5ed12e61dp-1}, /* 2-3 */
    {0x1.1db8f6d6a5128p-4, 0x1.fec0b7170fff6p-1}, {0x1.64fd6b8c28103p-4, 0x1.fe0d3b41815a2p-1}, /* 4-5 */
    {0x1.ac2609b3c576cp-4, 0x1.fd31f94f867c6p-1}, {0x1.f32d44c4f62d3p-4, 0x1.fc2f025a23e8bp-1}, /* 6-7 */
    {0x1.1d06c968d9e19p-3, 0x1.fb046a930947ap-1}, {0x1.4060b67a85375p-3, 0x1.f9b24942fe45cp-1}, /* 8-9 */
    {0x1.63a1a7e0b738ap-3, 0x1.f838b8c811c17p-1}, {0x1.86c6ddd76624fp-3, 0x1.f697d6938b6c2p-1}, /* 10-11 */
    {0x1.a9cd9ac4258f6p-3, 0x1.f4cfc327a0080p-1}, {0x1.ccb3236cdc675p-3, 0x1.f2e0a214e870fp-1}, /* 12-13 */
    {0x1.ef74bf2e4b91dp-3, 0x1.f0ca99f79ba25p-1}, {0x1.0907dc1930690p-2, 0x1.ee8dd4748bf15p-1}, /* 14-15 */
    {0x1.1a40add328e29p-2, 0x1.ec2a7e35e7b80p-1}, {0x1.2b637cf83d5c7p-2, 0x1.e9a0c6e7bdb1fp-1}, /* 16-17 */
    {0x1.3c6ef372fe950p-2, 0x1.e6f0e134454ffp-1}, {0x1.4d61bd000cddbp-2, 0x1.e41b02bfeb4cbp-1}, /* 18-19 */
    {0x1.5e3a8748a0bf5p-2, 0x1.e11f642522d1cp-1}, {0x1.6ef801fced33cp-2, 0x1.ddfe40effb805p-1}, /* 20-21 */
    {0x1.7f98deee59681p-2, 0x1.dab7d7997cb58p-1}, {0x1.901bd2298ffabp-2, 0x1.d74c6982c666fp-1}, /* 22-23 */
    {0x1.a07f921061ad1p-2, 0x1.d3bc3aeff7f95p-1}, {0x1.b0c2d77379853p-2, 0x1.d0079302dd767p-1}, /* 24-25 */
    {0x1.c0e45dabe05c8p-2, 0x1.cc2ebbb5638cap-1}, {0x1.d0e2e2b44de01p-2, 0x1.c83201d3d2c6dp-1}, /* 26-27 */
    {0x1.e0bd274245078p-2, 0x1.c411b4f6d2708p-1}, {0x1.f071eedefa0ecp-2, 0x1.bfce277d339c7p-1}, /* 28-29 */
    {0x1.0000000000000p-1, 0x1.bb67ae8584caap-1}, {0x1.07b3120fddf13p-1, 0x1.b6dea1e76eadep-1}, /* 30-31 */
    {0x1.0f5193eacdd2ap-1, 0x1.b2335c2cda945p-1}, {0x1.16daed770771dp-1, 0x1.ad663a8ae2fdcp-1}, /* 32-33 */
    {0x1.1e4e88411fd12p-1, 0x1.a8779cda8eea5p-1}, {0x1.25abcf87c4978p-1, 0x1.a367e59158747p-1}, /* 34-35 */
    {0x1.2cf2304755a5ep-1, 0x1.9e3779b97f4a8p-1}, {0x1.342119455beb6p-1, 0x1.98e6c0ea27a14p-1}, /* 36-37 */
    {0x1.3b37fb1bdc939p-1, 0x1.9376253f463d1p-1}, {0x1.4236484487abep-1, 0x1.8de613515a328p-1}, /* 38-39 */
    {0x1.491b7523c161dp-1, 0x1.8836fa2cf5039p-1}, {0x1.4fe6f81384fd4p-1, 0x1.82694b4a11c37p-1}, /* 40-41 */
    {0x1.5698496e20bd8p-1, 0x1.7c7d7a833bec2p-1}, {0x1.5d2ee398c9c2bp-1, 0x1.7673fe0c86982p-1}, /* 42-43 */
    {0x1.63aa430e07310p-1, 0x1.704d4e6a54d39p-1}, {0x1.6a09e667f3bcdp-1, 0x1.6a09e667f3bcdp-1}, /* 44-45 */
    {0x1.704d4e6a54d39p-1, 0x1.63aa430e07310p-1}, {0x1.7673fe0c86982p-1, 0x1.5d2ee398c9c2bp-1}, /* 46-47 */
    {0x1.7c7d7a833bec2p-1, 0x1.5698496e20bd8p-1}, {0x1.82694b4a11c37p-1, 0x1.4fe6f81384fd4p-1}, /* 48-49 */
    {0x1.8836fa2cf5039p-1, 0x1.491b7523c161dp-1}, {0x1.8de613515a328p-1, 0x1.4236484487abep-1}, /* 50-51 */
    {0x1.9376253f463d1p-1, 0x1.3b37fb1bdc939p-1}, {0x1.98e6c0ea27a14p-1, 0x1.342119455beb6p-1}, /* 52-53 */
    {0x1.9e3779b97f4a8p-1, 0x1.2cf2304755a5ep-1}, {0x1.a367e59158747p-1, 0x1.25abcf87c4978p-1}, /* 54-55 */
    {0x1.a8779cda8eea5p-1, 0x1.1e4e88411fd12p-1}, {0x1.ad663a8ae2fdcp-1, 0x1.16daed770771dp-1}, /* 56-57 */
    {0x1.b2335c2cda945p-1, 0x1.0f5193eacdd2ap-1}, {0x1.b6dea1e76eadep-1, 0x1.07b3120fddf13p-1}, /* 58-59 */
    {0x1.bb67ae8584caap-1, 0x1.0000000000000p-1}, {0x1.bfce277d339c7p-1, 0x1.f071eedefa0ecp-2}, /* 60-61 */
    {0x1.c411b4f6d2708p-1, 0x1.e0bd274245078p-2}, {0x1.c83201d3d2c6dp-1, 0x1.d0e2e2b44de01p-2}, /* 62-63 */
    {0x1.cc2ebbb5638cap-1, 0x1.c0e45dabe05c8p-2}, {0x1.d0079302dd767p-1, 0x1.b0c2d77379853p-2}, /* 64-65 */
    {0x1.d3bc3aeff7f95p-1, 0x1.a07f921061ad1p-2}, {0x1.d74c6982c666fp-1, 0x1.901bd2298ffabp-2}, /* 66-67 */
    {0x1.dab7d7997cb58p-1, 0x1.7f98deee59681p-2}, {0x1.ddfe40effb805p-1, 0x1.6ef801fced33cp-2}, /* 68-69 */
    {0x1.e11f642522d1cp-1, 0x1.5e3a8748a0bf5p-2}, {0x1.e41b02bfeb4cbp-1, 0x1.4d61bd000cddbp-2}, /* 70-71 */
    {0x1.e6f0e134454ffp-1, 0x1.3c6ef372fe950p-2}, {0x1.e9a0c6e7bdb1fp-1, 0x1.2b637cf83d5c7p-2}, /* 72-73 */
    {0x1.ec2a7e35e7b80p-1, 0x1.1a40add328e29p-2}, {0x1.ee8dd4748bf15p-1, 0x1.0907dc1930690p-2}, /* 74-75 */
    {0x1.f0ca99f79ba25p-1, 0x1.ef74bf2e4b91dp-3}, {0x1.f2e0a214e870fp-1, 0x1.ccb3236cdc675p-3}, /* 76-77 */
    {0x1.f4cfc327a0080p-1, 0x1.a9cd9ac4258f6p-3}, {0x1.f697d6938b6c2p-1, 0x1.86c6ddd76624fp-3}, /* 78-79 */
    {0x1.f838b8c811c17p-1, 0x1.63a1a7e0b738ap-3}, {0x1.f9b24942fe45cp-1, 0x1.4060b67a85375p-3}, /* 80-81 */
    {0x1.fb046a930947ap-1, 0x1.1d06c968d9e19p-3}, {0x1.fc2f025a23e8bp-1, 0x1.f32d44c4f62d3p-4}, /* 82-83 */
    {0x1.fd31f94f867c6p-1, 0x1.ac2609b3c576cp-4}, {0x1.fe0d3b41815a2p-1, 0x1.64fd6b8c28103p-4}, /* 84-85 */
    {0x1.fec0b7170fff6p-1, 0x1.1db8f6d6a5128p-4}, {0x1.ff4c5ed12e61dp-1, 0x1.acbc748efc90ep-5}, /* 86-87 */
    {0x1.ffb0278bf0567p-1, 0x1.1de58c9f7dc27p-5}, {0x1.ffec097f5af8ap-1, 0x1.1df0b2b89dd1ep-6}, /* 88-89 */
    {0x1.0000000000000p+0, 0x0.0p+0}, {0x1.ffec097f5af8ap-1, -0x1.1df0b2b89dd1ep-6}, /* 90-91 */
    {0x1.ffb0278bf0567p-1, -0x1.1de58c9f7dc27p-5}, {0x1.ff4c5ed12e61dp-1, -0x1.acbc748efc90ep-5}, /* 92-93 */
    {0x1.fec0b7170fff6p-1, -0x1.1db8f6d6a5128p-4}, {0x1.fe0d3b41815a2p-1, -0x1.64fd6b8c28103p-4}, /* 94-95 */
    {0x1.fd31f94f867c6p-1, -0x1.ac2609b3c576cp-4}, {0x1.fc2f025a23e8bp-1, -0x1.f32d44c4f62d3p-4}, /* 96-97 */
    {0x1.fb046a930947ap-1, -0x1.1d06c968d9e19p-3}, {0x1.f9b24942fe45cp-1, -0x1.4060b67a85375p-3}, /* 98-99 */
    {0x1.f838b8c811c17p-1, -0x1.63a1a7e0b738ap-3}, {0x1.f697d6938b6c2p-1, -0x1.86c6ddd76624fp-3}, /* 100-101 */
    {0x1.f4cfc327a0080p-1, -0x1.a9cd9ac4258f6p-3}, {0x1.f2e0a214e870fp-1, -0x1.ccb3236cdc675p-3}, /* 102-103 */
    {0x1.f0ca99f79ba25p-1, -0x1.ef74bf2e4b91dp-3}, {0x1.ee8dd4748bf15p-1, -0x1.0907dc1930690p-2}, /* 104-105 */
    {0x1.ec2a7e35e7b80p-1, -0x1.1a40add328e29p-2}, {0x1.e9a0c6e7bdb1fp-1, -0x1.2b637cf83d5c7p-2}, /* 106-107 */
    {0x1.e6f0e134454ffp-1, -0x1.3c6ef372fe950p-2}, {0x1.e41b02bfeb4cbp-1, -0x1.4d61bd000cddbp-2}, /* 108-109 */
    {0x1.e11f642522d1cp-1, -0x1.5e3a8748a0bf5p-2}, {0x1.ddfe40effb805p-1, -0x1.6ef801fced33cp-2}, /* 110-111 */
    {0x1.dab7d7997cb58p-1, -0x1.7f98deee59681p-2}, {0x1.d74c6982c666fp-1, -0x1.901bd2298ffabp-2}, /* 112-113 */
    {0x1.d3bc3aeff7f95p-1, -0x1.a07f921061ad1p-2}, {0x1.d0079302dd767p-1, -0x1.b0c2d77379853p-2}, /* 114-115 */
    {0x1.cc2ebbb5638cap-1, -0x1.c0e45dabe05c8p-2}, {0x1.c83201d3d2c6dp-1, -0x1.d0e2e2b44de01p-2}, /* 116-117 */
    {0x1.c411b4f6d2708p-1, -0x1.e0bd274245078p-2}, {0x1.bfce277d339c7p-1, -0x1.f071eedefa0ecp-2}, /* 118-119 */
    {0x1.bb67ae8584caap-1, -0x1.0000000000000p-1}, {0x1.b6dea1e76eadep-1, -0x1.07b3120fddf13p-1}, /* 120-121 */
    {0x1.b2335c2cda945p-1, -0x1.0f5193eacdd2ap-1}, {0x1.ad663a8ae2fdcp-1, -0x1.16daed770771dp-1}, /* 122-123 */
    {0x1.a8779cda8eea5p-1, -0x1.1e4e88411fd12p-1}, {0x1.a367e59158747p-1, -0x1.25abcf87c4978p-1}, /* 124-125 */
    {0x1.9e3779b97f4a8p-1, -0x1.2cf2304755a5ep-1}, {0x1.98e6c0ea27a14p-1, -0x1.342119455beb6p-1}, /* 126-127 */
    {0x1.9376253f463d1p-1, -0x1.3b37fb1bdc939p-1}, {0x1.8de613515a328p-1, -0x1.4236484487abep-1}, /* 128-129 */
    {0x1.8836fa2cf5039p-1, -0x1.491b7523c161dp-1}, {0x1.82694b4a11c37p-1, -0x1.4fe6f81384fd4p-1}, /* 130-131 */
    {0x1.7c7d7a833bec2p-1, -0x1.5698496e20bd8p-1}, {0x1.7673fe0c86982p-1, -0x1.5d2ee398c9c2bp-1}, /* 132-133 */
    {0x1.704d4e6a54d39p-1, -0x1.63aa430e07310p-1}, {0x1.6a09e667f3bcdp-1, -0x1.6a09e667f3bcdp-1}, /* 134-135 */
    {0x1.63aa430e07310p-1, -0x1.704d4e6a54d39p-1}, {0x1.5d2ee398c9c2bp-1, -0x1.7673fe0c86982p-1}, /* 136-137 */
    {0x1.5698496e20bd8p-1, -0x1.7c7d7a833bec2p-1}, {0x1.4fe6f81384fd4p-1, -0x1.82694b4a11c37p-1}, /* 138-139 */
    {0x1.491b7523c161dp-1, -0x1.8836fa2cf5039p-1}, {0x1.4236484487abep-1, -0x1.8de613515a328p-1}, /* 140-141 */
    {0x1.3b37fb1bdc939p-1, -0x1.9376253f463d1p-1}, {0x1.342119455beb6p-1, -0x1.98e6c0ea27a14p-1}, /* 142-143 */
    {0x1.2cf2304755a5ep-1, -0x1.9e3779b97f4a8p-1}, {0x1.25abcf87c4978p-1, -0x1.a367e59158747p-1}, /* 144-145 */
    {0x1.1e4e88411fd12p-1, -0x1.a8779cda8eea5p-1}, {0x1.16daed770771dp-1, -0x1.ad663a8ae2fdcp-1}, /* 146-147 */
    {0x1.0f5193eacdd2ap-1, -0x1.b2335c2cda945p-1}, {0x1.07b3120fddf13p-1, -0x1.b6dea1e76eadep-1}, /* 148-149 */
    {0x1.0000000000000p-1, -0x1.bb67ae8584caap-1}, {0x1.f071eedefa0ecp-2, -0x1.bfce277d339c7p-1}, /* 150-151 */
    {0x1.e0bd274245078p-2, -0x1.c411b4f6d2708p-1}, {0x1.d0e2e2b44de01p-2, -0x1.c83201d3d2c6dp-1}, /* 152-153 */
    {0x1.c0e45dabe05c8p-2, -0x1.cc2ebbb5638cap-1}, {0x1.b0c2d77379853p-2, -0x1.d0079302dd767p-1}, /* 154-155 */
    {0x1.a07f921061ad1p-2, -0x1.d3bc3aeff7f95p-1}, {0x1.901bd2298ffabp-2, -0x1.d74c6982c666fp-1}, /* 156-157 */
    {0x1.7f98deee59681p-2, -0x1.dab7d7997cb58p-1}, {0x1.6ef801fced33cp-2, -0x1.ddfe40effb805p-1}, /* 158-159 */
    {0x1.5e3a8748a0bf5p-2, -0x1.e11f642522d1cp-1}, {0x1.4d61bd000cddbp-2, -0x1.e41b02bfeb4cbp-1}, /* 160-161 */
    {0x1.3c6ef372fe950p-2, -0x1.e6f0e134454ffp-1}, {0x1.2b637cf83d5c7p-2, -0x1.e9a0c6e7bdb1fp-1}, /* 162-163 */
    {0x1.1a40add328e29p-2, -0x1.ec2a7e35e7b80p-1}, {0x1.0907dc1930690p-2, -0x1.ee8dd4748bf15p-1}, /* 164-165 */
    {0x1.ef74bf2e4b91dp-3, -0x1.f0ca99f79ba25p-1}, {0x1.ccb3236cdc675p-3, -0x1.f2e0a214e870fp-1}, /* 166-167 */
    {0x1.a9cd9ac4258f6p-3, -0x1.f4cfc327a0080p-1}, {0x1.86c6ddd76624fp-3, -0x1.f697d6938b6c2p-1}, /* 168-169 */
    {0x1.63a1a7e0b738ap-3, -0x1.f838b8c811c17p-1}, {0x1.4060b67a85375p-3, -0x1.f9b24942fe45cp-1}, /* 170-171 */
    {0x1.1d06c968d9e19p-3, -0x1.fb046a930947ap-1}, {0x1.f32d44c4f62d3p-4, -0x1.fc2f025a23e8bp-1}, /* 172-173 */
    {0x1.ac2609b3c576cp-4, -0x1.fd31f94f867c6p-1}, {0x1.64fd6b8c28103p-4, -0x1.fe0d3b41815a2p-1}, /* 174-175 */
    {0x1.1db8f6d6a5128p-4, -0x1.fec0b7170fff6p-1}, {0x1.acbc748efc90ep-5, -0x1.ff4c5ed12e61dp-1}, /* 176-177 */
    {0x1.1de58c9f7dc27p-5, -0x1.ffb0278bf0567p-1}, {0x1.1df0b2b89dd1ep-6, -0x1.ffec097f5af8ap-1}, /* 178-179 */
    {0x0.0p+0, -0x1.0000000000000p+0} /* 180 */
};

/* sin and cos of one angle in degrees per lane, |a| <= 180 or NaN. |a| = n + d, n whole
 * and |d| <= 1/2 (both exact: n is |a| rounded by adding and removing 1.5 2**52, d the
 * difference of two doubles within a factor of 2), r = d pi/180 radians (|r| < 0.0088),
 * then with S, C the sine and cosine of n degrees (gs_degree_sincos)
 *   sin |a| = S + (C sin r - S (1 - cos r)),   cos |a| = C - (S sin r + C (1 - cos r)),
 * sin r and 1 - cos r from their Taylor polynomials (the next terms below 1e-18). The
 * corrections are below 0.0088, so their rounding is far below S's and C's last place:
 * each result is within half a unit in the last place of S or C plus its own rounding
 * (1.1e-16 absolute at most) of the sine and cosine of the degrees given, with no
 * rounding of the angle in radians. sin a takes the sign of a. Whole degrees give S and
 * C exactly (cos 90 is 0). checked (a constant): lanes may be NaN (then row 0, results
 * NaN) or beyond 180 degrees (a huge angle's inexact wrap: taken as 180), so that the
 * table is never read outside its rows. */
GS_INLINE void sincos_degrees(gs_v4 a, const int checked, gs_v4 *sin_a, gs_v4 *cos_a)
{
    const double round_magic = 6755399441055744.0; /* 1.5 2**52 */
    const int64_t round_magic_bits = 0x4338000000000000LL;
    const double d2r = 3.141592653589793 / 180.0;
    const gs_i4 sign = {INT64_MIN, INT64_MIN, INT64_MIN, INT64_MIN};
    gs_v4 m = (gs_v4)((gs_i4)a & ~sign);
    if (checked)
        m = v4_select(m > 180.0, v4_splat(180.0), m);
    gs_v4 rounded = m + round_magic;
    gs_i4 row = (gs_i4)rounded - round_magic_bits; /* the whole number in its low bits */
    if (checked)
        row &= (gs_i4)(m == m);
    gs_v4 r = (m - (rounded - round_magic)) * d2r;
    gs_v4 z = r * r;
    gs_v4 sin_r = r + (r * z) * (-1.0 / 6.0 + z * (1.0 / 120.0));
    gs_v4 one_minus_cos_r = z * (0.5 - z * (1.0 / 24.0 - z * (1.0 / 720.0)));
    const double(*T)[2] = gs_degree_sincos;
    gs_v4 S = {T[row[0]][0], T[row[1]][0], T[row[2]][0], T[row[3]][0]};
    gs_v4 C = {T[row[0]][1], T[row[1]][1], T[row[2]][1], T[row[3]][1]};
    gs_v4 sin_m = S + (C * sin_r - S * one_minus_cos_r);
    *sin_a = (gs_v4)((gs_i4)sin_m ^ ((gs_i4)a & sign));
    *cos_a = C - (S * sin_r + C * one_minus_cos_r);
}

/* Unit vectors of 4 latitude/longitude pairs in degrees: the one formula of every
 * compiled path (unit_vectors, undulation_latlon), so they agree bit for bit. Angles
 * beyond +-180 degrees (longitudes outside [-180, 180); unit_vectors checks no range)
 * are wrapped first (lanes inside keep their bits; a huge longitude wraps inexactly). */
GS_INLINE void directions4(const gs_v4 *latitude_, const gs_v4 *longitude_, gs_v4 *x, gs_v4 *y, gs_v4 *z)
{
    gs_v4 latitude = *latitude_, longitude = *longitude_;
    const gs_i4 sign = {INT64_MIN, INT64_MIN, INT64_MIN, INT64_MIN};
    /* Every latitude within +-90 and longitude in [-180, 180) (no NaN: every valid batch):
     * no wrap, no NaN. Otherwise (one test for the 4) both wrapped, their lanes checked. */
    gs_i4 inside = ((gs_v4)((gs_i4)latitude & ~sign) <= 90.0) & (longitude >= -180.0) & (longitude < 180.0);
    gs_v4 sin_phi, cos_phi, sin_lam, cos_lam;
    if (!v4_any(~inside)) {
        sincos_degrees(latitude, 0, &sin_phi, &cos_phi);
        sincos_degrees(longitude, 0, &sin_lam, &cos_lam);
    } else {
        sincos_degrees(wrapped_degrees4(latitude), 1, &sin_phi, &cos_phi);
        sincos_degrees(wrapped_degrees4(longitude), 1, &sin_lam, &cos_lam);
    }
    *x = cos_phi * cos_lam;
    *y = cos_phi * sin_lam;
    *z = sin_phi;
}

typedef uint32_t gs_u4 __attribute__((vector_size(16)));

GS_INLINE gs_u4 spread2(gs_u4 v)
{
    v &= 0xFFFF;
    v = (v | (v << 8)) & 0x00FF00FF;
    v = (v | (v << 4)) & 0x0F0F0F0F;
    v = (v | (v << 2)) & 0x33333333;
    v = (v | (v << 1)) & 0x55555555;
    return v;
}

/* Sort codes with the lanes of a NaN coordinate moved to bucket LL_BUCKETS (the last). */
GS_INLINE gs_u4 nan_in_last_bucket(gs_u4 code, gs_v4 la, gs_v4 lo)
{
    gs_i4 nan = (la != la) | (lo != lo);
    gs_u4 nan32 = __builtin_convertvector(nan, gs_u4); /* all ones or zero */
    return (code & ~nan32) | (nan32 & ((uint32_t)LL_BUCKETS << LL_LOW_BITS));
}

/* Morton codes of 4 points' cells on the latitude/longitude sort grid, one lane each;
 * a code's bucket of the sort's first pass (a 5.6 degree cell) is code >> LL_LOW_BITS.
 * NaN: bucket LL_BUCKETS. (The codes only order the points: a value does not depend on
 * them.) */
GS_INLINE gs_u4 latlon_code4(gs_v4 la, gs_v4 lo)
{
    const double lat_cells = 1 << LL_LAT_BITS, lon_cells = 1 << LL_LON_BITS;
    gs_v4 fi = (la + 90.0) * (lat_cells / 180.0);
    gs_v4 w = wrapped_degrees4(lo) + 180.0;
    gs_v4 fj = w * (lon_cells / 360.0);
    /* clamped to the grid (NaN to 0 here, its own bucket below), then truncated */
    fi = v4_select(fi >= lat_cells, v4_splat(lat_cells - 1.0), v4_select(fi >= 0.0, fi, v4_splat(0.0)));
    fj = v4_select(fj >= lon_cells, v4_splat(lon_cells - 1.0), v4_select(fj >= 0.0, fj, v4_splat(0.0)));
    gs_u4 i = (gs_u4)__builtin_convertvector(fi, gs_w4), j = (gs_u4)__builtin_convertvector(fj, gs_w4);
    gs_u4 code = spread2(j) | (spread2(i) << 1);
    return nan_in_last_bucket(code, la, lo);
}

typedef struct {
    const double *latitude, *longitude;
    double *out;
    int64_t m;
} unit_job;

GS_HOT static void unit_task(void *ctx, int64_t task)
{
    const unit_job *J = ctx;
    int64_t lo = task * CHUNK, hi = lo + CHUNK < J->m ? lo + CHUNK : J->m;
    for (int64_t s = lo; s < hi; s += 4) {
        gs_v4 la, lo_, x, y, z;
        for (int i = 0; i < 4; ++i) { /* past the end: the last point again */
            la[i] = J->latitude[s + i < hi ? s + i : hi - 1];
            lo_[i] = J->longitude[s + i < hi ? s + i : hi - 1];
        }
        directions4(&la, &lo_, &x, &y, &z);
        for (int i = 0; i < 4 && s + i < hi; ++i) {
            J->out[3 * (s + i)] = x[i];
            J->out[3 * (s + i) + 1] = y[i];
            J->out[3 * (s + i) + 2] = z[i];
        }
    }
}

/* Directions (m, 3) (cos phi cos lambda, cos phi sin lambda, sin phi) of latitude and
 * longitude in degrees (directions4()). */
GS_EXPORT void gs_unit_vectors(const double *latitude, const double *longitude, int64_t m, double *out,
                               int64_t nthreads)
{
    unit_job J = {latitude, longitude, out, m};
    gs_parallel_for((int)nthreads, (m + CHUNK - 1) / CHUNK, unit_task, &J);
}

/* A point in the sort: its latlon_code above AT_BITS, its position in the caller's arrays
 * below; 8 bytes, so the scatter and the bucket sorts move little. */
#define AT_BITS 42
#define KEY_AT(key) ((int64_t)((key) & ((((uint64_t)1) << AT_BITS) - 1)))
#define KEY_CODE(key) ((key) >> AT_BITS)

typedef struct {
    const gs_spline *S;
    const double *latitude, *longitude;
    double *out;
    double max_abs_longitude; /* degrees: a longitude beyond it is invalid */
    int64_t m, nblocks, size;
    uint32_t *code;
    int64_t *counts, *invalid; /* (nblocks, LL_BUCKETS + 1), (nblocks) */
    int64_t *bucket_start;     /* LL_BUCKETS + 2 */
    uint64_t *by_bucket;       /* the points in the order of their buckets (code, position) */
    uint64_t *sorted;          /* and in the order of their codes */
    double *ordered;           /* their values in that order (by_bucket's memory, free by then) */
    int cells;                 /* sort by cell_code4 (else latlon_code4) */
    int cell_shift;            /* cell_code4's lattice: cells of the finest level, 2**cell_shift a side */
    double cell_scale, cell_offset;
    int ahead;                 /* prefetch_bricks: the tables' bricks are prefetched ahead of the points */
    int brick_code_shift;      /* a cell code >> brick_code_shift: the Morton code of its finest-level brick */
    int64_t brick_code_offset; /* that brick's index per axis minus the brick key's */
    int halving;               /* each level's 1/h is the finest's over a power of two (descent_box) */
} latlon_job;

/* The lanes of 4 coordinates that gs_undulation_latlon refuses (all ones): a latitude beyond
 * +-90 or infinite, a longitude infinite or beyond +-max_abs_longitude (NaN is not). */
GS_INLINE gs_i4 invalid_lanes(gs_v4 la, gs_v4 lo, double max_abs_longitude)
{
    const gs_i4 sign = {INT64_MIN, INT64_MIN, INT64_MIN, INT64_MIN};
    gs_v4 abs_la = (gs_v4)((gs_i4)la & ~sign), abs_lo = (gs_v4)((gs_i4)lo & ~sign);
    return (abs_la > 90.0) | (abs_lo == INFINITY) | (abs_lo > max_abs_longitude);
}

/* sin and cos of 4 angles within +-pi/2 (Taylor polynomials: errors below 3.6e-6 and
 * 4.7e-7; any value outside): only for cell_code4, which orders the points (a value never
 * depends on the order). */
GS_INLINE void rough_sincos(gs_v4 x, gs_v4 *sin_x, gs_v4 *cos_x)
{
    gs_v4 z = x * x;
    *sin_x = x + (x * z) * (-1.0 / 6.0 + z * (1.0 / 120.0 + z * (-1.0 / 5040.0 + z * (1.0 / 362880.0))));
    *cos_x = 1.0 + z * (-0.5 + z * (1.0 / 24.0 + z * (-1.0 / 720.0 + z * (1.0 / 40320.0 + z * (-1.0 / 3628800.0)))));
}

GS_INLINE gs_u4 spread3_4(gs_u4 v)
{
    v = (v | (v << 8)) & 0x0000F00F;
    v = (v | (v << 4)) & 0x000C30C3;
    v = (v | (v << 2)) & 0x00249249;
    return v;
}

/* spread3_4 undone for one lane: every third bit of v from bit 0, packed */
GS_INLINE uint32_t compact3(uint32_t v)
{
    v &= 0x00249249;
    v = (v | (v >> 2)) & 0x000C30C3;
    v = (v | (v >> 4)) & 0x0000F00F;
    v = (v | (v >> 8)) & 0x000000FF;
    return v;
}

/* The sort codes of 4 points by their cell on the finest level's lattice (a brick-major
 * order: the bricks of every level are runs of codes): the 3-D Morton code of the cell,
 * coarsened to 2**cell_shift cells a side so that 7 bits an axis hold the unit sphere
 * (21 bits, as latlon_code4's); from a rough direction (rough_sincos), as the codes only
 * order the points. NaN: bucket LL_BUCKETS. */
GS_INLINE gs_u4 cell_code4(const latlon_job *J, gs_v4 la, gs_v4 lo)
{
    const double d2r = 3.141592653589793 / 180.0;
    gs_v4 sin_phi, cos_phi, sin_half, cos_half;
    lo = wrapped_degrees4(lo);
    rough_sincos(la * d2r, &sin_phi, &cos_phi);
    rough_sincos(lo * (0.5 * d2r), &sin_half, &cos_half); /* half the longitude: within +-pi/2 */
    gs_v4 sin_lam = 2.0 * sin_half * cos_half, cos_lam = 1.0 - 2.0 * sin_half * sin_half;
    const double scale = J->cell_scale, offset = J->cell_offset;
    gs_v4 fx = cos_phi * cos_lam * scale + offset, fy = cos_phi * sin_lam * scale + offset, fz = sin_phi * scale + offset;
    const int shift = J->cell_shift;
    gs_u4 i = ((gs_u4)__builtin_convertvector(fx, gs_w4) >> shift) & 127;
    gs_u4 j = ((gs_u4)__builtin_convertvector(fy, gs_w4) >> shift) & 127;
    gs_u4 k = ((gs_u4)__builtin_convertvector(fz, gs_w4) >> shift) & 127;
    gs_u4 code = (spread3_4(i) << 2) | (spread3_4(j) << 1) | spread3_4(k);
    return nan_in_last_bucket(code, la, lo);
}

GS_INLINE void latlon_count_range(latlon_job *J, const int cells, int64_t blk)
{
    int64_t *counts = J->counts + blk * (LL_BUCKETS + 1), bad = 0;
    int64_t lo = blk * J->size, hi = lo + J->size < J->m ? lo + J->size : J->m;
    for (int64_t s = lo; s < hi; s += 4) {
        gs_v4 la, lo_;
        for (int i = 0; i < 4; ++i) { /* past the end: the last point again, not counted */
            la[i] = J->latitude[s + i < hi ? s + i : hi - 1];
            lo_[i] = J->longitude[s + i < hi ? s + i : hi - 1];
        }
        gs_i4 wrong = invalid_lanes(la, lo_, J->max_abs_longitude);
        gs_u4 code = cells ? cell_code4(J, la, lo_) : latlon_code4(la, lo_);
        for (int i = 0; i < 4 && s + i < hi; ++i) {
            bad -= wrong[i]; /* -1 where wrong */
            J->code[s + i] = code[i];
            counts[code[i] >> LL_LOW_BITS] += 1;
        }
    }
    J->invalid[blk] = bad;
}

GS_HOT static void latlon_count(void *ctx, int64_t blk)
{
    latlon_job *J = ctx;
    if (J->cells)
        latlon_count_range(J, 1, blk);
    else
        latlon_count_range(J, 0, blk);
}

static void latlon_scatter(void *ctx, int64_t blk)
{
    latlon_job *J = ctx;
    int64_t *counts = J->counts + blk * (LL_BUCKETS + 1);
    int64_t lo = blk * J->size, hi = lo + J->size < J->m ? lo + J->size : J->m;
    for (int64_t s = lo; s < hi; ++s) {
        uint32_t code = J->code[s];
        J->by_bucket[counts[code >> LL_LOW_BITS]++] = ((uint64_t)code << AT_BITS) | (uint64_t)s;
    }
}

#define SORT_TASK_BUCKETS 16
/* Brick-major (cell) codes are refined by the top LL_LOW_BITS - CELL_REFINE_SHIFT of their
 * low bits only: groups of 32 codes in input order, still within a few bricks, for a
 * 32-entry count a bucket instead of 1,024. The latitude/longitude codes of quantised
 * tables lose locality that way, so they keep every bit (benchmarks/README.md). */
#define CELL_REFINE_SHIFT 5

/* The sort's second pass: each bucket's points from by_bucket into sorted by their low
 * code bits (from bit shift up: CELL_REFINE_SHIFT for cell codes, else all), stably (a
 * bucket holds increasing positions), so the order is that of (code >> shift, position):
 * insertion sort for small buckets (by the whole code), a counting sort otherwise. */
static void latlon_refine(void *ctx, int64_t task)
{
    latlon_job *J = ctx;
    int64_t b_lo = task * SORT_TASK_BUCKETS, b_hi = b_lo + SORT_TASK_BUCKETS;
    if (b_hi > LL_BUCKETS + 1)
        b_hi = LL_BUCKETS + 1; /* NaN's bucket: its codes are all equal */
    const uint64_t low_mask = (1u << LL_LOW_BITS) - 1;
    const int shift = J->cells ? CELL_REFINE_SHIFT : 0;
    const uint64_t top = low_mask >> shift; /* the last group */
    int64_t counts[(1 << LL_LOW_BITS) + 1];
    for (int64_t b = b_lo; b < b_hi; ++b) {
        const uint64_t *in = J->by_bucket + J->bucket_start[b];
        uint64_t *a = J->sorted + J->bucket_start[b];
        int64_t n = J->bucket_start[b + 1] - J->bucket_start[b];
        if (n <= 32 || b == LL_BUCKETS) {
            for (int64_t i = 0; i < n; ++i) {
                uint64_t t = in[i];
                int64_t j = i;
                for (; j >= 1 && a[j - 1] > t; --j)
                    a[j] = a[j - 1];
                a[j] = t;
            }
            continue;
        }
        memset(counts, 0, sizeof(int64_t) * (top + 2));
        for (int64_t i = 0; i < n; ++i)
            counts[((KEY_CODE(in[i]) & low_mask) >> shift) + 1] += 1;
        for (uint64_t k = 1; k <= top; ++k)
            counts[k] += counts[k - 1];
        for (int64_t i = 0; i < n; ++i)
            a[counts[(KEY_CODE(in[i]) & low_mask) >> shift]++] = in[i];
    }
}

/* The value weights of a point's three axes at once (t: its position in its cell per axis):
 * w[j] = {wx_j, wy_j, wz_j, unused}, the closed forms of gs_weights lane by lane for
 * orders 4 and 6 (the same operations, so the same bits, in a third of the instructions). */
GS_INLINE void weights_xyz(const int order, const double t[3], gs_v4 *w)
{
    const gs_v4 tv = {t[0], t[1], t[2], 0.0};
    if (order == 4) {
        GS_WEIGHTS4(gs_v4, tv, w[0], w[1], w[2], w[3]);
    } else if (order == 6) {
        GS_WEIGHTS6(gs_v4, tv, w[0], w[1], w[2], w[3], w[4], w[5]);
    } else {
        double wx[GS_MAX_ORDER], wy[GS_MAX_ORDER], wz[GS_MAX_ORDER];
        gs_weights(t[0], order, 0, wx, order);
        gs_weights(t[1], order, 0, wy, order);
        gs_weights(t[2], order, 0, wz, order);
        for (int j = 0; j < order; ++j)
            w[j] = (gs_v4){wx[j], wy[j], wz[j], 0.0};
    }
}

/* The latitude/longitude loop's pipeline (latlon_range), in points: tables in the caches
 * (float64 ones: below QUANTISE_FROM_COEFFICIENTS) and dense points have a point located
 * LL_AHEAD points before it is summed, its values asked for then; tables beyond them
 * (quantised) at sparse points (latlon_evaluate) have the chain of a new brick's loads
 * spread over the points: the hash slot asked for LL_SLOT points before the point is
 * located, the column offsets then, read to ask for the values LL_OFFS points later,
 * summed LL_VALUES points after that. */
#ifndef LL_AHEAD
#define LL_AHEAD 7
#endif
#ifndef LL_SLOT
#define LL_SLOT 4
#endif
#ifndef LL_OFFS
#define LL_OFFS 4
#endif
#ifndef LL_VALUES
#define LL_VALUES 6
#endif
#ifndef LL_LOC_SLOT /* the locality of the chain's prefetches: 1 into L2, 3 into L1 */
#define LL_LOC_SLOT 3
#endif
#ifndef LL_LOC_OFFS
#define LL_LOC_OFFS 1
#endif
#ifndef LL_LOC_VALUES
#define LL_LOC_VALUES 1
#endif
#ifndef LL_SPARSE
#define LL_SPARSE 0.25
#endif
#define LL_RING 32 /* a power of two > every point in flight */
_Static_assert(LL_SLOT + LL_OFFS + LL_VALUES < LL_RING && LL_AHEAD < LL_RING, "the ring holds every point in flight");

/* A point of the latitude/longitude loop between reading it and summing it: its
 * direction and, when the first level with a brick at it holds it in its band (points on
 * the sphere: always but at the edges of coverage), that brick (else brick -1: point_sum
 * then does the whole descent). */
typedef struct {
    double x, y, z, t[3]; /* direction; position in the cell of the brick's level */
    int64_t lev, brick, lx, ly, lz;
} located;

/* Ask the memory for the hash slot where the finest level's lookup of a point on the
 * sphere starts (the first link of a new brick's chain: slot, then its tables' column
 * offsets, then their values). */
GS_INLINE void prefetch_slot(const gs_spline *S, double x, double y, double z)
{
    const int64_t lev = S->nlev - 1;
    double inv_h = S->inv_hs[lev];
    int64_t key = gs_pack((int64_t)floor(x * inv_h) >> BRICK_BITS, (int64_t)floor(y * inv_h) >> BRICK_BITS,
                          (int64_t)floor(z * inv_h) >> BRICK_BITS);
    __builtin_prefetch(S->slots + 2 * (S->slot_start[lev] + hash_slot(key, S->slot_mask[lev])), 0, LL_LOC_SLOT);
}

/* Where the last point's descent ended (latlon_locate): the box of the finest level's
 * brick it started in, in units of that level's lattice (the direction times inv_h, its
 * 1/h; a fourth lane always inside). Levels halve their spacing exactly (latlon_job's
 * halving), so a coarser level's product x 1/h is the finest level's scaled by a power of
 * two and its bricks hold the finest level's whole: a point in the box meets the same
 * brick key on every level, and its descent ends in the same brick (lev, brick). The test
 * is exact. Brick-major batches enter a new box every few hundred points; a point inside
 * skips the descent's keys (egm96-15's points end a level below the finest:
 * benchmarks/README.md). */
typedef struct {
    gs_v4 lo, hi, inv_h;
    int64_t lev, brick;
    int boxed; /* 0: every point descends (one level: its key is all a descent reads) */
} descent_box;

/* Locate a point on the sphere as point_sum does (brick_at: the same products, so the
 * same weights); inside the box of the last descent (D) only the cell on its level.
 * chain (a constant): ask the memory for what the next link needs, the column offsets of
 * the rows of the folded table it will read (full columns), its full map, qbase and
 * fold_base (prefetch_values reads it: 2 MB for the 1 mm store, evicted from the caches
 * by the values streaming through them), unless the point before (prev) was in the same
 * cell column. */
GS_INLINE void latlon_locate(const gs_spline *S, const int order, const int chain, located *L, const located *prev,
                             int64_t *last_key, int64_t *last_brick, descent_box *D)
{
    const int64_t side = (1 << BRICK_BITS) + order - 1;
    L->brick = -1;
    L->lev = -1;
    if (!(L->x == L->x && L->z == L->z))
        return;
    double x = L->x, y = L->y, z = L->z, r2 = x * x + y * y + z * z;
    int64_t cell[3], lev, brick = -1;
    gs_v4 f = {0.0, 0.0, 0.0, 0.0};
    int inside = 0;
    if (D->boxed) {
        f = (gs_v4){x, y, z, 0.0} * D->inv_h;
        inside = !v4_any(~((f >= D->lo) & (f < D->hi)));
    }
    if (inside) {
        lev = D->lev;
        brick = D->brick;
        lattice_cell(S, lev, x, y, z, cell, L->t);
    } else {
        for (lev = S->nlev - 1; lev >= 0; --lev) {
            brick = brick_at(S, lev, x, y, z, cell, L->t, last_key, last_brick);
            if (brick >= 0)
                break;
        }
        if (brick < 0)
            return;
        if (D->boxed) { /* the finest level's brick: every coarser one holds it whole */
            for (int a = 0; a < 3; ++a) {
                double first = (double)(((int64_t)floor(f[a]) >> BRICK_BITS) * (1 << BRICK_BITS));
                D->lo[a] = first;
                D->hi[a] = first + (1 << BRICK_BITS);
            }
            D->lev = lev;
            D->brick = brick;
        }
    }
    L->lev = lev;
    if (!(S->band_lo2[lev] <= r2 && r2 <= S->band_hi2[lev]))
        return; /* outside the band: point_sum's descent */
    L->brick = brick;
    L->lx = cell[0] & BRICK_MASK;
    L->ly = cell[1] & BRICK_MASK;
    L->lz = cell[2] & BRICK_MASK;
    if (!chain || (brick == prev->brick && L->lx == prev->lx && L->ly == prev->ly))
        return;
    /* the order rows of order offsets, side apart: every line from the first to the last */
    const int64_t ow = S->qwidth ? 2 : 4; /* bytes an offset (column_offset) */
    const char *row = (const char *)S->fold_offs + ow * ((brick * side + L->lx) * side + L->ly);
    uintptr_t last = (uintptr_t)(row + ow * ((order - 1) * side + order - 1));
    for (uintptr_t at = (uintptr_t)row & ~(uintptr_t)63; at <= last; at += 64)
        __builtin_prefetch((const void *)at, 0, LL_LOC_OFFS);
    __builtin_prefetch(S->fold_full + (brick << (2 * BRICK_BITS)) + (L->lx << BRICK_BITS) + L->ly, 0, LL_LOC_OFFS);
    if (S->qwidth)
        __builtin_prefetch(S->qbase + brick, 0, LL_LOC_OFFS);
    __builtin_prefetch(S->fold_base + brick, 0, LL_LOC_OFFS);
}

/* Ask the memory for the values a located point will sum (its folded table's full
 * columns: row p's columns lie between its first's start and its last's end). chain (a
 * constant): every line of each row, unless the point before (prev) read the same
 * columns; else a row's first and last coefficients. */
GS_INLINE void prefetch_values(const gs_spline *S, const int order, const int chain, const located *L,
                               const located *prev)
{
    const int64_t side = (1 << BRICK_BITS) + order - 1;
    if (chain && L->brick == prev->brick && L->lx == prev->lx && L->ly == prev->ly && L->lz == prev->lz)
        return;
    const int quant = S->qwidth != 0;
    const int64_t row = (L->brick * side + L->lx) * side + L->ly;
    int64_t width = S->qwidth ? S->qwidth : (int64_t)sizeof(double); /* the brick's bytes a value */
    const char *v = (const char *)(S->qwidth ? S->qvalues : (const void *)S->values) + width * S->fold_base[L->brick];
    if (quant && S->qbase[L->brick] == QBASE_WIDE)
        width = 4;
    v += width * L->lz;
    for (int p = 0; p < order; ++p) {
        const char *first = v + width * column_offset(quant, S->fold_offs, row + p * side);
        const char *last = v + width * (column_offset(quant, S->fold_offs, row + p * side + order - 1) + order - 1);
        if (chain) {
            for (uintptr_t at = (uintptr_t)first & ~(uintptr_t)63; at <= (uintptr_t)last; at += 64)
                __builtin_prefetch((const void *)at, 0, LL_LOC_VALUES);
        } else {
            __builtin_prefetch(first);
            __builtin_prefetch(last);
        }
    }
}

/* Bricks ahead (prefetch_bricks): AHEAD_LINES lines are asked for every 4 points, up to
 * AHEAD_MAX_BYTES of a brick's table, the next brick's once the last one's are asked for
 * and its first point is at most AHEAD_POINTS ahead; into L2 (locality 2). */
#define AHEAD_LINES 16
#define AHEAD_POINTS 512
#define AHEAD_MAX_BYTES 65536
/* chunks with fewer points than this a brick take the chain pipeline instead
 * (latlon_evaluate) */
#define AHEAD_SPARSE 48

/* The brick code of sorted point p (J->ahead: the Morton code of its finest-level brick) */
GS_INLINE int64_t brick_code(const latlon_job *J, int64_t p)
{
    return (int64_t)(KEY_CODE(J->sorted[p]) >> J->brick_code_shift);
}

/* The bricks ahead of a brick-major batch's points: scan, the first point not yet
 * looked at; code, the brick code of the points before it; brick, the last brick
 * prefetched; [at, end) the lines of its table still to ask for. */
typedef struct {
    int64_t scan, code, brick;
    uintptr_t at, end;
} bricks_ahead;

/* Ask the memory for the tables of the bricks the points after p will read, a part every
 * 4 points (float64 tables beyond the caches: a global batch's brick-major order enters a
 * new brick every few hundred points, whose table no hardware prefetcher sees coming;
 * benchmarks/README.md). The brick comes from the next points' sort codes (a rough
 * direction: a hint, never a value): the finest level with a brick at that brick code
 * (levels halve their spacing: a coarser level's key is the finer's halved). */
GS_INLINE void prefetch_bricks(const latlon_job *J, bricks_ahead *B, int64_t p)
{
    const gs_spline *S = J->S;
    for (int k = 0; k < AHEAD_LINES && B->at < B->end; ++k) {
        __builtin_prefetch((const void *)B->at, 0, 2);
        B->at += 64;
    }
    if (B->at < B->end || B->scan >= J->m || B->scan >= p + AHEAD_POINTS)
        return;
    int64_t scan = B->scan;
    while (scan < J->m && brick_code(J, scan) == B->code)
        ++scan;
    B->scan = scan;
    if (scan >= J->m)
        return;
    B->code = brick_code(J, scan);
    int64_t key[3]; /* the Morton code's three axes */
    for (int a = 0; a < 3; ++a)
        key[a] = (int64_t)compact3((uint32_t)B->code >> (2 - a)) - J->brick_code_offset;
    int64_t brick = -1;
    for (int64_t lev = S->nlev - 1, u = 0; lev >= 0 && brick < 0; --lev, ++u)
        brick = hash_find(S->slots + 2 * S->slot_start[lev], S->slot_mask[lev],
                          gs_pack(key[0] >> u, key[1] >> u, key[2] >> u));
    if (brick < 0 || brick == B->brick)
        return;
    B->brick = brick;
    int64_t bytes = (int64_t)sizeof(double) * S->fold_size[brick];
    const char *table = (const char *)(S->values + S->fold_base[brick]);
    B->at = (uintptr_t)table & ~(uintptr_t)63;
    B->end = (uintptr_t)table + (bytes < AHEAD_MAX_BYTES ? bytes : AHEAD_MAX_BYTES);
}

/* Values at the points sorted[lo..hi) into ordered[lo..hi): nearby points follow each
 * other, so they read the same coefficients. A point's loads depend on its own location
 * (and, for a new brick, on each other: hash slot, column offsets, values), so they are
 * asked for points ahead of its sum (see LL_AHEAD): chain (a constant) for tables beyond
 * the caches at sparse points; ahead for float64 ones at denser points, whole bricks
 * asked for ahead (prefetch_bricks; a variable: one more copy of this loop would make
 * latlon_evaluate's others slower). */
GS_INLINE void latlon_range(const latlon_job *J, const int order, const int chain, const int direct, int64_t lo,
                             int64_t hi, int64_t *invalid, int ahead)
{
    const gs_spline *S = J->S;
    int64_t last_key[S->nlev], last_brick[S->nlev], sum_key[S->nlev], sum_brick[S->nlev];
    located ring[LL_RING];
    gs_v4 dx, dy, dz; /* directions of the points from p - (p - lo) % 4 on */
    reset_cache(S->nlev, last_key, last_brick);
    reset_cache(S->nlev, sum_key, sum_brick);
    bricks_ahead bricks = {lo, -1, -1, 0, 0};
    const double inv_h = S->nlev ? S->inv_hs[S->nlev - 1] : 0.0;
    descent_box box = {{INFINITY, INFINITY, INFINITY, -1.0}, {-INFINITY, -INFINITY, -INFINITY, 1.0},
                       {inv_h, inv_h, inv_h, 0.0}, -1, -1, J->halving && S->nlev > 1}; /* empty */
    /* point p read at step p, located at p + to_locate, values asked for at p + to_values,
     * summed at p + to_sum */
    const int64_t to_locate = chain ? LL_SLOT : 0, to_values = chain ? LL_SLOT + LL_OFFS : 0;
    const int64_t to_sum = chain ? LL_SLOT + LL_OFFS + LL_VALUES : LL_AHEAD;
    const located none = {.brick = -1};
    for (int64_t p = lo; p < hi + to_sum; ++p) {
        if (!direct && p + 16 < hi) { /* the coordinates are read out of order: ask for them early */
            __builtin_prefetch(&J->latitude[KEY_AT(J->sorted[p + 16])]);
            __builtin_prefetch(&J->longitude[KEY_AT(J->sorted[p + 16])]);
        }
        if (p < hi) {
            int64_t i = (p - lo) & 3; /* p >= lo: masks, not signed remainders */
            if (i == 0) { /* the next 4 points' directions at once */
                if (ahead)
                    prefetch_bricks(J, &bricks, p);
                gs_v4 la, lo_;
                for (int k = 0; k < 4; ++k) {
                    int64_t at = direct ? (p + k < hi ? p + k : hi - 1) : KEY_AT(J->sorted[p + k < hi ? p + k : hi - 1]);
                    la[k] = J->latitude[at];
                    lo_[k] = J->longitude[at];
                }
                if (direct) { /* the check of latlon_count; an invalid point is summed as NaN */
                    gs_i4 wrong = invalid_lanes(la, lo_, J->max_abs_longitude);
                    for (int k = 0; k < 4; ++k)
                        *invalid -= p + k < hi ? wrong[k] : 0; /* -1 where wrong */
                    la = v4_select(wrong, v4_splat(NAN), la);
                }
                directions4(&la, &lo_, &dx, &dy, &dz);
            }
            located *L = &ring[(uint64_t)p % LL_RING];
            L->x = dx[i];
            L->y = dy[i];
            L->z = dz[i];
            if (chain && L->x == L->x && L->z == L->z)
                prefetch_slot(S, L->x, L->y, L->z);
        }
        int64_t q = p - to_locate; /* located now */
        if (q >= lo && q < hi) {
            located *L = &ring[(uint64_t)q % LL_RING];
            latlon_locate(S, order, chain, L, chain && q > lo ? &ring[(uint64_t)(q - 1) % LL_RING] : &none, last_key,
                          last_brick, &box);
            /* brick-major batches (J->cells) read the lines of the points before: asking
             * for a point's first and last values costs more than it saves there */
            if (!chain && !J->cells && L->brick >= 0)
                prefetch_values(S, order, 0, L, &none);
        }
        int64_t r = p - to_values; /* values asked for now (chain) */
        if (chain && r >= lo && r < hi && ring[(uint64_t)r % LL_RING].brick >= 0)
            prefetch_values(S, order, 1, &ring[(uint64_t)r % LL_RING], r > lo ? &ring[(uint64_t)(r - 1) % LL_RING] : &none);
        int64_t e = p - to_sum; /* summed now */
        if (e < lo)
            continue;
        const located *L = &ring[(uint64_t)e % LL_RING];
        double result[1] = {0.0};
        if (L->brick >= 0) {
            gs_v4 w[GS_MAX_ORDER]; /* {wx, wy, wz, -} per B-spline */
            weights_xyz(order, L->t, w);
            const double *wx = (const double *)w;
            brick_sum(S, order, 0, wx, wx + 1, wx + 2, 4, S->fold_base[L->brick], S->fold_cols, S->fold_offs, S->fold_full,
                      L->brick, L->lx, L->ly, L->lz, S->inv_hs[L->lev], result);
            *(direct ? &J->out[e] : &J->ordered[e]) = result[0];
        } else if (L->lev >= 0) {
            point_sum(S, order, 0, L->x, L->y, L->z, sum_key, sum_brick, result);
            *(direct ? &J->out[e] : &J->ordered[e]) = result[0];
        } else {
            *(direct ? &J->out[e] : &J->ordered[e]) = L->x == L->x && L->z == L->z ? 0.0 : NAN; /* no brick at the point: 0 */
        }
    }
}

static void latlon_back(void *ctx, int64_t blk)
{
    latlon_job *J = ctx;
    int64_t lo = blk * J->size, hi = lo + J->size < J->m ? lo + J->size : J->m;
    for (int64_t p = lo; p < hi; ++p)
        J->out[KEY_AT(J->sorted[p])] = J->ordered[p];
}

GS_HOT static void latlon_evaluate(void *ctx, int64_t task)
{
    const latlon_job *J = ctx;
    int64_t lo = task * CHUNK, hi = lo + CHUNK < J->m ? lo + CHUNK : J->m;
    const int order = (int)J->S->order;
    /* the chain pipeline for tables too big for the caches (quantised ones:
     * QUANTISE_FROM_COEFFICIENTS) and points so sparse that most reach a new brick or
     * cell column: the chunk's sort codes span more than LL_SPARSE sort cells a point
     * (1,000,000 global points about 2, a regional batch of as many 0.04); dense points
     * find their tables in the caches and would pay the chain's prefetches for nothing. */
    uint64_t span = KEY_CODE(J->sorted[hi - 1]) - KEY_CODE(J->sorted[lo]);
    int chain = J->S->qwidth && span > (uint64_t)(LL_SPARSE * (hi - lo)), ahead = 0;
    /* float64 tables beyond the caches (J->ahead): the chain pipeline where the chunk
     * has fewer than AHEAD_SPARSE points a brick (a global batch of 100,000 points: about
     * 25; of 1,000,000 about 230), else the bricks ahead unless its points share one */
    if (J->ahead) {
        int64_t bricks = 1;
        for (int64_t p = lo + 1; p < hi; ++p)
            bricks += brick_code(J, p) != brick_code(J, p - 1);
        chain = bricks * AHEAD_SPARSE > hi - lo;
        ahead = !chain && bricks > 1;
    }
    if (chain) {
        if (order == 6)
            latlon_range(J, 6, 1, 0, lo, hi, NULL, 0);
        else
            latlon_range(J, order, 1, 0, lo, hi, NULL, 0);
    } else if (order == 4)
        latlon_range(J, 4, 0, 0, lo, hi, NULL, ahead);
    else if (order == 6)
        latlon_range(J, 6, 0, 0, lo, hi, NULL, ahead);
    else
        latlon_range(J, order, 0, 0, lo, hi, NULL, ahead);
}

/* The points lo..hi of task as they come (gs_undulation_latlon's in_order): each value
 * written in its place, the invalid coordinates counted into J->invalid[task]. */
GS_HOT static void latlon_direct(void *ctx, int64_t task)
{
    const latlon_job *J = ctx;
    int64_t lo = task * CHUNK, hi = lo + CHUNK < J->m ? lo + CHUNK : J->m, bad = 0;
    const int order = (int)J->S->order;
    if (order == 4)
        latlon_range(J, 4, 0, 1, lo, hi, &bad, 0);
    else if (order == 6)
        latlon_range(J, 6, 0, 1, lo, hi, &bad, 0);
    else
        latlon_range(J, order, 0, 1, lo, hi, &bad, 0);
    J->invalid[task] = bad;
}

/* Spline values at the directions of latitude/longitude (degrees) into out. Returns the
 * number of invalid coordinates (a latitude beyond +-90 or infinite, a longitude infinite
 * or beyond +-max_abs_longitude; out is then left unset), or -1 when memory ran out. NaN
 * gives NaN. (The bound is checked here, in the pass that reads the coordinates anyway,
 * rather than by the caller in two more serial passes over the longitudes.)
 *
 * in_order: the points are evaluated as they come (latlon_direct; tables that fit the
 * caches), chunks in parallel, each value written in its place. Otherwise they are
 * sorted by a 21-bit code in two passes: for float64 tables the 3-D Morton code of their
 * cell on the finest level's lattice (cell_code4: brick-major, so each brick's table is
 * read in one stretch), for quantised ones (the chain pipeline's) the Morton code of
 * their 0.18 degree latitude/longitude cell (latlon_code4):
 * 1. per block of points (nblocks in parallel): the codes and a histogram of their
 *    high 11 bits (the bucket) per block;
 * 2. exclusive prefix sums over (bucket, block): a stable order by bucket;
 * 3. per block: each point's (code, position) scattered in that order; then each bucket
 *    sorted by the low bits of the code (latlon_refine; cell codes by their top 5);
 * 4. per chunk of the sorted points, in that order: directions (4 at a time), each
 *    point's loads asked for points before its sum (latlon_range); float64 tables beyond
 *    the caches (S->fold_size) have the tables of the bricks ahead asked for, or at
 *    sparse points take the chain pipeline (latlon_evaluate);
 * 5. per block: each value written to its point's place (writing it from step 4 is
 *    slower: scattered stores in the hot loop).
 * A point's value does not depend on the order, blocks or threads, and equals
 * gs_evaluate_bricks at the direction gs_unit_vectors gives. */
GS_EXPORT int64_t gs_undulation_latlon(const gs_spline *S, const double *latitude, const double *longitude, int64_t m,
                                       int64_t nblocks, double *out, int64_t nthreads, double max_abs_longitude,
                                       int64_t in_order)
{
    latlon_job J = {S, latitude, longitude, out, max_abs_longitude, m, nblocks, (m + nblocks - 1) / nblocks};
    int64_t result = -1;
    J.halving = S->nlev > 0;
    for (int64_t lev = 0; lev < S->nlev; ++lev)
        J.halving &= ldexp(S->inv_hs[lev], (int)(S->nlev - 1 - lev)) == S->inv_hs[S->nlev - 1];
    if (in_order) {
        const int64_t ntasks = (m + CHUNK - 1) / CHUNK;
        J.invalid = malloc(sizeof(int64_t) * (size_t)(ntasks ? ntasks : 1));
        if (!J.invalid)
            return -1;
        gs_parallel_for((int)nthreads, ntasks, latlon_direct, &J);
        result = 0;
        for (int64_t task = 0; task < ntasks; ++task)
            result += J.invalid[task];
        free(J.invalid);
        return result;
    }
    J.code = malloc(sizeof(uint32_t) * (size_t)(m ? m : 1));
    J.bucket_start = malloc(sizeof(int64_t) * (LL_BUCKETS + 2));
    J.counts = calloc((size_t)nblocks * (LL_BUCKETS + 1), sizeof(int64_t));
    J.invalid = calloc((size_t)nblocks, sizeof(int64_t));
    J.by_bucket = malloc(sizeof(uint64_t) * (size_t)(m ? m : 1));
    J.sorted = malloc(sizeof(uint64_t) * (size_t)(m ? m : 1));
    if (!J.code || !J.bucket_start || !J.counts || !J.invalid || !J.by_bucket || !J.sorted)
        goto done;
    /* float64 tables: a brick-major order (cell_code4); quantised ones (beyond the caches) keep
     * the latitude/longitude order, which the chain pipeline's sparse test reads */
    J.cells = S->qwidth == 0 && S->nlev > 0;
    if (J.cells) {
        double inv_h = S->inv_hs[S->nlev - 1];
        double offset = 16.0 * ceil((inv_h + 2.0) / 16.0); /* whole bricks: the lattice's bricks stay runs */
        int shift = 0;
        while (2.0 * offset > ldexp(128.0, shift) && shift < 24)
            shift += 1;
        J.cell_scale = inv_h;
        J.cell_offset = offset;
        J.cell_shift = shift;
        /* a brick is 2**(BRICK_BITS - shift) cells of the code's lattice a side when that
         * is whole (offset: whole bricks) */
        J.ahead = S->fold_size != NULL && shift <= BRICK_BITS;
        J.brick_code_shift = 3 * (BRICK_BITS - shift);
        J.brick_code_offset = (int64_t)offset >> BRICK_BITS;
    }
    gs_parallel_for((int)nthreads, nblocks, latlon_count, &J);
    result = 0;
    for (int64_t blk = 0; blk < nblocks; ++blk)
        result += J.invalid[blk];
    if (result)
        goto done;
    int64_t total = 0;
    for (int64_t b = 0; b <= LL_BUCKETS; ++b) {
        J.bucket_start[b] = total;
        for (int64_t blk = 0; blk < nblocks; ++blk) {
            int64_t *c = J.counts + blk * (LL_BUCKETS + 1) + b, n = *c;
            *c = total;
            total += n;
        }
    }
    J.bucket_start[LL_BUCKETS + 1] = total;
    gs_parallel_for((int)nthreads, nblocks, latlon_scatter, &J);
    gs_parallel_for((int)nthreads, (LL_BUCKETS + SORT_TASK_BUCKETS) / SORT_TASK_BUCKETS, latlon_refine, &J);
    J.ordered = (double *)J.by_bucket; /* 8 bytes a point, no longer needed */
    gs_parallel_for((int)nthreads, (m + CHUNK - 1) / CHUNK, latlon_evaluate, &J);
    gs_parallel_for((int)nthreads, nblocks, latlon_back, &J);
done:
    free(J.code);
    free(J.bucket_start);
    free(J.counts);
    free(J.invalid);
    free(J.by_bucket);
    free(J.sorted);
    return result;
}

/* ---- building the index ----------------------------------------------------------- */

/* Every (brick, coefficient) pair of one row of a level's bricks (brick index row on the
 * first axis): a B-spline is listed in each brick of 2**bits cells a side whose tables
 * hold it (1 to 8; within a row at most 4, so every output holds 4 n entries). keys:
 * sorted packed keys (those outside the row are skipped). Fills brick_keys (B),
 * brick_start (B + 1), brick_of_entry (E), local (E, 3) = k - brick 2**bits + order - 1
 * per axis, coef (E), entries sorted by (brick key, local position) (a counting sort by
 * brick over the keys in order); sizes = (B, E). Returns 0, or -1 when memory ran out. */
GS_EXPORT int64_t gs_brick_row_entries(const int64_t *keys, int64_t n, int64_t first, int64_t order, int64_t bits,
                                       int64_t row, int64_t *brick_keys, int64_t *brick_start, int32_t *brick_of_entry,
                                       int16_t *local, int32_t *coef, int64_t *sizes)
{
    const int64_t big = ((int64_t)1) << 40;
    int64_t lo1 = big, hi1 = -big, lo2 = big, hi2 = -big;
    for (int64_t c = 0; c < n; ++c) {
        int64_t a0 = ((keys[c] >> (2 * GS_KEY_BITS)) & GS_KEY_MASK) - GS_KEY_OFFSET;
        if ((a0 >> bits) != row && ((a0 + order - 1) >> bits) != row)
            continue;
        int64_t a1 = ((keys[c] >> GS_KEY_BITS) & GS_KEY_MASK) - GS_KEY_OFFSET;
        int64_t a2 = (keys[c] & GS_KEY_MASK) - GS_KEY_OFFSET;
        if ((a1 >> bits) < lo1) lo1 = a1 >> bits;
        if (((a1 + order - 1) >> bits) > hi1) hi1 = (a1 + order - 1) >> bits;
        if ((a2 >> bits) < lo2) lo2 = a2 >> bits;
        if (((a2 + order - 1) >> bits) > hi2) hi2 = (a2 + order - 1) >> bits;
    }
    int64_t n1 = hi1 - lo1 + 1 > 0 ? hi1 - lo1 + 1 : 0, n2 = hi2 - lo2 + 1 > 0 ? hi2 - lo2 + 1 : 0;
    int64_t *counts = calloc((size_t)(n1 * n2 + 1), sizeof(int64_t));
    int64_t *brick_of_cell = malloc(sizeof(int64_t) * (size_t)(n1 * n2 + 1));
    if (!counts || !brick_of_cell) {
        free(counts);
        free(brick_of_cell);
        return -1;
    }
    int64_t nb = 0, total = 0;
    for (int sweep = 0; sweep < 2; ++sweep) { /* 0: count per brick; 1: place */
        if (sweep == 1) {
            for (int64_t cell = 0; cell < n1 * n2; ++cell) {
                brick_of_cell[cell] = -1;
                if (counts[cell] > 0) {
                    brick_keys[nb] = gs_pack(row, lo1 + cell / n2, lo2 + cell % n2);
                    brick_start[nb] = total;
                    brick_of_cell[cell] = nb;
                    total += counts[cell];
                    counts[cell] = brick_start[nb]; /* now the brick's cursor */
                    nb += 1;
                }
            }
            brick_start[nb] = total;
        }
        for (int64_t c = 0; c < n; ++c) {
            int64_t a0 = ((keys[c] >> (2 * GS_KEY_BITS)) & GS_KEY_MASK) - GS_KEY_OFFSET;
            if ((a0 >> bits) != row && ((a0 + order - 1) >> bits) != row)
                continue;
            int64_t l0 = a0 - (row << bits) + order - 1;
            int64_t a1 = ((keys[c] >> GS_KEY_BITS) & GS_KEY_MASK) - GS_KEY_OFFSET;
            int64_t a2 = (keys[c] & GS_KEY_MASK) - GS_KEY_OFFSET;
            for (int64_t b1 = a1 >> bits; b1 <= (a1 + order - 1) >> bits; ++b1)
                for (int64_t b2 = a2 >> bits; b2 <= (a2 + order - 1) >> bits; ++b2) {
                    int64_t cell = (b1 - lo1) * n2 + (b2 - lo2);
                    if (sweep == 0) {
                        counts[cell] += 1;
                    } else {
                        int64_t e = counts[cell]++;
                        local[3 * e] = (int16_t)l0;
                        local[3 * e + 1] = (int16_t)(a1 - (b1 << bits) + order - 1);
                        local[3 * e + 2] = (int16_t)(a2 - (b2 << bits) + order - 1);
                        coef[e] = (int32_t)(first + c);
                        brick_of_entry[e] = (int32_t)brick_of_cell[cell];
                    }
                }
        }
    }
    free(counts);
    free(brick_of_cell);
    sizes[0] = nb;
    sizes[1] = total;
    return 0;
}

/* The own table of one row of bricks from its entries (gs_brick_row_entries): a run per
 * (brick, column lx, ly) from its first to its last local k (gaps hold 0), runs in entry
 * order; the column entry is the run's offset from its brick's base << COL_SHIFT | first
 * k << COL_KBITS | length. With values NULL only counts: returns the number of values.
 * Otherwise fills base (nb), cols (nb, side, side; zeroed by the caller) and values
 * (zeroed). */
GS_EXPORT int64_t gs_own_table_row(const int64_t *brick_start, int64_t nb, const int16_t *local,
                                   const int32_t *coef_index, const double *coefficients, int64_t side, int64_t *base,
                                   int32_t *cols, double *values)
{
    int64_t at = 0;
    for (int64_t b = 0; b < nb; ++b) {
        int64_t b_base = at;
        if (values)
            base[b] = at;
        int64_t e = brick_start[b], end = brick_start[b + 1];
        while (e < end) {
            int64_t f = e;
            while (f + 1 < end && local[3 * (f + 1)] == local[3 * e] && local[3 * (f + 1) + 1] == local[3 * e + 1])
                f += 1;
            int64_t k0 = local[3 * e + 2];
            int64_t length = (int64_t)local[3 * f + 2] - k0 + 1;
            if (values) {
                cols[(b * side + local[3 * e]) * side + local[3 * e + 1]] =
                    (int32_t)(((at - b_base) << COL_SHIFT) | (k0 << COL_KBITS) | length);
                for (int64_t g = e; g <= f; ++g)
                    values[at + local[3 * g + 2] - k0] = coefficients[coef_index[g]];
            }
            at += length;
            e = f + 1;
        }
    }
    return at;
}

/* The own table of one row of a level's bricks (brick index row on the first axis)
 * straight from the level's sorted keys: the same bricks, column entries and values as
 * gs_brick_row_entries then gs_own_table_row give, without listing the (brick,
 * coefficient) pairs (building a single-level index: 5 times faster). keys: the n keys
 * whose first index is in [row S - order + 1, row S + S - 1] (S = 2**BRICK_BITS), sorted;
 * coefficients: theirs. sizes = (bricks, values) always; when they are within the
 * capacities (max_bricks, max_values) fills brick_keys, base, cols (bricks, side, side;
 * zeroed by the caller) and values (zeroed) and returns 0, else returns 1 (nothing
 * written); -1 when memory ran out. */
GS_EXPORT int64_t gs_own_table_keys(const int64_t *keys, int64_t n, const double *coefficients, int64_t order,
                                    int64_t row, int64_t max_bricks, int64_t max_values, int64_t *brick_keys,
                                    int64_t *base, int32_t *cols, double *values, int64_t *sizes)
{
    const int64_t bits = BRICK_BITS, side = (1 << BRICK_BITS) + order - 1;
    const int64_t big = ((int64_t)1) << 40;
    int64_t lo1 = big, hi1 = -big, lo2 = big, hi2 = -big;
    for (int64_t c = 0; c < n; ++c) {
        int64_t a1 = ((keys[c] >> GS_KEY_BITS) & GS_KEY_MASK) - GS_KEY_OFFSET;
        int64_t a2 = (keys[c] & GS_KEY_MASK) - GS_KEY_OFFSET;
        if ((a1 >> bits) < lo1) lo1 = a1 >> bits;
        if (((a1 + order - 1) >> bits) > hi1) hi1 = (a1 + order - 1) >> bits;
        if ((a2 >> bits) < lo2) lo2 = a2 >> bits;
        if (((a2 + order - 1) >> bits) > hi2) hi2 = (a2 + order - 1) >> bits;
    }
    int64_t n1 = hi1 - lo1 + 1 > 0 ? hi1 - lo1 + 1 : 0, n2 = hi2 - lo2 + 1 > 0 ? hi2 - lo2 + 1 : 0;
    int32_t *brick_of_cell = malloc(sizeof(int32_t) * (size_t)(n1 * n2 + 1));
    if (!brick_of_cell)
        return -1;
    for (int64_t cell = 0; cell < n1 * n2; ++cell)
        brick_of_cell[cell] = -1;
    /* the bricks: wherever a B-spline touches a cell; numbered in key order */
    for (int64_t c = 0; c < n; ++c) {
        int64_t a1 = ((keys[c] >> GS_KEY_BITS) & GS_KEY_MASK) - GS_KEY_OFFSET;
        int64_t a2 = (keys[c] & GS_KEY_MASK) - GS_KEY_OFFSET;
        for (int64_t b1 = a1 >> bits; b1 <= (a1 + order - 1) >> bits; ++b1)
            for (int64_t b2 = a2 >> bits; b2 <= (a2 + order - 1) >> bits; ++b2)
                brick_of_cell[(b1 - lo1) * n2 + (b2 - lo2)] = 0;
    }
    int64_t nb = 0;
    for (int64_t cell = 0; cell < n1 * n2; ++cell)
        if (brick_of_cell[cell] == 0)
            brick_of_cell[cell] = (int32_t)nb++;
    sizes[0] = nb;
    sizes[1] = 0;
    /* per column of each brick: its first and last local k */
    int8_t *k_first = malloc((size_t)(2 * nb * side * side + 1)), *k_last = k_first + nb * side * side;
    if (!k_first) {
        free(brick_of_cell);
        return -1;
    }
    memset(k_first, 127, (size_t)(nb * side * side));
    memset(k_last, -1, (size_t)(nb * side * side));
    int64_t result = 0;
    for (int pass = 0; pass < 2; ++pass) { /* 0: the runs' bounds; 1: the values */
        for (int64_t c = 0; c < n; ++c) {
            int64_t a0 = ((keys[c] >> (2 * GS_KEY_BITS)) & GS_KEY_MASK) - GS_KEY_OFFSET;
            int64_t a1 = ((keys[c] >> GS_KEY_BITS) & GS_KEY_MASK) - GS_KEY_OFFSET;
            int64_t a2 = (keys[c] & GS_KEY_MASK) - GS_KEY_OFFSET;
            int64_t l0 = a0 - (row << bits) + order - 1;
            for (int64_t b1 = a1 >> bits; b1 <= (a1 + order - 1) >> bits; ++b1)
                for (int64_t b2 = a2 >> bits; b2 <= (a2 + order - 1) >> bits; ++b2) {
                    int64_t b = brick_of_cell[(b1 - lo1) * n2 + (b2 - lo2)];
                    int64_t col = (b * side + l0) * side + a1 - (b1 << bits) + order - 1;
                    int64_t l2 = a2 - (b2 << bits) + order - 1;
                    if (pass == 0) {
                        if (l2 < k_first[col]) k_first[col] = (int8_t)l2;
                        if (l2 > k_last[col]) k_last[col] = (int8_t)l2;
                    } else {
                        values[base[b] + (cols[col] >> COL_SHIFT) + l2 - k_first[col]] = coefficients[c];
                    }
                }
        }
        if (pass == 1)
            break;
        int64_t total = 0;
        for (int64_t col = 0; col < nb * side * side; ++col)
            total += k_last[col] >= 0 ? (int64_t)k_last[col] - k_first[col] + 1 : 0;
        sizes[1] = total;
        if (nb > max_bricks || total > max_values) {
            result = 1;
            break;
        }
        /* the bricks' keys and the runs in (brick, column) order */
        for (int64_t cell = 0; cell < n1 * n2; ++cell)
            if (brick_of_cell[cell] >= 0)
                brick_keys[brick_of_cell[cell]] = gs_pack(row, lo1 + cell / n2, lo2 + cell % n2);
        int64_t at = 0;
        for (int64_t b = 0; b < nb; ++b) {
            base[b] = at;
            for (int64_t col = b * side * side; col < (b + 1) * side * side; ++col) {
                if (k_last[col] < 0)
                    continue;
                int64_t length = (int64_t)k_last[col] - k_first[col] + 1;
                cols[col] = (int32_t)(((at - base[b]) << COL_SHIFT) | ((int64_t)k_first[col] << COL_KBITS) | length);
                at += length;
            }
        }
    }
    free(k_first);
    free(brick_of_cell);
    return result;
}

/* The least k <= max_halvings such that every one of the n coefficients is bitwise
 * (double)(int32) q * (step / 2**k) for an integer q (as a store's decoder makes them:
 * its tiles are quantised with the manifest's step or a power-of-two fraction of it, and
 * a multiple of step / 2**k is one of step / 2**(k + 1), bitwise: scaling by 2 is exact),
 * or -1 when there is none. */
GS_EXPORT int64_t gs_finest_step(const double *coefficients, int64_t n, double step, int64_t max_halvings)
{
    int64_t k = 0;
    double s = step;
    for (int64_t c = 0; c < n; ++c)
        for (;;) {
            double r = rint(coefficients[c] / s);
            double back = fabs(r) < 2147483648.0 ? (double)(int32_t)r * s : NAN;
            if (memcmp(&back, &coefficients[c], sizeof back) == 0)
                break;
            if (++k > max_halvings)
                return -1;
            s *= 0.5;
        }
    return k;
}

/* The least and greatest q = c / step of values [lo, hi) (INT64_MAX, INT64_MIN when
 * empty); 0 when a value is not (double)(int32) q * step bitwise. */
static int brick_q_range(const double *values, int64_t lo, int64_t hi, double step, int64_t *q_min, int64_t *q_max)
{
    *q_min = INT64_MAX;
    *q_max = INT64_MIN;
    for (int64_t v = lo; v < hi; ++v) {
        double r = rint(values[v] / step);
        if (!(fabs(r) < 2147483648.0))
            return 0;
        int64_t qv = (int64_t)r;
        double back = (double)(int32_t)qv * step;
        if (memcmp(&back, &values[v], sizeof back) != 0) /* bitwise: -0.0 is not 0.0 */
            return 0;
        if (qv < *q_min) *q_min = qv;
        if (qv > *q_max) *q_max = qv;
    }
    return 1;
}

/* The base of an int16 brick whose integers span q_min .. q_max (at most 65,535 apart):
 * their middle, so that q - base lies in [-32768, 32767] and the base times the step is
 * about the brick's mean value (table_sum adds it once to sums of w (q - base): their
 * rounding then scales with the values, not with an offset of 32,768 steps); > INT32_MIN
 * (QBASE_WIDE), as q_min is (brick_q_range). */
static int64_t centred_base(int64_t q_min, int64_t q_max)
{
    return q_min + (q_max - q_min + 1) / 2;
}

/* A table's values (total, bricks by base (nb): brick b owns [base[b], base[b + 1]) as
 * integers q[v] = c / step - qbase[b] when every value c is (double)(int32) q * step
 * bitwise (a store's coefficients are): width 2, int16 (qbase[b] = centred_base: its q
 * must span at most 65,535 steps), or 4, int32 (qbase 0). Returns 0, or the first brick
 * that is not so (+ 1): q and qbase are then partly written. */
GS_EXPORT int64_t gs_quantise_table(const double *values, int64_t total, const int64_t *base, int64_t nb,
                                    double step, int64_t width, void *q, int32_t *qbase)
{
    for (int64_t b = 0; b < nb; ++b) {
        int64_t lo = base[b], hi = b + 1 < nb ? base[b + 1] : total;
        int64_t q_min, q_max;
        if (!brick_q_range(values, lo, hi, step, &q_min, &q_max))
            return b + 1;
        if (width == 2 && hi > lo && q_max - q_min > 65535)
            return b + 1;
        int64_t qb = width == 2 && hi > lo ? centred_base(q_min, q_max) : 0;
        if (qb > INT32_MAX || qb < INT32_MIN)
            return b + 1;
        qbase[b] = (int32_t)qb;
        for (int64_t v = lo; v < hi; ++v) {
            int64_t qv = (int64_t)rint(values[v] / step) - qb;
            if (width == 2)
                ((int16_t *)q)[v] = (int16_t)qv;
            else
                ((int32_t *)q)[v] = (int32_t)qv;
        }
    }
    return 0;
}

/* A table's values as gs_quantise_table's width 2, except that a brick whose q span
 * more than 65,535 steps holds them as int32 (qbase QBASE_WIDE), two int16 slots each:
 * starts (nb) receives each brick's first slot. q: room for 2 total slots. Returns the
 * slots used, or -(the first brick whose values are not multiples of step + 1). */
GS_EXPORT int64_t gs_quantise_mixed(const double *values, int64_t total, const int64_t *base, int64_t nb, double step,
                                    int16_t *q, int32_t *qbase, int64_t *starts)
{
    int64_t at = 0;
    for (int64_t b = 0; b < nb; ++b) {
        int64_t lo = base[b], hi = b + 1 < nb ? base[b + 1] : total;
        int64_t q_min, q_max;
        if (!brick_q_range(values, lo, hi, step, &q_min, &q_max))
            return -(b + 1);
        starts[b] = at;
        if (hi > lo && q_max - q_min > 65535) {
            qbase[b] = QBASE_WIDE;
            for (int64_t v = lo; v < hi; ++v, at += 2) {
                int32_t qv = (int32_t)rint(values[v] / step);
                memcpy(q + at, &qv, sizeof qv);
            }
        } else {
            int64_t qb = hi > lo ? centred_base(q_min, q_max) : 0;
            qbase[b] = (int32_t)qb;
            for (int64_t v = lo; v < hi; ++v)
                q[at++] = (int16_t)((int64_t)rint(values[v] / step) - qb);
        }
    }
    return at;
}

/* The full-column maps of a table (gs_spline's *_offs and *_full, see table_sum) from its
 * column entries cols (nb, side, side): offs, per column, its run's offset minus its first
 * local k (0 for an empty column), so that local k is at values + base + offs + k; full
 * (nb, S, S), per cell column (lx, ly), bit lz set when every column (lx + p, ly + q),
 * p, q < order, holds k = lz .. lz + order - 1 (first k <= lz, lz + order <= first k +
 * length). offs_width: 4, int32 offs; 2, int16 (a brick's runs hold at most side^3 <=
 * 31^3 < 2^15 values, so every offset fits). */
GS_EXPORT void gs_full_columns(const int32_t *cols, int64_t nb, int64_t order, void *offs, int64_t offs_width,
                               uint16_t *full)
{
    const int64_t cells = 1 << BRICK_BITS, side = cells + order - 1;
    uint32_t column_mask[(1 << COL_KBITS) * (1 << COL_KBITS)], row_mask[(1 << COL_KBITS) << BRICK_BITS];
    for (int64_t b = 0; b < nb; ++b) {
        const int32_t *bc = cols + b * side * side;
        for (int64_t c = 0; c < side * side; ++c) {
            int64_t length = bc[c] & COL_KMASK, k0 = (bc[c] >> COL_KBITS) & COL_KMASK;
            int64_t last = k0 + length - order < cells - 1 ? k0 + length - order : cells - 1; /* last lz */
            int32_t off = length ? (int32_t)((bc[c] >> COL_SHIFT) - k0) : 0;
            if (offs_width == 2)
                ((int16_t *)offs)[b * side * side + c] = (int16_t)off;
            else
                ((int32_t *)offs)[b * side * side + c] = off;
            column_mask[c] = length && last >= k0 ? (uint32_t)(((1u << (last + 1)) - 1) & ~((1u << k0) - 1)) : 0;
        }
        /* over the order columns along y, then along x (inner loops over ly: vectors) */
        for (int64_t i = 0; i < side; ++i) {
            uint32_t *m = row_mask + i * cells;
            for (int64_t ly = 0; ly < cells; ++ly)
                m[ly] = column_mask[i * side + ly];
            for (int64_t q = 1; q < order; ++q)
                for (int64_t ly = 0; ly < cells; ++ly)
                    m[ly] &= column_mask[i * side + ly + q];
        }
        for (int64_t lx = 0; lx < cells; ++lx) {
            uint32_t m[1 << BRICK_BITS];
            for (int64_t ly = 0; ly < cells; ++ly)
                m[ly] = row_mask[lx * cells + ly];
            for (int64_t p = 1; p < order; ++p)
                for (int64_t ly = 0; ly < cells; ++ly)
                    m[ly] &= row_mask[(lx + p) * cells + ly];
            for (int64_t ly = 0; ly < cells; ++ly)
                full[(b * cells + lx) * cells + ly] = (uint16_t)m[ly];
        }
    }
}

typedef struct {
    const double *parents;
    const int64_t *parent_of, *half;
    const double *weights;
    double *out;
    int64_t n, nout, nparents;
} subdivide_job;

/* Child brick i's table on spacing h from its parent brick's table on 2h (see
 * gs_subdivide_bricks), axis by axis. */
static void subdivide_task(void *ctx, int64_t i)
{
    const subdivide_job *J = ctx;
    const int64_t n = J->n, cells = 1 << BRICK_BITS, side = cells + n - 1, width = cells / 2 + n - 1;
    double *tx = calloc((size_t)(side * width * width + side * side * width), sizeof(double));
    if (!tx) {
        for (int64_t c = 0; c < side * side * side; ++c)
            J->out[i * side * side * side + c] = NAN; /* out of memory: no numbers made up */
        return;
    }
    double *ty = tx + side * width * width;
    const double *parent = J->parents + J->parent_of[i] * side * side * side;
    int64_t ox = J->half[3 * i] * (cells / 2), oy = J->half[3 * i + 1] * (cells / 2),
            oz = J->half[3 * i + 2] * (cells / 2);
    for (int64_t a = 0; a < side; ++a)
        for (int64_t m = 0; m <= n; ++m) {
            int64_t num = a + n - 1 - m;
            if (num < 0 || (num & 1) != 0 || (num >> 1) >= width)
                continue;
            int64_t q = ox + (num >> 1);
            double wm = J->weights[m];
            for (int64_t j = 0; j < width; ++j)
                for (int64_t k = 0; k < width; ++k)
                    tx[(a * width + j) * width + k] += wm * parent[(q * side + oy + j) * side + oz + k];
        }
    for (int64_t a = 0; a < side; ++a)
        for (int64_t b = 0; b < side; ++b)
            for (int64_t m = 0; m <= n; ++m) {
                int64_t num = b + n - 1 - m;
                if (num < 0 || (num & 1) != 0 || (num >> 1) >= width)
                    continue;
                int64_t q = num >> 1;
                double wm = J->weights[m];
                for (int64_t k = 0; k < width; ++k)
                    ty[(a * side + b) * width + k] += wm * tx[(a * width + q) * width + k];
            }
    double *out = J->out + i * side * side * side;
    for (int64_t a = 0; a < side; ++a)
        for (int64_t b = 0; b < side; ++b)
            for (int64_t c = 0; c < side; ++c) {
                double acc = 0.0;
                for (int64_t m = 0; m <= n; ++m) {
                    int64_t num = c + n - 1 - m;
                    if (num < 0 || (num & 1) != 0 || (num >> 1) >= width)
                        continue;
                    acc += J->weights[m] * ty[(a * side + b) * width + (num >> 1)];
                }
                out[(a * side + b) * side + c] = acc;
            }
    free(tx);
}

/* Brick tables of a spline written on the grid of half the spacing (folding).
 *
 * parents (P, side, side, side) are brick tables on spacing 2h (table index c of brick b
 * is B-spline b S - n + 1 + c, S = 2**BRICK_BITS, n = order); child brick i lies in parent
 * brick parent_of[i], in its half half[i] (0/1 per axis). out[i] (side^3) receives the
 * child's table on spacing h by the refinement relation B(x) = sum_m weights[m] B(2x - m)
 * (weights: n + 1 of them, 2^-(n-1) binom(n, m)): child index c draws on parent index
 * q = (c + n - 1 - m) / 2 + half S / 2. n + 1 multiply-adds per output of each pass. */
GS_EXPORT void gs_subdivide_bricks(const double *parents, int64_t nparents, const int64_t *parent_of,
                                   const int64_t *half, const double *weights, int64_t nweights, double *out,
                                   int64_t nout, int64_t nthreads)
{
    subdivide_job J = {parents, parent_of, half, weights, out, nweights - 1, nout, nparents};
    gs_parallel_for((int)nthreads, nout, subdivide_task, &J);
}
