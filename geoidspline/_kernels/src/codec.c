/* Store codec, format 3: the radial-foot prediction of one tile level's quantised values
 * (geoidspline/store/codec.py, radial_code), for encoding (residuals from values) and
 * decoding (values from residuals) by the same code, so both predict alike bit for bit.
 *
 * Slab order: rows sorted by their index along the axis a nearest the level's mean radial
 * direction (the largest |sum of 2 P|, P = index + order/2 the support centre in
 * spacings; the first such axis), then by the other two axes b < c. A row at P is
 * predicted from slab P_a - 1 at its radial foot P - P / P_a (bicubic, Catmull-Rom, where
 * the 16 nodes around it are there, else bilinear normalised over the four nodes present;
 * the foot in 1/256 of a spacing) plus, when the previous row is
 * the same (a, b) column at c - 1 and was predicted from its foot too, that row's value
 * minus its foot prediction (when column is set: this helps where the coefficients are
 * smooth at the step, and adds noise where the step is far below their noise); a row without a foot node by the previous row when that
 * is the same column at c - 1, else by 0. Integers only. Every node and the previous row
 * come before the row in slab order: one pass decodes. */
#include <stdlib.h>

#include "gs_common.h"

#define FRACTION 256 /* the foot's fixed point: 1/256 of a spacing (2 FRACTION^2 = 2^17) */

/* floor(x / y) for y != 0 */
GS_INLINE int64_t floor_div(int64_t x, int64_t y)
{
    int64_t q = x / y;
    return (x % y != 0 && ((x < 0) != (y < 0))) ? q - 1 : q;
}

/* floor(x / y) for y != 0, in 32 bits */
GS_INLINE int32_t floor_div32(int32_t x, int32_t y)
{
    int32_t q = x / y;
    return (x % y != 0 && ((x < 0) != (y < 0))) ? q - 1 : q;
}

/* Catmull-Rom weights w[0..3] of the nodes -1, 0, 1, 2 at t = f / FRACTION, in 1/4096
 * (rounded from their exact values in 1/(2 FRACTION^3) = 2^-25; negative ones too). */
GS_INLINE void catmull_rom(int64_t f, int64_t *w)
{
    const int64_t F = FRACTION, f2 = f * f, f3 = f2 * f;
    const int64_t exact[4] = {-f3 + 2 * F * f2 - F * F * f, 3 * f3 - 5 * F * f2 + 2 * F * F * F,
                              -3 * f3 + 4 * F * f2 + F * F * f, f3 - F * f2};
    for (int m = 0; m < 4; ++m)
        w[m] = floor_div(exact[m] + (1 << 12), 1 << 13);
}

GS_INLINE int64_t unpack(int64_t key, int axis)
{
    return ((key >> ((2 - axis) * GS_KEY_BITS)) & GS_KEY_MASK) - GS_KEY_OFFSET;
}

/* First position in sorted keys[lo..hi) whose key is >= value, searched outwards from
 * *hint (the last answer: the feet of successive rows are near one another). */
GS_INLINE int64_t lower_bound_near(const int64_t *keys, int64_t lo, int64_t hi, int64_t value, int64_t *hint)
{
    int64_t at = *hint < lo ? lo : (*hint > hi ? hi : *hint);
    int64_t step = 1, left, right;
    if (at < hi && keys[at] < value) { /* the answer is after at: gallop right */
        left = at + 1;
        while (left + step - 1 < hi && keys[left + step - 1] < value) {
            left += step;
            step <<= 1;
        }
        right = left + step - 1 < hi ? left + step - 1 : hi;
    } else { /* the answer is at or before at: gallop left */
        right = at;
        while (right - step >= lo && keys[right - step] >= value) {
            right -= step;
            step <<= 1;
        }
        left = right - step + 1 > lo ? right - step + 1 : lo;
    }
    at = left + gs_lower_bound(keys + left, right - left, value);
    *hint = at;
    return at;
}

/* keys: the level's n sorted packed keys; values int64 holding int32; column: the
 * previous row's foot error is predicted too. decode: values from
 * residuals (values written); else residuals from values (residuals written). Returns 0, or
 * -1 when memory ran out. */
GS_EXPORT int gs_radial_code(int64_t n, const int64_t *keys, int64_t order, int64_t column, int64_t decode,
                             int64_t *values, int64_t *residuals)
{
    if (n <= 0)
        return 0;
    int64_t sum[3] = {0, 0, 0};
    for (int64_t i = 0; i < n; ++i)
        for (int d = 0; d < 3; ++d)
            sum[d] += 2 * unpack(keys[i], d) + order;
    int a = 0;
    for (int d = 1; d < 3; ++d)
        if (llabs(sum[d]) > llabs(sum[a]))
            a = d;
    int b = a == 0 ? 1 : 0, c = a == 2 ? 1 : 2;
    int64_t lo_a = unpack(keys[0], a), hi_a = lo_a;
    for (int64_t i = 1; i < n; ++i) {
        int64_t x = unpack(keys[i], a);
        lo_a = x < lo_a ? x : lo_a;
        hi_a = x > hi_a ? x : hi_a;
    }
    int64_t slabs = hi_a - lo_a + 1;
    int64_t *start = calloc((size_t)slabs + 1, sizeof *start); /* first row of each slab */
    int64_t *perm = malloc((size_t)n * sizeof *perm);          /* slab order -> key order */
    int64_t *slab_keys = malloc((size_t)n * sizeof *slab_keys); /* packed (a, b, c), sorted */
    int64_t *foot = malloc((size_t)n * sizeof *foot);            /* each row's foot prediction */
    uint8_t *footed = calloc((size_t)n, 1);                       /* whether it had one */
    if (!start || !perm || !slab_keys || !foot || !footed) {
        free(start);
        free(perm);
        free(slab_keys);
        free(foot);
        free(footed);
        return -1;
    }
    /* a stable counting sort by the a index keeps key order, (b, c), within a slab */
    for (int64_t i = 0; i < n; ++i)
        start[unpack(keys[i], a) - lo_a + 1]++;
    for (int64_t s = 0; s < slabs; ++s)
        start[s + 1] += start[s];
    for (int64_t i = 0; i < n; ++i) {
        int64_t s = unpack(keys[i], a) - lo_a;
        int64_t r = start[s]++;
        perm[r] = i;
        slab_keys[r] = gs_pack(unpack(keys[i], a), unpack(keys[i], b), unpack(keys[i], c));
    }
    for (int64_t s = slabs; s > 0; --s) /* back to each slab's first row */
        start[s] = start[s - 1];
    start[0] = 0;

    int64_t hint[4] = {0, 0, 0, 0};
    for (int64_t r = 0; r < n; ++r) {
        int64_t key = slab_keys[r], ia = unpack(key, 0), s = ia - lo_a;
        int64_t prediction = 0, total = 0, acc = 0;
        int64_t den = 2 * ia + order;
        if (s > 0 && den != 0) {
            int64_t base[2], frac[2];
            for (int x = 0; x < 2; ++x) {
                /* foot_x = ix - P_x / P_a = ix - (2 ix + order) / den, in 1/FRACTION, floored:
                 * ix FRACTION - ceil((2 ix + order) FRACTION / den), whose quotient's
                 * operands fit 32 bits (|2 ix + order| < 2^22): the faster division */
                int64_t ix = unpack(key, x + 1);
                int32_t num = (int32_t)((2 * ix + order) * FRACTION), d32 = (int32_t)den;
                int32_t up = -floor_div32(-num, d32);
                int64_t fixed = ix * FRACTION - up;
                base[x] = floor_div(fixed, FRACTION);
                frac[x] = fixed - base[x] * FRACTION;
            }
            int64_t lo = start[s - 1], hi = start[s];
            /* bicubic (Catmull-Rom) where the 4 x 4 nodes around the foot are all there:
             * it keeps the content near the lattice's Nyquist that bilinear smooths away
             * (the foot lies up to a spacing aside where no axis dominates) */
            int64_t wb[4], wc[4], cubic_acc = 0, cubic_total = 0;
            int complete = 1;
            catmull_rom(frac[0], wb);
            catmull_rom(frac[1], wc);
            for (int db = -1; db <= 2 && complete; ++db) {
                int64_t nb = base[0] + db, nc = base[1] - 1;
                /* a node off the key range would alias another key: never one */
                if (nb < -GS_KEY_OFFSET || nb >= GS_KEY_OFFSET || nc < -GS_KEY_OFFSET || nc + 3 >= GS_KEY_OFFSET) {
                    complete = 0;
                    break;
                }
                int64_t node = gs_pack(ia - 1, nb, nc);
                int64_t at = lower_bound_near(slab_keys, lo, hi, node, &hint[db + 1]);
                for (int dc = 0; dc < 4; ++dc, ++node, ++at) { /* the nodes along c are the next keys */
                    if (at >= hi || slab_keys[at] != node) {
                        complete = 0;
                        break;
                    }
                    int64_t w = wb[db + 1] * wc[dc];
                    cubic_acc += w * values[perm[at]];
                    cubic_total += w;
                }
            }
            if (complete) {
                acc = cubic_acc;
                total = cubic_total;
            } else {
                for (int db = 0; db < 2; ++db) { /* bilinear, over the nodes present */
                    int64_t nb = base[0] + db, nc = base[1];
                    if (nb < -GS_KEY_OFFSET || nb >= GS_KEY_OFFSET || nc < -GS_KEY_OFFSET || nc + 1 >= GS_KEY_OFFSET)
                        continue;
                    int64_t node = gs_pack(ia - 1, nb, nc);
                    int64_t at = lower_bound_near(slab_keys, lo, hi, node, &hint[db + 1]);
                    for (int dc = 0; dc < 2; ++dc, ++node) {
                        int64_t w = (db ? frac[0] : FRACTION - frac[0]) * (dc ? frac[1] : FRACTION - frac[1]);
                        if (at < hi && slab_keys[at] == node) {
                            acc += w * values[perm[at]];
                            total += w;
                            ++at;
                        }
                    }
                }
            }
        }
        int has_prev = r > 0 && key - slab_keys[r - 1] == 1;
        if (total > 0) {
            if (total == FRACTION * FRACTION) /* all four nodes: a shift (arithmetic: floor) */
                prediction = (2 * acc + total) >> 17;
            else
                prediction = floor_div(2 * acc + total, 2 * total); /* rounded half up */
            foot[r] = prediction;
            /* the foot's interpolation error varies slowly along a column: take the
             * previous row's off too, when that was predicted from its foot */
            if (column && has_prev && footed[r - 1])
                prediction += values[perm[r - 1]] - foot[r - 1];
            footed[r] = 1;
        } else if (has_prev) {
            prediction = values[perm[r - 1]];
        }
        int64_t row = perm[r];
        if (decode) /* values are int32: the sum wraps as the encoder's difference did */
            values[row] = (int32_t)(uint32_t)(uint64_t)(prediction + residuals[row]);
        else
            residuals[row] = values[row] - prediction;
    }
    free(start);
    free(perm);
    free(slab_keys);
    free(foot);
    free(footed);
    return 0;
}
