"""Cold start: the install, the README's first fit, a first 1,000,000-point batch and a
one-point query, each as its own process.

    python benchmarks/cold_start.py                    # this venv
    python benchmarks/cold_start.py --fresh-venv       # a fresh venv with `pip install .` first
    python benchmarks/cold_start.py --repeat 5

The kernels are C, compiled by pip when the package is installed (``--fresh-venv``
times that install, the compilation included); nothing is compiled at run time. Then:

1. (a) ``geoid-fit egm96-15 --region -60 -90 15 -30 --tolerance 0.5`` (the README's
   first command; needs PROJ's egm96_15.gtx): the first run after the install is
   "cold", the ``--repeat`` runs after it "warm" (issue 23: cold <= 1.5 x warm);
2. (b) a fresh Python process opens that store and evaluates 1,000,000 random points
   of its region (open + index + kernel library load + evaluation: "first batch"),
   then the same points again ("second batch", warm); ``--repeat`` processes;
3. (c) ``geoid-query --store STORE LAT LON``, ``--repeat`` fresh processes (numpy only).

Prints medians and appends one JSON row to ``benchmarks/results/cold_start.jsonl``
(date, commit, machine, load averages before and after). The machine's load changes
every figure: compare figures of one run, and read the load averages.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))
from _common import git_commit, machine_info  # noqa: E402

FIT_ARGS = ["egm96-15", "--region", "-60", "-90", "15", "-30", "--tolerance", "0.5"]
QUERY_POINT = ("-33.45", "-70.66")  # Santiago de Chile, as in the README

# one process: open the store, two batches of the same random points in its region
BATCH_CODE = r"""
import json, sys, time
started = float(sys.argv[4])  # time.time() just before the parent started this process
t0 = time.perf_counter()
import numpy as np
import geoidspline
store = geoidspline.open_store(sys.argv[1])
s, w, n, e = store.info()["region"]
rng = np.random.default_rng(int(sys.argv[3]))
count = int(sys.argv[2])
lat = rng.uniform(s, n, count)
lon = rng.uniform(w, e, count)
t1 = time.perf_counter()
first = store.undulation(lat, lon)
t2 = time.perf_counter()
first_done = time.time()
second = store.undulation(lat, lon)
t3 = time.perf_counter()
assert np.array_equal(first, second, equal_nan=True)
print(json.dumps({"open_s": t1 - t0, "first_batch_s": t2 - t1, "process_to_first_s": first_done - started,
                  "second_batch_s": t3 - t2, "finite": int(np.isfinite(first).sum())}))
"""


def _run(cmd, env, label, cwd):
    started = time.perf_counter()
    # cwd: a directory without a geoidspline source tree, which `python -c` would import
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=cwd)
    wall = time.perf_counter() - started
    if proc.returncode not in (0, 3):
        sys.exit(f"{label} failed ({proc.returncode}): {' '.join(map(str, cmd))}\n{proc.stderr[-3000:]}")
    return wall, proc.stdout


def _median(values):
    return round(statistics.median(values), 3) if values else None


class Install:
    """Where the commands come from."""

    def __init__(self, bin_dir: Path, scratch: Path):
        self.bin_dir = bin_dir
        self.scratch = scratch
        self.env = dict(os.environ)

    @property
    def python(self):
        return str(self.bin_dir / "python")

    def fit(self, out: Path):
        cmd = [str(self.bin_dir / "geoid-fit"), *FIT_ARGS, "--store", str(out), "--overwrite", "--json", "-q"]
        wall, stdout = _run(cmd, self.env, "geoid-fit", self.scratch)
        info = json.loads(stdout)
        return {"wall_s": round(wall, 3), "fit_wall_s": info["wall_seconds"], "coefficients": info["coefficients"],
                "node_max_error_m": info["node_max_error_m"]}

    def batch(self, store: Path, points: int, seed: int):
        wall, stdout = _run([self.python, "-c", BATCH_CODE, str(store), str(points), str(seed), repr(time.time())],
                            self.env, "batch", self.scratch)
        row = json.loads(stdout)
        row = {k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}
        row["wall_s"] = round(wall, 3)
        return row

    def query(self, store: Path):
        wall, stdout = _run([str(self.bin_dir / "geoid-query"), "--store", str(store), *QUERY_POINT], self.env,
                            "geoid-query", self.scratch)
        return round(wall, 3), stdout.strip()



def _fresh_venv(scratch: Path) -> tuple[Path, float]:
    venv = scratch / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    # a copy of the sources, so nothing is written into the repository (build/, egg-info)
    src = scratch / "src"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(".git", ".venv", "__pycache__", "*.egg-info", "build",
                                                              "out", "results"))
    started = time.perf_counter()
    subprocess.run([str(venv / "bin" / "pip"), "install", "-q", str(src)], check=True)
    seconds = time.perf_counter() - started
    print(f"fresh venv: pip install . (the C kernels compiled) took {seconds:.1f} s", file=sys.stderr)
    return venv / "bin", seconds


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fresh-venv", action="store_true",
                        help="install the repository into a new venv (pip install ., as the README) and use it")
    parser.add_argument("--repeat", type=int, default=3, help="warm fits, batch processes and queries (default 3)")
    parser.add_argument("--points", type=int, default=1_000_000, help="points of a batch (default 1,000,000)")
    parser.add_argument("--results", type=Path, default=HERE / "results" / "cold_start.jsonl")
    args = parser.parse_args(argv)

    load_before = os.getloadavg()
    scratch = Path(tempfile.mkdtemp(prefix="cold_start."))
    try:
        row = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "commit": git_commit(REPO),
               "machine": machine_info(), "fresh_venv": args.fresh_venv, "points": args.points,
               "repeat": args.repeat, "load_before": [round(x, 2) for x in load_before]}
        if args.fresh_venv:
            bin_dir, row["install_s"] = _fresh_venv(scratch)
            install = Install(bin_dir, scratch)
        else:
            install = Install(Path(sys.executable).parent, scratch)
        store = scratch / "andes"

        fits = [install.fit(store) for _ in range(1 + args.repeat)]
        row["fit_cold"] = fits[0]
        row["fit_warm"] = fits[1:]
        cold, warm = fits[0]["wall_s"], _median([f["wall_s"] for f in fits[1:]])
        row["fit_cold_over_warm"] = round(cold / warm, 3)
        print(f"(a) fit: first after install {cold:.1f} s, warm median {warm:.1f} s: ratio {cold / warm:.2f}")

        batches = [install.batch(store, args.points, seed) for seed in range(args.repeat)]
        row["batch"] = batches
        first = _median([b["process_to_first_s"] for b in batches])
        second = _median([b["second_batch_s"] for b in batches])
        print(f"(b) {args.points:,}-point batch in a fresh process: process start to first batch done {first:.2f} s "
              f"(median of {len(batches)}; open {_median([b['open_s'] for b in batches]):.2f} s, first batch "
              f"{_median([b['first_batch_s'] for b in batches]):.2f} s), second batch {second:.3f} s")

        install.query(store)  # priming run (file cache), not counted
        queries = [install.query(store) for _ in range(max(1, args.repeat))]
        row["query_s"] = [q[0] for q in queries]
        row["query_value"] = queries[0][1]
        print(f"(c) one-point geoid-query: median {_median(row['query_s']):.3f} s ({queries[0][1]} m)")

        row["load_after"] = [round(x, 2) for x in os.getloadavg()]
        print(f"load average before {row['load_before']}, after {row['load_after']}")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    args.results.parent.mkdir(parents=True, exist_ok=True)
    with open(args.results, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
