"""geoid-update: a regional update of a store (new data inside a region, blended in)."""

from __future__ import annotations

import json
import sys
import time

import click

from geoidspline.api import PRESETS

from ._common import REGION, Number, band_options, command, echo, store_options, user_errors, verbosity_options


@command("update")
@click.argument("source")
@store_options("The store to update (it must exist; it is changed atomically).")
@click.option("--region", nargs=4, type=REGION, metavar="S W N E", required=True,
              help="Region in degrees where SOURCE replaces the store's geoid: south west north east.")
@click.option("--blend-width", type=Number("blend_width_km"), default=100.0, show_default=True,
              help="Width in km outside --region over which SOURCE fades into the store; outside it the store "
                   "is unchanged (0: the change stays inside the region, so SOURCE is reached only away from its "
                   "edge).")
@click.option("--tolerance", type=Number("tolerance_m"), default=None,
              help="Largest |error| in metres accepted inside --region [default: the store's]. The update "
                   "may add levels finer than the store's, down to what SOURCE's node spacing determines.")
@click.option("--workers", type=Number("workers"), default=1, show_default=True,
              help="Worker processes solving blocks (same coefficients).")
@click.option("--correction", type=click.Path(exists=True, dir_okay=False), default=None,
              help="NGA zeta-to-N correction coefficients for a model SOURCE: CORRCOEF (EGM96, cm) or "
                   "Zeta-to-N_to2160_egm2008 (EGM2008, m; the unit follows the file name).")
@click.option("--preset", type=click.Choice(PRESETS), default=None,
              help="Synthesis conventions for a model SOURCE [default: chosen from the model].")
@click.option("--wait", "wait_seconds", type=Number("wait_seconds"), default=0.0, show_default=True,
              metavar="SECONDS", help="Wait this long for another process writing the store, then give up.")
@band_options
@click.option("--accept-datum", is_flag=True,
              help="Take a SOURCE on another datum that PROJ cannot convert well as it is (or with PROJ's less "
                   "accurate transformation).")
@click.option("--accept-quasi-geoid", is_flag=True,
              help="Take height anomalies into a geoid store (or undulations into a quasi-geoid one).")
@click.option("--accept-implausible", is_flag=True,
              help="Skip the plausibility check (a change beyond 10 m from the store, or a slope beyond 2e-3 m/m "
                   "between SOURCE's nodes, is refused otherwise).")
@click.option("--sign", "sign", type=click.Path(dir_okay=False), default=None, metavar="KEYFILE",
              help="Sign the updated store's manifest with this Ed25519 private key (PEM; see geoid-info --generate-key).")
@click.option("--json", "as_json", is_flag=True, help="Print the update's history record as JSON.")
@verbosity_options
@user_errors
def main(source, store_path, region, blend_width, tolerance, workers, correction, preset, wait_seconds, band, variable,
         accept_datum, accept_quasi_geoid, accept_implausible, sign, as_json, quiet, verbose):
    """Replace the geoid of the store at --store by SOURCE inside --region.

    The update fits overlays to w·(N_new − N_store) with the store's own parameters (w
    fades from 1 inside the region to 0 over --blend-width km outside it, and likewise
    from SOURCE's data into its no-data areas, such as a national grid's sea), so the
    result is still one C² spline with no step at the region's edge or the coast. The
    new B-splines lie inside the blend zone: outside it the store is unchanged, and
    only the tiles owning them are rewritten. Refused before anything is written when the store
    is read-only or being written by another process (after --wait), the source's datum or
    quantity differs from the store's without a well-defined conversion (tide systems and
    datums PROJ transforms well are converted, and said), the source is implausible
    against the store (a change beyond 10 m, a slope beyond 2e-3 m/m), or the region with
    its blend zone lies outside the source's extent (the message names the largest region
    that fits), or outside the store's region. Exit status 3: written, but the tolerance was not reached
    inside the region.
    """
    if store_path is None:
        raise click.UsageError("give --store DIR, the store to update")
    run_update(source, store_path, region, blend_width, workers, correction, preset, as_json, quiet, tolerance,
               wait_seconds, sign, band=band, variable=variable, accept_datum=accept_datum,
               accept_quasi_geoid=accept_quasi_geoid, accept_implausible=accept_implausible)


def run_update(source, store, region, blend_width, workers, correction, preset, as_json, quiet, tolerance=None,
               wait_seconds=0.0, sign=None, **choices):
    from geoidspline.api import update

    if region is None:
        raise click.UsageError("a regional update needs --region S W N E")
    started = time.perf_counter()
    record = update(store, source, region, blend_width_km=blend_width, tolerance_m=tolerance, workers=workers,
                    correction=correction, preset=preset, wait_seconds=wait_seconds, sign=sign, **choices)
    record["wall_seconds"] = round(time.perf_counter() - started, 2)
    if as_json:
        echo(json.dumps(record, indent=1))
        sys.exit(0 if record["converged"] else 3)
    echo(f"store      {store}  version {record['previous_version']} -> {record['store_version']}")
    echo(f"source     {record['source']} ({record['model']})")
    for note in record.get("source_notes", []):
        echo(f"source     {note}")
    s, w, n, e = record["region"]
    echo(f"region     S {s:g}  W {w:g}  N {n:g}  E {e:g}, blend {record['blend_width_km']:g} km")
    echo(f"tiles      {record['tiles_rewritten']} rewritten, {record['coefficients_added']:+,d} coefficients")
    if record["nodes_in_region"]:
        echo(f"region     {record['nodes_in_region']:,} nodes: max |error| {record['max_error_m']:.4f} m, "
                   f"RMS {record['rms_error_m']:.4f} m")
    if not record["converged"]:
        echo(f"tolerance  {record['tolerance_m']:g} m NOT reached inside the region")
        if record.get("hint"):
            echo(f"hint       {record['hint']}")
    if record.get("signed_by"):
        echo(f"signed     by key {record['signed_by']}")
    echo(f"time       {record['wall_seconds']:.1f} s")
    if not record["converged"]:
        sys.exit(3)


if __name__ == "__main__":  # pragma: no cover
    main()
