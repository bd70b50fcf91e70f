"""geoid-fit: fit a geoid grid (file or catalogue name) into a tile store."""

from __future__ import annotations

import json
import logging
import sys
import time

import click

from ._common import user_errors, verbosity_options

log = logging.getLogger("geoidspline.cli")


@click.command(name="fit", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("source")
@click.option("--out", "out", type=click.Path(file_okay=False), default=None,
              help="Store directory to write (must not exist unless --overwrite).")
@click.option("--update", "update", type=click.Path(file_okay=False, exists=True), default=None,
              help="Instead of --out: replace an existing store's geoid inside --region by SOURCE, refitting "
                   "only the tiles the region touches.")
@click.option("--blend-width", type=click.FloatRange(min=0.0), default=100.0, show_default=True,
              help="With --update: width in km outside --region over which SOURCE fades into the store.")
@click.option("--region", nargs=4, type=float, metavar="S W N E", default=None,
              help="Region in degrees: south west north east (default: global).")
@click.option("--tolerance", type=float, default=None,
              help="Largest |error| in metres accepted at the data nodes [default: 0.5; with --update: the "
                   "store's].")
@click.option("--h0", type=float, default=None, help="Level-0 grid spacing on the unit sphere [default: 0.1].")
@click.option("--max-level", type=int, default=None, help="Finest overlay level (h = h0 / 2**level) [default: 8].")
@click.option("--order", type=int, default=4, show_default=True, help="Spline order (4 = cubic, C²).")
@click.option("--workers", type=int, default=1, show_default=True, help="Worker processes solving tiles.")
@click.option("--scheduler", type=str, default=None, metavar="TEXT",
              help="dask scheduler address, or 'local' for a LocalCluster of --workers processes.")
@click.option("--correction", type=click.Path(exists=True, dir_okay=False), default=None,
              help="NGA zeta-to-N correction coefficients (CORRCOEF) for a model SOURCE.")
@click.option("--preset", type=click.Choice(["nga-f477", "nga-hsynth", "generic"]), default=None,
              help="Synthesis conventions for a model SOURCE [default: chosen from the model].")
@click.option("--sample-spacing", type=float, default=None,
              help="Lattice spacing in degrees at which a model SOURCE is synthesised "
                   "[default: 90/N for degree N, at most a quarter of h0].")
@click.option("--method", type=click.Choice(["least-squares", "interpolation"]), default="least-squares",
              show_default=True,
              help="How level 0 is computed: least squares (any source) or quasi-interpolation of a model "
                   "SOURCE (no linear solves: the way to millimetre-level global stores).")
@click.option("--overwrite", is_flag=True, help="Replace an existing store at --out.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@verbosity_options
@user_errors
def main(source, out, update, blend_width, region, tolerance, h0, max_level, order, workers, scheduler, correction,
         preset, sample_spacing, method, overwrite, as_json, quiet):
    """Fit SOURCE into ambient B-spline tiles stored at --out.

    SOURCE is a grid file (.gtx, .nc, WW15MGH.DAC, .pgm), a catalogue name such as
    egm96-15, or a spherical-harmonic model (ICGEM .gfc, NGA egm96_to360.ascii[.gz],
    EGM2008_to2190_*) whose synthesis is fitted directly.
    """
    from geoidspline.build import build_store
    from geoidspline.catalogue import open_source

    if (out is None) == (update is None):
        raise click.UsageError("give either --out STORE (a new fit) or --update STORE (a regional update)")
    if update is not None:
        return _update(source, update, region, blend_width, workers, correction, preset, as_json, quiet, tolerance)
    from geoidspline.fit import FitParameters, check_method
    from geoidspline.region import GLOBAL, Region

    defaults = FitParameters()
    params = FitParameters(
        order=order, tolerance_m=0.5 if tolerance is None else tolerance,
        h0=defaults.h0 if h0 is None else h0,
        max_level=defaults.max_level if max_level is None else max_level,
        workers=workers, sample_spacing_deg=sample_spacing, scheduler=scheduler, method=method,
    )
    fit_region = Region.from_bounds(*region) if region else GLOBAL
    src = open_source(source, correction, preset)
    check_method(src, params)
    log.info("source %s (%s), region %s", src.provenance.source, src.provenance.model, fit_region.as_tuple())
    started = time.perf_counter()
    bar = None
    if not quiet:
        from tqdm import tqdm

        bar = tqdm(desc="solving", unit=" problems", file=sys.stderr, leave=False)
    try:
        result, info = build_store(src, out, fit_region, params, progress=bar.update if bar is not None else None,
                                   overwrite=overwrite)
    finally:
        if bar is not None:
            bar.close()
    info["wall_seconds"] = round(time.perf_counter() - started, 2)
    if as_json:
        click.echo(json.dumps(info, indent=1))
        sys.exit(0 if result.converged else 3)  # the same exit status as without --json
    click.echo(f"store      {out}  ({info['tiles']} tiles, {info['bytes']:,} bytes)")
    click.echo(f"source     {src.provenance.source} ({src.provenance.model})")
    click.echo(f"region     S {fit_region.south:g}  W {fit_region.west:g}  N {fit_region.north:g}  E {fit_region.east:g}")
    click.echo("level  h          coefficients  max|err| m  nodes>tol  seconds")
    for r in result.levels:
        click.echo(f"{r.level:5d}  {r.h:<9.6g}  {r.coefficients:12,d}  {r.max_error_m:10.4f}  "
                   f"{r.nodes_above_tolerance:9d}  {r.seconds:7.1f}")
    state = "reached" if result.converged else "NOT reached (raise --max-level)"
    click.echo(f"total      {info['coefficients']:,} coefficients; tolerance {params.tolerance_m:g} m {state}")
    click.echo(f"nodes      {info['nodes']:,}: max |error| {info['node_max_error_m']:.4f} m, "
               f"RMS {info['node_rms_error_m']:.4f} m")
    if info["check_points"]:
        click.echo(f"check      {info['check_points']:,} points ({info['check_truth']}): "
                   f"max {info['max_error_m']:.4f} m, RMS {info['rms_error_m']:.4f} m")
    click.echo(f"time       {info['wall_seconds']:.1f} s")
    if not result.converged:
        sys.exit(3)


def _update(source, store, region, blend_width, workers, correction, preset, as_json, quiet, tolerance=None):
    from geoidspline.catalogue import open_source
    from geoidspline.region import Region
    from geoidspline.update import update_store

    if region is None:
        raise click.UsageError("--update needs --region S W N E")
    src = open_source(source, correction, preset)
    started = time.perf_counter()
    record = update_store(store, src, Region.from_bounds(*region), blend_width_km=blend_width, workers=workers,
                          tolerance_m=tolerance)
    record["wall_seconds"] = round(time.perf_counter() - started, 2)
    if as_json:
        click.echo(json.dumps(record, indent=1))
        sys.exit(0 if record["converged"] else 3)
    click.echo(f"store      {store}  version {record['previous_version']} -> {record['store_version']}")
    click.echo(f"source     {record['source']} ({record['model']})")
    s, w, n, e = record["region"]
    click.echo(f"region     S {s:g}  W {w:g}  N {n:g}  E {e:g}, blend {record['blend_width_km']:g} km")
    click.echo(f"tiles      {record['tiles_rewritten']} rewritten, {record['coefficients_added']:+,d} coefficients")
    if record["nodes_in_region"]:
        click.echo(f"region     {record['nodes_in_region']:,} nodes: max |error| {record['max_error_m']:.4f} m, "
                   f"RMS {record['rms_error_m']:.4f} m")
    if not record["converged"]:
        click.echo(f"tolerance  {record['tolerance_m']:g} m NOT reached with the store's levels")
    click.echo(f"time       {record['wall_seconds']:.1f} s")
    if not record["converged"]:
        sys.exit(3)


if __name__ == "__main__":  # pragma: no cover
    main()
