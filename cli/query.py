"""geoid-query: geoid undulations from a tile store (or a harmonic model), for one point
or a CSV stream, with optional derived quantities."""

from __future__ import annotations

import logging
import sys

import click

from geoidspline.api import HEIGHT_OUTPUT, PRESETS, TIDE_SYSTEM_NAMES

from ._common import Number, command, echo, output_stream, store_options, user_errors, verbosity_options

log = logging.getLogger("geoidspline.cli")

HELP = """Geoid undulation N (metres) at LAT LON (degrees), or for every row of --input.

\b
Source: --store DIR (a tile store written by geoid-fit), or --model FILE for the exact
spherical-harmonic synthesis at each point (ICGEM .gfc or NGA ASCII coefficients, with
an optional --correction FILE, NGA's CORRCOEF or Zeta-to-N_to2160_egm2008; --preset
defaults to nga-f477, i.e. NGA's F477 for EGM96, and nga-hsynth, NGA's hsynth_WGS84, for
an EGM2008 model alone or with its Zeta-to-N correction).
`geoid-query --model egm96_to360.ascii.gz --correction CORRCOEF.gz LAT LON` reproduces
NGA's F477.

\b
Every answer is true or refused. A point outside the store's coverage (outside the
region it was fitted for, or where its source had no data) gets no number: an
`ERROR: line N: outside the store's coverage (...)` row (for LAT LON: an ERROR line),
exit status 1; `--outside nan` writes nan (jsonl: null) there instead, exit 0.
NaN, infinite or non-numeric coordinates, a latitude beyond ±90 and a longitude beyond
±1e6 degrees (not wrapped) are errors in any case.

\b
CSV rows are echoed with the results appended as new columns, in this order
(column names, also appended to a header row when the input has one):
  latitude_deg, longitude_deg  with --crs: the input converted to WGS84 degrees
  undulation_m                 always: N in metres
  xi_arcsec, eta_arcsec,       with --deflection: deflection of the vertical
  dNdn_m_per_m, dNde_m_per_m     (xi = -dN/dnorth, eta = -dN/deast; arcseconds)
                                 and the geoid gradient in metres per metre
  orthometric_height_m         with --height-in ellipsoidal: H = h - N
  ellipsoidal_height_m         with --height-in orthometric: h = H + N
  error_bound_m                with --with-error: a bound on |N - truth| that held
                                 at 99.9% of random points or more (see README)
With LAT LON (or X Y [Z] [HEIGHT]) on the command line only the appended values are
printed, comma-separated. --precision gives the decimals of metres and arcseconds
(degrees get 5 more; the m/m gradients are printed as %.<precision>e).

\b
Input: comma-separated fields (blanks around a field and one pair of double quotes
are dropped; a UTF-8 byte-order mark is ignored; blank lines are skipped but counted).
Latitude, longitude in columns 0, 1 (0-based). With --crs they are x, y in that CRS
(longitude, latitude for a geographic CRS: always x first), plus z in column 2 for a
3D CRS (geocentric EPSG:4978, geographic 3D EPSG:4979), whose converted ellipsoidal
height is then what --height-in ellipsoidal uses. Otherwise the height for
--height-in is in --height-column (default 2, the third column; not a coordinate's).

\b
Header: the first non-blank line is a header (echoed with the new column names) when
each of its coordinate fields is a name: not a number, a letter or underscore first,
then letters, digits, underscores, blanks, '.' or '-', optionally a unit in brackets
(lat, Latitude, lon_deg, "y (m)"). Any other line is a data row: -33.45S,-70.66W or
N45,E7 is a bad row, not a header.

\b
--format jsonl prints one JSON object per row with the keys, always all present:
line, fields, latitude_deg, longitude_deg, undulation_m, [the optional columns above],
error (null, or the message of a bad row); null for values that are not available.
A header row is not echoed in jsonl.

A bad row becomes an `ERROR: line N: ...` row (jsonl: its "error" key), the rest go
on in order, and the exit status is then 1. Output that cannot be written (a full disk)
is one ERROR line on stderr, exit 1; a closed pipe (| head) ends quietly.
"""


@command("query", help=HELP, context={"ignore_unknown_options": True})
@store_options("Tile store directory.")
@click.option("--key", "key", type=click.Path(dir_okay=False), default=None, metavar="PUBKEY",
              help="Refuse the store unless this Ed25519 public key (PEM) signed it (see geoid-info --key).")
@click.option("--model", "model_path", type=click.Path(), default=None,
              help="Spherical-harmonic model file (instead of --store): exact synthesis at each point.")
@click.option("--correction", "correction_path", type=click.Path(), default=None,
              help="With --model: NGA zeta-to-N correction coefficients (CORRCOEF, cm; "
                   "Zeta-to-N_to2160_egm2008, m).")
@click.option("--preset", type=click.Choice(PRESETS), default=None,
              help="With --model: synthesis conventions [default: nga-f477; nga-hsynth for EGM2008].")
@click.option("--input", "input_path", type=click.File("r"), default=None,
              help="CSV file of lat,lon[,...] rows ('-' for stdin); a header row is optional.")
@click.option("--deflection", is_flag=True,
              help="Append xi_arcsec, eta_arcsec, dNdn_m_per_m, dNde_m_per_m (store only).")
@click.option("--height-in", type=click.Choice(sorted(HEIGHT_OUTPUT)), default=None,
              help="Convert a height: ellipsoidal h -> orthometric_height_m, orthometric H -> ellipsoidal_height_m.")
@click.option("--height-column", type=Number("height_column"), default=None,
              help="0-based column of the height for --height-in [default: 2, the third column].")
@click.option("--crs", default=None, metavar="CRS",
              help="Input coordinates are x,y[,z] in this CRS (e.g. EPSG:32633, EPSG:4978); "
                   "appends latitude_deg, longitude_deg.")
@click.option("--with-error", is_flag=True,
              help="Append error_bound_m, a bound on the store's error at the point (store only; see README).")
@click.option("--outside", type=click.Choice(["error", "nan"]), default="error", show_default=True,
              help="A point outside the store's coverage: an ERROR row (exit 1), or nan values (exit 0).")
@click.option("--format", "fmt", type=click.Choice(["csv", "jsonl"]), default="csv", show_default=True,
              help="Output format.")
@click.option("--precision", type=Number("precision"), default=4, show_default=True,
              help="Decimals of metres and arcseconds.")
@click.option("--tide-system", type=click.Choice(TIDE_SYSTEM_NAMES), default=None,
              help="Answer in this tide system: converted from the store's (or model's) own [default: its own].")
@click.argument("coordinates", nargs=-1, type=str, required=False, metavar="[LAT LON]")
@verbosity_options
@user_errors
def main(store_path, key, model_path, correction_path, preset, input_path, deflection, height_in, height_column,
         crs, with_error, outside, fmt, precision, tide_system, coordinates, quiet, verbose):
    unknown = [c for c in coordinates if c.startswith("--")]  # a coordinate is never spelled so
    if unknown:
        raise click.UsageError(f"No such option: {unknown[0]}")
    coordinates = tuple(coordinates) or None
    if (input_path is None) == (coordinates is None):
        raise click.UsageError("give either LAT LON or --input FILE (use '-' for stdin)")
    if (store_path is None) == (model_path is None):
        raise click.UsageError("give either --store DIR or --model FILE")
    if model_path is None and (correction_path is not None or preset is not None):
        raise click.UsageError("--correction and --preset go with --model")
    if key is not None and store_path is None:
        raise click.UsageError("--key goes with --store (a model file is not signed)")
    if model_path is not None and (deflection or with_error):
        raise click.UsageError("--deflection and --with-error need a --store (a model has no tiles or gradient here)")
    if height_column is not None and height_in is None:
        raise click.UsageError("--height-column goes with --height-in")

    crs_dim = 2
    if crs is not None:
        from geoidspline.api import crs_info

        crs_dim = crs_info(crs)[1]
        if crs_dim == 3:
            if height_column is not None:
                raise click.UsageError(f"--crs {crs} is 3D: the height is its z (column 2); drop --height-column")
            if height_in == "orthometric":
                raise click.UsageError(f"--crs {crs} is 3D: its z gives an ellipsoidal height, not an orthometric one")
    if height_column is not None and height_column < 2:
        what = ("x", "y") if crs is not None else ("latitude", "longitude")
        raise click.UsageError(f"--height-column {height_column} is the {what[height_column]} column: "
                               f"the height must be in another column (2 or more)")

    if store_path is not None:
        from geoidspline.api import open_store

        source = open_store(store_path, key=key)
    else:
        from geoidspline.api import load_synthesis

        source = load_synthesis(model_path, correction_path, preset)
        log.info("model %s, preset %s, degree %d", source.model.name, source.preset, source.max_degree)

    from geoidspline.api import BatchQuery, query_point, query_rows

    q = BatchQuery(source, is_store=store_path is not None, deflection=deflection, height_in=height_in,
              height_column=height_column, crs=crs, with_error=with_error, precision=precision, fmt=fmt,
              outside=outside, tide_system=tide_system)
    if coordinates is not None:
        if len(coordinates) != q.width:
            raise click.UsageError(f"expected {q.width} coordinate values ({q.layout()}), got {len(coordinates)}")
        echo(query_point(q, coordinates))
        return
    bad = query_rows(q, input_path, output_stream())
    if bad:
        log.error("%d row(s) could not be processed", bad)
        sys.exit(1)


if __name__ == "__main__":  # pragma: no cover
    main()
