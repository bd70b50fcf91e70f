"""Predicted against measured level-0 error: ``geoidspline.fitting.level0_error`` checked
by fits (issue 22 item 3).

    python benchmarks/level0_prediction.py MODEL --region S,W,N,E [--region ...]
        [--tolerance 0.01 0.001] [--points 10000] [--cache DIR] [--json OUT]
        [--correction FILE] [--truth independent|geoidspline]

For each region and tolerance: the parameters ``geoid-fit MODEL --tolerance T --region``
chooses (spectrum-aware), then level 0 alone (``max_level=0``) by the existing engine,
and its max / RMS error at the lattice nodes and at ``--points`` random points in the
region against the independent exact synthesis (``independent_synthesis.py``, cached by
model hash; ``--truth geoidspline`` for EGM96, whose F477 conventions it does not
know), beside the chooser's prediction (max over the sphere, RMS at the worst ring and
grid orientation), the region's own (its rings and longitudes, the extreme over its
area) and the target the chooser aimed at (``choose.LEVEL0_OVER_TOLERANCE`` x T).
One JSON line per fit; the date, commit and load average with it.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
from _common import git_commit, machine_info  # noqa: E402
from independent_synthesis import reference_values, ring_points  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
DEFAULT_CACHE = Path("/work/scratch/egm2008/reference")


def run(model, region_bounds, tolerance, points, cache, correction=None, preset=None, truth_by="independent"):
    import dataclasses

    from geoidspline.fitting import choose, level0_error
    from geoidspline.fitting.driver import fit_source
    from geoidspline.sources.resolve import open_source
    from geoidspline.sphere.region import Region

    source = open_source(model, correction, preset)
    region = Region.from_bounds(*region_bounds)
    choice = choose.choose_parameters(source, tolerance, region)
    params = dataclasses.replace(choice.parameters, max_level=0)
    # the chooser's prediction (the whole sphere's), and the region's own rings and extreme
    predicted_max, predicted_rms = level0_error.predicted_level0(
        level0_error.ModelSpectrum.of(source), params.h0, params.order, 4 * math.pi)
    spectrum = level0_error.ModelSpectrum.of(source, region.south, region.north, region.west, region.east)
    tile_max, tile_rms = level0_error.predicted_level0(spectrum, params.h0, params.order, choose.region_area(region))
    if truth_by == "independent":
        lat, lon, truth, ref_seconds = reference_values(model, region_bounds, points, cache, correction_path=correction)
    else:  # EGM96 (F477 + CORRCOEF): the independent evaluator knows hsynth only
        lat, lon = ring_points(points, 10, region_bounds, 22)
        lat, lon = np.repeat(lat, lon.shape[1]), lon.ravel()
        start = time.perf_counter()
        truth = source.undulation(lat, lon)
        ref_seconds = time.perf_counter() - start
    load = os.getloadavg()[0]
    start = time.perf_counter()
    result = fit_source(source, region, params)
    seconds = time.perf_counter() - start
    errors = result.spline.undulation(lat, lon) - truth
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "commit": git_commit(REPO), "load_1min": load, "model": str(model), "degree": source.max_degree,
        "region": list(region_bounds), "tolerance_m": tolerance, "order": params.order, "h0": params.h0,
        "h_times_degree": params.h0 * source.max_degree,
        "level0_target_mm": choose.LEVEL0_OVER_TOLERANCE * tolerance * 1e3,
        "predicted_max_mm": predicted_max * 1e3, "predicted_rms_mm": predicted_rms * 1e3,
        "region_predicted_max_mm": tile_max * 1e3, "region_predicted_rms_mm": tile_rms * 1e3,
        "node_max_mm": result.node_max_error_m * 1e3, "node_rms_mm": result.node_rms_error_m * 1e3,
        "truth": truth_by, "check_points": int(truth.size), "check_max_mm": float(np.abs(errors).max() * 1e3),
        "check_rms_mm": float(np.sqrt(np.mean(errors**2)) * 1e3),
        "coefficients": int(sum(len(level) for level in result.spline.levels)),
        "fit_s": round(seconds, 1), "reference_s": round(ref_seconds, 1), "machine": machine_info(),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model")
    parser.add_argument("--correction", default=None)
    parser.add_argument("--region", action="append", required=True, help="S,W,N,E in degrees (repeatable)")
    parser.add_argument("--tolerance", type=float, nargs="+", default=[0.01, 0.001])
    parser.add_argument("--points", type=int, default=10_000)
    parser.add_argument("--cache", default=str(DEFAULT_CACHE))
    parser.add_argument("--json", default=None, help="append the rows to this JSONL file")
    parser.add_argument("--truth", choices=("independent", "geoidspline"), default="independent",
                        help="the exact values: the independent synthesis (EGM2008, hsynth) or geoidspline's own "
                             "(EGM96 with F477 and CORRCOEF)")
    args = parser.parse_args(argv)
    for region in args.region:
        bounds = tuple(float(v) for v in region.split(","))
        for tolerance in args.tolerance:
            row = run(args.model, bounds, tolerance, args.points, args.cache, args.correction, truth_by=args.truth)
            line = json.dumps(row)
            print(line, flush=True)
            if args.json:
                with open(args.json, "a", encoding="utf-8") as fh:
                    fh.write(line + "\n")


if __name__ == "__main__":
    main()
