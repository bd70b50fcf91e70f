"""Compile every numba kernel into numba's on-disk cache, ahead of the first real use.

    geoid-warmup            # compile (or load) every kernel, print a table
    geoid-warmup --check    # exit 1 if any kernel had to be compiled

(``python -m geoidspline.warmup`` is the same, but run from a directory holding a
``geoidspline`` source tree, such as the repository root, it imports and warms up that
tree instead of the installed package; numba keys its cache on the source file's path.)

The kernels (:data:`KERNEL_MODULES`) are compiled on first use and kept by numba's
cache (``cache=True``): in ``__pycache__`` beside the installed sources, or in
``$NUMBA_CACHE_DIR`` when that is set. An empty cache costs minutes of
compilation on the first fit or large query of a process; this module pays it once, at
install time (the README's set-up command, the Dockerfile), by running the package's own
code paths on tiny synthetic inputs: a least-squares grid fit with one overlay level, a
quasi-interpolation fit of a small spherical-harmonic model, large-batch queries and
a large coverage lookup against a no-data mask.
Every kernel is therefore compiled for exactly the argument types real use passes
(dtypes, layouts and read-only flags are part of a numba signature), and
:func:`warm_up` checks that no public kernel was left out.

A cache entry is valid for the same source file (path, modification time, size), numba
version and CPU model; anything else recompiles (once) on first use, as without this
step. ``--check`` in a fresh process after the warm-up proves the cache is usable.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time

import numpy as np

#: Modules holding numba kernels (every public dispatcher in them is warmed up).
KERNEL_MODULES = (
    "geoidspline._kernels.common",
    "geoidspline._kernels.coverage",
    "geoidspline._kernels.fitting",
    "geoidspline._kernels.interpolation",
    "geoidspline._kernels.legendre",
)


def kernel_dispatchers() -> dict[str, object]:
    """Every numba dispatcher defined in :data:`KERNEL_MODULES`, by qualified name.

    Private helpers (leading underscore) are only called from other kernels and are
    compiled into them; they are listed too, so a report shows what was compiled on its
    own, but :func:`warm_up` requires signatures of the public ones only.
    """
    from numba.core.registry import CPUDispatcher

    found = {}
    for module_name in KERNEL_MODULES:
        module = importlib.import_module(module_name)
        for name, obj in vars(module).items():
            if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == module_name:
                found[f"{module_name}.{name}"] = obj
    return found


def _smooth_field(latitude, longitude):
    """A smooth synthetic undulation field (metres) with structure at a few scales."""
    phi = np.radians(latitude)
    lam = np.radians(longitude)
    return 20.0 * np.sin(3.0 * phi) * np.cos(2.0 * lam) + 3.0 * np.cos(17.0 * phi + 11.0 * lam)


def _grid_fit():
    """A least-squares fit of a small synthetic grid, refined once (level 0 + overlay)."""
    from .fitting.driver import fit_source
    from .fitting.parameters import FitParameters
    from .sources.base import Provenance
    from .sources.grid import GeoidGrid
    from .sphere.region import Region

    lat = np.arange(-10.0, 10.01, 0.25)
    lon = np.arange(20.0, 40.01, 0.25)
    grid = GeoidGrid(lat, lon, _smooth_field(lat[:, None], lon[None, :]),
                     Provenance(source="geoidspline.warmup synthetic grid"))
    params = FitParameters(h0=0.1, max_level=1, tolerance_m=1e-6)
    return fit_source(grid, Region(-4.0, 26.0, 4.0, 34.0), params)


def _model_fit():
    """A quasi-interpolation fit of a small spherical-harmonic model and its exact
    synthesis at scattered points (the check points of a model fit)."""
    from .fitting.driver import fit_source
    from .fitting.parameters import FitParameters
    from .sources.harmonics.models import HarmonicModel
    from .sources.harmonics.synthesis import GeoidSynthesis
    from .sphere.region import Region

    nmax = 12
    rng = np.random.default_rng(12)
    # a geoid-like model: small random coefficients (tens of metres of N) on the normal
    # field's zonals, which a synthesis subtracts (random zonals alone would be km of N)
    C = np.tril(rng.normal(scale=3e-7, size=(nmax + 1, nmax + 1)))
    S = np.tril(rng.normal(scale=3e-7, size=(nmax + 1, nmax + 1)))
    S[:, 0] = 0.0
    C[1, :] = S[1, :] = 0.0
    C[2, 0] += -0.484166774985e-3
    C[4, 0] += 0.790304073e-6
    C[0, 0] = 1.0
    model = HarmonicModel(name="warmup", gm=3.986004418e14, radius=6378137.0, max_degree=nmax,
                          tide_system="tide_free", C=C, S=S)
    synthesis = GeoidSynthesis(model, preset="generic")
    params = FitParameters(h0=0.1, max_level=0, tolerance_m=1.0, method="interpolation", sample_spacing_deg=1.0)
    fit_source(synthesis, Region(-5.0, 10.0, 5.0, 20.0), params)
    synthesis.undulation(np.linspace(-5.0, 5.0, 16), np.linspace(10.0, 20.0, 16))


def _queries(spline):
    """Large-batch queries of a fitted spline: values, gradients and Hessians."""
    from .hierarchy.ambient import FOLDED_FROM_POINTS
    from .bspline.index import _ORDER_THRESHOLD
    from .sphere.coordinates import directions

    rng = np.random.default_rng(3)
    count = max(FOLDED_FROM_POINTS, _ORDER_THRESHOLD)
    latitude = rng.uniform(-4.0, 4.0, count)
    longitude = rng.uniform(26.0, 34.0, count)
    spline.undulation(latitude, longitude)
    points = directions(latitude, longitude)
    for nderiv in (0, 1, 2):
        spline.evaluate_points(points, nderiv=nderiv)


def _coverage_lookup():
    """A large batch against a coverage with a no-data mask (a national grid's sea)."""
    from .sphere.sample import NodeSample
    from .sphere.coordinates import COMPILED_FROM_POINTS
    from .sphere.coverage import Coverage
    from .sphere.region import Region

    lat = np.arange(-2.0, 2.01, 0.5)
    lon = np.arange(30.0, 34.01, 0.5)
    values = np.ones((lat.size, lon.size))
    values[4, 4] = np.nan
    coverage = Coverage.from_sample(NodeSample(lat, lon, values), Region(-2.0, 30.0, 2.0, 34.0))
    rng = np.random.default_rng(4)
    coverage.covers(rng.uniform(-2.0, 2.0, COMPILED_FROM_POINTS), rng.uniform(30.0, 34.0, COMPILED_FROM_POINTS))


def _legendre_table():
    """:func:`~geoidspline._kernels.legendre.plm_bar`, public but not on a fit's path."""
    from ._kernels import legendre

    nmax = 4
    AT, BT = legendre.recursion_tables(nmax)
    legendre.plm_bar(nmax, 0.5, float(np.sqrt(0.75)), AT, BT, np.zeros((nmax + 1, nmax + 1)))


def _cache_counts(dispatchers):
    return {name: (sum(d.stats.cache_hits.values()), sum(d.stats.cache_misses.values()))
            for name, d in dispatchers.items()}


def warm_up() -> dict:
    """Run every kernel once; return what was loaded from and compiled into the cache.

    ``{"seconds": ..., "cache": path or None, "kernels": {name: {"signatures": n,
    "loaded": hits, "compiled": misses}}}``; ``compiled`` counts compilations of a
    kernel called on its own (helpers compiled into a caller are not counted).
    Raises RuntimeError when, with nothing in the cache (so that kernels called only
    from other kernels are compiled on their own too), a public kernel was never
    compiled: this module is then out of date with the package's code paths.
    """
    started = time.perf_counter()
    result = _grid_fit()
    _queries(result.spline)
    _model_fit()
    _coverage_lookup()
    _legendre_table()
    seconds = time.perf_counter() - started
    dispatchers = kernel_dispatchers()
    counts = _cache_counts(dispatchers)
    missing = [name for name, d in dispatchers.items()
               if not d.signatures and not name.rsplit(".", 1)[1].startswith("_")]
    if missing and not any(hits for hits, _ in counts.values()):
        raise RuntimeError(f"geoidspline.warmup did not reach these kernels: {', '.join(missing)}")
    cache = next((d.stats.cache_path for d in dispatchers.values() if d.stats.cache_path), None)
    kernels = {name: {"signatures": len(d.signatures), "loaded": counts[name][0], "compiled": counts[name][1]}
               for name, d in dispatchers.items() if d.signatures}
    return {"seconds": seconds, "cache": cache, "kernels": kernels}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="geoid-warmup",
        description="Compile geoidspline's numba kernels into numba's cache (once per install).",
    )
    parser.add_argument("--check", action="store_true",
                        help="exit 1 if any kernel had to be compiled (the cache was missing or invalid)")
    parser.add_argument("-q", "--quiet", action="store_true", help="print only the summary line")
    args = parser.parse_args(argv)
    report = warm_up()
    compiled = sum(k["compiled"] for k in report["kernels"].values())
    loaded = sum(k["loaded"] for k in report["kernels"].values())
    if not args.quiet:
        for name, k in sorted(report["kernels"].items()):
            print(f"{name:55s} {k['signatures']} signature(s), {k['loaded']} loaded, {k['compiled']} compiled")
    print(f"geoidspline kernels: {compiled} compiled, {loaded} loaded from the cache in {report['seconds']:.1f} s "
          f"(cache: {report['cache'] or 'none'})")
    if args.check and compiled:
        print("ERROR: kernels had to be compiled: the compile cache is missing or not valid here", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
