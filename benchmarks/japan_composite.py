"""Japan's national geoid inside, EGM96 outside: a regional update of a global store, measured.

    pip install '.[bench,plot]'
    python benchmarks/japan_composite.py                      # GSIGEO2011 and JPGEO2024
    python benchmarks/japan_composite.py --model gsigeo2011 --base /tmp/egm96-0.1 --workers 2

Steps (every store and file goes to --out-dir, default benchmarks/out/japan/):

1. GSI's GSIGEO2011 (ver2.2, land only: NaN over the sea) and JPGEO2024 (the whole
   15-50°N, 120-160°E window), embedded in the MIT-licensed ``japan-geoid`` package, are
   decoded node for node (its binary format, checked against the package's own
   ``get_heights`` at random nodes and cell interiors) and written as CF netCDF with
   geoidspline's own writer (:func:`geoidspline.sources.netcdf.write_netcdf`);
2. a global EGM96 store: ``geoid-fit egm96-15 --tolerance 0.1 --store BASE`` (reused when
   --base names an existing one);
3. per national model, a copy of BASE updated with
   ``geoid-update NATIONAL.nc --store COPY --region S W N E --blend-width 100``;
4. measured with the library, against the national grid and the untouched BASE:
   agreement at the national model's own nodes inside the region, and at the centres of
   its cells (against the mean of the four corners: bilinear, as GSI interpolates); profiles crossing the
   region's edge every 100 m (steps, second differences, deflections of the vertical);
   for GSIGEO2011 its sea holes (never NaN; after - before by distance from the coast;
   profiles across the coast); after - before outside the blend zone; tiles rewritten
   vs untouched;
5. ``geoid-plot COPY --minus BASE --region ...`` draws the difference the update made.

Each model appends one JSON row to benchmarks/results/japan.jsonl and prints a summary.
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import math
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import git_commit, machine_info  # noqa: E402

import geoidspline  # noqa: E402
from geoidspline.sources.grid import GeoidGrid
from geoidspline.query.derived import deflection
from geoidspline.sources.formats import read_grid, write_netcdf
from geoidspline.sphere.region import Region
from geoidspline.sources.base import Provenance
from geoidspline.geodesy.ellipsoids import KM_PER_DEGREE

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results" / "japan.jsonl"
#: The Japan window: every GSIGEO2011 node with data (24.0-45.7°N, 122.9-145.8°E) is inside.
JAPAN = (24.0, 122.0, 46.0, 146.0)
MODELS = ("gsigeo2011", "jpgeo2024")
#: Profile sampling: 100 m of arc, as the issue asks ("steps per 100 m").
STEP_M = 100.0
EARTH_RADIUS_M = 6_371_000.0


# ------------------------------------------------------------------------ national grids


def decode_gsi_binary(raw: bytes):
    """Latitudes, longitudes (degrees) and N (metres, NaN = no data) of japan-geoid's
    binary grid format (``GsiGeoid.to_binary()``; src/gsi.rs of github.com/ciscorn/japan-geoid):

    a 28-byte little-endian header (x_num u16, y_num u16, x_denom u16, y_denom u16,
    x_min f32, y_min f32, ikind u16, version 10 bytes), then one i32 per node, rows of
    constant latitude from the south, each the difference from the linear prediction
    left + below − below-left (9990000 standing for the missing neighbours of the first
    row and column); values are 1e-4 m, 9990000 is no data. The prediction residual
    R = P[k] − P[k − x_num] is the running sum of the stored differences, so
    P = 9990000 + Σ_rows R exactly (integers).
    """
    nx, ny, x_denom, y_denom = (int(v) for v in np.frombuffer(raw[:8], "<u2"))
    x_min, y_min = (float(v) for v in np.frombuffer(raw[8:16], "<f4"))
    version = raw[18:28].rstrip(b"\0").decode("ascii", "replace")
    diffs = np.frombuffer(raw[28:], "<i4").astype(np.int64)
    if diffs.size != nx * ny:
        raise ValueError(f"japan-geoid grid: {diffs.size} values, the header says {ny} x {nx}")
    points = 9_990_000 + np.cumsum(np.cumsum(diffs).reshape(ny, nx), axis=0)
    values = np.where(points == 9_990_000, np.nan, points / 10_000.0)
    latitude = y_min + np.arange(ny) / y_denom
    longitude = x_min + np.arange(nx) / x_denom
    return latitude, longitude, values, version


def national_grid(name: str) -> GeoidGrid:
    """GSIGEO2011 or JPGEO2024 from the japan-geoid package, checked against its own
    interpolation at 2,000 random nodes and 2,000 cell interiors (bilinear)."""
    import importlib.metadata

    import japan_geoid

    model = {"gsigeo2011": japan_geoid.load_embedded_gsigeo2011,
             "jpgeo2024": japan_geoid.load_embedded_jpgeo2024}[name]()
    lat, lon, values, version = decode_gsi_binary(model.to_binary())
    rng = np.random.default_rng(0)
    i, j = rng.integers(0, lat.size - 1, 2000), rng.integers(0, lon.size - 1, 2000)
    heights = model.get_heights(lon[j], lat[i])
    if not np.allclose(heights, values[i, j], rtol=0, atol=1e-9, equal_nan=True):
        raise AssertionError(f"{name}: decoded nodes differ from japan_geoid.get_heights")
    fy, fx = 0.3, 0.6
    bilinear = ((1 - fy) * (1 - fx) * values[i, j] + fy * (1 - fx) * values[i + 1, j]
                + (1 - fy) * fx * values[i, j + 1] + fy * fx * values[i + 1, j + 1])
    heights = model.get_heights(lon[j] + fx * (lon[1] - lon[0]), lat[i] + fy * (lat[1] - lat[0]))
    if not np.allclose(heights, bilinear, rtol=0, atol=1e-9, equal_nan=True):
        raise AssertionError(f"{name}: decoded cells differ from japan_geoid.get_heights")
    package = importlib.metadata.version("japan-geoid")
    label = {"gsigeo2011": "GSIGEO2011", "jpgeo2024": "JPGEO2024"}[name]
    provenance = Provenance(
        source=f"{label} {version} (japan-geoid {package})", model=label, kind="grid",
        # JGD2011 heights above GRS80; GRS80 and WGS84 share a and differ by 0.1 mm in b,
        # so the undulations are the same to 0.1 mm (the store is on WGS84).
        ellipsoid="WGS84", tide_system=None,
        notes=(f"GSI {label} {version}, decoded from the japan-geoid {package} package (MIT); "
               "heights above the GRS80 ellipsoid (JGD2011), written as WGS84 (0.1 mm apart)",),
    )
    return GeoidGrid(lat, lon, values, provenance)


# ------------------------------------------------------------------------ running commands


def run(cmd, expect=(0,)):
    started = time.perf_counter()
    proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if proc.returncode not in expect:
        raise SystemExit(f"{' '.join(map(str, cmd))} exited {proc.returncode}:\n{proc.stderr[-3000:]}")
    return proc, seconds


def bin_path(name):
    return Path(sys.executable).with_name(name)


def ensure_base(path: Path, tolerance: float, workers: int) -> dict:
    if (path / "manifest.json").exists():
        return {"reused": True, "command": None, "seconds": None}
    cmd = [bin_path("geoid-fit"), "egm96-15", "--tolerance", tolerance, "--workers", workers,
           "--store", path, "--json", "-q"]
    proc, seconds = run(cmd, expect=(0, 3))
    return {"reused": False, "command": " ".join(map(str, cmd)), "seconds": round(seconds, 1),
            "exit_status": proc.returncode}


def tile_files(path: Path) -> dict:
    manifest = json.loads((path / "manifest.json").read_text())
    return {tuple(e["tile"]): (e["file"], e["sha256"]) for e in manifest["tiles"]}


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ------------------------------------------------------------------------ measurements


def _lattice_nodes(grid: GeoidGrid, region: Region):
    sample = grid.nodes(region)
    lat2, lon2 = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")
    return lat2, lon2, sample.undulation


def agreement(after, grid: GeoidGrid, region: Region) -> dict:
    """|after − national| at every national node with data inside the region."""
    lat2, lon2, truth = _lattice_nodes(grid, region)
    have = np.isfinite(truth)
    diff = after.undulation(lat2[have], lon2[have]) - truth[have]
    worst = int(np.argmax(np.abs(diff)))
    return {"nodes": int(have.sum()), "max_abs_m": float(np.abs(diff).max()),
            "rms_m": float(np.sqrt(np.mean(diff**2))), "p99_abs_m": float(np.percentile(np.abs(diff), 99)),
            "mean_m": float(diff.mean()),
            "worst_point": [float(lat2[have][worst]), float(lon2[have][worst])]}


def between_nodes(after, grid: GeoidGrid, region: Region) -> dict:
    """|after − national| at the centre of every cell of the national grid inside the
    region whose four corners have data, the national value there being the mean of the
    four (its bilinear interpolation, as GSI and japan-geoid interpolate): what a fit
    does between the nodes, where a level finer than the data would be free."""
    lat2, lon2, truth = _lattice_nodes(grid, region)
    centre = 0.25 * (truth[:-1, :-1] + truth[1:, :-1] + truth[:-1, 1:] + truth[1:, 1:])
    have = np.isfinite(centre)
    lat_c = 0.5 * (lat2[:-1, :-1] + lat2[1:, 1:])
    lon_c = 0.5 * (lon2[:-1, :-1] + lon2[1:, 1:])
    diff = after.undulation(lat_c[have], lon_c[have]) - centre[have]
    worst = int(np.argmax(np.abs(diff)))
    return {"cells": int(have.sum()), "max_abs_m": float(np.abs(diff).max()),
            "rms_m": float(np.sqrt(np.mean(diff**2))), "p99_abs_m": float(np.percentile(np.abs(diff), 99)),
            "above_1cm": int((np.abs(diff) > 0.01).sum()),
            "worst_point": [float(lat_c[have][worst]), float(lon_c[have][worst])]}


def _profile(lat0, lon0, bearing_deg, start_m, stop_m):
    """Points every STEP_M metres of arc along a great circle from (lat0, lon0)."""
    distance = np.arange(start_m, stop_m + STEP_M / 2, STEP_M)
    delta = distance / EARTH_RADIUS_M
    phi1, lam1, theta = math.radians(lat0), math.radians(lon0), math.radians(bearing_deg)
    phi2 = np.arcsin(math.sin(phi1) * np.cos(delta) + math.cos(phi1) * np.sin(delta) * math.cos(theta))
    lam2 = lam1 + np.arctan2(math.sin(theta) * np.sin(delta) * math.cos(phi1),
                             np.cos(delta) - math.sin(phi1) * np.sin(phi2))
    return distance, np.degrees(phi2), np.degrees(lam2)


def edge_profiles(region: Region, blend_km: float, count_per_edge=6):
    """Profiles crossing each edge of the region outward, from 30 km inside to 30 km
    beyond the blend zone, at ``count_per_edge`` evenly spaced positions per edge.
    Yields (edge, distance from the edge in m (positive outside), lat, lon)."""
    s, w, n, e = region.as_tuple()
    inside, outside = 30_000.0, blend_km * 1000.0 + 30_000.0
    fractions = (np.arange(count_per_edge) + 0.5) / count_per_edge
    for f in fractions:
        lon = w + f * (e - w)
        yield ("south", *_profile(s, lon, 180.0, -inside, outside))
        yield ("north", *_profile(n, lon, 0.0, -inside, outside))
        lat = s + f * (n - s)
        yield ("west", *_profile(lat, w, 270.0, -inside, outside))
        yield ("east", *_profile(lat, e, 90.0, -inside, outside))


def profile_figures(after, before, grid, region: Region, blend_km: float) -> dict:
    """Along profiles crossing the region's edge every 100 m: the largest step
    |N(x + 100 m) − N(x)| and second difference |N(x+1) − 2N(x) + N(x−1)| (metres), in
    the blend zone and on either side; deflections (ξ, η, arcseconds) after vs before;
    and what a hard switch at the edge would have given (|national − store| there)."""
    rows = []
    for edge, distance, lat, lon in edge_profiles(region, blend_km):
        n_after = after.undulation(lat, lon)
        n_before = before.undulation(lat, lon)
        d1, d2 = np.abs(np.diff(n_after)), np.abs(np.diff(n_after, 2))
        mid1 = 0.5 * (distance[1:] + distance[:-1])
        zone = (distance[1:-1] >= 0) & (distance[1:-1] <= blend_km * 1000.0)
        zone1 = (mid1 >= 0) & (mid1 <= blend_km * 1000.0)
        xi_a, eta_a = deflection(after, lat, lon)[:2]
        xi_b, eta_b = deflection(before, lat, lon)[:2]
        change = np.maximum(np.abs(xi_a - xi_b), np.abs(eta_a - eta_b))
        in_blend = (distance >= 0) & (distance <= blend_km * 1000.0)
        national_edge = float(grid.undulation(lat[distance == 0], lon[distance == 0], method="bilinear")[0]) \
            if np.any(distance == 0) else float("nan")
        rows.append({
            "edge": edge, "start": [float(lat[0]), float(lon[0])],
            "max_step_blend_m": float(d1[zone1].max()), "max_step_outside_blend_m": float(d1[~zone1].max()),
            "max_second_diff_blend_m": float(d2[zone].max()),
            "max_second_diff_outside_blend_m": float(d2[~zone].max()),
            "max_second_diff_before_m": float(np.abs(np.diff(n_before, 2)).max()),
            "max_deflection_jump_arcsec": float(max(np.abs(np.diff(xi_a)).max(), np.abs(np.diff(eta_a)).max())),
            "max_deflection_change_inside_arcsec": float(change[distance < 0].max()),
            "max_deflection_change_blend_arcsec": float(change[in_blend].max()),
            "max_deflection_change_beyond_arcsec": float(change[distance > blend_km * 1000.0].max()),
            "hard_switch_step_m": abs(national_edge - float(n_before[distance == 0][0]))
            if np.isfinite(national_edge) else None,
            "after_minus_before_at_blend_end_m": float(abs(n_after[-1] - n_before[-1])),
        })
    keys = [k for k in rows[0] if k.startswith(("max_", "after_"))]
    summary = {k: max(r[k] for r in rows) for k in keys}
    switches = [r["hard_switch_step_m"] for r in rows if r["hard_switch_step_m"] is not None]
    summary["hard_switch_step_max_m"] = max(switches) if switches else None
    summary["profiles"] = len(rows)
    summary["profile_km"] = [-30.0, blend_km + 30.0]
    return {"summary": summary, "profiles": rows}


def outside_blend(after, before, region: Region, blend_km: float) -> dict:
    """|after − before| on a 0.1° lattice 15° around the blend zone, outside it, by
    distance beyond the zone (the update must not change the store there)."""
    zone = region.expanded(blend_km / KM_PER_DEGREE)
    window = zone.expanded(15.0)
    lat = np.arange(window.south, window.north + 1e-9, 0.1)
    lon = np.arange(window.west, window.east + 1e-9, 0.1)
    lat2, lon2 = np.meshgrid(lat, lon, indexing="ij")
    outside = ~zone.contains(lat2, lon2)
    diff = np.abs(after.undulation(lat2, lon2) - before.undulation(lat2, lon2))
    # distance beyond the zone's box in degrees of arc (approximate, for binning)
    dlat = np.maximum.reduce([zone.south - lat2, lat2 - zone.north, np.zeros_like(lat2)])
    dlon = np.maximum.reduce([zone.west - lon2, lon2 - zone.east, np.zeros_like(lon2)]) * np.cos(np.radians(lat2))
    beyond_km = np.hypot(dlat, dlon) * KM_PER_DEGREE
    bands = {}
    for lo, hi in ((0, 100), (100, 500), (500, 1000), (1000, 1e9)):
        sel = outside & (beyond_km > lo) & (beyond_km <= hi)
        if sel.any():
            bands[f"{lo}-{hi if hi < 1e9 else 'inf'} km"] = float(diff[sel].max())
    worst = np.unravel_index(int(np.argmax(np.where(outside, diff, -1))), diff.shape)
    return {"lattice_points": int(outside.sum()), "max_abs_m": float(diff[outside].max()),
            "worst_point": [float(lat2[worst]), float(lon2[worst])], "max_abs_by_distance_m": bands}


def sea_holes(after, before, grid: GeoidGrid, region: Region) -> dict:
    """GSIGEO2011's no-data nodes inside the region: NaN count of the composite there,
    after − before by distance from the nearest node with data, and profiles across the
    coast (along grid rows, every 100 m for 10 km either side of the last land node)."""
    from scipy.ndimage import distance_transform_edt

    lat2, lon2, truth = _lattice_nodes(grid, region)
    sea = ~np.isfinite(truth)
    n_after = after.undulation(lat2, lon2)
    n_before = before.undulation(lat2, lon2)
    mid_lat = math.radians(0.5 * (region.south + region.north))
    sampling = (grid.latitude_spacing * 111_195.0, grid.longitude_spacing * 111_195.0 * math.cos(mid_lat))
    coast_km = distance_transform_edt(sea, sampling=sampling) / 1000.0
    change = np.abs(n_after - n_before)
    bands = {}
    for lo, hi in ((0, 5), (5, 20), (20, 50), (50, 100), (100, 1e9)):
        sel = sea & (coast_km > lo) & (coast_km <= hi)
        if sel.any():
            bands[f"{lo}-{hi if hi < 1e9 else 'inf'} km"] = {
                "nodes": int(sel.sum()), "max_abs_change_m": float(change[sel].max()),
                "median_abs_change_m": float(np.median(change[sel]))}
    # what a hard switch national -> global at the coast would give: the step there
    coastal = ~sea & (np.pad(sea, 1, constant_values=False)[:-2, 1:-1] | np.pad(sea, 1, constant_values=False)[2:, 1:-1]
                      | np.pad(sea, 1, constant_values=False)[1:-1, :-2] | np.pad(sea, 1, constant_values=False)[1:-1, 2:])
    switch = np.abs(truth[coastal] - n_before[coastal])
    # coast crossings along rows: land node followed by a sea node (east-going coasts)
    crossings = np.argwhere(~sea[:, :-1] & sea[:, 1:])
    rng = np.random.default_rng(0)
    picks = crossings[rng.choice(len(crossings), size=min(300, len(crossings)), replace=False)]
    coast = _row_profiles(after, lat2, lon2, picks)
    # the same profiles on land at least 20 km from the sea: what the national model's
    # own detail gives, for comparison
    inland_km = distance_transform_edt(~sea, sampling=sampling) / 1000.0
    inland_nodes = np.argwhere(~sea & (inland_km >= 20.0))
    inland = _row_profiles(after, lat2, lon2,
                           inland_nodes[rng.choice(len(inland_nodes), size=min(300, len(inland_nodes)), replace=False)])
    return {
        "sea_nodes_in_region": int(sea.sum()),
        "nan_in_composite": int(np.count_nonzero(~np.isfinite(n_after[sea]))),
        "change_by_distance_from_coast": bands,
        "coastal_nodes": int(coastal.sum()),
        "coast_hard_switch_step_m": {"median": float(np.median(switch)), "p99": float(np.percentile(switch, 99)),
                                     "max": float(switch.max())},
        "coast_profiles": coast, "inland_profiles": inland,
    }


def _row_profiles(after, lat2, lon2, picks) -> dict:
    """Profiles along the parallel through each picked node, 10 km either side, every
    100 m: the largest step, second difference and deflection change between samples."""
    steps, second, jumps = [], [], []
    for i, j in picks:
        _, plat, plon = _profile(lat2[i, j], lon2[i, j], 90.0, -10_000.0, 10_000.0)
        values = after.undulation(plat, plon)
        steps.append(np.abs(np.diff(values)).max())
        second.append(np.abs(np.diff(values, 2)).max())
        xi, eta = deflection(after, plat, plon)[:2]
        jumps.append(max(np.abs(np.diff(xi)).max(), np.abs(np.diff(eta)).max()))
    return {"profiles": len(picks), "max_step_m": float(max(steps)), "median_max_step_m": float(np.median(steps)),
            "max_second_diff_m": float(max(second)), "median_max_second_diff_m": float(np.median(second)),
            "max_deflection_jump_arcsec": float(max(jumps)),
            "median_max_deflection_jump_arcsec": float(np.median(jumps))}


def tiles(before_path: Path, after_path: Path, record: dict) -> dict:
    old, new = tile_files(before_path), tile_files(after_path)
    same = [t for t in new if t in old and old[t][1] == new[t][1]]
    identical = all(sha256(after_path / new[t][0]) == old[t][1] for t in same)
    return {"tiles_before": len(old), "tiles_after": len(new), "untouched": len(same),
            "rewritten": len(new) - len(same), "untouched_files_identical": identical,
            "record_tiles_rewritten": record.get("tiles_rewritten"),
            "coefficients_added": record.get("coefficients_added")}


# ------------------------------------------------------------------------ main


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", choices=MODELS + ("both",), default="both")
    parser.add_argument("--out-dir", type=Path, default=REPO / "benchmarks" / "out" / "japan")
    parser.add_argument("--base", type=Path, default=None,
                        help="global EGM96 store to update copies of (fitted when absent) [OUT_DIR/egm96-TOL]")
    parser.add_argument("--base-tolerance", type=float, default=0.1)
    parser.add_argument("--tolerance", type=float, default=None,
                        help="tolerance of the update in metres [default: the store's]")
    parser.add_argument("--region", nargs=4, type=float, default=JAPAN, metavar=("S", "W", "N", "E"))
    parser.add_argument("--blend-width", type=float, default=100.0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--no-plot", action="store_true")
    parser.add_argument("--measure-only", action="store_true",
                        help="measure an existing OUT_DIR/egm96+MODEL (its last update) instead of updating anew")
    parser.add_argument("--json", type=Path, default=RESULTS, help="append the rows here")
    args = parser.parse_args(argv)

    out = args.out_dir
    out.mkdir(parents=True, exist_ok=True)
    base = args.base or out / f"egm96-{args.base_tolerance:g}"
    base_run = ensure_base(base, args.base_tolerance, args.workers)
    before = geoidspline.open_store(base)
    region = Region.from_bounds(*args.region)
    models = MODELS if args.model == "both" else (args.model,)
    for name in models:
        started = time.perf_counter()
        grid = national_grid(name)
        nc = write_netcdf(out / f"{name}.nc", grid)
        export_seconds = time.perf_counter() - started
        national = read_grid(nc)  # what geoid-fit reads: the file, with its sha256
        composite = out / f"egm96+{name}"
        cmd = [bin_path("geoid-update"), nc, "--store", composite, "--region", *args.region,
               "--blend-width", args.blend_width, "--workers", args.workers, "--json", "-q"]
        if args.tolerance is not None:
            cmd += ["--tolerance", args.tolerance]
        if args.measure_only:
            record = json.loads((composite / "manifest.json").read_text())["history"][-1]
            if record.get("sha256") != national.provenance.sha256:
                raise SystemExit(f"{composite}: its last update is not from {nc} (sha256 differs)")
            exit_status, update_seconds = None, record.get("wall_seconds")
        else:
            if composite.exists():
                shutil.rmtree(composite)
            shutil.copytree(base, composite)
            proc, update_seconds = run(cmd, expect=(0, 3))
            record = json.loads(proc.stdout)
            exit_status = proc.returncode
        after = geoidspline.open_store(composite)
        row = {
            "date": dt.datetime.now(dt.timezone.utc).replace(microsecond=0).isoformat(),
            "git_commit": git_commit(REPO), "machine": machine_info(),
            "model": name, "national_file": str(nc), "national_sha256": national.provenance.sha256,
            "national_nodes": int(np.isfinite(national.values).sum()),
            "national_no_data_nodes": int((~np.isfinite(national.values)).sum()),
            "export_seconds": round(export_seconds, 1),
            "base": str(base), "base_run": base_run, "base_tolerance_m": before.manifest["fit"]["tolerance_m"],
            "region": list(region.as_tuple()), "blend_width_km": args.blend_width,
            "update_command": " ".join(map(str, cmd)), "update_exit_status": exit_status,
            "update_wall_seconds": None if update_seconds is None else round(update_seconds, 1),
            "measured_only": bool(args.measure_only),
            "update_record": {k: record.get(k) for k in ("tiles_rewritten", "coefficients_added", "nodes_in_region",
                                                         "max_error_m", "rms_error_m", "tolerance_m", "converged")},
            "agreement": agreement(after, national, region),
            "between_nodes": between_nodes(after, national, region),
            "edge": profile_figures(after, before, national, region, args.blend_width),
            "outside_blend": outside_blend(after, before, region, args.blend_width),
            "tiles": tiles(base, composite, record),
        }
        if np.isnan(national.values).any():
            row["sea_holes"] = sea_holes(after, before, national, region)
        if not args.no_plot:
            figure = out / f"japan_{name}_difference.png"
            s, w, n, e = region.expanded(args.blend_width / KM_PER_DEGREE).expanded(2.0).as_tuple()
            plot_cmd = [bin_path("geoid-plot"), composite, "--minus", base, "--region",
                        *(round(v * 2.0) / 2.0 for v in (s, w, n, e)), "--dpi", 100, "--out", figure, "--json", "-q"]
            plot_proc, _ = run(plot_cmd)
            row["plot_command"] = " ".join(map(str, plot_cmd))
            row["plot"] = {k: json.loads(plot_proc.stdout)[k] for k in ("file", "stats")}
        with open(args.json, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(row) + "\n")
        print(json.dumps({k: row[k] for k in ("model", "update_wall_seconds", "update_record", "agreement",
                                               "between_nodes", "tiles")}, indent=1))
        print(json.dumps(row["edge"]["summary"], indent=1))
        print(json.dumps(row["outside_blend"], indent=1))
        if "sea_holes" in row:
            print(json.dumps(row["sea_holes"], indent=1))


if __name__ == "__main__":
    main()
