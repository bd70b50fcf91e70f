#!/usr/bin/env python3
"""Between the nodes (issue 21, item 3): how far a grid fit leaves the interval of the
grid's bilinear and bicubic interpolants at its cell centres, per way of fitting.

    python benchmarks/cell_centres.py T [T...] [--variant NAME ...] [--region S W N E]

Fits egm96-15 (PROJ's GTX) over the region (default: the Andes, -60 -90 15 -30) with
the parameters chosen for the tolerance, in process, with the cell-centre
pseudo-observations of :mod:`geoidspline.fitting.cell_centres` switched per variant:

- ``nodes``: the nodes only (no pseudo-observations; the fit before issue 21 item 3);
- ``centres`` (the package's rule): the leaves of levels finer than
  ``CELL_CENTRE_SPACINGS`` node spacings take every centre as a site (weight 1), and a
  centre outside its interval by more than the target marks its B-splines for refinement;
- ``all-W``: every cell centre a site of weight W on every level from the first step
  (centres outside still mark).

The check is **independent of the fit**: the GTX file is read with numpy
(``fit_matrix.read_gtx``), the bilinear (mean of the 4 corners) and Catmull-Rom bicubic
(weights -1/16, 9/16, 9/16, -1/16 per axis) values are formed at every cell centre in
the region, and the fitted spline (not quantised) is evaluated there. One JSON line per
fit goes to benchmarks/results/cell_centres.jsonl.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import git_commit, machine_info  # noqa: E402
from fit_matrix import PROJ_EGM96, read_gtx  # noqa: E402

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "cell_centres.jsonl"
ANDES = (-60.0, -90.0, 15.0, -30.0)
CATMULL_ROM = np.array([-1.0, 9.0, 9.0, -1.0]) / 16.0
#: the package's CELL_CENTRE_SPACINGS, read before any variant changes it
SPACINGS = None


def centre_intervals(latitude, longitude, values, region):
    """Cell centres of a global lattice inside ``region`` and (low, high) of the
    bilinear and bicubic interpolants there (numpy only)."""
    south, west, north, east = region
    dlon = longitude[1] - longitude[0]
    ncol = int(round(360.0 / dlon))
    centre_lat = latitude[:-1] + 0.5 * (latitude[1] - latitude[0])
    centre_lon = longitude[:ncol] + 0.5 * dlon
    lon_in = np.flatnonzero(np.mod(centre_lon - west, 360.0) <= (east - west))
    lat_in = np.flatnonzero((centre_lat >= south) & (centre_lat <= north))
    lat_in = lat_in[(lat_in >= 1) & (lat_in + 2 < latitude.size)]
    rows = lat_in[:, None] + np.arange(-1, 3)
    cols = (lon_in[:, None] + np.arange(-1, 3)) % ncol
    block = values[rows[:, None, :, None], cols[None, :, None, :]]
    bicubic = np.einsum("abij,i,j->ab", block, CATMULL_ROM, CATMULL_ROM)
    bilinear = block[:, :, 1:3, 1:3].mean(axis=(2, 3))
    lat2, lon2 = np.meshgrid(centre_lat[lat_in], centre_lon[lon_in], indexing="ij")
    ok = np.isfinite(bicubic) & np.isfinite(bilinear)
    return lat2[ok], lon2[ok], np.minimum(bicubic, bilinear)[ok], np.maximum(bicubic, bilinear)[ok]


def outside_interval(spline, region):
    from geoidspline.sphere.coordinates import directions

    lat, lon, low, high = centre_intervals(*read_gtx(PROJ_EGM96), region)
    values = spline.evaluate_points(directions(lat, lon))
    return np.maximum(np.maximum(low - values, values - high), 0.0)


def configure(variant):
    """Module switches for a variant (see the module docstring)."""
    from geoidspline.fitting import hierarchical

    global SPACINGS
    SPACINGS = hierarchical.CELL_CENTRE_SPACINGS if SPACINGS is None else SPACINGS
    hierarchical.CELL_CENTRE_WEIGHT = 1.0
    hierarchical.CELL_CENTRE_SPACINGS = SPACINGS
    if variant.startswith("all-"):
        hierarchical.CELL_CENTRE_WEIGHT = float(variant[4:])
        hierarchical.CELL_CENTRE_SPACINGS = float("inf")
    return variant != "nodes"


def run(tolerance, variant, region):
    from geoidspline.fitting import driver
    from geoidspline.fitting.choose import choose_parameters
    from geoidspline.sources.resolve import open_source
    from geoidspline.sphere.region import Region

    use_centres = configure(variant)
    source = open_source("egm96-15")
    fit_region = Region(*region)
    params = choose_parameters(source, tolerance, fit_region).parameters
    started = time.perf_counter()
    sample = source.nodes(driver.clip_to_extent(fit_region.expanded(driver.support_margin_deg(params)), source))
    result = driver.fit_nodes(sample, fit_region, params, cell_centres=use_centres)
    seconds = time.perf_counter() - started
    outside = outside_interval(result.spline, region)
    return {
        "tolerance_m": tolerance, "variant": variant, "region": list(region),
        "coefficients": result.spline.coefficient_count,
        "per_level": [len(level) for level in result.spline.levels], "fit_s": round(seconds, 1),
        "node_max_m": result.node_max_error_m, "converged": bool(result.converged),
        "cell_centre_max_m": float(outside.max()), "cell_centre_max_per_T": float(outside.max() / tolerance),
        "cell_centre_p99_m": float(np.quantile(outside, 0.99)),
        "cells_outside_T": int((outside > tolerance).sum()), "cells": int(outside.size),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tolerances", nargs="+", type=float)
    parser.add_argument("--variant", action="append", default=None,
                        help="nodes, centres, all-W (default: nodes and centres)")
    parser.add_argument("--region", nargs=4, type=float, default=ANDES, metavar=("S", "W", "N", "E"))
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args(argv)
    for tolerance in args.tolerances:
        for variant in args.variant or ["nodes", "centres"]:
            load = os.getloadavg()[0]
            row = run(tolerance, variant, tuple(args.region))
            row.update({"date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                        "commit": git_commit(HERE.parent), "load_before": round(load, 2),
                        "load_after": round(os.getloadavg()[0], 2), "machine": machine_info()})
            print(json.dumps(row), flush=True)
            if not args.no_record:
                RESULTS.parent.mkdir(parents=True, exist_ok=True)
                with RESULTS.open("a", encoding="utf-8") as fh:
                    fh.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
