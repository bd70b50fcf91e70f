"""geoid-info: what a tile store holds and how accurate it is."""

from __future__ import annotations

import json

import click

from geoidspline.api import PRESETS

from ._common import Number, command, echo, store_options, user_errors, verbosity_options


@command("info")
@store_options("Tile store directory (may also be given as the argument STORE).", positional=True)
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.option("--check-against", "model_path", type=click.Path(), default=None, metavar="MODEL",
              help="Also compare the store with the exact synthesis of this spherical-harmonic model "
                   "(ICGEM .gfc or NGA ASCII) at random points (JSON key check_against).")
@click.option("--correction", "correction_path", type=click.Path(), default=None,
              help="With --check-against: zeta-to-N correction coefficients (NGA CORRCOEF).")
@click.option("--preset", type=click.Choice(PRESETS), default=None,
              help="With --check-against: synthesis conventions [default: the store's, when it was fitted from "
                   "MODEL; else nga-f477, nga-hsynth for EGM2008].")
@click.option("--points", type=Number("points"), default=20_000, show_default=True,
              help="With --check-against: random points, uniform in area over the store's region (fixed seed).")
@click.option("--verify", is_flag=True,
              help="Check every tile's size and sha256 against the manifest; name each missing, truncated or "
                   "altered tile and exit 1 if there is any.")
@click.option("--upgrade", is_flag=True,
              help="Rewrite a format-1 store in format 2 (compact tiles), atomically, then describe it "
                   "(with --verify: upgrade first, then verify the upgraded store).")
@click.option("--key", "key", type=click.Path(dir_okay=False), default=None, metavar="PUBKEY",
              help="Refuse the store unless this Ed25519 public key (PEM) signed it; with --verify, a missing or "
                   "wrong signature is a problem like an altered tile.")
@click.option("--generate-key", "generate_key", type=click.Path(dir_okay=False), default=None, metavar="KEYFILE",
              help="Write a new Ed25519 key pair for --sign: KEYFILE (private, mode 0600) and KEYFILE's .pub.pem "
                   "(public); no store is read.")
@verbosity_options
@user_errors
@click.pass_context
def main(ctx, store_path, as_json, model_path, correction_path, preset, points, verify, quiet, verbose, upgrade, key,
         generate_key):
    """Summary of the tile store at --store (a directory written by geoid-fit).

    With --check-against MODEL: max, RMS and 99th percentile of |store - model| at
    --points random points uniform in area over the store's region (seed fixed, so
    repeatable; random points are not the fit's lattice nodes).

    Several actions run in this order: --upgrade, then --verify (of the store as it now
    is; problems end the command, exit 1), then the summary (with --check-against). With
    --verify alone only the verification is printed.
    """
    import sys

    from click.core import ParameterSource

    import geoidspline

    if generate_key is not None:
        if store_path is not None or verify or upgrade or model_path is not None or key is not None:
            raise click.UsageError("--generate-key writes a key pair and reads no store: give it alone")
        from geoidspline.api import generate_key as make_key
        from geoidspline.api import key_fingerprint

        private, public = make_key(generate_key)
        echo(f"wrote {private} (private: keep it secret) and {public} (public: give it to users), "
             f"key {key_fingerprint(private)}")
        return
    if store_path is None:
        raise click.UsageError("give --store DIR, the store to describe")
    if model_path is None and (correction_path is not None or preset is not None):
        raise click.UsageError("--correction and --preset go with --check-against")
    if model_path is None and ctx.get_parameter_source("points") is not ParameterSource.DEFAULT:
        raise click.UsageError("--points goes with --check-against")
    upgraded = None
    if upgrade:
        from geoidspline.api import upgrade_store

        upgraded = upgrade_store(store_path)
        if not as_json:
            click.echo(f"{store_path}: format {upgraded['from_format']} -> {upgraded['to_format']}, tiles "
                       f"{upgraded['tile_bytes_before']:,} -> {upgraded['tile_bytes_after']:,} bytes, value step "
                       f"{upgraded['value_step_m']:g} m (bound {upgraded['value_error_bound_m']:g} m)")
    if verify:
        from geoidspline.api import verify_store

        problems = verify_store(store_path, key=key)
        summary_too = model_path is not None
        if as_json and (problems or not summary_too):
            echo(json.dumps({"store": str(store_path), "ok": not problems, "problems": problems,
                             **({"upgrade": upgraded} if upgraded else {})}, indent=1))
        elif not as_json:
            for problem in problems:
                echo(f"ERROR: {problem}")
            if not problems:
                signed = " and is signed by that key" if key is not None else ""
                echo(f"{store_path}: every tile matches the manifest{signed}")
        if problems or not summary_too:
            sys.exit(1 if problems else 0)
    store = geoidspline.open_store(store_path, key=key)
    info = store.info()
    if model_path is not None:
        from geoidspline.api import check_against, load_synthesis

        synthesis = load_synthesis(model_path, correction_path, preset, like_store=store)
        info["check_against"] = check_against(store, synthesis, points)
    if upgraded and as_json:
        info["upgrade"] = upgraded
    if verify and as_json:
        info["verify"] = {"ok": True, "problems": []}
    if as_json:
        echo(json.dumps(info, indent=1))
        return
    prov = info["provenance"]
    echo(f"store        {info['store']} (format {info['format_version']}, version {info['store_version']})")
    if info["signature"]:
        checked = "checked with the key given" if key is not None else "not checked: give --key PUBKEY"
        echo(f"signature    {info['signature']} ({checked})")
    echo(f"source       {_file_name(prov.get('source'))}" + (f" ({prov['source']})" if _file_name(prov.get('source'))
                                                              != prov.get('source') else ""))
    echo(f"  sha256     {prov.get('sha256') or 'not recorded'}")
    echo(f"model        {prov['model']}, ellipsoid {prov['ellipsoid']}, tide system {prov['tide_system']}, "
               f"zero-degree term {prov['zero_degree_term_m']} m")
    s, w, n, e = info["region"]
    echo(f"region       S {s:g}  W {w:g}  N {n:g}  E {e:g} (degrees)")
    echo(f"spline       order {info['order']}, h0 {info['h0']:g}, tolerance {info['tolerance_m']:g} m, "
               f"{'converged' if info['converged'] else 'tolerance NOT reached'}")
    echo(f"method       {info['fit_method']}")
    rows = level_rows(info)
    max_level = info["levels_chosen"] - 1
    with_coefficients = [lv["level"] for lv in rows if lv["coefficients"]]
    echo(f"levels       {info['levels_used']} of {info['levels_chosen']} chosen levels used (levels 0-{max_level} "
         f"allowed; coefficients in {_numbers(with_coefficients)})")
    for lv in rows:
        note = "" if lv["level"] <= max_level else "  (added by an update)"
        echo(f"  level {lv['level']:<3d} h {lv['h']:<10.6g} {lv['coefficients']:>10,d} coefficients{note}")
    echo(f"coefficients {info['coefficients']:,} in {info['tiles']} tiles, {info['bytes']:,} bytes")
    echo(f"data nodes   {info['nodes']:,}: max |error| {info['node_max_error_m']:.4f} m, "
               f"RMS {info['node_rms_error_m']:.4f} m")
    if info["check_points"]:
        echo(f"check points {info['check_points']:,}: max {info['max_error_m']:.4f} m, "
                   f"RMS {info['rms_error_m']:.4f} m, 99% {info['p99_error_m']:.4f} m")
        echo(f"             truth: {info['check_truth']}")
    if info.get("cell_centre_max_m") is not None:
        echo(f"cell centres at most {info['cell_centre_max_m']:.4f} m outside the interval of the grid's bilinear "
             "and bicubic interpolants")
    check = info.get("check_against")
    if check is not None:
        corr = f" + {check['correction']}" if check["correction"] else ""
        echo(f"check against {check['model']}{corr} ({check['model_name']}, degree {check['max_degree']}, "
                   f"preset {check['preset']})")
        echo(f"             {check['points']:,} random points uniform in area (seed {check['seed']}): "
                   f"max {check['max_error_m']:.4f} m, RMS {check['rms_error_m']:.4f} m, "
                   f"99% {check['p99_error_m']:.4f} m, mean {check['mean_error_m']:+.4f} m")
        if not check["same_source"]:
            echo("             note: the store was not fitted from this model file (sha256 differs): "
                       "the figures include its source's own difference from the model")
    history = info.get("history") or []
    echo(f"history      {len(history)} record{'s' if len(history) != 1 else ''}")
    for record in history:
        echo("  " + history_line(record))


def _file_name(source) -> str:
    text = str(source) if source is not None else "(not recorded)"
    return text.replace("\\", "/").rsplit("/", 1)[-1]


def _numbers(levels) -> str:
    """0, 1, 2, 5 -> "levels 0-2, 5"."""
    if not levels:
        return "no level"
    runs, start = [], levels[0]
    for previous, current in zip(levels, levels[1:] + [None]):
        if current != previous + 1:
            runs.append(f"{start}" if start == previous else f"{start}-{previous}")
            start = current
    return ("level " if len(levels) == 1 else "levels ") + ", ".join(runs)


def level_rows(info) -> list[dict]:
    """Every level from 0 to the finest the fit allowed (or an update added), with its
    coefficients: 0 where a level has none."""
    stored = {int(lv["level"]): lv for lv in info["levels"]}
    last = max(info["levels_chosen"] - 1, max(stored, default=0))
    return [stored.get(level, {"level": level, "h": info["h0"] / 2.0 ** level, "coefficients": 0})
            for level in range(last + 1)]


def history_line(record) -> str:
    """One line of the manifest's history: when, what, version, source file and sha256,
    region; for an update its blend, tiles rewritten, coefficients added and error."""
    s, w, n, e = record.get("region") or (float("nan"),) * 4
    sha = record.get("sha256")
    text = (f"{record.get('time', '?')}  {record.get('action', '?'):<7s} v{record.get('store_version', '?')}  "
            f"{_file_name(record.get('source'))} sha256 {sha[:12] + '...' if sha else 'not recorded'}  "
            f"region S {s:g} W {w:g} N {n:g} E {e:g}")
    if record.get("action") == "update":
        text += (f", blend {record.get('blend_width_km', 0):g} km, {record.get('tiles_rewritten', 0)} tiles rewritten, "
                 f"{record.get('coefficients_added', 0):+,d} coefficients")
        if record.get("max_error_m") is not None:
            text += (f", max |error| inside {record['max_error_m']:.4f} m of {record.get('tolerance_m', 0):g} m"
                     f"{'' if record.get('converged', True) else ' (NOT reached)'}")
    elif record.get("action") == "upgrade":
        text += f", format {record.get('from_format', '?')} -> {record.get('to_format', '?')}"
    return text


if __name__ == "__main__":  # pragma: no cover
    main()
