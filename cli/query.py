"""geoid-query: geoid undulations from a tile store, for one point or a CSV stream."""

from __future__ import annotations

import logging
import os
import select
import sys

import click

from ._common import user_errors, verbosity_options

log = logging.getLogger("geoidspline.cli")

BATCH_BYTES = 1 << 16


def _line_batches(stream):
    """Yield lists of complete lines (str, without newline) as soon as they arrive.

    Reads whatever the stream has ready (up to 64 KiB) instead of waiting for a full
    batch, so a co-process sending one line gets its answer at once while a file or
    pipe is processed in large vectorised batches.
    """
    try:
        fd = stream.fileno()
    except (AttributeError, OSError, ValueError):
        fd = None
    if fd is None or getattr(stream, "buffer", None) is None:
        batch = []
        for line in stream:
            batch.append(line.rstrip("\r\n"))
            if len(batch) >= 4096:
                yield batch
                batch = []
        if batch:
            yield batch
        return
    pending = b""
    while True:
        chunk = os.read(fd, BATCH_BYTES)
        if not chunk:
            break
        pending += chunk
        # take more while it is already there, up to one batch
        while len(pending) < BATCH_BYTES and select.select([fd], [], [], 0)[0]:
            more = os.read(fd, BATCH_BYTES)
            if not more:
                break
            pending += more
        *lines, pending = pending.split(b"\n")
        if lines:
            yield [ln.decode("utf-8", "replace").rstrip("\r") for ln in lines]
    if pending:
        yield [pending.decode("utf-8", "replace").rstrip("\r")]


def _parse(rows, line_numbers, lat_col, lon_col):
    """Split rows into fields and parse lat/lon; return (fields, lat, lon, problems)."""
    import numpy as np

    lat = np.full(len(rows), np.nan)
    lon = np.full(len(rows), np.nan)
    problems = {}
    fields = []
    for i, row in enumerate(rows):
        parts = [p.strip() for p in row.split(",")]
        fields.append(parts)
        n = line_numbers[i]
        if len(parts) <= max(lat_col, lon_col):
            problems[i] = f"line {n}: expected at least {max(lat_col, lon_col) + 1} columns (lat,lon), got {len(parts)}"
            continue
        try:
            la, lo = float(parts[lat_col]), float(parts[lon_col])
        except ValueError:
            problems[i] = f"line {n}: latitude/longitude are not numbers: {parts[lat_col]!r}, {parts[lon_col]!r}"
            continue
        if not (np.isfinite(la) and np.isfinite(lo)):
            problems[i] = f"line {n}: latitude/longitude must be finite numbers, got {parts[lat_col]!r}, {parts[lon_col]!r}"
        elif abs(la) > 90.0:
            problems[i] = f"line {n}: latitude {la:g} is outside [-90, 90] degrees"
        else:
            lat[i], lon[i] = la, lo
    return fields, lat, lon, problems


def _looks_like_header(line, lat_col, lon_col):
    parts = [p.strip() for p in line.split(",")]
    if len(parts) <= max(lat_col, lon_col):
        return False
    try:
        float(parts[lat_col])
        float(parts[lon_col])
    except ValueError:
        return True
    return False


@click.command(name="query", context_settings={"help_option_names": ["-h", "--help"],
                                               "ignore_unknown_options": True})
@click.option("--store", "store_path", required=True, type=click.Path(), help="Tile store directory.")
@click.option("--input", "input_path", type=click.File("r"), default=None,
              help="CSV file of lat,lon[,...] rows ('-' for stdin); a header row is optional.")
@click.option("--precision", type=int, default=4, show_default=True, help="Decimals of the undulation (metres).")
@click.argument("coordinates", nargs=2, type=float, required=False, metavar="[LAT LON]")
@verbosity_options
@user_errors
def main(store_path, input_path, precision, coordinates, quiet):
    """Geoid undulation N (metres) at LAT LON (degrees), or for every row of --input.

    CSV rows are echoed with the undulation appended as the last column
    (``undulation_m``); a bad row becomes an ``ERROR: line N: ...`` row, the rest go
    on, and the exit status is then 1.
    """
    import geoidspline

    if (input_path is None) == (coordinates is None):
        raise click.UsageError("give either LAT LON or --input FILE (use '-' for stdin)")
    store = geoidspline.open_store(store_path)
    if coordinates is not None:
        value = store.undulation(*coordinates)
        click.echo(f"{value:.{precision}f}")
        return
    bad = _stream(store, input_path, precision)
    if bad:
        log.error("%d row(s) could not be processed", bad)
        sys.exit(1)


def _stream(store, stream, precision, lat_col=0, lon_col=1):
    out = sys.stdout
    line_number = 0
    bad = 0
    header_checked = False
    for batch in _line_batches(stream):
        numbers = range(line_number + 1, line_number + 1 + len(batch))
        line_number += len(batch)
        # blank lines are skipped, but rows keep their line numbers for messages
        numbered = [(n, row) for n, row in zip(numbers, batch) if row.strip()]
        if not header_checked and numbered:
            header_checked = True
            if _looks_like_header(numbered[0][1], lat_col, lon_col):
                out.write(numbered[0][1].rstrip() + ",undulation_m\n")
                numbered = numbered[1:]
        if not numbered:
            continue
        rows = [row for _, row in numbered]
        fields, lat, lon, problems = _parse(rows, [n for n, _ in numbered], lat_col, lon_col)
        values = store.undulation(lat, lon)
        lines = []
        for i, row in enumerate(rows):
            if i in problems:
                lines.append(f"ERROR: {problems[i]}")
                bad += 1
            else:
                lines.append(f"{row.rstrip()},{values[i]:.{precision}f}")
        out.write("\n".join(lines) + "\n")
        out.flush()
    return bad


if __name__ == "__main__":  # pragma: no cover
    main()
