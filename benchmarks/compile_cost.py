#!/usr/bin/env python3
"""What numba's IR-level inlining of the query helpers costs to compile, and what it buys.

    python benchmarks/compile_cost.py --store STORE [--points 1000000]

The query kernels' small helpers (``geoidspline._kernels._jit.ijit``) are inlined into the
query loop at numba's IR level (``inline="always"``). This benchmark copies the package's
source twice into a temporary folder, once as it is and once with that flag removed (LLVM
may still inline on its own), and for each copy runs one fresh process with an empty
``NUMBA_CACHE_DIR``:

* the CPU seconds until the first 10,000-point batch of ``open_store(STORE).undulation``
  returns (imports, reading the store, the query index, and compiling the query kernels
  for the store's order);
* then the median over 7 batches of N random points uniform on the sphere (seed 1), in ns
  per point, on one thread and on all of numba's threads.

Both variants run in the same invocation, one after the other; the values of the two must
agree to 1e-12 m (the flag changes code generation, not arithmetic).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FLAG = ', inline="always")'

CHILD = r"""
import json, statistics, sys, time
import numpy as np
cpu0, wall0 = time.process_time(), time.perf_counter()
import numba
import geoidspline
store = geoidspline.open_store(sys.argv[1])
n = int(sys.argv[2])
rng = np.random.default_rng(1)
lat = np.degrees(np.arcsin(rng.uniform(-1, 1, n)))
lon = rng.uniform(-180, 180, n)
store.undulation(lat[:10000], lon[:10000])
first = {"cpu_s": time.process_time() - cpu0, "wall_s": time.perf_counter() - wall0}
values = store.undulation(lat, lon)
speed = {}
for threads in sorted({1, numba.config.NUMBA_NUM_THREADS}):
    numba.set_num_threads(threads)
    times = []
    for _ in range(7):
        t = time.perf_counter()
        store.undulation(lat, lon)
        times.append(time.perf_counter() - t)
    speed[threads] = statistics.median(times) / n * 1e9
np.save(sys.argv[3], values)
print(json.dumps({"first": first, "ns_per_point": speed}))
"""


def run_variant(name: str, inline: bool, store: str, points: int, work: Path) -> dict:
    root = work / name
    shutil.copytree(REPO / "geoidspline", root / "geoidspline", ignore=shutil.ignore_patterns("__pycache__"))
    jit = root / "geoidspline" / "_kernels" / "_jit.py"
    text = jit.read_text()
    if FLAG not in text:
        raise SystemExit(f"{jit}: the ijit decorator no longer has {FLAG!r}; update this benchmark")
    if not inline:
        jit.write_text(text.replace(FLAG, ")"))
    env = dict(os.environ, NUMBA_CACHE_DIR=str(root / "cache"), PYTHONPATH=str(root))
    out = subprocess.run([sys.executable, "-c", CHILD, store, str(points), str(root / "values.npy")],
                         env=env, cwd=root, check=True, capture_output=True, text=True).stdout
    result = json.loads(out.strip().splitlines()[-1])
    result["values"] = np.load(root / "values.npy")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", required=True)
    parser.add_argument("--points", type=int, default=1_000_000)
    args = parser.parse_args()
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        rows = {name: run_variant(name, inline, args.store, args.points, Path(tmp))
                for name, inline in (("inline-always", True), ("llvm-only", False))}
    diff = float(np.nanmax(np.abs(rows["inline-always"]["values"] - rows["llvm-only"]["values"])))
    print(f"store {args.store}, {args.points:,} points; load {load_before[0]:.2f} before, {os.getloadavg()[0]:.2f} after")
    print("| variant | first batch CPU s (compile + open + index) | wall s | " +
          " | ".join(f"ns/pt, {t} thread(s)" for t in rows["inline-always"]["ns_per_point"]) + " |")
    print("|---|---:|---:|" + "---:|" * len(rows["inline-always"]["ns_per_point"]))
    for name, r in rows.items():
        print(f"| {name} | {r['first']['cpu_s']:.1f} | {r['first']['wall_s']:.1f} | " +
              " | ".join(f"{v:.1f}" for v in r["ns_per_point"].values()) + " |")
    print(f"largest difference between the two variants' values: {diff:.3g} m")
    if not diff <= 1e-12:
        raise SystemExit("the variants disagree beyond 1e-12 m")


if __name__ == "__main__":
    main()
