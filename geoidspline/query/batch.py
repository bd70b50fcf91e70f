"""The batch query engine: CSV rows in, values out, in vectorised batches as rows arrive.

What ``geoid-query`` streams through, for Python callers too::

    q = BatchQuery(store, is_store=True, deflection=True)
    bad = query_rows(q, open("points.csv"), sys.stdout)

A source is any object with ``undulation(latitude, longitude)``: a store (then also
``covers``, ``coverage_reason``, ``error_bound``, ``manifest["region"]`` and its
spline for deflections) or a harmonic synthesis. Input rows, output columns and the
messages of bad rows: see ``geoid-query --help``.
"""

from __future__ import annotations

import json
import math
import os
import re
import select

from ..errors import CoordinateError
from ..options import DECIMAL
from ..sphere.region import MAX_ABS_POINT_LONGITUDE_DEG

__all__ = ["BatchQuery", "query_rows", "query_point", "HEIGHT_OUTPUT", "DEFLECTION_COLUMNS"]

BATCH_BYTES = 1 << 16

#: The UTF-8 byte-order mark some editors put at the start of a CSV file.
_BOM = b"\xef\xbb\xbf"

#: The longest input line read (bytes): a longer one is a bad row, and is not kept.
MAX_LINE_BYTES = 1 << 24

DEFLECTION_COLUMNS = ("xi_arcsec", "eta_arcsec", "dNdn_m_per_m", "dNde_m_per_m")
HEIGHT_OUTPUT = {"ellipsoidal": "orthometric_height_m", "orthometric": "ellipsoidal_height_m"}


def _byte_chunks(stream):
    """Yield the stream's bytes in chunks as soon as they arrive.

    Reads whatever the stream has ready (up to 64 KiB) instead of waiting for a full
    batch, so a co-process sending one line gets its answer at once while a file or
    pipe is processed in large vectorised batches. Every kind of stream is read as
    bytes, so lines are split the same way (on LF only) whatever it is.
    """
    try:
        fd = stream.fileno()
    except (AttributeError, OSError, ValueError):
        fd = None
    buffer = getattr(stream, "buffer", None)
    if fd is not None and buffer is not None:
        while True:
            chunk = os.read(fd, BATCH_BYTES)
            if not chunk:
                return
            # take more while it is already there, up to one batch
            while len(chunk) < BATCH_BYTES and select.select([fd], [], [], 0)[0]:
                more = os.read(fd, BATCH_BYTES)
                if not more:
                    break
                chunk += more
            yield chunk
    elif buffer is not None:
        read = getattr(buffer, "read1", None) or buffer.read
        while chunk := read(BATCH_BYTES):
            yield chunk
    else:  # a text stream without bytes underneath (io.StringIO)
        while text := stream.read(BATCH_BYTES):
            yield text.encode("utf-8", "surrogatepass")


class _TooLong(str):
    """A line longer than :data:`MAX_LINE_BYTES`: only its beginning, for the message."""


def _decoded(line: bytes) -> str:
    return line.decode("utf-8", "replace").rstrip("\r")


def _line_batches(stream):
    """Yield lists of complete lines (str, without LF or a final CR) as they arrive.

    Bytes that are not UTF-8 become U+FFFD (the row is then reported as bad); a UTF-8
    byte-order mark at the start of the stream is dropped. A line longer than
    :data:`MAX_LINE_BYTES` is not kept: it comes as a :class:`_TooLong` holding its
    first bytes, and memory stays bounded whatever the input (``--input /dev/zero``).
    """
    parts, size = [], 0  # the line being read, in pieces (no quadratic joining)
    too_long = None  # the head of a line beyond MAX_LINE_BYTES whose rest is skipped
    start = b""  # the first bytes, until a BOM can be told apart

    def feed(chunk):
        nonlocal parts, size, too_long
        pieces = chunk.split(b"\n")
        batch = []
        if len(pieces) > 1:  # the line being read ends here; the others are whole
            if too_long is not None:
                batch.append(_TooLong(_decoded(too_long) + "..."))
                too_long = None
            else:
                parts.append(pieces[0])
                batch.append(_decoded(b"".join(parts)))
            parts, size = [], 0
            batch += [ln.decode("utf-8", "replace").rstrip("\r") for ln in pieces[1:-1]]
        tail = pieces[-1]
        if too_long is None and tail:
            parts.append(tail)
            size += len(tail)
            if size > MAX_LINE_BYTES:
                too_long = b"".join(parts)[:40]
                parts, size = [], 0
        return batch

    for chunk in _byte_chunks(stream):
        if start is not None:
            start += chunk
            if len(start) < len(_BOM) and b"\n" not in start:
                continue  # the bytes of a BOM may still be arriving
            chunk, start = start.removeprefix(_BOM), None
        batch = feed(chunk)
        if batch:
            yield batch
    last = feed((start or b"").removeprefix(_BOM) + b"\n") if (start or parts or too_long is not None) else []
    if last:
        yield last


def _unquoted(field):
    """A field without surrounding blanks and one pair of double quotes (CSV quoting)."""
    field = field.strip()
    if len(field) >= 2 and field[0] == field[-1] == '"':
        field = field[1:-1].strip()
    return field


def _number(field):
    """The float a (possibly quoted) CSV field spells as a plain ASCII decimal
    (:data:`geoidspline.options.DECIMAL`: no ``1_000``, no non-ASCII digits, no nan or
    inf); ValueError for anything else. nan, inf (in Python's spellings) and a decimal
    beyond float's range come back as the non-finite float they spell, for the
    message "must be finite numbers"."""
    text = _unquoted(field)
    if DECIMAL.fullmatch(text):
        return float(text)
    value = float(text)  # ValueError: not a number in any spelling
    if math.isfinite(value):  # 1_000, non-ASCII digits: Python-only spellings
        raise ValueError(f"not a plain decimal number: {text!r}")
    return value


#: A column name: a letter or underscore, then letters, digits, underscores, blanks,
#: '.' or '-', optionally a unit in brackets: lat, Latitude, lon_deg, "y (m)", x [m].
_NAME = re.compile(r"[^\W\d][\w .\-]*?(\s*[(\[][^()\[\]]*[)\]])?")
#: A hemisphere letter before a number (N45.2, s 33.4) is a coordinate, not a name.
_HEMISPHERE_FIRST = re.compile(r"[NSEWnsew]\s*[-+]?[0-9.]")


def _is_name(field):
    """Whether a field looks like a column name (see :data:`_NAME`) and not a number."""
    text = _unquoted(field)
    try:
        float(text)
        return False  # nan, inf, 1e5: numbers, even when spelled with letters
    except ValueError:
        pass
    return bool(_NAME.fullmatch(text)) and not _HEMISPHERE_FIRST.match(text)


def _looks_like_header(line, coord_columns):
    """The header rule: the first non-blank line is a header when every coordinate
    field of it is a column name (:func:`_is_name`). So ``lat,lon`` is a header while
    ``-33.45S,-70.66W``, ``abc,30`` or ``N45,E7`` are data rows (bad ones)."""
    parts = line.split(",")
    if len(parts) <= max(coord_columns):
        return False
    return all(_is_name(parts[c]) for c in coord_columns)


def _geodetic_problem(latitude, longitude):
    """Why a finite latitude/longitude (degrees) cannot be answered, or None."""
    if abs(latitude) > 90.0:
        return f"latitude {latitude:g} is outside [-90, 90] degrees"
    if abs(longitude) > MAX_ABS_POINT_LONGITUDE_DEG:
        return (f"longitude {longitude:g} is beyond ±{MAX_ABS_POINT_LONGITUDE_DEG:g} degrees "
                f"(not wrapped: a value this large is a mistake)")
    return None


def coverage(store, latitude, longitude):
    """Which points (1-D degrees) a store covers, and a message for each one it does not.

    Returns (covered mask, {position: message}). The reason comes from the store's
    ``coverage_reason`` where it has one (outside the region, no data in the source
    here); a store without it covers its region.
    """
    import numpy as np

    covered = np.asarray(store.covers(latitude, longitude), dtype=bool).reshape(-1)
    outside = np.flatnonzero(~covered)
    messages = {}
    if outside.size:
        s, w, n, e = store.manifest["region"]
        where = f"S {s:g} W {w:g} N {n:g} E {e:g}"
        reason_of = getattr(store, "coverage_reason", None)
        reasons = ["outside the region"] * outside.size
        if callable(reason_of):
            reasons = [str(r) for r in np.asarray(reason_of(latitude[outside], longitude[outside]),
                                                  dtype=object).reshape(-1)]
        for k, reason in zip(outside.tolist(), reasons):
            if reason == "outside the region":
                reason = f"outside its region {where}"
            messages[k] = f"outside the store's coverage ({reason})"
    return covered, messages


class BatchQuery:
    """What to compute for each row: the input layout and the output columns.

    Input columns (0-based): without ``crs`` latitude, longitude in 0, 1; with ``crs``
    x, y in 0, 1 (always_xy order) and, for a 3D CRS, z in 2. With ``height_in`` (2D
    input) the height is in ``height_column``; with a 3D CRS the ellipsoidal height is
    the one the CRS conversion gives.

    A row gets values only when they are true: its coordinates are finite numbers in
    range (latitude within ±90°, longitude within ±1e6° before wrapping) and, for a
    store, the point is inside the store's coverage. Otherwise the row is a problem
    (an ``ERROR`` row), except that with ``outside="nan"`` a point outside the coverage
    gets NaN values instead.
    """

    def __init__(self, source, *, is_store, deflection=False, height_in=None, height_column=None,
                 crs=None, with_error=False, precision=4, fmt="csv", outside="error", tide_system=None):
        from ..geodesy.tides import tide_conversion

        self.source = source
        # --tide-system: (own system, asked one), or None; refused when the store's is unknown
        own = source.manifest["provenance"].get("tide_system") if is_store else source.provenance.tide_system
        self.tide = tide_conversion(own, tide_system, getattr(source, "path", None) or source.provenance.source)
        self.is_store = is_store
        self.deflection = deflection
        self.height_in = height_in
        self.crs = crs
        self.with_error = with_error
        self.precision = precision
        self.fmt = fmt
        self.outside = outside
        self.crs_dim = 2
        if crs is not None:
            from .crs import crs_info

            _, self.crs_dim = crs_info(crs)
        if self.crs_dim == 3:
            self.coord_columns = (0, 1, 2)
            self.height_column = None  # h comes from the conversion
        else:
            self.coord_columns = (0, 1)
            self.height_column = (2 if height_column is None else height_column) if height_in else None
        if self.height_column is not None and self.height_column in self.coord_columns:
            raise CoordinateError(f"height column {self.height_column} is a coordinate column: give another column")
        needed = list(self.coord_columns) + ([self.height_column] if self.height_column is not None else [])
        #: fields a row needs at least
        self.width = max(needed) + 1
        #: parsed numbers per row: the coordinates, then the height (if any)
        self.slots = len(self.coord_columns) + (self.height_column is not None)
        # output columns: (name, kind) with kind deg | m | arcsec | ratio
        columns = []
        if crs is not None:
            columns += [("latitude_deg", "deg"), ("longitude_deg", "deg")]
        columns.append(("undulation_m", "m"))
        if deflection:
            columns += [(DEFLECTION_COLUMNS[0], "arcsec"), (DEFLECTION_COLUMNS[1], "arcsec"),
                        (DEFLECTION_COLUMNS[2], "ratio"), (DEFLECTION_COLUMNS[3], "ratio")]
        if height_in:
            columns.append((HEIGHT_OUTPUT[height_in], "m"))
        if with_error:
            columns.append(("error_bound_m", "m"))
        self.columns = columns
        self.plain = columns == [("undulation_m", "m")]
        self.json_keys = ["line", "fields", "latitude_deg", "longitude_deg"] + [
            name for name, _ in columns if name not in ("latitude_deg", "longitude_deg")
        ] + ["error"]

    # -- parsing --------------------------------------------------------------------
    def parse(self, rows, line_numbers):
        """Split rows into fields and parse the numbers; return (fields, numbers, problems).

        ``numbers`` has shape (len(rows), slots): the coordinates, then the height, NaN
        in rows with a problem; ``problems`` maps a row's position to its message.
        """
        import numpy as np

        fast = self._parse_plain(rows)
        if fast is not None:
            return fast
        numbers = np.full((len(rows), self.slots), np.nan)
        problems = {}
        fields = []
        names = "x/y" if self.crs is not None else "latitude/longitude"
        if self.crs_dim == 3:
            names = "x/y/z"
        for i, row in enumerate(rows):
            parts = [p.strip() for p in row.split(",")]
            fields.append(parts)
            n = line_numbers[i]
            if isinstance(row, _TooLong):
                problems[i] = f"line {n}: longer than {MAX_LINE_BYTES:,} bytes, not read ({row[:40]!r})"
                continue
            if len(parts) < self.width:
                what = self.layout()
                problems[i] = f"line {n}: expected at least {self.width} columns ({what}), got {len(parts)}"
                continue
            coords = [parts[c] for c in self.coord_columns]
            try:
                values = [_number(v) for v in coords]
            except ValueError:
                shown = ", ".join(repr(v) for v in coords)
                problems[i] = f"line {n}: {names} are not numbers: {shown}"
                continue
            if not all(math.isfinite(v) for v in values):
                shown = ", ".join(repr(v) for v in coords)
                problems[i] = f"line {n}: {names} must be finite numbers, got {shown}"
                continue
            if self.crs is None:
                problem = _geodetic_problem(values[0], values[1])
                if problem:
                    problems[i] = f"line {n}: {problem}"
                    continue
            if self.height_column is not None:
                token = parts[self.height_column]
                try:
                    height = _number(token)
                except ValueError:
                    problems[i] = f"line {n}: {self.height_in} height (column {self.height_column}) is not a number: {token!r}"
                    continue
                if not math.isfinite(height):
                    problems[i] = f"line {n}: {self.height_in} height must be a finite number, got {token!r}"
                    continue
                numbers[i, -1] = height
            numbers[i, : len(values)] = values
        return fields, numbers, problems

    def _parse_plain(self, rows):
        """The common case in one vectorised pass: plain CSV output, geodetic input, no
        height column, and every row valid. Anything else (or any bad row) returns None
        and the row-by-row parser gives the per-line messages."""
        if self.fmt != "csv" or self.crs is not None or self.height_column is not None or len(rows) < 64:
            return None
        if any(isinstance(row, _TooLong) for row in rows):
            return None
        import io

        import numpy as np

        try:
            coords = np.loadtxt(io.StringIO("\n".join(rows)), delimiter=",", usecols=self.coord_columns,
                                dtype=np.float64, ndmin=2, comments=None)
        except ValueError:
            return None
        if (coords.shape[0] != len(rows) or not np.all(np.isfinite(coords)) or np.any(np.abs(coords[:, 0]) > 90.0)
                or np.any(np.abs(coords[:, 1]) > MAX_ABS_POINT_LONGITUDE_DEG)):
            return None
        return _SplitRows(rows), coords, {}

    def layout(self) -> str:
        """The input columns expected, in words (for messages)."""
        if self.crs is None:
            names = ["lat", "lon"]
        elif self.crs_dim == 3:
            names = ["x", "y", "z"]
        else:
            names = ["x", "y"]
        if self.height_column is not None:
            gap = self.height_column - len(names)
            names = names + ["..."] * min(gap, 1) + [f"{self.height_in} height in column {self.height_column}"]
        return ",".join(names)

    # -- evaluation -----------------------------------------------------------------
    def evaluate(self, numbers, line_numbers, problems):
        """Output values (len, ncolumns) for the rows without problems; adds problems.

        A store is asked only at the points it covers; a point outside its coverage is a
        problem, or (``outside="nan"``) a row of NaN values; so is a NaN the source
        returns anywhere else (never printed as if it were a value).
        """
        import numpy as np

        count = numbers.shape[0]
        out = np.full((count, len(self.columns)), np.nan)
        lat = np.full(count, np.nan)
        lon = np.full(count, np.nan)
        good = np.ones(count, dtype=bool)
        if problems:
            good[list(problems)] = False
        h_known = None
        if self.crs is None:
            lat[good], lon[good] = numbers[good, 0], numbers[good, 1]
        elif good.any():
            from geoidspline.query.crs import to_geodetic

            z = numbers[good, 2] if self.crs_dim == 3 else None
            la, lo, h = to_geodetic(numbers[good, 0], numbers[good, 1], z, crs=self.crs)
            lat[good], lon[good] = la, lo
            h_known = np.full(count, np.nan)
            h_known[good] = h
            for i in np.flatnonzero(good & ~(np.isfinite(lat) & np.isfinite(lon))):
                problems[int(i)] = (f"line {line_numbers[i]}: cannot transform "
                                    f"{tuple(float(v) for v in numbers[i, :len(self.coord_columns)])} "
                                    f"from {self.crs} to WGS84 latitude/longitude")
                good[i] = False
        if self.crs is not None:
            out[:, 0], out[:, 1] = lat, lon  # the converted position, even outside the coverage
        if self.is_store and good.any():
            idx = np.flatnonzero(good)
            covered, reasons = coverage(self.source, lat[idx], lon[idx])
            for k in np.flatnonzero(~covered):
                i = int(idx[k])
                good[i] = False
                if self.outside != "nan":
                    problems[i] = f"line {line_numbers[i]}: {reasons[int(k)]}"
        if not good.any():
            return out, lat, lon
        idx = np.flatnonzero(good)
        la, lo = lat[idx], lon[idx]
        undulation = np.asarray(self.source.undulation(la, lo), dtype=float).reshape(-1)
        if self.tide is not None:  # N in the asked tide system
            from ..geodesy.tides import tide_offset_m

            undulation = undulation + tide_offset_m(la, *self.tide)
        values = {"undulation_m": undulation, "latitude_deg": la, "longitude_deg": lo}
        if self.deflection:
            from .derived import deflection

            d = deflection(self.source, la, lo)
            values.update(zip(DEFLECTION_COLUMNS, (np.asarray(v).reshape(-1) for v in d)))
            if self.tide is not None:  # the tide term's slope too: ξ = −dN/dnorth
                from ..geodesy.tides import tide_slope_north

                slope = tide_slope_north(la, *self.tide)
                values[DEFLECTION_COLUMNS[2]] = values[DEFLECTION_COLUMNS[2]] + slope
                values[DEFLECTION_COLUMNS[0]] = values[DEFLECTION_COLUMNS[0]] - np.degrees(slope) * 3600.0
        if self.height_in:
            from .derived import convert_height

            height = h_known[idx] if self.crs_dim == 3 else numbers[idx, -1]
            values[HEIGHT_OUTPUT[self.height_in]] = np.asarray(convert_height(undulation, height, self.height_in)).reshape(-1)
        if self.with_error:  # the store's measured bound (the points are covered: no NaN added)
            values["error_bound_m"] = np.asarray(self.source.error_bound(la, lo)).reshape(-1)
        for k, (name, _) in enumerate(self.columns):
            out[idx, k] = values[name]
        first_value = 2 if self.crs is not None else 0  # keep the converted position
        for k in np.flatnonzero(~np.isfinite(undulation)):
            # a store that has no value here (a hole it knows of) says so with NaN
            i = int(idx[k])
            out[i, first_value:] = np.nan
            if self.outside != "nan":
                problems[i] = f"line {line_numbers[i]}: the source has no value at this point (NaN)"
        return out, lat, lon

    # -- formatting -----------------------------------------------------------------
    def format_value(self, value, kind):
        p = self.precision
        if not math.isfinite(value):
            return "nan"
        if kind == "ratio":
            return f"{value:.{p}e}"
        if kind == "deg":
            return f"{value:.{p + 5}f}"
        return f"{value:.{p}f}"

    def json_value(self, value, kind):
        if not math.isfinite(value):
            return None
        return float(self.format_value(value, kind))

    def csv_values(self, row_values):
        return ",".join(self.format_value(float(v), kind) for v, (_, kind) in zip(row_values, self.columns))

    def json_record(self, line, fields, row_values, lat, lon, error=None):
        record = dict.fromkeys(self.json_keys)
        record["line"] = line
        record["fields"] = list(fields)
        if error is None:
            record["latitude_deg"] = self.json_value(float(lat), "deg")
            record["longitude_deg"] = self.json_value(float(lon), "deg")
            for v, (name, kind) in zip(row_values, self.columns):
                record[name] = self.json_value(float(v), kind)
        record["error"] = error
        return json.dumps(record)


def query_point(q: BatchQuery, coordinates) -> str:
    """One point (its coordinate values): the line of values (CSV or JSON), or a
    :class:`~geoidspline.errors.CoordinateError` with the message a CSV row would get."""
    fields = [v.strip() if isinstance(v, str) else repr(float(v)) for v in coordinates]  # as typed: a row's rules
    _, numbers, problems = q.parse([",".join(fields)], [1])
    out, lat, lon = q.evaluate(numbers, [1], problems)
    if problems:
        raise CoordinateError(problems[0].split(": ", 1)[1])
    if q.fmt == "jsonl":
        return q.json_record(None, fields, out[0], lat[0], lon[0])
    return q.csv_values(out[0])


class _SplitRows:
    """Fields of each row, split only if asked for (the fast path never needs them)."""

    def __init__(self, rows):
        self.rows = rows

    def __getitem__(self, i):
        return [p.strip() for p in self.rows[i].split(",")]


def query_rows(q: BatchQuery, stream, out) -> int:
    """Answer every row of ``stream`` (a text or binary file of CSV rows) in batches as
    they arrive, writing result lines to ``out`` (anything with ``write(str)``); returns
    the number of bad rows (each written as an ``ERROR: line N: ...`` row or a JSON
    record with its ``error``)."""
    line_number = 0
    bad = 0
    header_checked = False
    jsonl = q.fmt == "jsonl"
    names = ",".join(name for name, _ in q.columns)
    for batch in _line_batches(stream):
        numbers_range = range(line_number + 1, line_number + 1 + len(batch))
        line_number += len(batch)
        # blank lines are skipped, but rows keep their line numbers for messages
        numbered = [(n, row) for n, row in zip(numbers_range, batch) if row.strip()]
        if not header_checked and numbered:
            header_checked = True
            if _looks_like_header(numbered[0][1], q.coord_columns):
                if not jsonl:
                    out.write(numbered[0][1].rstrip() + "," + names + "\n")
                numbered = numbered[1:]
        if not numbered:
            continue
        rows = [row for _, row in numbered]
        line_numbers = [n for n, _ in numbered]
        fields, numbers, problems = q.parse(rows, line_numbers)
        values, lat, lon = q.evaluate(numbers, line_numbers, problems)
        if not problems and not jsonl and q.plain:
            # the common case formatted in one comprehension (NaN prints as "nan", as below)
            p = q.precision
            out.write("\n".join(f"{row.rstrip()},{v:.{p}f}" for row, v in zip(rows, values[:, 0].tolist())) + "\n")
            continue
        lines = []
        for i, row in enumerate(rows):
            if i in problems:
                bad += 1
                if jsonl:
                    lines.append(q.json_record(line_numbers[i], fields[i], None, None, None, error=problems[i]))
                else:
                    lines.append(f"ERROR: {problems[i]}")
            elif jsonl:
                lines.append(q.json_record(line_numbers[i], fields[i], values[i], lat[i], lon[i]))
            else:
                lines.append(f"{row.rstrip()},{q.csv_values(values[i])}")
        out.write("\n".join(lines) + "\n")
    return bad


