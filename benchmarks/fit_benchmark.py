#!/usr/bin/env python3
"""Fit benchmark: run named geoid-fit scenarios and record size, accuracy, time, memory.

    python benchmarks/fit_benchmark.py SCENARIO [SCENARIO...] [--workers N] [--out-dir DIR] [--json OUT]

Each scenario runs ``geoid-fit SOURCE ... --store DIR/SCENARIO --overwrite --json -q``
as a subprocess under ``/usr/bin/time -v`` (peak RSS of the largest single process,
i.e. the main process or one worker; without GNU time, ``getrusage(RUSAGE_CHILDREN)``,
which is the same figure), and, if psutil is importable, also samples the summed RSS
of the whole process tree every 0.5 s (the figure that matters with --workers > 1).
Then ``geoid-info --store STORE --json`` reads the written store, and the figures recorded are
the store's own: coefficients per level, store bytes, max/RMS |error| at the source
grid's nodes, max/RMS at the check points (cell centres, against the grid's bicubic
interpolation), plus the wall time of the subprocess (interpreter start included).

Every scenario appends one JSON row to benchmarks/results/fits.jsonl (date, git commit,
machine: nproc and CPU model, scenario, command, figures) and prints a markdown table
row. Scenarios with targets (andes: the thesis's headline, METHOD.md section 5) say
whether they were met; the exit status is 1 if any scenario failed or missed a target.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import re
import resource
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import git_commit, machine_info  # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results" / "fits.jsonl"
DEFAULT_OUT = HERE / "out"

#: name -> (geoid-fit arguments before --store, targets, description)
SCENARIOS = {
    "andes": (
        ["egm96-15", "--region", "-60", "-90", "15", "-30", "--tolerance", "0.5"],
        {"node_max_error_m": 0.5, "coefficients": 50_000},
        "western South America (the thesis's region, about 1/12 of the Earth), EGM96 15', tolerance 0.5 m",
    ),
    "global-0.5": (
        ["egm96-15", "--tolerance", "0.5"],
        {"node_max_error_m": 0.5},
        "the whole EGM96 15' grid, tolerance 0.5 m",
    ),
    "global-0.1": (
        ["egm96-15", "--tolerance", "0.1"],
        {"node_max_error_m": 0.1},
        "the whole EGM96 15' grid, tolerance 0.1 m",
    ),
    # spherical-harmonic models from ../shared/data (skipped when absent): issue 3's stores
    "egm96-mm": (
        ["{shared}/egm96/egm96_to360.ascii.gz", "--correction", "{shared}/egm96/CORRCOEF.gz",
         "--method", "interpolation", "--order", "6", "--h0", "0.0045", "--max-level", "1",
         "--tolerance", "0.0015"],
        {"check_max_error_m": 0.002, "check_rms_error_m": 0.0003, "wall_seconds": 1800},
        "global EGM96 (degree 360, NGA F477 with CORRCOEF) from its coefficients: quintic "
        "quasi-interpolation at h = 0.0045, least-squares overlays where nodes exceed 1.5 mm",
    ),
    "egm96-cm": (
        ["{shared}/egm96/egm96_to360.ascii.gz", "--correction", "{shared}/egm96/CORRCOEF.gz",
         "--method", "interpolation", "--order", "4", "--h0", "0.004", "--max-level", "1",
         "--tolerance", "0.007"],
        {"check_max_error_m": 0.01, "node_max_error_m": 0.01},
        "global EGM96 (NGA F477 with CORRCOEF) to 1 cm with cubics, the query benchmark's store: "
        "quasi-interpolation at h = 0.004, least-squares overlays where nodes exceed 7 mm",
    ),
    # issue 11: no option but the tolerance (geoidspline.fitting.choose picks the rest)
    "egm96-default-2mm": (
        ["{shared}/egm96/egm96_to360.ascii.gz", "--correction", "{shared}/egm96/CORRCOEF.gz", "--tolerance", "0.002"],
        {"check_max_error_m": 0.002, "check_rms_error_m": 0.0003, "wall_seconds": 180, "coefficients": 5_586_925},
        "global EGM96 (F477 + CORRCOEF) with --tolerance 0.002 only: the parameters chosen from it",
    ),
    "egm96-default-1cm": (
        ["{shared}/egm96/egm96_to360.ascii.gz", "--correction", "{shared}/egm96/CORRCOEF.gz", "--tolerance", "0.01"],
        {"check_max_error_m": 0.01},
        "global EGM96 (F477 + CORRCOEF) with --tolerance 0.01 only",
    ),
    "egm96-default-1mm": (
        ["{shared}/egm96/egm96_to360.ascii.gz", "--correction", "{shared}/egm96/CORRCOEF.gz", "--tolerance", "0.001"],
        {"check_max_error_m": 0.001},
        "global EGM96 (F477 + CORRCOEF) with --tolerance 0.001 only",
    ),
    "egm2008-120-default-1mm": (
        ["{shared}/egm2008/EGM2008_120.gfc", "--tolerance", "0.001"],
        {"check_max_error_m": 0.001},
        "global EGM2008 to degree 120 with --tolerance 0.001 only",
    ),
    "egm2008-120-mm": (
        ["{shared}/egm2008/EGM2008_120.gfc", "--method", "interpolation", "--order", "6",
         "--h0", "0.011", "--max-level", "1", "--tolerance", "0.0008", "--sample-spacing", "0.0833"],
        {"node_max_error_m": 0.001, "check_max_error_m": 0.001, "wall_seconds": 1800},
        "global EGM2008 to degree 120 (ICGEM path, hsynth conventions) at 1 mm: quintic "
        "quasi-interpolation at h = 0.011, least-squares overlays where 5' nodes exceed 0.8 mm",
    ),
}

#: where the scenarios' model files live: the shared data beside the repository
SHARED_DATA = REPO.parent / "shared" / "data"

TABLE_HEADER = (
    "| scenario | workers | coefficients | store bytes | node max m | node RMS m | check max m | check RMS m "
    "| wall s | peak RSS MB | targets |\n"
    "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"
)


def command(name: str) -> str:
    """The console script next to this interpreter, else the one on PATH."""
    local = Path(sys.executable).parent / name
    if local.exists():
        return str(local)
    found = shutil.which(name)
    if not found:
        raise SystemExit(f"{name} not found: install the package (pip install .)")
    return found


class TreeRSS:
    """Peak of the summed RSS of a process and its descendants, sampled (needs psutil)."""

    def __init__(self, pid: int, interval: float = 0.5):
        try:
            import psutil
        except ImportError:
            self.peak_mb = None
            self._thread = None
            return
        self.peak_mb = 0.0
        self._stop = threading.Event()

        def sample():
            try:
                root = psutil.Process(pid)
            except psutil.Error:
                return
            while not self._stop.is_set():
                total = 0
                try:
                    procs = [root] + root.children(recursive=True)
                except psutil.Error:
                    break
                for p in procs:
                    try:
                        total += p.memory_info().rss
                    except psutil.Error:
                        pass
                self.peak_mb = max(self.peak_mb, total / 2**20)
                self._stop.wait(interval)

        self._thread = threading.Thread(target=sample, daemon=True)
        self._thread.start()

    def stop(self):
        if self._thread is not None:
            self._stop.set()
            self._thread.join()


def run_fit(args: list[str], out: Path) -> dict:
    """Run geoid-fit under /usr/bin/time -v; return its JSON summary, wall s and peak RSS."""
    fit_cmd = [command("geoid-fit"), *args, "--store", str(out), "--overwrite", "--json", "-q"]
    gnu_time = Path("/usr/bin/time")
    use_time = gnu_time.exists()
    cmd = [str(gnu_time), "-v", *fit_cmd] if use_time else fit_cmd
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                            text=True)
    tree = TreeRSS(proc.pid)
    stdout, stderr = proc.communicate()
    wall = time.perf_counter() - start
    tree.stop()
    peak_kb = None
    if use_time:
        m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", stderr)
        peak_kb = int(m.group(1)) if m else None
        stderr = "\n".join(ln for ln in stderr.splitlines() if not ln.startswith("\t")
                           and not ln.startswith("Command exited with non-zero status"))
    if peak_kb is None:
        after = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        # the running maximum over all children so far: exact only if this child is the largest yet
        peak_kb = after if after > before else None
    # geoid-fit exits 3 when the tolerance was not reached; the store is still written
    if proc.returncode not in (0, 3):
        raise RuntimeError(f"{' '.join(fit_cmd)} exited {proc.returncode}:\n{stderr.strip()}")
    try:
        summary = json.loads(stdout)
    except json.JSONDecodeError as exc:
        raise RuntimeError(f"geoid-fit --json printed no JSON ({exc}):\n{stdout[:500]}\n{stderr.strip()}") from None
    return {
        "command": fit_cmd,
        "exit_status": proc.returncode,
        "summary": summary,
        "wall_seconds": round(wall, 2),
        "peak_rss_mb": round(peak_kb / 1024, 1) if peak_kb else None,
        "peak_rss_source": "/usr/bin/time -v" if use_time else "getrusage(RUSAGE_CHILDREN)",
        "peak_tree_rss_mb": round(tree.peak_mb, 1) if tree.peak_mb else None,
        "stderr": stderr.strip()[-2000:] or None,
    }


def store_info(store: Path) -> dict:
    proc = subprocess.run([command("geoid-info"), "--store", str(store), "--json"], capture_output=True, text=True,
                          stdin=subprocess.DEVNULL)
    if proc.returncode != 0:
        raise RuntimeError(f"geoid-info {store} --json exited {proc.returncode}: {proc.stderr.strip()}")
    return json.loads(proc.stdout)


def run_scenario(name: str, workers: int, out_dir: Path) -> dict:
    args, targets, description = SCENARIOS[name]
    args = [a.format(shared=SHARED_DATA) for a in args] + ["--workers", str(workers)]
    missing = [a for a in args if str(SHARED_DATA) in a and not Path(a).exists()]
    if missing:
        raise FileNotFoundError(f"scenario {name} needs {', '.join(missing)} (the shared data beside the repository)")
    store = out_dir / name
    fit = run_fit(args, store)
    info = store_info(store)
    figures = {
        "coefficients": info["coefficients"],
        "coefficients_per_level": {str(lv["level"]): lv["coefficients"] for lv in info["levels"]},
        "h_per_level": {str(lv["level"]): lv["h"] for lv in info["levels"]},
        "tiles": info["tiles"],
        "store_bytes": info["bytes"],
        "converged": info["converged"],
        "nodes": info["nodes"],
        "node_max_error_m": info["node_max_error_m"],
        "node_rms_error_m": info["node_rms_error_m"],
        "check_points": info["check_points"],
        "check_truth": info["check_truth"],
        "check_max_error_m": info["max_error_m"],
        "check_rms_error_m": info["rms_error_m"],
        "check_p99_error_m": info["p99_error_m"],
        "fit_seconds": info["fit_seconds"],
        "wall_seconds": fit["wall_seconds"],
        "peak_rss_mb": fit["peak_rss_mb"],
        "peak_rss_source": fit["peak_rss_source"],
        "peak_tree_rss_mb": fit["peak_tree_rss_mb"],
    }
    checks = {}
    for key, limit in targets.items():
        value = figures[key]
        checks[key] = {"limit": limit, "value": value, "met": value is not None and value <= limit}
    return {
        "date": dt.datetime.now(dt.timezone.utc).replace(microsecond=0).isoformat(),
        "git_commit": git_commit(REPO),
        "machine": machine_info(),
        "scenario": name,
        "description": description,
        "workers": workers,
        "command": " ".join(["geoid-fit", *fit["command"][1:]]),
        "exit_status": fit["exit_status"],
        "figures": figures,
        "targets": checks,
        "targets_met": all(c["met"] for c in checks.values()),
    }


def _fmt(value, spec):
    return "n/a" if value is None else format(value, spec)


def table_row(row: dict) -> str:
    f = row["figures"]
    targets = "; ".join(f"{k} {'≤' if c['met'] else '>'} {c['limit']:g}" for k, c in row["targets"].items())
    peak = f["peak_rss_mb"]
    if f["peak_tree_rss_mb"] and row["workers"] > 1:
        peak_s = f"{_fmt(peak, '.0f')} (tree {f['peak_tree_rss_mb']:.0f})"
    else:
        peak_s = _fmt(peak, ".0f")
    return (f"| {row['scenario']} | {row['workers']} | {f['coefficients']:,} | {f['store_bytes']:,} "
            f"| {_fmt(f['node_max_error_m'], '.4f')} | {_fmt(f['node_rms_error_m'], '.4f')} "
            f"| {_fmt(f['check_max_error_m'], '.4f')} | {_fmt(f['check_rms_error_m'], '.4f')} "
            f"| {f['wall_seconds']:.1f} | {peak_s} | {'met' if row['targets_met'] else 'MISSED'}: {targets} |")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenarios", nargs="+", metavar="SCENARIO", help=f"one of: {', '.join(SCENARIOS)}")
    parser.add_argument("--workers", type=int, default=1, help="passed to geoid-fit --workers (default 1)")
    parser.add_argument("--out-dir", type=Path, default=DEFAULT_OUT,
                        help=f"where the stores go, one directory per scenario (default {DEFAULT_OUT.relative_to(REPO)})")
    parser.add_argument("--json", type=Path, default=None, help="also write this run's rows as a JSON list")
    parser.add_argument("--results", type=Path, default=RESULTS, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    unknown = [s for s in args.scenarios if s not in SCENARIOS]
    if unknown:
        parser.error(f"unknown scenario(s) {', '.join(unknown)}; known: {', '.join(SCENARIOS)}")
    if args.workers < 1:
        parser.error("--workers must be at least 1")
    args.out_dir.mkdir(parents=True, exist_ok=True)
    args.results.parent.mkdir(parents=True, exist_ok=True)

    rows, failed = [], False
    print(TABLE_HEADER, flush=True)
    for name in args.scenarios:
        try:
            row = run_scenario(name, args.workers, args.out_dir)
        except (RuntimeError, FileNotFoundError) as exc:
            print(f"| {name} | {args.workers} | FAILED: {str(exc).splitlines()[0]} |", flush=True)
            print(exc, file=sys.stderr)
            failed = True
            continue
        rows.append(row)
        with open(args.results, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(row) + "\n")
        print(table_row(row), flush=True)
        failed |= not row["targets_met"]
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
