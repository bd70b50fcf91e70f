"""Before/after check of a restructuring: the Andes headline fit and a 1,000,000-point
query, with digests of every coefficient and every value, so two trees (old and new
layout) can be compared bit for bit and timed in the same run.

    git worktree add /tmp/old <commit>
    for i in 1 2 3; do for tree in /tmp/old .; do PYTHONPATH=$tree python benchmarks/restructure_check.py; done; done

Needs PROJ's egm96_15.gtx in /usr/share/proj (Debian's proj-data).
"""
import hashlib, time, json
import numpy as np
try:
    from geoidspline.api import build_store  # new layout
    from geoidspline.sources.resolve import resolve_source
    from geoidspline.sphere.region import Region
    from geoidspline.fitting.parameters import FitParameters
except ImportError:
    from geoidspline.build import build_store
    from geoidspline.catalogue import resolve_source
    from geoidspline.region import Region
    from geoidspline.fit import FitParameters
import tempfile
src = resolve_source("/usr/share/proj/egm96_15.gtx")
out = tempfile.mkdtemp() + "/s"
t = time.perf_counter()
result, info = build_store(src, out, Region(-60, -90, 15, -30), FitParameters(tolerance_m=0.5))
wall = time.perf_counter() - t
h = hashlib.sha256()
for lv in result.spline.levels:
    h.update(lv.keys.tobytes()); h.update(lv.coefficients.tobytes())
print(json.dumps({"wall_s": round(wall, 2), "coefficients": info["coefficients"], "node_max": info["node_max_error_m"], "digest": h.hexdigest()[:16]}))
# query: 1,000,000 random global points on the store just written (folded index, all threads)
try:
    from geoidspline.store.reader import TileStore
except ImportError:
    from geoidspline.store import TileStore
store = TileStore.open(out)
rng = np.random.default_rng(1)
lat = np.degrees(np.arcsin(rng.uniform(-1, 1, 1_000_000))); lon = rng.uniform(-180, 180, 1_000_000)
store.undulation(lat[:4096], lon[:4096])
times = []
for _ in range(5):
    t = time.perf_counter(); v = store.undulation(lat, lon); times.append(time.perf_counter() - t)
print(json.dumps({"query_ns_per_point_median": round(sorted(times)[2] * 1e9 / lat.size, 1), "query_digest": hashlib.sha256(np.nan_to_num(v).tobytes()).hexdigest()[:16]}))
