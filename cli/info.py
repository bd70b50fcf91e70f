"""geoid-info: what a tile store holds and how accurate it is."""

from __future__ import annotations

import json

import click

from ._common import user_errors, verbosity_options


@click.command(name="info", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("store_path", metavar="STORE", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@verbosity_options
@user_errors
def main(store_path, as_json, quiet):
    """Summary of the tile store STORE (a directory written by geoid-fit)."""
    import geoidspline

    info = geoidspline.open_store(store_path).info()
    if as_json:
        click.echo(json.dumps(info, indent=1))
        return
    prov = info["provenance"]
    click.echo(f"store        {info['store']} (format {info['format_version']}, version {info['store_version']})")
    click.echo(f"source       {prov['source']} sha256 {str(prov['sha256'])[:16]}...")
    click.echo(f"model        {prov['model']}, ellipsoid {prov['ellipsoid']}, tide system {prov['tide_system']}, "
               f"zero-degree term {prov['zero_degree_term_m']} m")
    s, w, n, e = info["region"]
    click.echo(f"region       S {s:g}  W {w:g}  N {n:g}  E {e:g} (degrees)")
    click.echo(f"spline       order {info['order']}, h0 {info['h0']:g}, tolerance {info['tolerance_m']:g} m, "
               f"{'converged' if info['converged'] else 'tolerance NOT reached'}")
    for lv in info["levels"]:
        click.echo(f"  level {lv['level']}    h {lv['h']:<10.6g} {lv['coefficients']:>10,d} coefficients")
    click.echo(f"coefficients {info['coefficients']:,} in {info['tiles']} tiles, {info['bytes']:,} bytes")
    click.echo(f"data nodes   {info['nodes']:,}: max |error| {info['node_max_error_m']:.4f} m, "
               f"RMS {info['node_rms_error_m']:.4f} m")
    if info["check_points"]:
        click.echo(f"check points {info['check_points']:,}: max {info['max_error_m']:.4f} m, "
                   f"RMS {info['rms_error_m']:.4f} m, 99% {info['p99_error_m']:.4f} m")
        click.echo(f"             truth: {info['check_truth']}")


if __name__ == "__main__":  # pragma: no cover
    main()
