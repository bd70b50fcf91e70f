"""geoid-fit: fit a geoid grid (file or catalogue name) into a tile store."""

from __future__ import annotations

import json
import sys

import click

from geoidspline.api import FIT_METHODS, PRESETS, REFINEMENTS, TIDE_SYSTEM_NAMES, FitParameters

from ._common import REGION, Number, band_options, command, echo, store_options, user_errors, verbosity_options

_DEFAULTS = FitParameters()

#: Options that fix a fit parameter (given: used as given; not given: chosen from the
#: tolerance by geoidspline.fitting.choose), option name -> FitParameters field.
_CHOSEN = {"method": "method", "refinement": "refinement", "order": "order", "h0": "h0", "max_level": "max_level",
           "sample_spacing": "sample_spacing_deg", "tolerance": "tolerance_m"}

#: Options of a new fit that a regional update cannot honour: it refits with the store's
#: own parameters, so that the result is one spline.
_FIT_ONLY = ("h0", "max_level", "order", "method", "refinement", "sample_spacing", "overwrite", "scheduler",
             "max_memory", "resume")


@command("fit")
@click.argument("source")
@store_options("Store directory to write (must not exist unless --overwrite).", aliases=("--out",))
@click.option("--update", "update", type=click.Path(file_okay=False), default=None, hidden=True,
              help="Old spelling of 'geoid-update SOURCE --store DIR'.")
@click.option("--blend-width", type=Number("blend_width_km"), default=100.0, show_default=True, hidden=True,
              help="With --update: width in km outside --region over which SOURCE fades into the store.")
@click.option("--region", nargs=4, type=REGION, metavar="S W N E", default=None,
              help="Region in degrees: south west north east (default: the source's extent; global for a "
                   "global grid or a model).")
@click.option("--tolerance", type=Number("tolerance_m"), default=_DEFAULTS.tolerance_m,
              show_default=True, help="Largest |error| in metres accepted. The options below that are not "
                                      "given are chosen from it for the fewest coefficients (the summary says why).")
@click.option("--h0", type=Number("h0"), default=None, help="Level-0 grid spacing on the unit sphere [default: chosen].")
@click.option("--max-level", type=Number("max_level"), default=None, help="Finest level (h = h0 / 2**level) [default: chosen].")
@click.option("--order", type=Number("order"), default=None, help="Spline order (4 = cubic, C²) [default: chosen].")
@click.option("--max-memory", "max_memory", type=Number("max_memory_gb"), default=None, metavar="GB",
              help="Memory in GB the fit plans against; a fit that needs more is refused before any work, "
                   "naming the figure [default: 60 % of the machine's].")
@click.option("--workers", type=Number("workers"), default=1, show_default=True,
              help="Worker processes solving blocks (same coefficients, not stored).")
@click.option("--scheduler", type=str, default=None, metavar="TEXT",
              help="dask scheduler address, or 'local' for a LocalCluster of --workers processes.")
@click.option("--correction", type=click.Path(exists=True, dir_okay=False), default=None,
              help="NGA zeta-to-N correction coefficients for a model SOURCE: CORRCOEF (EGM96, cm) or "
                   "Zeta-to-N_to2160_egm2008 (EGM2008, m; the unit follows the file name).")
@click.option("--preset", type=click.Choice(PRESETS), default=None,
              help="Synthesis conventions for a model SOURCE [default: chosen from the model].")
@click.option("--sample-spacing", type=Number("sample_spacing_deg"), default=None,
              help="Lattice spacing in degrees at which a model SOURCE is synthesised "
                   "[default: chosen].")
@click.option("--method", type=click.Choice(FIT_METHODS), default=None,
              help="How level 0 is computed: least squares (any source) or quasi-interpolation of a model "
                   "SOURCE (no linear solves: the way to millimetre-level global stores) [default: chosen: "
                   "interpolation for a model, least squares for a grid].")
@click.option("--refinement", type=click.Choice(REFINEMENTS), default=None,
              help="How levels are added: hierarchical overlays (each level fitted to the residual, thesis "
                   "5.2) or one linearly independent hierarchical B-spline basis over all levels (5.3; least "
                   "squares, or with --method interpolation its quasi-interpolant for a model SOURCE) "
                   "[default: chosen: hierarchical for least squares, overlays after quasi-interpolation].")
@band_options
@click.option("--tide-system", type=click.Choice(TIDE_SYSTEM_NAMES), default=None,
              help="Tide system of the store: SOURCE is converted to it [default: SOURCE's own].")
@click.option("--accept-datum", is_flag=True,
              help="Take a SOURCE on another datum that PROJ cannot convert well (e.g. NAD27, Bessel without a "
                   "datum) as it is, or with PROJ's less accurate transformation.")
@click.option("--accept-quasi-geoid", is_flag=True,
              help="Fit a quasi-geoid SOURCE (height anomalies): the store then says it holds a quasi-geoid.")
@click.option("--overwrite", is_flag=True, help="Replace an existing store at --store.")
@click.option("--resume", is_flag=True,
              help="Continue the interrupted fit at --store from its last committed band (a model's whole globe "
                   "is fitted and committed band by band); without one there, start it.")
@click.option("--sign", "sign", type=click.Path(dir_okay=False), default=None, metavar="KEYFILE",
              help="Sign the store's manifest with this Ed25519 private key (PEM; see geoid-info --generate-key).")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@verbosity_options
@user_errors
@click.pass_context
def main(ctx, source, store_path, update, blend_width, region, tolerance, h0, max_level, order, max_memory, workers,
         scheduler, correction, preset, sample_spacing, method, refinement, band, variable, tide_system, accept_datum,
         accept_quasi_geoid, overwrite, resume, sign, as_json, quiet, verbose):
    """Fit SOURCE into ambient B-spline tiles stored at --store.

    SOURCE is a grid file (.gtx, .nc, WW15MGH.DAC, .pgm), a catalogue name such as
    egm96-15, or a spherical-harmonic model (ICGEM .gfc, NGA egm96_to360.ascii[.gz],
    EGM2008_to2190_*) whose synthesis is fitted directly.
    """
    from geoidspline.api import for_terminal, run_fit

    if update is not None:
        from click.core import ParameterSource

        ignored = [f"--{name.replace('_', '-')}" for name in _FIT_ONLY
                   if ctx.get_parameter_source(name) is not ParameterSource.DEFAULT]
        if ignored:
            raise click.UsageError(f"a regional update refits with the store's own parameters: "
                                   f"{', '.join(ignored)} cannot be honoured (use geoid-update)")
        if store_path is not None:
            raise click.UsageError("give --update STORE or --store STORE, not both")
        from .update import run_update

        if tide_system is not None:
            raise click.UsageError("a regional update converts SOURCE to the store's own tide system: drop "
                                   "--tide-system (use geoid-update)")
        return run_update(source, update, region, blend_width, workers, correction, preset, as_json, quiet,
                          tolerance if ctx.get_parameter_source("tolerance") is not ParameterSource.DEFAULT else None,
                          band=band, variable=variable, accept_datum=accept_datum,
                          accept_quasi_geoid=accept_quasi_geoid, sign=sign)
    if store_path is None:
        raise click.UsageError("give --store DIR, the store to write (or use geoid-update for a regional update)")
    from click.core import ParameterSource

    if ctx.get_parameter_source("blend_width") is not ParameterSource.DEFAULT:
        raise click.UsageError("--blend-width goes with --update (a new fit has no blend zone)")
    out = store_path
    options = {"method": method, "refinement": refinement, "order": order, "h0": h0, "max_level": max_level,
               "sample_spacing": sample_spacing, "tolerance": tolerance}
    given = {field: options[name] for name, field in _CHOSEN.items()
             if name != "tolerance" and ctx.get_parameter_source(name) is not ParameterSource.DEFAULT}
    run = run_fit(source, out, region=region, overwrite=overwrite, workers=workers, scheduler=scheduler,
                  correction=correction, preset=preset, progress=for_terminal(quiet, verbose), tolerance_m=tolerance,
                  band=band, variable=variable, tide_system=tide_system, accept_datum=accept_datum,
                  accept_quasi_geoid=accept_quasi_geoid, sign=sign, max_memory_gb=max_memory, resume=resume, **given)
    result, info, choice, params, src, fit_region = (run.result, run.info, run.choice, run.parameters, run.source,
                                                     run.region)
    promise = run.promise
    info["wall_seconds"] = round(run.seconds, 2)
    info["converged"] = bool(result.converged)
    info["choices"] = choice.as_manifest()
    info["promise"] = promise
    if run.source_notes:  # what was converted or taken, as the manifest's provenance notes say
        info["source_notes"] = run.source_notes
    if as_json:
        echo(json.dumps(info, indent=1))
        sys.exit(0 if promise["kept"] else 3)
    echo(f"store      {out}  ({info['tiles']} tiles, {info['bytes']:,} bytes)")
    echo(f"source     {src.provenance.source} ({src.provenance.model})")
    for note in run.source_notes:
        echo(f"source     {note}")
    echo(f"region     S {fit_region.south:g}  W {fit_region.west:g}  N {fit_region.north:g}  E {fit_region.east:g}")
    for field in _CHOSEN.values():
        value = getattr(params, field)
        reason = choice.reasons[field]
        label = "given " if reason.startswith("given") else "chosen"
        echo(f"{label}     {field} = {value if value is not None else '-'}: {reason}")
    if result.basis is not None:  # hierarchical: a row per refinement step, every level refitted
        echo("step  finest level  h          coefficients  max|err| m  nodes>tol  seconds")
        for step, r in enumerate(result.levels):
            echo(f"{step:4d}  {r.level:12d}  {r.h:<9.6g}  {r.coefficients:12,d}  {r.max_error_m:10.4f}  "
                 f"{r.nodes_above_tolerance:9d}  {r.seconds:7.1f}")
    else:
        echo("level  h          coefficients  max|err| m  nodes>tol  seconds")
        for r in result.levels:
            echo(f"{r.level:5d}  {r.h:<9.6g}  {r.coefficients:12,d}  {r.max_error_m:10.4f}  "
                 f"{r.nodes_above_tolerance:9d}  {r.seconds:7.1f}")
    if result.refinement_fallback:
        echo(f"fallback   {result.refinement_fallback}")
    where = ("at the nodes and check points" if promise["check_max_m"] is not None
             else "at the nodes and cell centres" if promise["cell_centre_max_m"] is not None else "at the nodes")
    state = "kept" if promise["kept"] else f"NOT kept ({_why_not(result, choice, promise)})"
    echo(f"total      {info['coefficients']:,} coefficients; tolerance {promise['tolerance_m']:.3g} m {where} {state} "
         "in the store")
    echo(f"nodes      {info['nodes']:,}: max |error| {info['node_max_error_m']:.4f} m, "
         f"RMS {info['node_rms_error_m']:.4f} m")
    if info["check_points"]:
        echo(f"check      {info['check_points']:,} points ({info['check_truth']}): "
             f"max {info['max_error_m']:.4f} m, RMS {info['rms_error_m']:.4f} m")
    if promise["cell_centre_max_m"] is not None:
        echo(f"between    cell centres: at most {promise['cell_centre_max_m']:.4f} m outside the interval of the "
             "grid's bilinear and bicubic interpolants")
    echo(f"time       {info['wall_seconds']:.1f} s")
    if not promise["kept"]:
        sys.exit(3)


def _why_not(result, choice, promise) -> str:
    """Why a fit left nodes (or a grid's cell centres) above its tolerance, and only
    advice that can help."""
    given = {name for name, reason in choice.reasons.items() if reason.startswith("given")}
    if promise["node_max_m"] is not None and promise["node_max_m"] <= promise["tolerance_m"] \
            and (promise["check_max_m"] is None or promise["check_max_m"] <= promise["tolerance_m"]):
        # the nodes are kept: only the cell centres are not
        outside = f"cell centres up to {promise['cell_centre_max_m']:.4g} m outside the grid's interpolants' interval"
        if result.basis is None:
            return f"{outside}: overlays do not fit the cell centres, leave --refinement to be chosen"
        if given & {"h0", "order", "max_level"}:
            return f"{outside} with the given options: leave them to be chosen"
        return f"{outside} at the finest level the data determine"
    if result.data_limited:
        return "the finest level the data determine was reached"
    if "max_level" in given:
        return "the given --max-level stopped the refinement: raise it, or leave it to be chosen"
    if given & {"h0", "order", "method", "refinement", "sample_spacing_deg"}:
        return "with the given options: leave them to be chosen"
    return "the refinement stopped"


if __name__ == "__main__":  # pragma: no cover
    main()
