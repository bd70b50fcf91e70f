"""Tile codecs of store formats 2 and 3: keys as runs, values quantised and predicted,
Zstandard coded.

A tile's coefficients, level by level and in key order (i, j, k), are stored as

- **runs**: maximal sequences of consecutive ``k`` in one ``(i, j)`` column (a level-0
  tile of a global quintic store has about 18 coefficients per run): the start triple
  and the length of each run. Sorted runs change slowly from one to the next, so the
  three start columns and the lengths are each delta-coded before entropy coding; the keys cost well under a byte per run.
- **values**: integers ``q = rint(c / step)`` (``step``: :func:`value_step`, stated in
  the manifest), each minus a prediction from values before it, byte-shuffled and
  entropy-coded. Decoding gives ``q · step``, bitwise the same in both formats.
  Format 3 (``MAGICS[3]``, written now) predicts a coefficient from its *radial foot*
  in the lattice plane before it (:func:`radial_residuals`: the coefficients sample a
  function constant along the radius) and zigzags the residuals; format 2 (``MAGIC``,
  still read, and written for ``format_version=2``) predicts by the previous value in
  key order. Format 3 is 27-41 % smaller on level-0 tiles of EGM96 and EGM2008 stores
  (benchmarks/README.md, "Store codec"). Format 4 (``MAGICS[4]``, written now) predicts
  a coefficient whose *template* is whole (the 4 x 4 rows of the slab before around the
  level's mean radial foot, the 3 x 3 of the slab two before, the four rows before it in
  its own slab: :func:`template_shift`) by least-squares weights fitted to the level's
  own values and stated in its header (:func:`template_weights`: a fitted level's
  coefficients are far from smooth at the step, and the weights learn how its slabs
  follow one another), the others as format 3 does; the residuals of the template and
  of the others (grouped by how each was predicted) are two arrays. Half the
  coefficients of an EGM2008 1 cm tile take the template at 1.3 bits instead of 3;
  the tiles are about a fifth smaller than format 3's.

Quantisation error bound: every coefficient moves by at most ``step / 2`` (a step where
a banded fit corrected its rounding at the nodes: :func:`geoidspline.fitting.bands.band_step`,
whose manifest states the bound that follows). The B-splines
of one level are non-negative and sum to at most 1 at every point (a partition of unity
where the level is complete, less where an overlay is partial), so one level's value
moves by at most ``step / 2`` anywhere, and a store of ``L`` levels by at most
``L · step / 2`` (:func:`value_error_bound`), on or off the sphere. The tests quantise,
evaluate and compare.

Entropy coding is Zstandard through python-zstandard (a maintained binding of the
reference library; no codec is written here), after two numpy transforms: differences of
neighbours (wrapping in int32) and a byte shuffle of the differences (all first bytes,
then all second bytes, ...). Each array is one standard Zstandard frame with its content
size and checksum: the layout numcodecs' ``Delta(int32)``, ``Shuffle(4)`` and
``Zstd(level=19, checksum=True)`` write, with which the first format-2 stores were
written and which this module reads; format 3's value array is zigzagged instead of
delta-coded (numcodecs itself is not used: its import scans
every installed package's entry points, 40-90 ms of a cold one-point query). A tile file is its format's signature (``MAGICS``), a 4-byte little-endian header length,
a UTF-8 JSON header (tile, step, per-level coefficient and run counts and, formats 3 and
4, whether the level's column term is used, format 4 its template; the encoded arrays'
byte counts) and the encoded arrays. Why not netCDF4/HDF5 as in format 1: an
HDF5 file with four compressed variables costs about 17.7 kB before any data (measured
with netCDF4 1.7.5, HDF5 1.14), more than the data of a 10,000-coefficient tile; this
container costs about 300 bytes.

Numeric functions without validation; :func:`decode_tile` checks the bytes it is given
and raises :class:`ValueError` with the rule broken (the store turns it into
:class:`~geoidspline.errors.StoreCorruptError` naming the file).
"""

from __future__ import annotations

import json
import struct

import numpy as np

from ..bspline import keys as _keys
from ..sphere.sample import interval_distance

ZSTD_LEVEL = 19
"""Zstandard level: tiles are written once and read many times; 19 is ~10 % smaller
than 3 on coefficient tiles and decodes as fast."""


MAGIC = b"GSPLTILE2\n"
"""First bytes of a format-2 tile file (format 1 tiles are netCDF4/HDF5: ``\\x89HDF``)."""

MAGICS = {2: MAGIC, 3: b"GSPLTILE3\n", 4: b"GSPLTILE4\n"}
"""First bytes of a coded tile file of each format (all of one length)."""

TILE_FORMAT = 4
"""The coded tile format written (stores of format 4); formats 2 and 3 are read as ever."""

CODECS = {2: f"Delta(int32) + Shuffle(4) + Zstd(level={ZSTD_LEVEL}, checksum)",
          3: f"RadialFoot(bicubic or bilinear, 1/256; column term per level) + ZigZag(int32) + Shuffle(4) + "
             f"Zstd(level={ZSTD_LEVEL}, checksum)",
          4: "LS template + radial foot; zstd"}  # short: a global store has 8,000 tiles
"""What each format's header states of its value array's coding."""

QUANTISATION_SHARE = 2.0 / 3.0
"""Share of the fit tolerance that the quantisation may add at most, over all levels
(a bound; the error it adds at random points is a small fraction of it: rounding errors
of neighbouring coefficients are independent and the B-splines average them)."""


_HEADER_LIMIT = 1 << 24


def value_step(tolerance_m: float, levels: int) -> float:
    """Quantisation step (metres) of a store fitted to ``tolerance_m`` with ``levels`` levels:
    the largest whole number of micrometres whose bound ``levels · step / 2`` is at most
    ``QUANTISATION_SHARE · tolerance_m`` (at least 1 µm)."""
    budget = 2.0 * QUANTISATION_SHARE * float(tolerance_m) / max(int(levels), 1)
    return max(1, int(np.floor(budget / 1e-6 + 1e-6))) * 1e-6


FIRST_STEP_FACTOR = 4
"""How many times :func:`value_step`'s step a banded model fit's search for its step
starts from (:func:`first_step`): the proven bound is the worst case, every rounding
change at once of one sign; the changes are independent and the B-splines average
them, so at the 27.7 M nodes of a global EGM2008 band at 1 cm the largest change was
0.35 step against the bound's 0.5 (benchmarks/README.md, "Store codec"). The search
checks the stored spline at every node of the model's lattice and halves: a power of
two, so that its steps pass through :func:`value_step`'s and a band that needs that
step still gets it."""


def first_step(tolerance_m: float, levels: int) -> float:
    """The step (metres) a banded model fit's search for its stored spline's step starts
    from (:func:`geoidspline.fitting.bands.band_step`): ``FIRST_STEP_FACTOR`` times
    :func:`value_step`'s."""
    return FIRST_STEP_FACTOR * value_step(tolerance_m, levels)


def node_safe_step(spline, node_directions, node_errors, tolerance_m: float, start_step: float | None = None,
                   between=None):
    """(step, node errors of the stored spline): the largest step, from :func:`value_step`
    halving down to 1 µm, at which the quantised spline's largest |error| at the fit's
    nodes is at most ``max(tolerance_m, the fit's own node max)``.

    The proven bound :func:`value_error_bound` (``L · step / 2`` for ``L`` levels) is the
    worst case; a fit that meets its tolerance at the nodes with no slack left (a grid fit
    reaches 0.4999 m of 0.5 m) would get no quantisation from it at all, yet rounding
    moves the worst nodes by a fraction of that (0.041 m of a 0.333 m bound in the 6-level
    global 0.5 m store). So the quantised spline is evaluated at every node, where the
    fit's errors ``node_errors`` (truth − fit, metres) are known: its errors there are
    ``node_errors − (quantised − fit)``, exactly. More levels give a smaller start
    (:func:`value_step` divides the share by the level count); more halvings follow where
    the fit left no room (:func:`slack_step` when the nodes are not at hand). (A banded
    model fit starts above it, :func:`first_step`: its nodes are a lattice as dense as
    its spline; a grid's are the data's own, and a store's error between them, at
    another source's nodes, grew with a larger step.)

    Halving stops at :func:`slack_step` of the room the fit left under ``tolerance_m``
    (a fit aims at a little less than its tolerance for this:
    :attr:`geoidspline.fitting.parameters.FitParameters.node_target_m`), whose proven
    bound keeps every node within ``tolerance_m``.

    ``start_step``: start there and halve exactly instead (a regional update's tiles,
    whose step must nest in the store's: :func:`geoidspline.store.format.steps_nest`).

    ``between``: ``(directions, low, high)`` of points between the nodes with an interval
    each (a grid's cell centres and the interval of its bilinear and bicubic interpolants
    there, metres): the step must also keep the quantised spline's largest distance
    outside those intervals within ``max(tolerance_m, the fit's own)`` (rounding moved an
    Andes 0.1 m store's centre from 0.099 to 0.104 m when the step was chosen against the
    nodes alone).
    """
    errors = np.asarray(node_errors, dtype=np.float64)
    fit_max = float(np.abs(errors).max()) if errors.size else 0.0
    target = max(float(tolerance_m), fit_max)
    if between is not None:
        between_directions, low, high = between
        between_fit = spline.evaluate_points(between_directions)
        between_max = float(interval_distance(between_fit, low, high).max(initial=0.0))
        between_target = max(float(tolerance_m), between_max)
        fit_max = max(fit_max, between_max)  # the room left for the proven step is the smaller
    step = value_step(tolerance_m, len(spline.levels)) if start_step is None else float(start_step)
    # a fit that left room under the tolerance has a step whose proven bound fits in it:
    # halving stops there, so the store keeps the tolerance at every node (and within the
    # room of the fit everywhere else)
    floor = slack_step(tolerance_m, fit_max, len(spline.levels)) \
        if start_step is None and fit_max < float(tolerance_m) else 0.0
    while True:
        stored_errors = errors - quantisation_change(spline, step, node_directions)
        following = max(1, int(round(step / 1e-6)) // 2) * 1e-6 if start_step is None else step / 2.0
        if following < floor <= step:  # the proven step, once halving reaches it
            following = floor
        kept = not stored_errors.size or np.abs(stored_errors).max() <= target
        if kept and between is not None:
            moved = between_fit + quantisation_change(spline, step, between_directions)
            kept = float(interval_distance(moved, low, high).max(initial=0.0)) <= between_target
        if following < 1e-6 or following >= step or kept:
            return step, stored_errors
        step = following


def slack_step(tolerance_m: float, node_max_error_m: float, levels: int) -> float:
    """The step whose proven bound ``levels · step / 2`` fits in the room a fit left at its
    nodes (``tolerance_m`` minus its node max; at least 1 µm): for a store whose nodes
    are not at hand (``geoid-info --upgrade``)."""
    room = max(float(tolerance_m) - float(node_max_error_m), 0.0)
    return value_step(room / QUANTISATION_SHARE, levels)


def quantisation_change(spline, step, directions):
    """Quantised minus exact spline at ``directions`` (M, 3): one evaluation of the
    spline whose coefficients are the rounding changes (the sum is linear in them)."""
    from ..bspline.level import LevelSpline
    from ..hierarchy.ambient import AmbientSpline

    change = AmbientSpline([LevelSpline(lv.level, lv.h, lv.order, lv.keys,
                                        quantise(lv.coefficients, step) * step - lv.coefficients)
                            for lv in spline.levels])
    return change.evaluate_points(directions)


def value_error_bound(step: float, levels: int) -> float:
    """Largest change (metres) of the spline's value that quantising with ``step`` can cause
    in a store of ``levels`` levels: ``levels · step / 2`` (see the module docstring)."""
    return max(int(levels), 1) * float(step) / 2.0


def quantise(values, step):
    """Integers nearest to values / step (int64)."""
    return np.rint(np.asarray(values, dtype=np.float64) / step).astype(np.int64)


def _compressor():
    import zstandard

    # checksum: a damaged array is refused even when the sha256 check is skipped
    return zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_checksum=True, write_content_size=True)


def _shuffle_compress(words):
    """Byte shuffle (all first bytes, then all second bytes, ...) and Zstandard of 32-bit
    words: small numbers' high bytes form long runs of one byte (19 % smaller than
    Zstandard alone on the 2 mm EGM96 store's deltas)."""
    shuffled = np.ascontiguousarray(words).view(np.uint8).reshape(-1, 4).T
    return _compressor().compress(np.ascontiguousarray(shuffled).tobytes())


def _shuffle_decompress(blob, count):
    """Inverse of :func:`_shuffle_compress` (uint32 words); :class:`ValueError` when the
    bytes are not one array of ``count`` words."""
    import zstandard

    try:
        data = zstandard.ZstdDecompressor().decompress(bytes(blob), max_output_size=count * 4)
    except zstandard.ZstdError as exc:
        raise ValueError(f"has a damaged array ({exc})") from None
    if len(data) != count * 4:
        raise ValueError(f"an array holds {len(data)} bytes, the header says {count} numbers")
    return np.frombuffer(data, dtype=np.uint8).reshape(4, count).T.copy().view(np.uint32).ravel()


def _zigzag(residuals):
    """int32 (wrapping) to uint32 with the sign in the lowest bit: small magnitudes of
    either sign become small words, whose high bytes are all 0 (11 % smaller than two's
    complement after the shuffle, on EGM2008 tiles)."""
    r = np.asarray(residuals, dtype=np.int64).astype(np.int32)
    return ((r.astype(np.uint32) << np.uint32(1)) ^ (r >> 31).astype(np.uint32))


def _unzigzag(words):
    """Inverse of :func:`_zigzag` (int64 holding int32 values)."""
    words = words.astype(np.uint32)
    return ((words >> np.uint32(1)) ^ (np.uint32(0) - (words & np.uint32(1)))).view(np.int32).astype(np.int64)


def _delta_encode(array, dtype):
    """Format-2 array: delta (wrapping in ``dtype``), byte shuffle, Zstandard."""
    array = np.ascontiguousarray(array, dtype=dtype)
    delta = np.empty_like(array)
    if array.size:
        delta[0] = array[0]
        np.subtract(array[1:], array[:-1], out=delta[1:])
    return _shuffle_compress(delta.view(np.uint32))


def _delta_decode(blob, dtype, count):
    """Inverse of :func:`_delta_encode`."""
    return np.cumsum(_shuffle_decompress(blob, count).view(dtype), dtype=dtype)


def runs_of(keys):
    """(start index into keys, length) of the runs of consecutive keys along k (sorted keys)."""
    keys = np.asarray(keys, dtype=np.int64)
    if keys.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    starts = np.flatnonzero(np.r_[True, np.diff(keys) != 1])
    lengths = np.diff(np.r_[starts, keys.size])
    return starts, lengths


def keys_of_runs(start_keys, lengths):
    """The sorted keys of runs starting at ``start_keys`` (packed) with ``lengths``."""
    total = int(lengths.sum())
    offsets = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    return np.repeat(start_keys, lengths) + offsets


# -- format 3: values predicted along the radius -------------------------------------------


def radial_residuals(keys, order, values, column=True):
    """Format 3's prediction residuals (int64) of one level's quantised ``values`` (int32
    range, in the order of its sorted packed ``keys``; ``order``: the spline's).

    The coefficients of a level are samples of a function constant along the radius (a
    thin shell of the lattice around the unit sphere, each B-spline's value that of its
    support centre's direction), so a coefficient is predicted from the lattice plane
    before it along the axis ``a`` nearest the radial direction, at its *radial foot*:
    the point of that plane on the ray from the origin through its support centre ``P``
    (``P - P / P_a`` in spacings, placed to 1/256 of a spacing; bicubic, Catmull-Rom,
    where the plane's 16 nodes around it are there, else bilinear between its four
    nodes, normalised over those present), plus (``column``)
    the previous coefficient's own foot error when it is the one before along the last
    axis in the same column (the interpolation error varies slowly along a column; where
    the step is far below the coefficients' noise this adds noise instead, so the
    encoder chooses per level: :func:`_encode_values`). Where the plane
    has none of the foot's nodes (the shell's first layer along ``a``), the prediction is
    that previous coefficient, else 0. Integers only,
    so encoder and decoder agree bit for bit on every machine; C (one pass, each
    coefficient after those it is predicted from): :mod:`geoidspline._kernels.codec`.
    """
    from .._kernels.codec import radial_code

    q = np.ascontiguousarray(values, dtype=np.int64)
    out = np.empty_like(q)
    radial_code(keys, order, column, False, q, out)
    return out


def radial_values(keys, order, residuals, column=True):
    """Inverse of :func:`radial_residuals`: the values (int64 in int32 range)."""
    from .._kernels.codec import radial_code

    r = np.ascontiguousarray(residuals, dtype=np.int64)
    out = np.zeros_like(r)
    radial_code(keys, order, column, True, out, r)
    return out


def _entropy_bits(values):
    """Zero-order entropy (bits) of an integer array."""
    _, counts = np.unique(values, return_counts=True)
    return float(-(counts * np.log2(counts / values.size)).sum()) if values.size else 0.0


# -- format 4: a template by least squares, residuals grouped by how they were predicted ----

TEMPLATE_WEIGHT_LIMIT = 1 << 20
"""Largest |weight| (in 1/65536) of format 4's template: the prediction's sum of 29
products of int32 values stays far inside int64."""

TEMPLATE_BOX_LIMIT = 1 << 26
"""Largest box (cells, the level's key range along its three axes) a tile level gets a
template for: the decoder's lookup table (4 bytes a cell)."""


def template_shift(keys, order):
    """Format 4's template position of a tile level (4 ints, ``src/codec.c``): its mean
    radial foot offset in the slab before (floored, the Catmull-Rom stencil's corner + 1)
    and twice it (rounded) in the slab two before, along the slab axes b < c (the axis a
    nearest the level's mean radial direction, as format 3 takes it); None when the level
    is too large for the decoder's table or has no slab before."""
    idx = _keys.unpack_keys(np.asarray(keys, dtype=np.int64))
    centres = 2 * idx + int(order)
    sums = centres.sum(axis=0)
    a = int(np.argmax(np.abs(sums)))
    b, c = [axis for axis in range(3) if axis != a]
    span = idx.max(axis=0) - idx.min(axis=0) + 1
    den = centres[:, a].astype(np.float64)
    usable = den != 0
    if int(np.prod(span.astype(np.float64))) > TEMPLATE_BOX_LIMIT or span[a] < 3 or not usable.any():
        return None
    offset = -(centres[usable][:, [b, c]] / den[usable, None]).mean(axis=0)
    return [int(np.floor(offset[0])), int(np.floor(offset[1])), int(np.rint(2 * offset[0])),
            int(np.rint(2 * offset[1]))]


def _least_squares(q, taps, rows):
    """Weights (int64 in 1/65536) predicting ``q[rows]`` from ``q[taps[rows]]``, or None
    (too few rows; a weight beyond :data:`TEMPLATE_WEIGHT_LIMIT`)."""
    if rows.sum() < 4 * taps.shape[1]:
        return None
    q = np.asarray(q, dtype=np.float64)
    design = q[taps[rows]]
    # the normal equations (29 x 29): 50x faster than an SVD of the design matrix, and the
    # weights only need to predict well (any weights decode exactly)
    weights, *_ = np.linalg.lstsq(design.T @ design, design.T @ q[rows], rcond=None)
    fixed = np.rint(weights * 65536.0).astype(np.int64)
    return fixed if np.abs(fixed).max() < TEMPLATE_WEIGHT_LIMIT else None


def template_weights(keys, order, q, shift):
    """Format 4's weights (int64 in 1/65536, or None) of a level's whole and small
    templates at ``shift``: the least-squares predictions of its quantised values ``q``
    from their templates' rows, over the rows that each will predict (the small one's:
    those without the whole one's rows)."""
    from .._kernels.codec import template_rows

    taps, whole = template_rows(keys, order, shift)
    weights = _least_squares(q, taps, whole)
    small_taps, small = template_rows(keys, order, shift, small=True)
    return weights, _least_squares(q, small_taps, small & ~whole if weights is not None else small)


def _template_pass(keys, order, column, decode, template, values=None, residuals=None):
    """(values, residuals, kinds) of format 4's pass over one level (``template``: its
    header entry, ``{"shift", "weights", "small"}`` or None)."""
    from .._kernels.codec import template_code

    n = np.asarray(keys).size
    values = np.zeros(n, np.int64) if values is None else np.ascontiguousarray(values, dtype=np.int64)
    residuals = np.zeros(n, np.int64) if residuals is None else np.ascontiguousarray(residuals, dtype=np.int64)
    kinds = np.empty(n, np.uint8)
    shift, weights, small = (None, None, None) if template is None else \
        (template["shift"], template["weights"], template["small"])
    template_code(keys, order, column, decode, shift, weights, small, values, residuals, kinds)
    return values, residuals, kinds


def _grouped_bits(residuals, kinds):
    """Zero-order entropy (bits) of residuals coded in groups by kind (format 4's arrays)."""
    return sum(_entropy_bits(residuals[kinds == kind]) for kind in np.unique(kinds))


def _encode_values4(level_keys, level_q, order):
    """Format 4's value arrays (whole-template residuals; the others, stably sorted by
    how they were predicted) and per level (column flag, template entry)."""
    templated, others, other_kinds, meta = [], [], [], []
    for keys, q in zip(level_keys, level_q):
        shift = template_shift(keys, order) if order else None
        weights, small = template_weights(keys, order, q, shift) if shift is not None else (None, None)
        template = None if weights is None and small is None else \
            {"shift": shift, **{name: None if w is None else [int(v) for v in w]
                                for name, w in (("weights", weights), ("small", small))}}
        both = [_template_pass(keys, order, column, False, template, q) for column in (False, True)]
        rest = [residuals[kinds != 0] for _, residuals, kinds in both]
        column = _entropy_bits(rest[1]) < _entropy_bits(rest[0])
        _, residuals, kinds = both[column]
        if template is not None:
            # the template only where it pays for its weights in the header (a sparse
            # overlay's level, a grid store's tile: +1.6 % on egm96-15 0.5 m otherwise)
            _, plain, plain_kinds = _template_pass(keys, order, column, False, None, q)
            if _grouped_bits(plain, plain_kinds) <= _grouped_bits(residuals, kinds) + 8 * len(json.dumps(template)):
                template, residuals, kinds = None, plain, plain_kinds
        templated.append(residuals[kinds == 0])
        others.append(residuals[kinds != 0])
        other_kinds.append(kinds[kinds != 0])
        meta.append((bool(column), template))
    rest = np.concatenate(others) if others else np.zeros(0, np.int64)
    rest = rest[np.argsort(np.concatenate(other_kinds) if other_kinds else np.zeros(0), kind="stable")]
    first = np.concatenate(templated) if templated else np.zeros(0, np.int64)
    return {"value_template": _shuffle_compress(_zigzag(first)), "value_rest": _shuffle_compress(_zigzag(rest))}, meta


def _decode_values4(blobs, level_keys, meta, order, n_coefs):
    """Inverse of :func:`_encode_values4`: each level's quantised values (int64)."""
    kinds = [_template_pass(keys, order, column, False, template)[2]
             for keys, (column, template) in zip(level_keys, meta)]
    every = np.concatenate(kinds) if kinds else np.zeros(0, np.uint8)
    first = every == 0
    n_first = int(first.sum())
    residuals = np.empty(n_coefs, np.int64)
    residuals[first] = _unzigzag(_shuffle_decompress(blobs["value_template"], n_first))
    rest_at = np.flatnonzero(~first)
    residuals[rest_at[np.argsort(every[rest_at], kind="stable")]] = \
        _unzigzag(_shuffle_decompress(blobs["value_rest"], n_coefs - n_first))
    out, at = [], 0
    for keys, (column, template) in zip(level_keys, meta):
        values, _, _ = _template_pass(keys, order, column, True, template, residuals=residuals[at:at + keys.size])
        out.append(values)
        at += keys.size
    return out


def _encode_values(level_keys, level_q, order, tile_format):
    """(value array's bytes, per level: whether format 3's column term is used)."""
    if tile_format == 2:
        return _delta_encode(np.concatenate(level_q) if level_q else np.zeros(0), np.int32), []
    parts, columns = [], []
    for keys, q in zip(level_keys, level_q):
        # the smaller of the two predictions by their zero-order entropy (what the
        # shuffle and Zstandard then approach), without compressing twice
        both = [radial_residuals(keys, order, q, column) for column in (False, True)]
        column = _entropy_bits(both[1]) < _entropy_bits(both[0])
        parts.append(both[column])
        columns.append(bool(column))
    return _shuffle_compress(_zigzag(np.concatenate(parts) if parts else np.zeros(0, np.int64))), columns


def encode_tile(tile, levels, indices, values, step, record=None, tile_format=TILE_FORMAT) -> bytes:
    """A tile file's bytes (``tile_format`` 3, or 2 as the first stores were written) from
    coefficients in any order: ``levels`` (M,), ``indices`` (M, 3) on their level's grid,
    ``values`` (M,) in metres. ``record``: more header entries (what the tile belongs
    to: store id, order, h0, tile size); format 3's prediction takes the support
    centres' positions from its ``order`` (0 without one: the prediction is a little
    worse, the values the same)."""
    levels = np.asarray(levels, dtype=np.int64)
    keys = _keys.pack_keys(indices)
    order = np.lexsort((keys, levels))
    levels, keys = levels[order], keys[order]
    q = quantise(np.asarray(values, dtype=np.float64)[order], step)
    if q.size and np.abs(q).max() >= 2**31:
        raise ValueError(f"a coefficient of {np.abs(values).max()} m does not fit 32 bits at step {step} m")
    level_meta, starts_all, lengths_all, level_keys, level_q = [], [], [], [], []
    for level in np.unique(levels):
        a, b = np.searchsorted(levels, [level, level + 1])
        starts, lengths = runs_of(keys[a:b])
        starts_all.append(keys[a:b][starts])
        lengths_all.append(lengths)
        level_keys.append(keys[a:b])
        level_q.append(q[a:b])
        level_meta.append({"level": int(level), "coefficients": int(b - a), "runs": int(starts.size)})
    start_keys = np.concatenate(starts_all) if starts_all else np.zeros(0, np.int64)
    lengths = np.concatenate(lengths_all) if lengths_all else np.zeros(0, np.int64)
    spline_order = int((record or {}).get("order", 0))
    blobs = {
        # i, j, k columns one after the other: each changes slowly from run to run
        "run_start": _delta_encode(_keys.unpack_keys(start_keys).T.ravel(), np.int32),
        "run_length": _delta_encode(lengths, np.int32),
    }
    if tile_format == 4:
        value_blobs, per_level = _encode_values4(level_keys, level_q, spline_order)
        blobs.update(value_blobs)
        for meta, (column, template) in zip(level_meta, per_level):
            meta["column"] = column
            meta["template"] = template
    else:
        blobs["value"], columns = _encode_values(level_keys, level_q, spline_order, tile_format)
        for meta, column in zip(level_meta, columns):
            meta["column"] = column
    header = {
        "tile": [int(v) for v in tile],
        "value_step_m": float(step),
        "value_units": "m",
        "levels": level_meta,
        "codec": CODECS[tile_format],
        "arrays": [[name, len(blob)] for name, blob in blobs.items()],
        **(record or {}),
    }
    head = json.dumps(header, separators=(",", ":")).encode("utf-8")
    return b"".join([MAGICS[tile_format], struct.pack("<I", len(head)), head, *blobs.values()])


def _flag(value) -> bool:
    if not isinstance(value, bool):
        raise TypeError(f"a level's column flag is {value!r}, not true or false")
    return value


def tile_format_of(data):
    """The coded tile format (2 or 3) of a tile file's bytes, or None (not a coded tile:
    format 1's netCDF4, or not a tile)."""
    head = bytes(data[: len(MAGIC)])
    return next((version for version, magic in MAGICS.items() if head == magic), None)


def is_coded_tile(data) -> bool:
    """Whether a tile file's bytes are a coded tile (format 2 or 3), not netCDF4."""
    return tile_format_of(data) is not None


def decode_tile(data):
    """(header, {level: (sorted keys int64, values float64)}) of a coded tile's bytes
    (format 2 or 3); :class:`ValueError` naming the rule broken when they are not one."""
    data = memoryview(data)
    tile_format = tile_format_of(data)
    if tile_format is None:
        raise ValueError("does not start with a coded tile's signature (format 2 or 3)")
    at = len(MAGIC)
    if len(data) < at + 4:
        raise ValueError("ends inside its header")
    (size,) = struct.unpack("<I", data[at:at + 4])
    at += 4
    if size > _HEADER_LIMIT or len(data) < at + size:
        raise ValueError("ends inside its header")
    try:
        header = json.loads(bytes(data[at:at + size]).decode("utf-8"))
        arrays = {name: int(count) for name, count in header["arrays"]}
        step = float(header["value_step_m"])
        level_meta = [(int(m["level"]), int(m["coefficients"]), int(m["runs"])) for m in header["levels"]]
        columns = [_flag(m["column"]) for m in header["levels"]] if tile_format >= 3 else []
        templates = [_template_entry(m["template"]) for m in header["levels"]] if tile_format == 4 else []
        spline_order = int(header.get("order", 0))
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"has a damaged header ({exc})") from None
    if not 0 <= spline_order <= 16:
        raise ValueError(f"has a damaged header (order {spline_order})")
    at += size
    names = {"run_start", "run_length", *(("value_template", "value_rest") if tile_format == 4 else ("value",))}
    if at + sum(arrays.values()) != len(data) or set(arrays) != names:
        raise ValueError("array sizes in the header do not add up to the file's size")
    blobs = {}
    for name, count in header["arrays"]:
        blobs[name] = data[at:at + int(count)]
        at += int(count)
    n_runs = sum(m[2] for m in level_meta)
    n_coefs = sum(m[1] for m in level_meta)
    if min((min(m[1], m[2]) for m in level_meta), default=0) < 0:
        raise ValueError("has a damaged header (a negative count)")
    start = _delta_decode(blobs["run_start"], np.int32, 3 * n_runs).reshape(3, n_runs).T
    lengths = _delta_decode(blobs["run_length"], np.int32, n_runs).astype(np.int64)
    if tile_format == 2:
        q = _delta_decode(blobs["value"], np.int32, n_coefs).astype(np.int64)
    elif tile_format == 3:
        q = _unzigzag(_shuffle_decompress(blobs["value"], n_coefs))
    if np.any(lengths < 1) or int(lengths.sum()) != n_coefs:
        raise ValueError("run lengths do not add up to the coefficient count")
    start_keys = _keys.pack_keys(start)
    level_keys = []
    run_at = 0
    for level, count, runs in level_meta:
        keys = keys_of_runs(start_keys[run_at:run_at + runs], lengths[run_at:run_at + runs])
        if keys.size != count or (keys.size > 1 and not np.all(keys[1:] > keys[:-1])):
            raise ValueError(f"level {level}'s runs are not in increasing key order")
        level_keys.append(keys)
        run_at += runs
    if tile_format == 4:
        level_values = _decode_values4(blobs, level_keys, list(zip(columns, templates)), spline_order, n_coefs)
    else:
        level_values, coef_at = [], 0
        for at_level, keys in enumerate(level_keys):
            values = q[coef_at:coef_at + keys.size]
            if tile_format == 3:
                values = radial_values(keys, spline_order, values, columns[at_level])
            level_values.append(values)
            coef_at += keys.size
    out = {level: (keys, values.astype(np.int32) * step)
           for (level, _, _), keys, values in zip(level_meta, level_keys, level_values)}
    return header, out


def _template_entry(value):
    """A format-4 level's template entry, checked: None, or 4 shifts and the whole and
    small templates' weights (each a list of its taps' or None)."""
    from .._kernels.codec import template_taps

    if value is None:
        return None
    shift, weights, small = value["shift"], value["weights"], value["small"]

    def integers(values, count):
        return (isinstance(values, list) and len(values) == count
                and all(isinstance(v, int) and not isinstance(v, bool) for v in values))

    if (not integers(shift, 4) or max(abs(v) for v in shift) > 64
            or not all(w is None or (integers(w, template_taps(tiny)) and max(abs(v) for v in w) < TEMPLATE_WEIGHT_LIMIT)
                       for w, tiny in ((weights, False), (small, True)))):
        raise ValueError(f"a level's template is not 4 shifts and {template_taps()} and {template_taps(True)} "
                         "weights in range")
    return {"shift": shift, "weights": weights, "small": small}


def stored_values(values, step):
    """Coefficients (metres) as a format-2 store with ``step`` holds them, bitwise."""
    return quantise(values, step).astype(np.int32) * step


def quantised_spline(spline, step):
    """The :class:`~geoidspline.hierarchy.ambient.AmbientSpline` a format-2 store with
    ``step`` holds for ``spline``: every coefficient rounded to a multiple of ``step``
    (what reading the store gives, bitwise)."""
    from ..bspline.level import LevelSpline
    from ..hierarchy.ambient import AmbientSpline

    return AmbientSpline([LevelSpline(lv.level, lv.h, lv.order, lv.keys, stored_values(lv.coefficients, step))
                          for lv in spline.levels])
