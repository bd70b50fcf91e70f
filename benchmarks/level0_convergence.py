"""Level-0 convergence of quasi-interpolation against h·N: the table behind
``geoidspline.fitting.choose.LEVEL0_ERROR``.

    python benchmarks/level0_convergence.py ORDER:H0 [ORDER:H0 ...]
    python benchmarks/level0_convergence.py --calibrate

``--calibrate`` prints ``geoidspline.fitting.level0_error.KAPPA`` from that table
(``choose.LEVEL0_ERROR``) and EGM96's own spectrum: per measured point, the error ratio
to the upper half of degrees and the measured global max over the predicted RMS and
√(2 ln M).

EGM96 (F477 + CORRCOEF, from the shared data beside the repository), level 0 alone
(``max_level=0``, ``method="interpolation"``) over 25..35N 80..95E (the Himalaya, the
steepest geoid). One JSON line per fit: level-0 coefficients in the region, the max
|error| at the 5' nodes, and max/RMS at 5,000 random points against the exact synthesis.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from geoidspline.fitting.check_points import check_points
from geoidspline.fitting.driver import fit_source
from geoidspline.fitting.parameters import FitParameters
from geoidspline.sources.resolve import open_source
from geoidspline.sphere.region import Region

# the shared data beside the repository, or $GEOIDSPLINE_TEST_DATA (as the tests find it)
DATA = Path(os.environ.get("GEOIDSPLINE_TEST_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data") / "egm96"
REGION = Region.from_bounds(25, 80, 35, 95)


def calibrate():
    import math

    from geoidspline.fitting import choose, level0_error

    source = open_source(DATA / "egm96_to360.ascii.gz", DATA / "CORRCOEF.gz")
    spectrum = level0_error.ModelSpectrum.of(source)
    upper = spectrum.upper_half_rms_m()
    table = {}
    for order, points in choose.LEVEL0_ERROR.items():
        rows = []
        for h_n, regional_max in points:
            h = h_n / source.max_degree
            rms, n_eff = level0_error._rms_and_degree(spectrum, h, order, level0_error.prefilter_terms(order))
            global_max = regional_max * choose.GLOBAL_OVER_REGIONAL
            kappa = global_max / (rms * level0_error.extreme_factor(4 * math.pi, n_eff))
            rows.append((float(f"{rms / upper:.6f}"), round(kappa, 4)))
        table[order] = tuple(rows)
    print(json.dumps(table))


def main(specs):
    if specs == ["--calibrate"]:
        return calibrate()
    source = open_source(DATA / "egm96_to360.ascii.gz", DATA / "CORRCOEF.gz")
    check = check_points(source, REGION, count=5000, seed=3)
    for spec in specs:
        order, h0 = int(spec.split(":")[0]), float(spec.split(":")[1])
        start = time.perf_counter()
        params = FitParameters(order=order, h0=h0, max_level=0, tolerance_m=1e-6, method="interpolation")
        result = fit_source(source, REGION, params)
        errors = result.spline.undulation(check.latitude, check.longitude) - check.truth
        print(json.dumps({
            "order": order, "h": h0, "hN": h0 * source.max_degree, "coef": len(result.spline.levels[0]),
            "node_max_mm": result.node_max_error_m * 1e3, "check_max_mm": float(np.abs(errors).max() * 1e3),
            "check_rms_mm": float(np.sqrt(np.mean(errors**2)) * 1e3), "s": round(time.perf_counter() - start, 1),
        }), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
