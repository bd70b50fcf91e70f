#!/usr/bin/env python3
"""Streaming benchmark: many CSV rows through ``geoid-query --input -``, rows/s and memory.

    python benchmarks/stream_speed.py --store STORE [--rows 10000000] [--repeat 1] [--json OUT]

Writes ``--rows`` random global points (uniform in area, fixed seed) as a ``lat,lon``
CSV file (kept in ``--work-dir``, reused when the row count matches), then runs
``geoid-query --store STORE --input - -q`` under ``/usr/bin/time -v`` with the file on
stdin and stdout to ``/dev/null``, ``--repeat`` times. Recorded per run: wall seconds,
rows per second and peak RSS (the process's "Maximum resident set size"); the median
over repeats is printed. The output is checked once on a 1,000-row prefix: as many rows
out as in, no ``ERROR:`` rows. Appends one JSON row to benchmarks/results/stream.jsonl.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import git_commit, machine_info  # noqa: E402
from fit_benchmark import command  # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results" / "stream.jsonl"


def write_rows(path: Path, rows: int, seed: int = 0, chunk: int = 1_000_000) -> Path:
    """``rows`` random points as ``lat,lon`` CSV (5 decimals), written in chunks."""
    if path.exists() and sum(1 for _ in open(path, "rb")) == rows + 1:
        return path
    rng = np.random.default_rng(seed)
    with open(path, "w", encoding="ascii") as fh:
        fh.write("lat,lon\n")
        for start in range(0, rows, chunk):
            n = min(chunk, rows - start)
            lat = np.degrees(np.arcsin(rng.uniform(-1.0, 1.0, n)))
            lon = rng.uniform(-180.0, 180.0, n)
            np.savetxt(fh, np.column_stack([lat, lon]), fmt="%.5f", delimiter=",")
    return path


def run_once(store: Path, rows_file: Path) -> dict:
    cmd = ["/usr/bin/time", "-v", command("geoid-query"), "--store", str(store), "--input", "-", "-q"]
    with open(rows_file, "rb") as stdin:
        start = time.perf_counter()
        proc = subprocess.run(cmd, stdin=stdin, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"geoid-query exited {proc.returncode}: {proc.stderr[-2000:]}")
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr)
    return {"wall_seconds": round(wall, 2), "peak_rss_mb": round(int(m.group(1)) / 1024, 1) if m else None}


def check_output(store: Path, rows_file: Path, rows: int = 1000) -> None:
    with open(rows_file, encoding="ascii") as fh:
        head = "".join(next(fh) for _ in range(rows + 1))
    proc = subprocess.run([command("geoid-query"), "--store", str(store), "--input", "-", "-q"], input=head,
                          capture_output=True, text=True)
    lines = proc.stdout.splitlines()
    if proc.returncode != 0 or len(lines) != rows + 1 or any(ln.startswith("ERROR") for ln in lines):
        raise SystemExit(f"unexpected output on the first {rows} rows (exit {proc.returncode}): {proc.stderr[-500:]}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--store", type=Path, required=True)
    parser.add_argument("--rows", type=int, default=10_000_000)
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--work-dir", type=Path, default=HERE / "out")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    args.work_dir.mkdir(parents=True, exist_ok=True)
    rows_file = write_rows(args.work_dir / f"rows{args.rows}.csv", args.rows)
    check_output(args.store, rows_file)
    runs = [run_once(args.store, rows_file) for _ in range(args.repeat)]
    wall = statistics.median(r["wall_seconds"] for r in runs)
    row = {
        "date": dt.datetime.now(dt.timezone.utc).replace(microsecond=0).isoformat(),
        "git_commit": git_commit(REPO),
        "machine": machine_info(),
        "store": str(args.store),
        "rows": args.rows,
        "input_bytes": rows_file.stat().st_size,
        "runs": runs,
        "median_wall_seconds": wall,
        "median_rows_per_second": round(args.rows / wall),
        "max_peak_rss_mb": max(r["peak_rss_mb"] or 0 for r in runs),
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    with open(RESULTS, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(row) + "\n")
    if args.json:
        args.json.write_text(json.dumps(row, indent=1) + "\n")
    print(f"{args.rows:,} rows: median {wall:.1f} s wall, {row['median_rows_per_second']:,} rows/s, "
          f"peak RSS {row['max_peak_rss_mb']:.0f} MB ({len(runs)} run(s))")
    return 0


if __name__ == "__main__":
    sys.exit(main())
