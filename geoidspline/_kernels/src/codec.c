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

/* Format 4's templates (geoidspline/store/codec.py, template_shift): the rows a row is
 * predicted from by the tile level's own least-squares weights, as (a, b, c) offsets in slab
 * axes. The whole template (WHOLE_TAPS): the 4 x 4 rows of slab a - 1 from (shift[0], shift[1])
 * - 1 (the level's mean radial foot offset, floored), the 3 x 3 of slab a - 2 around
 * (shift[2], shift[3]) (twice it, rounded), and the four rows before it in its own slab that
 * touch it. The small template (SMALL_TAPS), for a row whose whole one is not there: the 3 x 3
 * rows of slab a - 1 from (shift[0], shift[1]) and the same four. All come before the row in
 * slab order. */
#define WHOLE_TAPS 29
#define SMALL_TAPS 13
#define WEIGHT_BITS 16 /* the weights' fixed point: 1/65536 */

static void template_offsets(const int64_t *shift, int64_t whole[WHOLE_TAPS][3], int64_t small[SMALL_TAPS][3])
{
    int t = 0, u = 0;
    for (int db = -1; db <= 2; ++db)
        for (int dc = -1; dc <= 2; ++dc, ++t) {
            whole[t][0] = -1;
            whole[t][1] = shift[0] + db;
            whole[t][2] = shift[1] + dc;
            if (db >= 0 && dc >= 0) {
                small[u][0] = -1;
                small[u][1] = shift[0] + db;
                small[u][2] = shift[1] + dc;
                ++u;
            }
        }
    for (int db = -1; db <= 1; ++db)
        for (int dc = -1; dc <= 1; ++dc, ++t) {
            whole[t][0] = -2;
            whole[t][1] = shift[2] + db;
            whole[t][2] = shift[3] + dc;
        }
    const int64_t own[4][2] = {{0, -1}, {-1, -1}, {-1, 0}, {-1, 1}};
    for (int m = 0; m < 4; ++m, ++t, ++u) {
        whole[t][0] = small[u][0] = 0;
        whole[t][1] = small[u][1] = own[m][0];
        whole[t][2] = small[u][2] = own[m][1];
    }
}

/* Rows (slab order) of a template of count taps (linear offsets in the padded box) at cell:
 * whether all are there (at[] set). */
GS_INLINE int template_rows_at(const int32_t *box, int64_t cell, const int64_t *linear, int count, int64_t *at)
{
    for (int t = 0; t < count; ++t)
        if ((at[t] = box[cell + linear[t]]) < 0)
            return 0;
    return 1;
}

/* The shared pass of formats 3 and 4. keys: the level's n sorted packed keys; values int64
 * holding int32; column: the previous row's foot error is predicted too. decode: values from
 * residuals (values written); else residuals from values (residuals written). shift (4) given
 * (format 4): a row whose whole template's rows are all there is predicted by them with
 * weights (WHOLE_TAPS, in 1/2^WEIGHT_BITS; NULL: not), else one whose small template's are,
 * with small (SMALL_TAPS; NULL: not), else as format 3. kinds (n, key order, or NULL): how each
 * row was predicted (0 whole template, 1 small template, 2 bicubic foot, 3 bilinear foot, 4 the
 * row before, 5 by 0). taps (n x WHOLE_TAPS, or n x SMALL_TAPS when which is 1; key order; or
 * NULL): with shift given, only each row's rows of that template (key-order positions; -1 in
 * each place when one is missing) are written, and kinds: 0 where they are all there. Returns
 * 0, or -1 when memory ran out. */
static int radial_pass(int64_t n, const int64_t *keys, int64_t order, int64_t column, int64_t decode,
                       int64_t *values, int64_t *residuals, const int64_t *shift, const int64_t *weights,
                       const int64_t *small, uint8_t *kinds, int64_t *taps, int which)
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
    int32_t *box = NULL;
    int status = -1; /* until the pass is done: memory ran out */
    if (!start || !perm || !slab_keys || !foot || !footed)
        goto done;
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

    /* format 4: a dense box of the rows by slab-axis position, for the template's lookups,
     * padded by the templates' reach (2 slabs before, pad rows aside) so that no lookup
     * leaves it: a tap is a fixed offset in it */
    int64_t whole[WHOLE_TAPS][3], small_offsets[SMALL_TAPS][3], box_lo[3] = {lo_a - 2, 0, 0}, span[3] = {slabs + 2, 0, 0};
    int64_t whole_linear[WHOLE_TAPS], small_linear[SMALL_TAPS];
    if (shift) {
        template_offsets(shift, whole, small_offsets);
        int64_t pad = 0;
        for (int t = 0; t < WHOLE_TAPS; ++t)
            for (int x = 1; x < 3; ++x)
                pad = llabs(whole[t][x]) > pad ? llabs(whole[t][x]) : pad;
        for (int x = 1; x < 3; ++x) {
            int axis = x == 1 ? b : c;
            int64_t low = unpack(keys[0], axis), high = low;
            for (int64_t i = 1; i < n; ++i) {
                int64_t v = unpack(keys[i], axis);
                low = v < low ? v : low;
                high = v > high ? v : high;
            }
            box_lo[x] = low - pad;
            span[x] = high - low + 1 + 2 * pad;
        }
        for (int t = 0; t < WHOLE_TAPS; ++t)
            whole_linear[t] = (whole[t][0] * span[1] + whole[t][1]) * span[2] + whole[t][2];
        for (int t = 0; t < SMALL_TAPS; ++t)
            small_linear[t] = (small_offsets[t][0] * span[1] + small_offsets[t][1]) * span[2] + small_offsets[t][2];
        box = malloc((size_t)(span[0] * span[1] * span[2]) * sizeof *box);
        if (!box)
            goto done;
        for (int64_t i = 0; i < span[0] * span[1] * span[2]; ++i)
            box[i] = -1;
        for (int64_t r = 0; r < n; ++r)
            box[((unpack(slab_keys[r], 0) - box_lo[0]) * span[1] + unpack(slab_keys[r], 1) - box_lo[1]) * span[2]
                + unpack(slab_keys[r], 2) - box_lo[2]] = (int32_t)r;
    }

    int64_t hint[4] = {0, 0, 0, 0};
    for (int64_t r = 0; r < n; ++r) {
        int64_t key = slab_keys[r], ia = unpack(key, 0), s = ia - lo_a;
        int64_t prediction = 0, total = 0, acc = 0;
        int64_t den = 2 * ia + order;
        int kind = 5, templated = 0;
        if (box) { /* format 4: a template, where all of its rows are there */
            int64_t at[WHOLE_TAPS];
            int64_t cell = ((ia - box_lo[0]) * span[1] + unpack(key, 1) - box_lo[1]) * span[2] + unpack(key, 2) - box_lo[2];
            if (taps) {
                int count = which ? SMALL_TAPS : WHOLE_TAPS;
                int there = template_rows_at(box, cell, which ? small_linear : whole_linear, count, at);
                for (int t = 0; t < count; ++t)
                    taps[perm[r] * count + t] = there ? perm[at[t]] : -1;
                if (kinds)
                    kinds[perm[r]] = there ? 0 : 5;
                continue;
            }
            const int64_t *w = NULL;
            int count = 0;
            if (weights && template_rows_at(box, cell, whole_linear, WHOLE_TAPS, at)) {
                w = weights;
                count = WHOLE_TAPS;
                kind = 0;
            } else if (small && template_rows_at(box, cell, small_linear, SMALL_TAPS, at)) {
                w = small;
                count = SMALL_TAPS;
                kind = 1;
            }
            if (w) {
                for (int t = 0; t < count; ++t)
                    acc += w[t] * values[perm[at[t]]];
                prediction = (acc + ((int64_t)1 << (WEIGHT_BITS - 1))) >> WEIGHT_BITS; /* arithmetic: floor */
                templated = 1;
                acc = 0;
            }
        }
        if (!templated && s > 0 && den != 0) {
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
                kind = 2;
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
            kind = kind == 2 ? 2 : 3;
            /* the foot's interpolation error varies slowly along a column: take the
             * previous row's off too, when that was predicted from its foot */
            if (column && has_prev && footed[r - 1])
                prediction += values[perm[r - 1]] - foot[r - 1];
            footed[r] = 1;
        } else if (!templated && has_prev) {
            prediction = values[perm[r - 1]];
            kind = 4;
        }
        int64_t row = perm[r];
        if (kinds)
            kinds[row] = (uint8_t)kind;
        if (decode) /* values are int32: the sum wraps as the encoder's difference did */
            values[row] = (int32_t)(uint32_t)(uint64_t)(prediction + residuals[row]);
        else
            residuals[row] = values[row] - prediction;
    }
    status = 0;
done:
    free(start);
    free(perm);
    free(slab_keys);
    free(foot);
    free(footed);
    free(box);
    return status;
}

/* Format 3: the radial foot alone (radial_pass without a template). */
GS_EXPORT int gs_radial_code(int64_t n, const int64_t *keys, int64_t order, int64_t column, int64_t decode,
                             int64_t *values, int64_t *residuals)
{
    return radial_pass(n, keys, order, column, decode, values, residuals, NULL, NULL, NULL, NULL, NULL, 0);
}

/* Format 4: the templates by their weights where they are there, else format 3's prediction;
 * kinds (uint8, n) written. */
GS_EXPORT int gs_template_code(int64_t n, const int64_t *keys, int64_t order, int64_t column, int64_t decode,
                               const int64_t *shift, const int64_t *weights, const int64_t *small, int64_t *values,
                               int64_t *residuals, uint8_t *kinds)
{
    return radial_pass(n, keys, order, column, decode, values, residuals, shift, weights, small, kinds, NULL, 0);
}

/* Format 4's template rows: taps (n x its taps) and kinds of template which (0 whole, 1 small). */
GS_EXPORT int gs_template_rows(int64_t n, const int64_t *keys, int64_t order, const int64_t *shift, int64_t which,
                               int64_t *taps, uint8_t *kinds)
{
    return radial_pass(n, keys, order, 0, 0, NULL, NULL, shift, NULL, NULL, kinds, taps, (int)which);
}

GS_EXPORT int64_t gs_template_taps(int64_t which)
{
    return which ? SMALL_TAPS : WHOLE_TAPS;
}
