"""What answering only inside a store's coverage costs a large batch of queries.

Builds two small stores from the synthetic 2° test field over S 10 W 20 N 30 E 40 (one
from a complete grid, whose coverage is its region, and one with a 3×3-node no-data
hole, whose coverage carries the lattice's no-data mask), then times, for 10^6 random
points inside the region, the spline alone (``store.spline.full.undulation``), the
store's answer with its coverage (``store.undulation``) and ``store.covers`` alone.
Medians of 7 runs, measured in the same process.

    python benchmarks/coverage_overhead.py
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from conftest import make_synthetic_grid

import geoidspline
from geoidspline.api import build_store
from geoidspline.fitting.parameters import FitParameters
from geoidspline.sources.grid import GeoidGrid
from geoidspline.sphere.region import Region


def main(points=1_000_000, repeats=7):
    grid = make_synthetic_grid()
    region = Region(10, 20, 30, 40)
    params = FitParameters(h0=0.2, max_level=2, tolerance_m=0.02, tile_size=1.0)
    values = grid.values.copy()
    lat2, lon2 = np.meshgrid(grid.latitude, grid.longitude, indexing="ij")
    values[(lat2 >= 18) & (lat2 <= 22) & (lon2 >= 28) & (lon2 <= 32)] = np.nan
    holed = GeoidGrid(grid.latitude, grid.longitude, values, grid.provenance)
    rng = np.random.default_rng(0)
    lat, lon = rng.uniform(10, 30, points), rng.uniform(20, 40, points)
    with tempfile.TemporaryDirectory() as tmp:
        for name, source in (("region only", grid), ("with a no-data mask", holed)):
            build_store(source, Path(tmp) / name, region, params, check_count=100)
            store = geoidspline.open_store(Path(tmp) / name)
            store.spline.full.undulation(lat, lon)  # index built, kernels compiled
            spline, answer, covers = [], [], []
            for _ in range(repeats):
                t = time.perf_counter()
                store.spline.full.undulation(lat, lon)
                spline.append(time.perf_counter() - t)
                t = time.perf_counter()
                store.undulation(lat, lon)
                answer.append(time.perf_counter() - t)
                t = time.perf_counter()
                store.covers(lat, lon)
                covers.append(time.perf_counter() - t)
            m = statistics.median
            print(f"{name}: {points:,} points: spline {m(spline):.3f} s, with coverage {m(answer):.3f} s "
                  f"(x{m(answer) / m(spline):.2f}), covers alone {m(covers):.3f} s")


if __name__ == "__main__":
    main()
