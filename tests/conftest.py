"""Shared fixtures: a synthetic global geoid grid, its GTX file, and one small store.

The grid samples an analytic, low-degree field (metres) at 2° spacing, so every fit
here is tiny; the session store is built once (about a second) and reused read-only.
Tests that damage a store work on a copy (the ``store_copy`` fixture).
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from geoidspline.api import build_store
from geoidspline.fitting.driver import FitResult
from geoidspline.fitting.parameters import FitParameters
from geoidspline.sources.base import Provenance
from geoidspline.sources.formats import read_grid, write_gtx
from geoidspline.sources.grid import GeoidGrid
from geoidspline.sphere.region import Region

#: Node spacing of the synthetic grid, degrees.
SPACING_DEG = 2.0
#: The region of the session store: S W N E in degrees.
STORE_REGION = (10.0, 20.0, 30.0, 40.0)
#: Fit parameters of the session store. The field is smooth, so the tolerance is tight
#: (2 mm) to make the fit refine beyond level 0; max_level 2 leaves room to converge.
STORE_PARAMS = dict(h0=0.2, max_level=2, tolerance_m=0.002)


def analytic_undulation(lat, lon):
    """N = 20 sin(2φ) cos(λ) + 10 cos²φ sin(2λ) + 5 (metres), φ/λ in degrees."""
    phi, lam = np.radians(lat), np.radians(lon)
    return 20.0 * np.sin(2 * phi) * np.cos(lam) + 10.0 * np.cos(phi) ** 2 * np.sin(2 * lam) + 5.0


def make_synthetic_grid() -> GeoidGrid:
    lat = np.arange(-90.0, 90.0 + SPACING_DEG / 2, SPACING_DEG)
    lon = np.arange(-180.0, 180.0, SPACING_DEG)
    values = analytic_undulation(lat[:, None], lon[None, :])
    # float32-representable, so a GTX round trip keeps the values exactly
    values = values.astype(np.float32).astype(np.float64)
    return GeoidGrid(lat, lon, values, Provenance(source="synthetic", model="synthetic", kind="grid"))


@pytest.fixture(scope="session")
def synthetic_grid() -> GeoidGrid:
    """The analytic field on a global 2° grid (91 x 180 nodes, periodic in longitude)."""
    return make_synthetic_grid()


@pytest.fixture
def synthetic_gtx(tmp_path, synthetic_grid) -> Path:
    """The synthetic grid written as a PROJ GTX file in this test's tmp_path."""
    return write_gtx(tmp_path / "synthetic.gtx", synthetic_grid)


@dataclass(frozen=True)
class SmallStore:
    """The session store and what made it."""

    path: Path  # the store directory (read-only: use the store_copy fixture to modify)
    gtx: Path  # the GTX file the store was fitted from
    grid: GeoidGrid  # that file read back (provenance with sha256)
    region: Region
    params: FitParameters
    result: FitResult
    info: dict  # build_store's summary
    stored: object  # the spline the store holds: result.spline quantised (format 2)


@pytest.fixture(scope="session")
def small_store(tmp_path_factory) -> SmallStore:
    """A store fitted once per session from the synthetic GTX over STORE_REGION."""
    base = tmp_path_factory.mktemp("small_store")
    gtx = write_gtx(base / "synthetic.gtx", make_synthetic_grid())
    grid = read_grid(gtx)
    region = Region.from_bounds(*STORE_REGION)
    params = FitParameters(**STORE_PARAMS)
    path = base / "store"
    result, info = build_store(grid, path, region, params)
    return SmallStore(path=path, gtx=gtx, grid=grid, region=region, params=params, result=result, info=info,
                      stored=stored_spline(result.spline, path))


def stored_spline(spline, store_path):
    """What the store at ``store_path`` holds of ``spline``: its coefficients quantised
    with the store's step (format 2; format 1 stores float64 as it is)."""
    import json

    from geoidspline.store.codec import quantised_spline

    step = json.loads((Path(store_path) / "manifest.json").read_text())["spline"].get("value_step_m")
    return spline if step is None else quantised_spline(spline, step)


@pytest.fixture
def store_copy(tmp_path, small_store) -> Path:
    """A private copy of the session store that the test may damage or overwrite."""
    return Path(shutil.copytree(small_store.path, tmp_path / "store_copy"))


def random_synthesis(nmax, seed, name):
    """Generic-preset synthesis of a random model: C̄nm, S̄nm ~ N(0, (1e-6 / n)²) for
    n = 2..nmax (N of a few metres) and EGM96's C̄20, which the normal field removes."""
    from geoidspline.sources.harmonics import GeoidSynthesis, HarmonicModel

    rng = np.random.default_rng(seed)
    C = np.zeros((nmax + 1, nmax + 1))
    S = np.zeros((nmax + 1, nmax + 1))
    for n in range(2, nmax + 1):
        C[n, : n + 1] = rng.normal(size=n + 1) * 1e-6 / n
        S[n, 1 : n + 1] = rng.normal(size=n) * 1e-6 / n
    C[2, 0] = -0.484165371736e-3
    model = HarmonicModel(name=name, gm=3.986004415e14, radius=6378136.3, max_degree=nmax,
                          tide_system="tide_free", C=C, S=S)
    return GeoidSynthesis(model, preset="generic")


@pytest.fixture(scope="session")
def make_synthesis():
    """:func:`random_synthesis`, for tests that need their own degree or seed."""
    return random_synthesis


@pytest.fixture(scope="session")
def toy24():
    """A random degree-24 model's synthesis (seed 7)."""
    return random_synthesis(24, 7, "toy24")


@pytest.fixture(scope="session")
def analytic():
    """The analytic field the synthetic grid samples: ``analytic(lat, lon)`` in metres."""
    return analytic_undulation


# -- the slow tests -----------------------------------------------------------------------


def pytest_addoption(parser):
    parser.addoption("--slow", action="store_true",
                     help="also run the tests marked slow (the exhaustive kill matrices, the packaging replay)")


def pytest_collection_modifyitems(config, items):
    """Tests marked ``slow`` run only with ``--slow``."""
    if config.getoption("--slow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --slow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
