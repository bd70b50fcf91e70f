"""The Japan benchmark's national grids: japan-geoid's GSIGEO2011/JPGEO2024 decoded node
for node and written through geoidspline's netCDF writer without loss.

Needs the optional ``japan-geoid`` package (``pip install '.[bench]'``); skipped without.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("japan_geoid", reason="needs japan-geoid (pip install '.[bench]')")

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
from japan_composite import national_grid  # noqa: E402

from geoidspline.sources.formats import read_grid, write_netcdf


@pytest.fixture(scope="module")
def gsigeo2011():
    return national_grid("gsigeo2011")


def test_gsigeo2011_grid_layout_and_published_values(gsigeo2011):
    grid = gsigeo2011
    assert grid.shape == (1801, 1201)  # 20-50°N every 1', 120-150°E every 1.5'
    assert grid.latitude[0] == 20.0 and grid.latitude[-1] == pytest.approx(50.0)
    assert grid.longitude_spacing == pytest.approx(1.5 / 60) and grid.latitude_spacing == pytest.approx(1 / 60)
    assert 0.90 < np.isnan(grid.values).mean() < 0.95  # land only: the sea has no data
    # GSI's online geoid calculator (as quoted by japan-geoid's tests), bilinear like GSI's
    for lat, lon, published in ((43.12345, 141.12345, 32.8389), (26.212208125371717, 127.6791822004209, 31.4807)):
        assert grid.undulation(lat, lon, method="bilinear") == pytest.approx(published, abs=1e-4)
    assert np.isnan(grid.undulation(30.0, 120.5, method="bilinear"))  # the East China Sea


def test_jpgeo2024_covers_its_whole_window():
    grid = national_grid("jpgeo2024")
    assert grid.shape == (2101, 1601)  # 15-50°N, 120-160°E
    assert np.isfinite(grid.values).all()
    # GSI's geoidcalc values quoted by japan-geoid
    assert grid.undulation(36.104394, 140.085365, method="bilinear") == pytest.approx(40.2920, abs=1e-4)
    assert grid.undulation(30.0, 130.0, method="bilinear") == pytest.approx(30.5537, abs=1e-4)


def test_netcdf_round_trip_keeps_every_value_and_hole(gsigeo2011, tmp_path):
    back = read_grid(write_netcdf(tmp_path / "gsigeo2011.nc", gsigeo2011))
    np.testing.assert_array_equal(back.latitude, gsigeo2011.latitude)
    np.testing.assert_array_equal(back.longitude, gsigeo2011.longitude)
    np.testing.assert_array_equal(back.values, gsigeo2011.values)  # NaN in the same places
    assert back.provenance.model == "GSIGEO2011"
