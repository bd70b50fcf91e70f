"""Cold start: the README's first fit, a first 1,000,000-point batch and a one-point
query, from an empty numba compile cache.

    python benchmarks/cold_start.py                    # this venv, a fresh empty cache
    python benchmarks/cold_start.py --fresh-venv       # also a fresh venv with `pip install .`
    python benchmarks/cold_start.py --no-warmup-runs 0 --repeat 5

Every command runs as its own process. The compile cache starts empty: a new
``NUMBA_CACHE_DIR`` (or, with ``--fresh-venv``, a new venv whose non-editable install
keeps the cache in its own ``site-packages``, as the README's set-up does). Then:

1. install: ``geoid-warmup`` (the README's set-up step) fills the cache;
2. (a) ``geoid-fit egm96-15 --region -60 -90 15 -30 --tolerance 0.5`` (the README's
   first command; needs PROJ's egm96_15.gtx): the first run after the install is
   "cold", the ``--repeat`` runs after it "warm";
3. (b) a fresh Python process opens that store and evaluates 1,000,000 random points
   of its region (open + index + kernel load or compile + evaluation: "first batch"),
   then the same points again ("second batch", warm); ``--repeat`` processes;
4. (c) ``geoid-query --store STORE LAT LON``, ``--repeat`` fresh processes (numpy only);
5. without the install step: ``--no-warmup-runs`` times (default 1), the fit from a new
   empty cache and the first batch from another, which then compile their kernels on
   first use (what a user who skips the warm-up, or a test run, pays).

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
    """Where the commands come from, and the environment that gives them an empty cache."""

    def __init__(self, bin_dir: Path, scratch: Path, in_tree_cache: bool):
        self.bin_dir = bin_dir
        self.scratch = scratch
        self.in_tree_cache = in_tree_cache
        self.env = dict(os.environ)
        self.env.pop("NUMBA_CACHE_DIR", None)
        self.caches = 0

    @property
    def python(self):
        return str(self.bin_dir / "python")

    def empty_cache(self):
        """A new, empty compile cache for the commands that follow."""
        self.caches += 1
        if self.in_tree_cache:
            # the venv's own site-packages: remove what numba wrote beside the sources
            site = subprocess.run([self.python, "-c", "import geoidspline, os; print(os.path.dirname("
                                   "geoidspline.__file__))"], capture_output=True, text=True, check=True,
                                  cwd=self.scratch)
            for cache in Path(site.stdout.strip()).rglob("__pycache__"):
                for f in list(cache.glob("*.nbi")) + list(cache.glob("*.nbc")):
                    f.unlink()
        else:
            cache = self.scratch / f"numba_cache_{self.caches}"
            cache.mkdir()
            self.env["NUMBA_CACHE_DIR"] = str(cache)

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

    def warmup(self):
        wall, stdout = _run([str(self.bin_dir / "geoid-warmup"), "-q"], self.env, "geoid-warmup", self.scratch)
        return round(wall, 3), stdout.strip()


def _fresh_venv(scratch: Path) -> Path:
    venv = scratch / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    # a copy of the sources, so nothing is written into the repository (build/, egg-info)
    src = scratch / "src"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(".git", ".venv", "__pycache__", "*.egg-info", "build",
                                                              "out", "results"))
    started = time.perf_counter()
    subprocess.run([str(venv / "bin" / "pip"), "install", "-q", str(src)], check=True)
    print(f"fresh venv: pip install . took {time.perf_counter() - started:.1f} s", file=sys.stderr)
    return venv / "bin"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fresh-venv", action="store_true",
                        help="install the repository into a new venv (pip install ., as the README) and use it")
    parser.add_argument("--repeat", type=int, default=3, help="warm fits, batch processes and queries (default 3)")
    parser.add_argument("--points", type=int, default=1_000_000, help="points of a batch (default 1,000,000)")
    parser.add_argument("--no-warmup-runs", type=int, default=1,
                        help="runs without the install's warm-up step, each from a new empty cache (default 1)")
    parser.add_argument("--results", type=Path, default=HERE / "results" / "cold_start.jsonl")
    args = parser.parse_args(argv)

    load_before = os.getloadavg()
    scratch = Path(tempfile.mkdtemp(prefix="cold_start."))
    try:
        if args.fresh_venv:
            install = Install(_fresh_venv(scratch), scratch, in_tree_cache=True)
        else:
            install = Install(Path(sys.executable).parent, scratch, in_tree_cache=False)
        store = scratch / "andes"
        row = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "commit": git_commit(REPO),
               "machine": machine_info(), "fresh_venv": args.fresh_venv, "points": args.points,
               "repeat": args.repeat, "load_before": [round(x, 2) for x in load_before]}

        # the install: an empty cache, then the README's warm-up step
        install.empty_cache()
        row["warmup_s"], row["warmup_summary"] = install.warmup()
        print(f"install warm-up: {row['warmup_s']:.1f} s ({row['warmup_summary']})")

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

        row["no_warmup"] = []
        for _ in range(args.no_warmup_runs):
            install.empty_cache()
            nw_fit = install.fit(scratch / "andes_nowarm")
            install.empty_cache()  # the fit compiled the query kernels too
            nw_batch = install.batch(store, args.points, 0)
            row["no_warmup"].append({"fit": nw_fit, "batch": nw_batch})
            print(f"without the warm-up: fit {nw_fit['wall_s']:.1f} s (warm {warm:.1f} s: ratio "
                  f"{nw_fit['wall_s'] / warm:.2f}); then a fresh process's first batch "
                  f"{nw_batch['process_to_first_s']:.2f} s")
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
