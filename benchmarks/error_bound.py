#!/usr/bin/env python3
"""Error bound: how often ``--with-error`` (``store.error_bound``) bounds the true error.

    python benchmarks/error_bound.py STORE --label NAME [--grid SOURCE] [--model FILE [--correction FILE]]
                                     [--points N] [--seed S] [--json OUT]

For each truth given, the store's error e = N_store − N_truth is measured and compared
with the bound at the same points:

- ``model`` (``--model``): the exact spherical-harmonic synthesis at N random points
  uniform in area over the store's coverage (seed ``--seed``; the store's own check
  points used seed 0, so these are other points);
- ``grid-random`` (``--grid``): the grid's bicubic interpolation at N such random points;
- ``grid-nodes``: every node of the grid inside the coverage;
- ``grid-centres``: every cell centre inside the coverage, against the bicubic
  interpolation (the points the store's own check figures were measured at).

For each it records the fraction of points with |e| <= bound for the bound of this
version (``tile_error_bound``: F m + u) and for the bound before it (the tile's
check-point maximum alone, ``legacy``), the fractions for other safety factors F, the
quantiles of |e| / m with m the largest error measured near the point
(``nearby_measured_error``) and u the grid term (``grid_interpolation_uncertainty``),
and the factor m would need for 99.9 % and for 100 % of the points. One JSON row per truth is
appended to ``--json`` (default benchmarks/results/error_bound.jsonl).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import git_commit, machine_info  # noqa: E402

import geoidspline  # noqa: E402
from geoidspline.store import error_bound as derived  # noqa: E402
from geoidspline.sphere.coordinates import directions  # noqa: E402
from geoidspline.sphere.region import Region  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def legacy_bound(store, lat, lon):
    """The bound before this version: the tile's check-point maximum (NaN: none)."""
    size = float(store.manifest["spline"]["tile_size"])
    table = {tuple(e["tile"]): e.get("max_error_m") for e in store.manifest["tiles"]}
    tiles = np.floor(directions(lat, lon) / size).astype(np.int64)
    out = np.array([table.get(tuple(t)) for t in tiles.tolist()], dtype=object)
    return np.array([np.nan if v is None else float(v) for v in out])


def random_points(store, count, seed):
    """``count`` points uniform in area over the store's region, inside its coverage."""
    region = Region(*store.manifest["region"])
    rng = np.random.default_rng(seed)
    lat_parts, lon_parts = [], []
    have = 0
    while have < count:
        z_lo, z_hi = math.sin(math.radians(region.south)), math.sin(math.radians(region.north))
        lat = np.degrees(np.arcsin(rng.uniform(z_lo, z_hi, count)))
        lon = region.west + rng.uniform(0.0, region.longitude_span, count)
        keep = np.asarray(store.covers(lat, lon), dtype=bool)
        lat_parts.append(lat[keep])
        lon_parts.append(lon[keep])
        have += int(keep.sum())
    return np.concatenate(lat_parts)[:count], np.concatenate(lon_parts)[:count]


def grid_points(store, grid, centres):
    """The grid's nodes (or cell centres) inside the store's coverage, with the truth."""
    region = Region(*store.manifest["region"])
    sample = grid.nodes(region)
    lat, lon = sample.latitude, sample.longitude
    if centres:
        lat = lat[:-1] + 0.5 * np.diff(lat)
        lon = lon[:-1] + 0.5 * np.diff(lon)
    lat2, lon2 = np.meshgrid(lat, lon, indexing="ij")
    lat2, lon2 = lat2.ravel(), lon2.ravel()
    truth = grid.undulation(lat2, lon2) if centres else np.asarray(sample.undulation, dtype=float).ravel()
    keep = np.isfinite(truth) & np.asarray(store.covers(lat2, lon2), dtype=bool)
    return lat2[keep], lon2[keep], truth[keep]


#: Safety factors whose held fractions are recorded beside the one in use.
FACTORS = (1.0, 1.1, 1.25, 1.5, 2.0)


def measure(store, lat, lon, truth):
    error = np.abs(np.asarray(store.undulation(lat, lon), dtype=float) - truth)
    bound = np.asarray(derived.tile_error_bound(store, lat, lon), dtype=float)
    nearby = np.asarray(derived.nearby_measured_error(store, lat, lon), dtype=float)
    grid_term = np.asarray(derived.grid_interpolation_uncertainty(store, lat, lon), dtype=float)
    legacy = legacy_bound(store, lat, lon)
    ratio = error / nearby
    beyond_grid_term = np.maximum(error - grid_term, 0.0) / nearby
    quantiles = {f"q{q}": float(np.quantile(ratio, q / 100.0)) for q in (50, 99, 99.9, 99.99)}
    return {
        "points": int(error.size),
        "error_max_m": float(error.max()),
        "error_rms_m": float(np.sqrt(np.mean(error**2))),
        "error_p999_m": float(np.quantile(error, 0.999)),
        "bound_factor": derived.ERROR_BOUND_FACTOR,
        "bound_min_m": float(np.nanmin(bound)),
        "bound_median_m": float(np.nanmedian(bound)),
        "bound_max_m": float(np.nanmax(bound)),
        "bound_nan": int(np.isnan(bound).sum()),
        "grid_term_max_m": float(np.nanmax(grid_term)),
        "held_fraction": float(np.mean(error <= bound)),
        "held_count": int(np.sum(error <= bound)),
        "legacy_held_fraction": float(np.mean(error <= legacy)),
        "legacy_nan": int(np.isnan(legacy).sum()),
        "held_by_factor": {f"{f:g}": float(np.mean(error <= f * nearby + grid_term)) for f in FACTORS},
        "held_by_factor_without_grid_term": {f"{f:g}": float(np.mean(error <= f * nearby)) for f in FACTORS},
        "ratio_to_nearby": {**quantiles, "max": float(ratio.max())},
        "factor_for_99_9": float(np.quantile(ratio, 0.999)),
        "factor_for_all": float(ratio.max()),
        "factor_for_all_with_grid_term": float(beyond_grid_term.max()),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("store")
    parser.add_argument("--label", required=True)
    parser.add_argument("--grid", help="the store's source grid (file or catalogue name)")
    parser.add_argument("--model", help="a spherical-harmonic model file (exact truth)")
    parser.add_argument("--correction")
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=20261129)
    parser.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "error_bound.jsonl"))
    args = parser.parse_args(argv)

    store = geoidspline.open_store(args.store, lazy=False)
    base = {
        "date": dt.date.today().isoformat(),
        "commit": git_commit(REPO),
        "machine": machine_info(),
        "store": args.label,
        "store_region": store.manifest["region"],
        "store_tolerance_m": store.manifest["fit"]["tolerance_m"],
        "store_source": store.manifest["provenance"].get("source"),
        "store_check_max_m": store.manifest["accuracy"]["max_error_m"],
        "store_node_max_m": store.manifest["accuracy"]["node_max_error_m"],
        "command": "python benchmarks/error_bound.py " + " ".join(sys.argv[1:] if argv is None else argv),
    }
    cases = []
    if args.model:
        from geoidspline.sources.resolve import load_synthesis

        synthesis = load_synthesis(args.model, args.correction, None, like_store=store)
        lat, lon = random_points(store, args.points, args.seed)
        started = time.perf_counter()
        truth = np.asarray(synthesis.undulation(lat, lon), dtype=float)
        cases.append(("model", lat, lon, truth, f"exact synthesis ({Path(args.model).name}"
                      f"{' + ' + Path(args.correction).name if args.correction else ''}), "
                      f"{args.points} random points ({time.perf_counter() - started:.0f} s)"))
    if args.grid:
        from geoidspline.sources.resolve import open_source

        grid = open_source(args.grid)
        lat, lon = random_points(store, args.points, args.seed + 1)
        cases.append(("grid-random", lat, lon, grid.undulation(lat, lon),
                      f"bicubic interpolation of {args.grid} at {args.points} random points"))
        cases.append(("grid-nodes", *grid_points(store, grid, centres=False), f"every node of {args.grid}"))
        cases.append(("grid-centres", *grid_points(store, grid, centres=True),
                      f"every cell centre of {args.grid}, bicubic"))
    rows = []
    for name, lat, lon, truth, what in cases:
        row = {**base, "truth": name, "truth_description": what, **measure(store, lat, lon, truth)}
        rows.append(row)
        print(f"{args.label:12s} {name:12s} {row['points']:8d} points  max |e| {row['error_max_m']:.4f} m  "
              f"bound {row['bound_min_m']:.4f}..{row['bound_max_m']:.4f} m held {100 * row['held_fraction']:.4f} % "
              f"(before: {100 * row['legacy_held_fraction']:.4f} %)  |e|/nearby q99.9 {row['factor_for_99_9']:.3f} "
              f"max {row['factor_for_all']:.3f} (beyond the grid term {row['factor_for_all_with_grid_term']:.3f})")
    with open(args.json, "a", encoding="utf-8") as fh:
        for row in rows:
            fh.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
