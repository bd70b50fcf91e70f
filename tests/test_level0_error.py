"""Level 0's error predicted from a model's degree variances (geoidspline.fitting.level0_error)
and the spectrum a synthesis gives it (GeoidSynthesis.degree_power)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from geoidspline.fitting import choose, level0_error
from geoidspline.fitting.driver import fit_source
from geoidspline.fitting.parameters import FitParameters
from geoidspline.sources.harmonics import GeoidSynthesis, HarmonicModel
from geoidspline.sphere.region import Region


def one_degree_model(n, seed=3):
    """A model whose only degree is ``n`` (odd: no normal-field zonal of its own), without
    its zonal term: along a ring its part of N has mean zero, and every other part of N
    (the normal field's zonals that the model's C̄20 alone does not cancel) is constant."""
    rng = np.random.default_rng(seed)
    C = np.zeros((n + 1, n + 1))
    S = np.zeros((n + 1, n + 1))
    C[n, 1 : n + 1] = rng.normal(size=n) * 1e-6
    S[n, 1:] = rng.normal(size=n) * 1e-6
    C[2, 0] = -0.484165371736e-3
    model = HarmonicModel(name="one", gm=3.986004415e14, radius=6378136.3, max_degree=n, tide_system="tide_free",
                          C=C, S=S)
    return GeoidSynthesis(model, preset="generic")


def test_degree_power_is_the_mean_square_along_the_ring_on_the_ellipsoid():
    synthesis = one_degree_model(11)
    lon = np.arange(0.0, 360.0, 0.25)
    latitudes = np.array([0.0, 37.5, -61.0, 89.0])
    power = synthesis.degree_power(latitudes)
    assert power.shape == (4, 12, 1)
    for i, lat in enumerate(latitudes):
        values = synthesis.undulation(np.full(lon.size, lat), lon)
        assert power[i, 11, 0] == pytest.approx(np.var(values), rel=1e-9)
        assert power[i, [3, 5, 7, 9]].max() == 0.0 and power[i, 4, 0] > 0.0  # the normal field's J4 remains


def test_the_transfer_error_falls_as_the_spline_order_at_long_waves():
    for order, theta in ((4, 0.1), (6, 0.05)):
        e2 = level0_error.transfer_error(np.array([theta, 2 * theta]), order)
        slope = math.log(e2[1] / e2[0]) / math.log(2.0)
        assert slope == pytest.approx(2 * order, abs=0.2)  # E ~ θ^order
        # shorter waves, larger errors, up to the order of the wave itself at 2 cells a wave
        e2 = level0_error.transfer_error(np.linspace(0.1, math.pi, 30), order)
        assert np.all(np.diff(e2) > 0) and 0.1 < e2[-1] < 2.0


@pytest.mark.parametrize("order,h", [(6, 0.03), (4, 0.02)])
def test_the_predicted_rms_is_that_of_a_level_0_fit(make_synthesis, order, h):
    synthesis = make_synthesis(60, 11, "r60")
    region = Region.from_bounds(20, 10, 30, 20)
    params = FitParameters(order=order, h0=h, max_level=0, tolerance_m=1e-6, method="interpolation")
    result = fit_source(synthesis, region, params)
    rng = np.random.default_rng(2)
    lat = np.degrees(np.arcsin(rng.uniform(math.sin(math.radians(20)), math.sin(math.radians(30)), 3000)))
    lon = rng.uniform(10, 20, 3000)
    errors = result.spline.undulation(lat, lon) - synthesis.undulation(lat, lon)
    measured_rms = float(np.sqrt(np.mean(errors**2)))
    spectrum = level0_error.ModelSpectrum.of(synthesis, 20, 30, 10, 20)
    predicted_max, predicted_rms = level0_error.predicted_level0(spectrum, h, order, choose.region_area(region))
    assert 0.7 < measured_rms / predicted_rms < 1.4
    assert np.abs(errors).max() <= predicted_max  # the max is predicted with EGM96's (rougher) factor


def test_the_chosen_level_0_is_the_coarsest_the_prediction_allows(make_synthesis):
    synthesis = make_synthesis(60, 11, "r60")
    region = Region.from_bounds(20, 10, 30, 20)
    choice = choose.choose_parameters(synthesis, 0.002, region)
    p = choice.parameters
    assert "degree variances" in choice.reasons["h0"]
    # the whole sphere's prediction, whatever the region (a region's rings hold their
    # latitudes' average, not the region's own roughness)
    assert choose.choose_parameters(synthesis, 0.002, Region.from_bounds(-60, 100, -40, 150)).parameters == p
    spectrum = level0_error.ModelSpectrum.of(synthesis)
    area = 4 * math.pi
    target = choose.LEVEL0_OVER_TOLERANCE * 0.002
    assert level0_error.predicted_level0(spectrum, p.h0, p.order, area)[0] <= target
    assert level0_error.predicted_level0(spectrum, p.h0 * 1.01, p.order, area)[0] > target * 0.99
    # the whole globe, fitted band by band, keeps the tolerance with level 0 alone (room
    # for the bands' rounding at their edges): a finer level 0
    globe = choose.choose_parameters(synthesis, 0.002).parameters
    assert level0_error.predicted_level0(spectrum, globe.h0, p.order, area)[0] <= \
        choose.BANDED_LEVEL0_OVER_TOLERANCE * 0.002 < target
    assert globe.h0 < p.h0
    # a model with the same degrees but ten times the power above degree 40 needs a finer level 0
    rough = dataclasses.replace(spectrum, power=spectrum.power * np.where(np.arange(61) > 40, 10.0, 1.0)[None, :, None])
    assert level0_error.spacing_for_level0(rough, p.order, target, area, 0.05) < p.h0 * 0.95
