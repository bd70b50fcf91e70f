#!/usr/bin/env python3
"""Batch query speed of geoidspline stores against PROJ's bilinear egm96_15.gtx, one run.

    python benchmarks/query_benchmark.py --store STORE [--store STORE ...] [--points 1000000]
        [--region S W N E] [--repeat 5] [--json OUT]

For each store, in one process and on the same points:

* ``ours-1`` / ``ours-all``: ``geoidspline.open_store(STORE).undulation(lat, lon)`` on one
  thread and on all threads (``geoidspline._kernels._clib.set_threads``);
* ``pyproj``: ``Transformer.from_pipeline('+proj=vgridshift +grids=egm96_15.gtx')`` (PROJ's
  bilinear lookup, one thread), checked to return N (query_speed.verify_proj);
* ``geographiclib``: GeographicLib's cubic interpolation through PyGeodesy
  (``GeoidKarney``) when pygeodesy and a ``.pgm`` geoid file (``--pgm``) are present
  (timed on the batch's first GEOGRAPHICLIB_POINTS points: it answers one point at a time
  in Python); reported as absent otherwise. The model of the ``.pgm`` file is whatever it
  holds (its name is printed): a speed peer, not an accuracy one unless it is EGM96.

Two batches: N random points uniform on the sphere (seed 20130101) and a regional batch
of N points uniform in area in ``--region`` (default 35..60 N, 10 W..30 E: Europe), the
same points for every variant. Each variant is called once untimed first, then the
variants are timed in turn ``--repeat`` times (interleaved, so load from other processes
hits all alike); the figures are medians of wall time / N in ns per point, and the
ratios pyproj / ours come from the same run.

Roofline note: per point and evaluated table, an order-n query reads n² column offsets
(4 B; 2 B in quantised tables), one entry of the table's full-column map (2 B) and n³
coefficients (8 B; 2 B in quantised tables), and does n³ multiplies and n³ adds on z lanes, n²
products of weights, 2n for the last dot product, about 15n for the three axes' weights
and about 60 for the direction (two sin/cos pairs): printed with the measured ns/pt, the
achieved GFLOP/s and the compute limit of one core (8 double flops a cycle with AVX2
multiplies and adds, no FMA contraction) at the clock /proc/cpuinfo reports, or at
``--cpu-mhz`` (a virtual machine's /proc/cpuinfo may give the nominal clock, below the
one it runs at: benchmarks/README.md).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
from _common import git_commit, machine_info  # noqa: E402
from query_speed import PIPELINE, SEED, proj_transformer, proj_undulation, verify_proj  # noqa: E402

EUROPE = (35.0, -10.0, 60.0, 30.0)

GEOGRAPHICLIB_POINTS = 100  # PyGeodesy's GeoidKarney: about 10 ms a point (2026-12-03)


def random_points(n, seed=SEED, region=None):
    """n points uniform in area: on the sphere, or in region (south, west, north, east)."""
    rng = np.random.default_rng(seed)
    s, w, nn, e = region or (-90.0, -180.0, 90.0, 180.0)
    z0, z1 = np.sin(np.radians(s)), np.sin(np.radians(nn))
    return np.degrees(np.arcsin(rng.uniform(z0, z1, n))), rng.uniform(w, e, n)


def cpu_mhz():
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            values = [float(line.split(":")[1]) for line in fh if line.startswith("cpu MHz")]
        return statistics.median(values) if values else None
    except OSError:
        return None


def roofline(order, ns_per_point, mhz, value_bytes=8, offset_bytes=4):
    """Flops and table bytes a point and table; value_bytes / offset_bytes: 8 / 4 for
    float64 tables, 2 / 2 for quantised ones (int16 values and column offsets)."""
    n = order
    flops = 2 * n**3 + n**2 + 2 * n + 3 * 15 * n + 60
    bytes_ = value_bytes * n**3 + offset_bytes * n**2 + 2
    out = {"order": n, "flops_per_point": flops, "bytes_per_point": bytes_, "value_bytes": value_bytes,
           "offset_bytes": offset_bytes, "ns_per_point": ns_per_point,
           "achieved_gflops": flops / ns_per_point, "achieved_gbytes_s": bytes_ / ns_per_point}
    if mhz:
        limit = flops / (8 * mhz * 1e-3)  # ns at 8 flops a cycle
        out.update({"cpu_mhz": mhz, "compute_limit_ns_per_point": limit, "fraction_of_limit": limit / ns_per_point})
    return out


def geographiclib_geoid(pgm):
    """PyGeodesy's GeoidKarney (GeographicLib's cubic) on pgm, or (None, reason)."""
    try:
        import pygeodesy
    except ImportError:
        return None, "pygeodesy not installed"
    if not pgm or not Path(pgm).exists():
        return None, "no GeographicLib .pgm geoid file given (--pgm)"
    return pygeodesy.GeoidKarney(str(pgm), kind=3), None


def run_store(store, points, region, repeat, pgm, mhz=None):
    import geoidspline
    from geoidspline._kernels import _clib

    all_threads = _clib.threads()
    t0 = time.perf_counter()
    st = geoidspline.open_store(store)
    t_open = time.perf_counter() - t0
    t0 = time.perf_counter()
    st.spline.full
    t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    index = st.spline.index
    t_index = time.perf_counter() - t0
    transformer = proj_transformer()
    proj_check = verify_proj(transformer)
    karney, karney_absent = geographiclib_geoid(pgm)
    batches = {"global": random_points(points), "regional": random_points(points, SEED + 1, region)}
    zeros = np.zeros(points)

    def ours(lat, lon, nthreads):
        _clib.set_threads(nthreads)
        try:
            return st.undulation(lat, lon)
        finally:
            _clib.set_threads(all_threads)

    variants = {}
    for name, (lat, lon) in batches.items():
        variants[f"ours-1/{name}"] = (lambda lat=lat, lon=lon: ours(lat, lon, 1))
        variants[f"ours-all/{name}"] = (lambda lat=lat, lon=lon: ours(lat, lon, all_threads))
        variants[f"pyproj/{name}"] = (lambda lat=lat, lon=lon: proj_undulation(transformer, lat, lon, zeros))
        if karney is not None:
            # GeoidKarney answers one point at a time in about 10 ms (a cubic fit per new
            # cell, in Python): the first GEOGRAPHICLIB_POINTS of the batch, per point
            k = max(1, min(points, GEOGRAPHICLIB_POINTS))
            variants[f"geographiclib/{name}"] = (
                lambda lat=lat[:k], lon=lon[:k]: [karney.height(a, b) for a, b in zip(lat, lon)], k)
    first, results = {}, {}
    for name, v in variants.items():
        func = v[0] if isinstance(v, tuple) else v
        t0 = time.perf_counter()
        results[name] = func()
        first[name] = time.perf_counter() - t0
    for name in batches:
        if not np.array_equal(results[f"ours-1/{name}"], results[f"ours-all/{name}"], equal_nan=True):
            raise SystemExit("1 thread and all threads disagree: the threaded kernel is not deterministic")
    samples = {name: [] for name in variants}
    load_before = os.getloadavg()
    for _ in range(repeat):
        for name, v in variants.items():
            func, count = (v if isinstance(v, tuple) else (v, points))
            t0 = time.perf_counter()
            func()
            samples[name].append((time.perf_counter() - t0) / count * 1e9)
    medians = {name: statistics.median(s) for name, s in samples.items()}
    ratios = {}
    for name in batches:
        for ours_name in ("ours-1", "ours-all"):
            ratios[f"{ours_name}/{name}"] = medians[f"pyproj/{name}"] / medians[f"{ours_name}/{name}"]
    mhz = mhz or cpu_mhz()
    return {
        "store": str(store), "coefficients": st.manifest["spline"]["coefficients"], "order": st.spline.order,
        "levels": len(index.levels), "open_s": t_open, "read_all_tiles_s": t_read, "index_build_s": t_index,
        "index_bytes": int(index.nbytes), "points": points, "region": region, "repeat": repeat,
        "threads_all": all_threads, "pyproj_pipeline": PIPELINE, "pyproj_check": proj_check,
        "geographiclib": "measured" if karney is not None else karney_absent,
        "geographiclib_pgm": str(pgm) if karney is not None else None,
        "first_call_s": first, "ns_per_point": samples, "median_ns_per_point": medians,
        "ratio_pyproj_over_ours": ratios,
        "roofline_1_thread_global": roofline(
            st.spline.order, medians["ours-1/global"], mhz,
            value_bytes=index.values.itemsize if index.qvalues is None else index.qvalues.itemsize,
            offset_bytes=index.own_offs.itemsize),
        "load_average_during": [list(load_before), list(os.getloadavg())],
    }


def print_store(r):
    med = r["median_ns_per_point"]
    print(f"store {r['store']} ({r['coefficients']:,} coefficients, order {r['order']}, {r['levels']} levels): "
          f"manifest {r['open_s']:.3f} s, tiles {r['read_all_tiles_s']:.2f} s, index {r['index_build_s']:.2f} s "
          f"({r['index_bytes'] / 1e6:.0f} MB)")
    print(f"{r['points']:,} points a batch, {r['repeat']} repeats, medians; load "
          + " / ".join(" ".join(f"{v:.1f}" for v in la) for la in r["load_average_during"]))
    print("| batch | variant | ns/pt (median) | min..max | pyproj / this |")
    print("|---|---|---:|---:|---:|")
    for name, v in r["ns_per_point"].items():
        variant, batch = name.split("/")
        ratio = med[f"pyproj/{batch}"] / med[name]
        label = {"ours-1": "geoidspline, 1 thread", "ours-all": f"geoidspline, {r['threads_all']} threads",
                 "pyproj": "pyproj bilinear egm96_15.gtx",
                 "geographiclib": f"GeographicLib cubic (PyGeodesy) {Path(r['geographiclib_pgm'] or '').name}"}[variant]
        print(f"| {batch} | {label} | {med[name]:.1f} | {min(v):.1f}..{max(v):.1f} | {ratio:.3g} |")
    if r["geographiclib"] != "measured":
        print(f"GeographicLib cubic: not measured ({r['geographiclib']})")
    f = r["roofline_1_thread_global"]
    line = (f"roofline (1 thread, global): {f['flops_per_point']} flops and {f['bytes_per_point']} B of tables a "
            f"point and table; {f['ns_per_point']:.1f} ns/pt = {f['achieved_gflops']:.2f} GFLOP/s, "
            f"{f['achieved_gbytes_s']:.1f} GB/s of table reads ({f.get('value_bytes', 8)}-byte values, "
            f"{f.get('offset_bytes', 4)}-byte column offsets)")
    if "compute_limit_ns_per_point" in f:
        line += (f"; compute limit at {f['cpu_mhz']:.0f} MHz, 8 flops/cycle: {f['compute_limit_ns_per_point']:.1f} "
                 f"ns/pt ({100 * f['fraction_of_limit']:.0f} % of it)")
    print(line)
    print()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--store", action="append", required=True, type=Path)
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--region", type=float, nargs=4, default=EUROPE, metavar=("S", "W", "N", "E"))
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--pgm", type=Path, help="GeographicLib geoid file for PyGeodesy's GeoidKarney")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--cpu-mhz", type=float, help="the clock of the roofline's compute limit "
                        "(default: /proc/cpuinfo's)")
    args = parser.parse_args(argv)
    report = {"date": dt.datetime.now(dt.timezone.utc).replace(microsecond=0).isoformat(),
              "git_commit": git_commit(Path(__file__).resolve().parent.parent), "machine": machine_info(),
              "stores": []}
    print(f"{report['date']} commit {report['git_commit']}, {report['machine']['nproc']} CPUs "
          f"({report['machine']['cpu_model']})")
    for store in args.store:
        r = run_store(store, args.points, tuple(args.region), args.repeat, args.pgm, args.cpu_mhz)
        report["stores"].append(r)
        print_store(r)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
