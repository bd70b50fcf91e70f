"""Opening a store and building its query index: seconds and peak memory, per store.

    python benchmarks/store_index.py STORE [STORE ...] [--repeat 3]

Each run is a fresh subprocess (so the peak RSS, ``ru_maxrss``, is its own): open the
store, read every tile and build the compiled index (``store.spline.index``), evaluate
one batch so the kernels are loaded; ``--process command`` first pins glibc's mmap
threshold as the geoid-* commands do, ``--process library`` leaves it as a program using
the library does. The first run of a store warms the file cache; the median of the
others is the warm figure. Prints one JSON
line per store: bytes on disk, coefficients, bytes per coefficient, format, open and
index seconds (median of warm runs; reading every tile and building the index apart,
the latter including loading the compiled kernels' library), peak RSS in MB (max over
runs; also after reading alone).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

_CHILD = r"""
import json, resource, sys, time
t0 = time.perf_counter()
import numpy as np
import geoidspline
from geoidspline.store.reader import TileStore
if sys.argv[2] == "command":  # as a geoid-* command does when it starts
    from geoidspline._memory import pin_mmap_threshold
    pin_mmap_threshold()
t1 = time.perf_counter()
store = TileStore.open(sys.argv[1])
store.spline.full
t_read = time.perf_counter()
read_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
index = store.spline.index
t2 = time.perf_counter()
lat = np.linspace(-80, 80, 4096); lon = np.linspace(-179, 179, 4096)
store.undulation(lat, lon)
print(json.dumps({"import_s": t1 - t0, "open_index_s": t2 - t1, "read_s": t_read - t1,
                  "index_s": t2 - t_read, "peak_rss_after_read_mb": read_mb,
                  "index_mb": index.nbytes / 2**20,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def measure(store: Path, repeat: int, process: str) -> dict:
    runs = []
    for _ in range(repeat + 1):
        out = subprocess.run([sys.executable, "-c", _CHILD, str(store), process], capture_output=True, text=True,
                             check=True)
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    manifest = json.loads((store / "manifest.json").read_text())
    size = (store / "manifest.json").stat().st_size + sum(e["bytes"] for e in manifest["tiles"])
    coefficients = manifest["spline"]["coefficients"]
    warm = runs[1:]
    return {
        "store": str(store),
        "process": process,
        "format_version": manifest["format_version"],
        "tiles": len(manifest["tiles"]),
        "bytes": size,
        "coefficients": coefficients,
        "bytes_per_coefficient": round(size / coefficients, 3),
        "open_index_s_median": round(statistics.median(r["open_index_s"] for r in warm), 3),
        "open_index_s_runs": [round(r["open_index_s"], 3) for r in runs],
        "read_s_median": round(statistics.median(r["read_s"] for r in warm), 3),
        "index_s_median": round(statistics.median(r["index_s"] for r in warm), 3),
        "peak_rss_after_read_mb": round(max(r["peak_rss_after_read_mb"] for r in runs), 1),
        "index_mb": round(runs[-1]["index_mb"], 1),
        "peak_rss_mb": round(max(r["peak_rss_mb"] for r in runs), 1),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stores", nargs="+", type=Path)
    parser.add_argument("--repeat", type=int, default=3, help="warm runs per store (after one cold run)")
    parser.add_argument("--process", choices=("library", "command"), default="command",
                        help="a Python program using the library (the allocator left alone), or a geoid-* "
                             "command (glibc's mmap threshold pinned, geoidspline._memory) [command]")
    args = parser.parse_args(argv)
    for store in args.stores:
        print(json.dumps(measure(store, args.repeat, args.process)), flush=True)


if __name__ == "__main__":
    main()
