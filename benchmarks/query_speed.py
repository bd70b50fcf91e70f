#!/usr/bin/env python3
"""Query throughput of a geoidspline store versus PROJ's vgridshift on egm96_15.gtx.

    python benchmarks/query_speed.py --store STORE [--points N] [--repeat R] [--json OUT]

What it measures, all in one process and on the same points:

* ``ours-1``: ``geoidspline.open_store(STORE).undulation(lat, lon)`` on one thread
  (``geoidspline._kernels._clib.set_threads(1)``);
* ``ours-all``: the same call on all threads (``_clib.threads()`` at start: all cores);
* ``pyproj``: ``Transformer.from_pipeline('+proj=vgridshift +grids=egm96_15.gtx
  +multiplier=1').transform(lon, lat, zeros)`` (bilinear interpolation of PROJ's 15'
  EGM96 grid; PROJ evaluates it in one thread).

The points are N random points uniform on the sphere (fixed seed 20130101): latitude
asin(U(-1, 1)), longitude U(-180, 180). Each variant is called once untimed first (kernel
library load, PROJ grid opening), then the three variants are timed in turn R times
(interleaved, so a burst of load from other processes hits all of them alike). The
figure reported is the median over the R runs of (wall time / N), in ns per point; the
ratio is pyproj / ours (> 1: ours is faster).

Before the warm-up it times opening the store (the manifest only), reading every tile
(with sha256 checks) and building the folded query index, separately.

It also measures the first-query latency of a cold process: the wall time of
``geoid-query --store STORE LAT LON`` as a subprocess (interpreter start, imports,
opening the manifest, reading and checking the few tiles around the point, one numpy
evaluation: the compiled kernels are not loaded), median of 5 runs after one untimed priming run
(reported separately). LAT LON is the centre of the store's region. ``--cold-only``
measures just that. The load averages before and after are recorded (the machine is
shared).

Before timing, it checks that PROJ's z really is N (at grid nodes it must equal the
GTX values, between nodes their bilinear interpolation) and reports how far our store is
from PROJ's values inside the store's region (not an accuracy figure: PROJ's grid is
itself an interpolation; see METHOD.md section 7).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np
from _common import git_commit, machine_info  # noqa: E402

SEED = 20130101
GTX = "egm96_15.gtx"
PROJ_DIR = "/usr/share/proj"
PIPELINE = f"+proj=vgridshift +grids={GTX} +multiplier=1"
COLD_RUNS = 5


def random_points(n: int, seed: int = SEED):
    """n points uniform on the sphere: (lat, lon) in degrees."""
    rng = np.random.default_rng(seed)
    lat = np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, n)))
    lon = rng.uniform(-180.0, 180.0, n)
    return lat, lon


def proj_transformer():
    import pyproj

    pyproj.datadir.append_data_dir(PROJ_DIR)
    return pyproj.Transformer.from_pipeline(PIPELINE)


def proj_undulation(transformer, lat, lon, zeros):
    return transformer.transform(lon, lat, zeros)[2]


def _gtx_bilinear(grid, lat, lon):
    """Bilinear interpolation of the GTX grid's node values (what vgridshift does)."""
    la0, dla = grid.latitude[0], grid.latitude[1] - grid.latitude[0]
    lo0, dlo = grid.longitude[0], grid.longitude[1] - grid.longitude[0]
    nlon = grid.longitude.size
    y = (lat - la0) / dla
    x = ((lon - lo0) % 360.0) / dlo
    i = np.clip(np.floor(y).astype(int), 0, grid.latitude.size - 2)
    j = np.floor(x).astype(int)
    ty, tx = y - i, x - j
    v = grid.values
    j0, j1 = j % nlon, (j + 1) % nlon
    return ((1 - ty) * ((1 - tx) * v[i, j0] + tx * v[i, j1])
            + ty * ((1 - tx) * v[i + 1, j0] + tx * v[i + 1, j1]))


def verify_proj(transformer) -> dict:
    """PROJ's z must be N: equal to the GTX nodes, bilinear in between."""
    from geoidspline.sources.formats import read_grid

    grid = read_grid(Path(PROJ_DIR) / GTX)
    rng = np.random.default_rng(1)
    ii = rng.integers(1, grid.latitude.size - 1, 8)
    jj = rng.integers(0, grid.longitude.size, 8)
    lat_n, lon_n = grid.latitude[ii], grid.longitude[jj]
    at_nodes = np.abs(proj_undulation(transformer, lat_n, lon_n, np.zeros(8)) - grid.values[ii, jj]).max()
    lat_b = rng.uniform(-80.0, 80.0, 8)
    lon_b = rng.uniform(-180.0, 180.0, 8)
    between = np.abs(proj_undulation(transformer, lat_b, lon_b, np.zeros(8)) - _gtx_bilinear(grid, lat_b, lon_b)).max()
    ok = bool(at_nodes < 1e-4 and between < 1e-4)
    if not ok:
        raise SystemExit(f"pyproj vgridshift does not return N: |z - N| = {at_nodes:.3g} m at nodes, "
                         f"{between:.3g} m between nodes")
    return {"max_diff_at_nodes_m": float(at_nodes), "max_diff_between_nodes_m": float(between), "points": 16}


def timed(func, *args):
    start = time.perf_counter()
    out = func(*args)
    return time.perf_counter() - start, out


def cold_query(store: Path, lat: float, lon: float, runs: int = COLD_RUNS) -> dict:
    exe = Path(sys.executable).parent / "geoid-query"
    cmd = [str(exe) if exe.exists() else (shutil.which("geoid-query") or "geoid-query"),
           "--store", str(store), f"{lat:.6f}", f"{lon:.6f}"]

    def once():
        start = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, stdin=subprocess.DEVNULL)
        elapsed = time.perf_counter() - start
        if proc.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr.strip()}")
        return elapsed, proc.stdout.strip()

    priming, value = once()
    times = [once()[0] for _ in range(runs)]
    return {"command": cmd, "priming_run_s": priming, "runs_s": times, "median_s": statistics.median(times),
            "value_m": float(value)}


def region_centre(manifest: dict):
    s, w, n, e = manifest["region"]
    return 0.5 * (s + n), (w + 0.5 * (e - w) + 180.0) % 360.0 - 180.0  # east = west + span


def run(store: Path, points: int, repeat: int, cold: bool = True, cold_runs: int = COLD_RUNS) -> dict:
    from geoidspline._kernels import _clib

    import geoidspline

    load_before = os.getloadavg()
    all_threads = _clib.threads()
    lat, lon = random_points(points)
    zeros = np.zeros(points)

    t_open, st = timed(geoidspline.open_store, store)
    t_read, _ = timed(lambda: st.spline.full)
    t_index, _ = timed(lambda: st.spline.index)
    transformer = proj_transformer()
    proj_check = verify_proj(transformer)

    def ours():
        return st.undulation(lat, lon)

    def proj():
        return proj_undulation(transformer, lat, lon, zeros)

    variants = {
        "ours-1": (lambda: _clib.set_threads(1), ours),
        "ours-all": (lambda: _clib.set_threads(all_threads), ours),
        "pyproj": (lambda: None, proj),
    }
    # warm-up: first calls (kernel library load, PROJ grid open) untimed
    first = {}
    results = {}
    for name, (setup, func) in variants.items():
        setup()
        first[name], results[name] = timed(func)
    _clib.set_threads(all_threads)
    if not np.array_equal(results["ours-1"], results["ours-all"], equal_nan=True):
        raise SystemExit("ours-1 and ours-all disagree: the threaded kernel is not deterministic")

    samples = {name: [] for name in variants}
    for _ in range(repeat):
        for name, (setup, func) in variants.items():
            setup()
            elapsed, _ = timed(func)
            samples[name].append(elapsed / points * 1e9)
    _clib.set_threads(all_threads)

    medians = {name: statistics.median(v) for name, v in samples.items()}
    region = st.manifest["region"]
    inside = st.covers(lat, lon)
    diff = results["ours-all"][inside] - results["pyproj"][inside]
    centre = region_centre(st.manifest)
    out = {
        "date": dt.datetime.now(dt.timezone.utc).replace(microsecond=0).isoformat(),
        "git_commit": git_commit(Path(__file__).resolve().parent.parent),
        "machine": machine_info(),
        "store": str(store),
        "store_coefficients": st.manifest["spline"]["coefficients"],
        "store_region": region,
        "store_open_s": t_open,
        "store_read_all_tiles_s": t_read,
        "index_build_s": t_index,
        "index_bytes": int(st.spline.index.nbytes),
        "spline_order": st.spline.order,
        "points": points,
        "repeat": repeat,
        "seed": SEED,
        "threads_all": all_threads,
        "pyproj_pipeline": PIPELINE,
        "pyproj_check": proj_check,
        "first_call_s": first,
        "ns_per_point": samples,
        "median_ns_per_point": medians,
        "ratio_pyproj_over_ours_1": medians["pyproj"] / medians["ours-1"],
        "ratio_pyproj_over_ours_all": medians["pyproj"] / medians["ours-all"],
        "ours_minus_pyproj_in_region": {
            "points": int(inside.sum()),
            "max_abs_m": float(np.abs(diff).max()) if diff.size else None,
            "rms_m": float(np.sqrt(np.mean(diff**2))) if diff.size else None,
        },
    }
    if cold:
        out["cold_query"] = cold_query(store, *centre, runs=cold_runs)
    out["load_average_before_after"] = [list(load_before), list(os.getloadavg())]
    return out


def print_table(r: dict) -> None:
    med = r["median_ns_per_point"]
    print(f"{r['points']:,} random points uniform on the sphere, {r['repeat']} repeats, medians "
          f"({r['machine']['nproc']} CPUs: {r['machine']['cpu_model']})")
    print(f"store {r['store']} ({r['store_coefficients']:,} coefficients, order {r['spline_order']}; manifest "
          f"opened in {r['store_open_s']:.3f} s, every tile read in {r['store_read_all_tiles_s']:.2f} s, "
          f"index built in {r['index_build_s']:.2f} s, {r['index_bytes'] / 1e6:.0f} MB)")
    print()
    print("| variant | ns/point (median) | min..max | pyproj / this |")
    print("|---|---:|---:|---:|")
    labels = {"ours-1": "geoidspline, 1 thread", "ours-all": f"geoidspline, {r['threads_all']} threads",
              "pyproj": "pyproj vgridshift egm96_15.gtx"}
    for name in ("ours-1", "ours-all", "pyproj"):
        v = r["ns_per_point"][name]
        print(f"| {labels[name]} | {med[name]:.1f} | {min(v):.1f}..{max(v):.1f} | {med['pyproj'] / med[name]:.2f} |")
    print()
    print("first calls (untimed warm-up), s: " + ", ".join(f"{k} {v:.3f}" for k, v in r["first_call_s"].items()))
    c = r["ours_minus_pyproj_in_region"]
    if c["points"]:
        print(f"ours - pyproj inside the store's region: {c['points']:,} points, max {c['max_abs_m']:.3f} m, "
              f"RMS {c['rms_m']:.3f} m (PROJ is bilinear on 15'; not an accuracy figure)")
    print("load average before / after: " + " / ".join(" ".join(f"{v:.2f}" for v in la)
                                                      for la in r["load_average_before_after"]))
    if "cold_query" in r:
        q = r["cold_query"]
        print(f"cold process `geoid-query --store STORE {q['command'][-2]} {q['command'][-1]}`: median "
              f"{q['median_s'] * 1e3:.0f} ms over {len(q['runs_s'])} runs "
              f"({', '.join(f'{t * 1e3:.0f}' for t in q['runs_s'])}; priming run {q['priming_run_s'] * 1e3:.0f} ms)")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--store", required=True, type=Path, help="tile store directory (made by geoid-fit)")
    parser.add_argument("--points", type=int, default=1_000_000, help="random points per call (default 1,000,000)")
    parser.add_argument("--repeat", type=int, default=5, help="timed repetitions (default 5)")
    parser.add_argument("--json", type=Path, default=None, help="also write the results as JSON to this file")
    parser.add_argument("--no-cold", action="store_true", help="skip the cold-process geoid-query latency")
    parser.add_argument("--cold-only", action="store_true", help="only the cold-process geoid-query latency")
    parser.add_argument("--cold-runs", type=int, default=COLD_RUNS, help=f"timed cold runs (default {COLD_RUNS})")
    args = parser.parse_args(argv)
    if args.points < 1 or args.repeat < 1 or args.cold_runs < 1:
        parser.error("--points, --repeat and --cold-runs must be positive")
    if args.cold_only:
        manifest = json.loads((args.store / "manifest.json").read_text())
        before = os.getloadavg()
        result = {"date": dt.datetime.now(dt.timezone.utc).replace(microsecond=0).isoformat(),
                  "git_commit": git_commit(Path(__file__).resolve().parent.parent), "machine": machine_info(),
                  "store": str(args.store), "store_coefficients": manifest["spline"]["coefficients"],
                  "cold_query": cold_query(args.store, *region_centre(manifest), runs=args.cold_runs)}
        result["load_average_before_after"] = [list(before), list(os.getloadavg())]
        q = result["cold_query"]
        print(f"cold process `geoid-query --store {args.store} {q['command'][-2]} {q['command'][-1]}` = "
              f"{q['value_m']}: median {q['median_s'] * 1e3:.0f} ms over {len(q['runs_s'])} runs "
              f"({', '.join(f'{t * 1e3:.0f}' for t in q['runs_s'])}; priming run {q['priming_run_s'] * 1e3:.0f} ms); "
              f"load average before / after {before[0]:.2f} / {os.getloadavg()[0]:.2f}")
    else:
        result = run(args.store, args.points, args.repeat, cold=not args.no_cold, cold_runs=args.cold_runs)
        print_table(result)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
