"""EGM2008 at degree 2190 fitted with nothing but a tolerance (issue 22 item 7).

    python benchmarks/egm2008_benchmark.py [--model PATH] [--tolerance 0.01 0.001]
        [--region global] [--region S,W,N,E ...] [--points N] [--max-memory GB]
        [--workdir DIR] [--cache DIR] [--json OUT] [--query-points 1000000] [--repeat 5]

MODEL is the synthetic EGM2008 (``EGM2008_to2190_TideFree_synthetic.ascii.gz``); when
absent it is generated with ``make_synthetic_egm2008.py`` (``--generator``, default
``../shared/tools`` beside the repository). For every region and tolerance, in this order:

1. ``geoid-fit MODEL --tolerance T [--region S W N E] --store DIR --max-memory GB --json
   -q`` in a child process: wall seconds, exit status, peak RSS (``ru_maxrss`` of the
   fit's process tree, through a wrapper that runs nothing else), the fit's own summary;
2. the store: coefficients, bytes on disk (every file);
3. max / RMS / p99 |error| at random points (``--points``; 20,000 for the globe by
   default, 10,000 in a region) against the independent exact synthesis
   (``independent_synthesis.py``: SHTOOLS Legendre functions, NGA hsynth conventions,
   nothing of geoidspline), its values cached under ``--cache`` by the model's sha256;
4. query throughput: ``query_benchmark.run_store`` (1 thread and all, pyproj's bilinear
   egm96_15.gtx on the same points in the same run; medians of ``--repeat``), the
   ratio pyproj / ours reported for the batch inside the store (the globe or the region).

One JSON line per fit (date, commit, load average before and after, machine) to stdout
and ``--json``. ``--resume`` continues an interrupted global fit (``--keep`` its store
so that it can be). Big runs go through the shared lock: ``flock /work/scratch/bigrun.lock
python benchmarks/egm2008_benchmark.py ...``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
from _common import git_commit, machine_info  # noqa: E402
from independent_synthesis import reference_values, sha256_of  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("GEOIDSPLINE_SHARED") or REPO.parent / "shared")
MODEL_NAME = "EGM2008_to2190_TideFree_synthetic.ascii.gz"
GLOBAL = (-90.0, -180.0, 90.0, 180.0)

#: Runs the command in argv and prints, as its last stderr line, the exit status and the
#: peak RSS of the command's process tree (ru_maxrss of waited-for children, kB).
_WRAPPER = r"""
import json, resource, subprocess, sys, time
t0 = time.perf_counter()
done = subprocess.run(sys.argv[1:], stdout=subprocess.PIPE)
sys.stdout.buffer.write(done.stdout)
peak = resource.getrusage(resource.RUSAGE_CHILDREN)
print("WRAPPER " + json.dumps({"returncode": done.returncode, "wall_s": time.perf_counter() - t0,
      "peak_rss_mb": peak.ru_maxrss / 1024, "cpu_s": peak.ru_utime + peak.ru_stime}), file=sys.stderr)
"""


def ensure_model(model: Path, generator: Path) -> Path:
    if model.exists():
        return model
    if not generator.exists():
        raise SystemExit(f"{model} is absent and the generator {generator} too: give --model or --generator")
    model.parent.mkdir(parents=True, exist_ok=True)
    print(f"generating {model} with {generator} (about a minute)", file=sys.stderr, flush=True)
    subprocess.run([sys.executable, str(generator), str(model)], check=True)
    return model


def store_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def fit(model: Path, region, tolerance: float, store: Path, max_memory: float, extra, resume=False) -> dict:
    command = [sys.executable, "-m", "geoidspline", "fit", str(model), "--tolerance", repr(tolerance),
               "--store", str(store), "--resume" if resume else "--overwrite", "--json", "-v", "--max-memory",
               repr(max_memory), *extra]
    if tuple(region) != GLOBAL:
        command += ["--region", *[repr(v) for v in region]]
    log = store.with_name(store.name + ".log")  # the fit's progress, to follow a long run
    store.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w", encoding="utf-8") as err:
        done = subprocess.run([sys.executable, "-c", _WRAPPER, *command], stdout=subprocess.PIPE, stderr=err,
                              text=True, check=False)  # a failed fit is a row too
    lines = log.read_text(encoding="utf-8", errors="replace").splitlines()
    figures = next(json.loads(line[8:]) for line in lines[::-1] if line.startswith("WRAPPER "))
    summary = None
    try:
        summary = json.loads(done.stdout)
    except json.JSONDecodeError:
        pass
    tail = [line for line in lines if not line.startswith("WRAPPER ")][-5:]
    return {"command": " ".join(command), **figures, "summary": summary, "stderr_tail": tail, "fit_log": str(log)}


def errors_at_reference(store: Path, lat, lon, truth) -> dict:
    import geoidspline

    st = geoidspline.open_store(store)
    values = np.empty(truth.size)
    for start in range(0, truth.size, 100_000):
        values[start:start + 100_000] = st.undulation(lat[start:start + 100_000], lon[start:start + 100_000])
    errors = np.abs(values - truth)
    if np.isnan(errors).any():
        raise SystemExit(f"{store} gives no value at {int(np.isnan(errors).sum())} reference points")
    return {"check_points": int(truth.size), "check_max_mm": float(errors.max() * 1e3),
            "check_rms_mm": float(np.sqrt(np.mean(errors**2)) * 1e3),
            "check_p99_mm": float(np.percentile(errors, 99) * 1e3),
            "coefficients": int(st.manifest["spline"]["coefficients"]),
            "levels": [lv.get("coefficients") for lv in st.manifest["spline"].get("levels", [])]}


def query_speed(store: Path, region, points: int, repeat: int) -> dict:
    from query_benchmark import run_store

    batch_region = None if tuple(region) == GLOBAL else (region[0], region[1], region[2], region[3])
    result = run_store(store, points, batch_region, repeat, None)
    batch = "global" if batch_region is None else "regional"
    med = result["median_ns_per_point"]
    return {"query_batch": batch, "query_points": points,
            "ns_per_point_1_thread": med[f"ours-1/{batch}"], "ns_per_point_all_threads": med[f"ours-all/{batch}"],
            "pyproj_ns_per_point": med[f"pyproj/{batch}"],
            "pyproj_over_ours_1_thread": result["ratio_pyproj_over_ours"][f"ours-1/{batch}"],
            "pyproj_over_ours_all_threads": result["ratio_pyproj_over_ours"][f"ours-all/{batch}"],
            "query_load_average": result["load_average_during"], "pyproj_check": result["pyproj_check"]}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default=str(Path("/tmp/egm2008") / MODEL_NAME))
    parser.add_argument("--generator", default=str(SHARED / "tools" / "make_synthetic_egm2008.py"))
    parser.add_argument("--tolerance", type=float, nargs="+", default=[0.01, 0.001])
    parser.add_argument("--region", action="append", default=None, help="'global' or S,W,N,E (repeatable)")
    parser.add_argument("--points", type=int, default=None, help="reference points (default 20,000 global, "
                                                                  "10,000 in a region)")
    parser.add_argument("--max-memory", type=float, default=10.0, help="GB, passed to geoid-fit")
    parser.add_argument("--workdir", default="/tmp/egm2008/stores")
    parser.add_argument("--cache", default="/tmp/egm2008/reference")
    parser.add_argument("--json", default=None, help="append the rows to this JSONL file")
    parser.add_argument("--query-points", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--keep", action="store_true", help="keep the stores (default: removed after measuring)")
    parser.add_argument("--resume", action="store_true",
                        help="continue an interrupted global fit in --workdir (geoid-fit --resume; the time and "
                             "peak RSS are then this run's only) instead of starting anew")
    parser.add_argument("fit_args", nargs="*", help="after --: more geoid-fit options")
    args = parser.parse_args(argv)
    model = ensure_model(Path(args.model), Path(args.generator))
    model_sha = sha256_of(model)
    regions = [GLOBAL if r == "global" else tuple(float(v) for v in r.split(",")) for r in (args.region or ["global"])]
    for region in regions:
        count = args.points or (20_000 if region == GLOBAL else 10_000)
        for tolerance in args.tolerance:
            tag = "global" if region == GLOBAL else "_".join(f"{v:g}" for v in region)
            store = Path(args.workdir) / f"egm2008_{tag}_{tolerance:g}"
            load_before = os.getloadavg()
            row = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                   "commit": git_commit(REPO), "model": str(model), "model_sha256": model_sha,
                   "region": "global" if region == GLOBAL else list(region), "tolerance_m": tolerance}
            row.update(fit(model, region, tolerance, store, args.max_memory, args.fit_args, args.resume))
            row["resumed"] = args.resume
            if row["returncode"] in (0, 3) and store.exists():
                # after the fit: the reference may be computed meanwhile by another process (the cache)
                lat, lon, truth, ref_s = reference_values(model, region, count, args.cache)
                row["reference_s"] = round(ref_s, 1)
                row["store_bytes"] = store_bytes(store)
                row.update(errors_at_reference(store, lat, lon, truth))
                row.update(query_speed(store, region, args.query_points, args.repeat))
            row["load_average"] = [list(load_before), list(os.getloadavg())]
            row["machine"] = machine_info()
            line = json.dumps(row)
            print(line, flush=True)
            if args.json:
                with open(args.json, "a", encoding="utf-8") as fh:
                    fh.write(line + "\n")
            if not args.keep and store.exists():
                import shutil

                shutil.rmtree(store)


if __name__ == "__main__":
    main()
