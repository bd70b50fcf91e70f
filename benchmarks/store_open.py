#!/usr/bin/env python3
"""What a query costs from a store just opened: one point, a regional batch, a global batch.

    python benchmarks/store_open.py --store STORE [--store STORE ...] [--repeat 3]
        [--code DIR] [--skip global] [--json OUT]

Every figure comes from a fresh process (nothing cached but the operating system's page
cache, warmed by reading every file of the store once first), as a user meets it:

* ``one-point``: ``geoid-query --store STORE 45 10`` (the command line; wall time of the
  whole process and its peak RSS);
* ``city`` (100,000 points in 45..47 N, 7..9 E), ``regional`` (1,000,000 points uniform in
  area in 35..60 N, 10 W..30 E, query_benchmark.py's Europe) and ``global`` (1,000,000
  points uniform on the sphere): ``open_store(STORE).undulation(lat, lon)`` in a fresh
  Python process: ``first_s`` from opening to the first answer (tiles read, index built,
  batch evaluated), ``again_s`` the same batch once more (warm), the process's peak RSS,
  the tiles read, and a sha256 of the values (bitwise comparisons between code versions).

``--code DIR`` runs the same cases with the geoidspline package of another checkout (for
instance main's worktree), so that one run gives both (``--code`` may be repeated; the
geoid-query case of a checkout is ``python -m geoidspline.cli.query`` there). Points are
seeded (query_benchmark.py's seeds), so the values' digests agree between runs and versions
exactly when every value has the same bits. Stores of a few GB once read (the EGM2008 1 mm
store: 8.2 GB read whole) must go through the machine's bigrun lock.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import git_commit, machine_info  # noqa: E402

REPO = Path(__file__).resolve().parent.parent

CASES = {  # name: (points, seed, region S W N E or None)
    "city": (100_000, 20130102, (45.0, 7.0, 47.0, 9.0)),
    "regional": (1_000_000, 20130102, (35.0, -10.0, 60.0, 30.0)),
    "global": (1_000_000, 20130101, None),
}

BATCH = """
import hashlib, json, resource, sys, time
start = time.perf_counter()
sys.path.insert(0, {code!r})
import numpy as np
import geoidspline
n, seed, region = {points}, {seed}, {region!r}
rng = np.random.default_rng(seed)
s, w, nn, e = region or (-90.0, -180.0, 90.0, 180.0)
lat = np.degrees(np.arcsin(rng.uniform(np.sin(np.radians(s)), np.sin(np.radians(nn)), n)))
lon = rng.uniform(w, e, n)
t0 = time.perf_counter()
store = geoidspline.open_store({store!r})
values = store.undulation(lat, lon)
t1 = time.perf_counter()
again = store.undulation(lat, lon)
t2 = time.perf_counter()
assert np.array_equal(values, again, equal_nan=True)
print(json.dumps({{"import_s": t0 - start, "first_s": t1 - t0, "again_s": t2 - t1,
                  "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "tiles_read": store.spline.tiles_read, "tiles": len(store.manifest["tiles"]),
                  "module": geoidspline.__file__,
                  "sha256": hashlib.sha256(np.ascontiguousarray(values).tobytes()).hexdigest()}}))
"""


def run_child(argv):
    """(stdout, wall seconds) of a child process (which reports its own peak RSS)."""
    t0 = time.perf_counter()
    proc = subprocess.run(argv, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(f"{argv[:3]} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return proc.stdout, wall


def one_point(store, code):
    code_dir = str(code)
    argv = [sys.executable, "-c",
            f"import resource, sys; sys.path.insert(0, {code_dir!r}); from geoidspline.cli.query import main\n"
            f"try:\n    main(['--store', {str(store)!r}, '45', '10'], standalone_mode=False)\n"
            f"finally:\n    print('RSS', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)"]
    out, wall = run_child(argv)
    lines = out.split()
    return {"wall_s": wall, "value": lines[0], "maxrss_mb": float(lines[-1])}


def batch(store, code, case):
    points, seed, region = CASES[case]
    out, wall = run_child([sys.executable, "-c", BATCH.format(code=str(code), points=points, seed=seed,
                                                                  region=region, store=str(store))])
    result = json.loads(out.strip().splitlines()[-1])
    result["process_wall_s"] = wall
    return result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--store", action="append", required=True)
    parser.add_argument("--code", action="append", default=None,
                        help="checkout whose geoidspline to run (default: this one); repeatable")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--skip", action="append", default=[], choices=["one-point", *CASES])
    parser.add_argument("--threads", type=int, default=None,
                        help="GEOIDSPLINE_THREADS of the runs (decoding and query threads; default: all)")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if args.threads is not None:
        os.environ["GEOIDSPLINE_THREADS"] = str(args.threads)  # inherited by every run
    codes = [Path(c).resolve() for c in (args.code or [str(REPO)])]
    cases = [c for c in ("one-point", *CASES) if c not in args.skip]
    report = {"date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"), "machine": machine_info(),
              "codes": {str(c): git_commit(c) for c in codes},
              "threads": os.environ.get("GEOIDSPLINE_THREADS"), "load_before": os.getloadavg(), "runs": []}
    for store in args.store:
        for path in sorted(Path(store).rglob("*")):  # the page cache holds the store for every run alike
            if path.is_file():
                path.read_bytes()
        for case in cases:
            samples = {str(c): [] for c in codes}
            for _ in range(args.repeat):
                for code in codes:  # interleaved: load from other processes hits all alike
                    samples[str(code)].append(one_point(store, code) if case == "one-point"
                                              else batch(store, code, case))
            for code, runs in samples.items():
                key = "wall_s" if case == "one-point" else "first_s"
                row = {"store": store, "case": case, "code": code, "commit": report["codes"][code], "runs": runs,
                       "median_s": statistics.median(r[key] for r in runs),
                       "median_again_s": (statistics.median(r["again_s"] for r in runs) if case != "one-point"
                                          else None),
                       "max_rss_mb": max(r["maxrss_mb"] for r in runs)}
                report["runs"].append(row)
                again = f", again {row['median_again_s']:.3f} s" if row["median_again_s"] is not None else ""
                extra = (f", tiles {runs[0]['tiles_read']}/{runs[0]['tiles']}, sha256 {runs[0]['sha256'][:12]}"
                         if case != "one-point" else f", value {runs[0]['value']}")
                print(f"{Path(store).name} {case} [{Path(code).name} {str(row['commit'])[:9]}]: "
                      f"{row['median_s']:.3f} s (median of {len(runs)}){again}, peak RSS {row['max_rss_mb']:.0f} MB"
                      f"{extra}", flush=True)
    report["load_after"] = os.getloadavg()
    print("load before / after:", " ".join(f"{v:.1f}" for v in report["load_before"]), "/",
          " ".join(f"{v:.1f}" for v in report["load_after"]))
    if args.json:
        with open(args.json, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(report) + "\n")


if __name__ == "__main__":
    main()
