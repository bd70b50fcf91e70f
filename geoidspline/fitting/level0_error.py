"""Level 0's error predicted from a model's own degree variances (issue 22).

Quasi-interpolation (:mod:`.interpolation`) of a wave of θ radians per cell along one axis
gives coefficients ``q(θ)`` times the wave, ``q s = 1 - (1 - s)^(J+1)`` with ``s`` the
B-spline's symbol; the spline made from them holds the wave times ``q(θ) φ̂(θ)`` and
its aliases ``q(θ) φ̂(θ + 2πl)``, ``φ̂(ω) = sinc(ω / 2)^order`` the cardinal B-spline's
Fourier transform. The mean square error of a unit wave (Blu & Unser 1999, IEEE Trans.
Signal Process. 47(10), "Quantitative Fourier analysis of approximation techniques") is,
for the tensor product along the three axes of a wave vector θu,

    E²(θu) = |1 - Π_d a_0(θ u_d)|² + Π_d Σ_l |a_l(θ u_d)|² - Π_d |a_0(θ u_d)|²,
    a_l(θ) = q(θ) φ̂(θ + 2πl),

for a wave running in the direction u. The error depends on that direction (a wave along
an axis of the grid is worse than one across it: for order 6, 2.1-2.6 times the RMS
of the average over all directions, 5-15 times that of a wave along a face diagonal), and a model's waves need not run equally in every direction (the
synthetic EGM2008's orders near the degree, amplified so that its undulations on the
ellipsoid are as rough at the poles as at the equator, run mostly east-west). Degree n
has (n + 1/2) radians per unit length on the unit sphere, so at spacing h level 0's
mean square error at a point of a latitude ring is Σ_n Σ_b P_nb E²((n + 1/2) h u_b),
P_nb the degree's mean square on that ring from waves running at angle b from east
(:meth:`~geoidspline.sources.harmonics.GeoidSynthesis.degree_power`: on the ellipsoid,
with the (a/r)^n of the ring) and u_b that direction in R³ at the point. The
prediction takes the worst ring and the worst longitude of the region (the grid's axes
turn with the longitude: 0° and 45° are the extremes).

The max error is that RMS times a factor: for a field of M independent cells the
largest of Gaussian values is about √(2 ln M) standard deviations, M = area · n_eff²
(n_eff the RMS degree of the error's spectrum), times :data:`KAPPA`, measured on
EGM96 (which is not Gaussian: its steepest places, the Himalaya and the trenches, hold
more of the high degrees than the average). ``KAPPA`` varies with the error relative to
the model's upper half of degrees (finer levels leave errors more concentrated in the
steepest places) and is interpolated in that ratio, so EGM96's measured curve is
reproduced and other models scale by their own spectrum.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from ..bspline.basis import centred_bspline_samples
from .interpolation import prefilter_terms

__all__ = [
    "KAPPA",
    "ModelSpectrum",
    "grid_longitudes",
    "predicted_level0",
    "ring_latitudes",
    "spacing_for_level0",
    "transfer_error",
    "wave_directions",
]

#: Directions averaged over (a Fibonacci lattice of the sphere).
_DIRECTIONS = 96
#: Aliases summed each side (sinc^order falls as (2πl)^-order).
_ALIASES = 8
#: Table of E² against θ (radians per cell): step and end (beyond, E² is taken at the end).
_THETA_STEP = 0.005
_THETA_END = 3.0 * math.pi


def transfer_error(theta, order: int, terms: int | None = None, directions=None) -> np.ndarray:
    """E²(θ u): mean square error of quasi-interpolating a unit wave of ``theta``
    radians per cell running along ``directions`` (unit vectors in R³, shape (D, 3);
    returns shape (T, D)), or averaged over all directions when None (shape (T,)), for a
    spline ``order`` and a prefilter of ``terms`` (default :func:`~.interpolation.prefilter_terms`)."""
    terms = prefilter_terms(order) if terms is None else terms
    theta = np.atleast_1d(np.asarray(theta, dtype=np.float64))
    samples = centred_bspline_samples(order)
    centre = samples.size // 2
    if directions is None:
        i = np.arange(_DIRECTIONS) + 0.5
        z = 1.0 - 2.0 * i / _DIRECTIONS
        azimuth = math.pi * (1.0 + math.sqrt(5.0)) * i
        u = np.stack([np.sqrt(1 - z * z) * np.cos(azimuth), np.sqrt(1 - z * z) * np.sin(azimuth), z], axis=1)
    else:
        u = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    out = np.empty((theta.size, u.shape[0]))
    for start in range(0, theta.size, 256):  # in chunks: (θ, direction, axis, alias) arrays
        th = np.abs(theta[start:start + 256, None, None] * u[None, :, :])
        symbol = samples[centre] + 2.0 * sum(samples[centre + j] * np.cos(j * th) for j in range(1, centre + 1))
        q = (1.0 - (1.0 - symbol) ** (terms + 1)) / symbol
        shifted = th[..., None] + 2.0 * math.pi * np.arange(-_ALIASES, _ALIASES + 1)
        a = q[..., None] * np.sinc(shifted / (2.0 * math.pi)) ** order
        x = a[..., _ALIASES] ** 2  # the wave's own part, per axis
        r = (a**2).sum(-1) - x  # its aliases' power, per axis
        # Π(x + r) - Π x written without the difference of two near-equal products
        aliases = (r[..., 0] * (x[..., 1] + r[..., 1]) * (x[..., 2] + r[..., 2])
                   + x[..., 0] * r[..., 1] * (x[..., 2] + r[..., 2]) + x[..., 0] * x[..., 1] * r[..., 2])
        out[start:start + 256] = (1.0 - a[..., _ALIASES].prod(-1)) ** 2 + aliases
    return out.mean(axis=1) if directions is None else out


def wave_directions(latitude_deg: float, longitude_deg: float, bins: int) -> np.ndarray:
    """Unit vectors (bins, 3) in R³ of waves tangent to the sphere at a point, at the
    centres of ``bins`` equal bins of angle from east, 0°..90°."""
    lat, lon = math.radians(latitude_deg), math.radians(longitude_deg)
    east = np.array([-math.sin(lon), math.cos(lon), 0.0])
    north = np.array([-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)])
    angle = (np.arange(bins) + 0.5) * (0.5 * math.pi / bins)
    return np.cos(angle)[:, None] * east[None, :] + np.sin(angle)[:, None] * north[None, :]


@functools.lru_cache(maxsize=256)
def _table(order: int, terms: int, latitude_deg: float, longitude_deg: float, bins: int):
    theta = np.arange(0.0, _THETA_END + _THETA_STEP, _THETA_STEP)
    table = transfer_error(theta, order, terms, wave_directions(latitude_deg, longitude_deg, bins))
    table.flags.writeable = False
    return theta, table


def _e2(theta, order: int, terms: int, latitude_deg: float, longitude_deg: float, bins: int):
    """E² at ``theta`` (T,) for each direction bin: (T, bins), by the table (linear in θ;
    clamped beyond its end, where the wave is lost anyway)."""
    grid, table = _table(order, terms, latitude_deg, longitude_deg, bins)
    index = np.clip(theta / _THETA_STEP, 0.0, grid.size - 1.000001)
    low = index.astype(np.int64)
    frac = (index - low)[:, None]
    return table[low] * (1.0 - frac) + table[low + 1] * frac


#: Latitudes (degrees) at which a global model's spectrum is taken: north and south give
#: the same ring powers (P̄nm² is even in sin ψ), so |latitude| only.
GLOBAL_RING_LATITUDES = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 85.0, 89.5)


#: Angle bins (0°..90° from east) the spectrum is resolved in.
DIRECTION_BINS = 12


def grid_longitudes(west: float, east: float) -> tuple:
    """Longitudes (degrees, folded into 0..45: the grid's axes repeat every 90° and
    mirror at 45°) at which a region's error is predicted: its edges, its centre and
    the extremes 0° and 45° where the region holds them."""
    if east - west >= 90.0:
        return (0.0, 45.0)
    values = [west, east, 0.5 * (west + east)]
    values += [45.0 * k for k in range(math.ceil(west / 45.0), math.floor(east / 45.0) + 1)]
    folded = {round(min(v % 90.0, 90.0 - v % 90.0), 6) for v in values}
    return tuple(sorted(folded))


def ring_latitudes(south: float, north: float) -> tuple:
    """|Latitudes| (degrees) whose rings stand for a region from ``south`` to ``north``."""
    if south <= -89.5 and north >= 89.5:
        return GLOBAL_RING_LATITUDES
    lat = np.abs(np.linspace(south, north, 5))
    if south < 0.0 < north:
        lat = np.append(lat, 0.0)
    return tuple(sorted({float(min(v, 89.5)) for v in lat}))


@dataclass(frozen=True)
class ModelSpectrum:
    """A model's degree powers (m²) on latitude rings by wave direction:
    ``power[i, n, b]`` on ring i (``latitudes`` in degrees) from waves at angle bin b
    from east; ``longitudes``: where the grid's orientation is taken (0..45°)."""

    latitudes: tuple
    longitudes: tuple
    power: np.ndarray

    @property
    def max_degree(self) -> int:
        return self.power.shape[1] - 1

    @classmethod
    def of(cls, source, south: float = -90.0, north: float = 90.0, west: float = -180.0,
           east: float = 180.0) -> ModelSpectrum:
        """The spectrum of ``source`` (anything with ``degree_power(latitudes,
        directions)``) on the rings and longitudes of a region (degrees)."""
        latitudes = ring_latitudes(south, north)
        power = np.asarray(source.degree_power(np.array(latitudes), DIRECTION_BINS), dtype=np.float64)
        return cls(latitudes, grid_longitudes(west, east), power)

    def upper_half_rms_m(self) -> float:
        """RMS (m) of degrees above N/2 on the worst ring: the scale of the error ratio."""
        return float(np.sqrt(self.power[:, self.max_degree // 2 + 1:].sum(axis=(1, 2)).max()))


def _rms_and_degree(spectrum: ModelSpectrum, h: float, order: int, terms: int):
    """Level 0's RMS error (m) at the worst ring and longitude at spacing ``h``, and the
    RMS degree of that error."""
    n = np.arange(spectrum.max_degree + 1)
    bins = spectrum.power.shape[2]
    worst, worst_power = 0.0, None
    for i, latitude in enumerate(spectrum.latitudes):
        for longitude in spectrum.longitudes:
            per_degree = (spectrum.power[i] * _e2((n + 0.5) * h, order, terms, latitude, longitude, bins)).sum(axis=1)
            total = float(per_degree.sum())
            if worst_power is None or total > worst:
                worst, worst_power = total, per_degree
    if worst <= 0.0:
        return 0.0, 1.0
    n_eff = math.sqrt(float((worst_power * (n + 0.5) ** 2).sum() / worst))
    return math.sqrt(worst), n_eff


#: κ against the error relative to the upper half of degrees, per order: EGM96 (F477 +
#: CORRCOEF), level 0's global max as the measured curve of fitting.choose gives it
#: (Himalaya maxima, results/choose.jsonl 2026-11-29, times choose.GLOBAL_OVER_REGIONAL),
#: divided by the RMS this module predicts and √(2 ln M) over the sphere. Computed by
#: ``python benchmarks/level0_convergence.py --calibrate``; interpolated log-log in the
#: ratio, constant beyond the ends.
KAPPA = {
    6: ((0.000221, 1.2607), (0.000636, 1.1296), (0.004476, 0.9976), (0.021003, 1.0037)),
    4: ((0.000828, 2.0147), (0.003293, 1.7394), (0.010657, 1.5354)),
}


def extreme_factor(area_sr: float, n_eff: float) -> float:
    """√(2 ln M), M = area · n_eff²: the largest of M Gaussian values in standard deviations."""
    return math.sqrt(2.0 * math.log(max(area_sr * n_eff**2, math.e)))


def predicted_level0(spectrum: ModelSpectrum, h: float, order: int, area_sr: float, terms: int | None = None):
    """Level 0's predicted ``(max, rms)`` error (metres) at spacing ``h`` (unit sphere)
    over ``area_sr`` steradians; ``rms`` is that of the worst ring."""
    terms = prefilter_terms(order) if terms is None else terms
    rms, n_eff = _rms_and_degree(spectrum, h, order, terms)
    if rms == 0.0:
        return 0.0, 0.0
    return kappa(order, rms / spectrum.upper_half_rms_m()) * extreme_factor(area_sr, n_eff) * rms, rms


def kappa(order: int, relative_error: float) -> float:
    """:data:`KAPPA` of ``order`` at an error ``relative_error`` of the upper-half RMS."""
    points = KAPPA[order]
    x = np.log([p[0] for p in points])
    y = np.log([p[1] for p in points])
    return float(np.exp(np.interp(math.log(relative_error), x, y)))


def spacing_for_level0(spectrum: ModelSpectrum, order: int, target_max_m: float, area_sr: float,
                       coarsest_h: float) -> float:
    """The largest h ≤ ``coarsest_h`` whose predicted level-0 max is ≤ ``target_max_m``
    (bisection in log h; the prediction grows with h)."""
    if predicted_level0(spectrum, coarsest_h, order, area_sr)[0] <= target_max_m:
        return coarsest_h
    lo, hi = math.log(coarsest_h) - math.log(1e3), math.log(coarsest_h)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if predicted_level0(spectrum, math.exp(mid), order, area_sr)[0] <= target_max_m:
            lo = mid
        else:
            hi = mid
    return math.exp(lo)
