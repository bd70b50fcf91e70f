"""Level-0 convergence of quasi-interpolation against h*N: the table behind fitting.choose.LEVEL0_ERROR.

Usage: python benchmarks/level0_convergence.py ORDER:H [ORDER:H ...]  (EGM96 F477 + CORRCOEF from ../shared/data;
region 25..35N 80..95E; one JSON line per fit: node max at the 5' lattice, max/RMS at 5000 random exact points).
"""
import sys, time, json, numpy as np
from geoidspline.sources.resolve import open_source
from geoidspline.fitting.parameters import FitParameters
from geoidspline.fitting.driver import fit_source
from geoidspline.fitting.check_points import check_points
from geoidspline.sphere.region import Region
from pathlib import Path
D = str(Path(__file__).resolve().parents[2] / "shared" / "data" / "egm96") + "/"
src = open_source(D+"egm96_to360.ascii.gz", D+"CORRCOEF.gz")
region = Region.from_bounds(25, 80, 35, 95)   # Himalaya / Tibet edge, steepest
chk = check_points(src, region, count=5000, seed=3)
for order, h in [(int(a), float(b)) for a, b in (x.split(":") for x in sys.argv[1:])]:
    t = time.perf_counter()
    p = FitParameters(order=order, h0=h, max_level=0, tolerance_m=1e-6, method="interpolation", tile_size=0.4)
    r = fit_source(src, region, p)
    pts_err = r.spline.undulation(chk.latitude, chk.longitude) - chk.truth
    row = dict(order=order, h=h, hN=h*360, coef=len(r.spline.levels[0]), node_max_mm=r.node_max_error_m*1e3,
               check_max_mm=float(np.abs(pts_err).max()*1e3), check_rms_mm=float(np.sqrt(np.mean(pts_err**2))*1e3),
               s=round(time.perf_counter()-t,1))
    print(json.dumps(row), flush=True)
