"""Spline quasi-interpolation of a source that is exact everywhere (a harmonic model).

Least squares (:mod:`geoidspline.fitting.least_squares`) needs a sparse factorisation per block; at the
millimetre level a global EGM96 level has millions of unknowns and the factorisations
dominate the fit (hours on two cores). A source that can be evaluated anywhere does not
need them: a tensor-product B-spline interpolates values on the lattice of B-spline
centres when its coefficients are those values passed through the inverse of the
B-spline's symbol, separably along each axis (the "prefilter" of cardinal spline
interpolation: Unser, Aldroubi & Eden 1991, IEEE Trans. Signal Process. 39(2); Unser
1999, IEEE Signal Process. Mag. 16(6)). Here the inverse is the truncated Neumann series

    q = sum_{j=0}^{J} (1 - s)^j,    q s = 1 - (1 - s)^(J+1),

with ``s`` the symbol of the B-spline sampled at integer offsets from its centre
(``[1, 4, 1] / 6`` for cubics), so the filter is finite (``2 J (order // 2) + 1`` taps), reproduces
polynomials of degree ``2 J + 1`` exactly (the large, smooth part of the geoid passes
without loss) and departs from exact interpolation only by ``(1 - s)^(J+1)``, which for
cubics is ``((1 - cos θ) / 3)^(J+1)`` at the frequency θ per cell: 2.5e-4 at 5.6
lattice points per wavelength with J = 4 (:func:`prefilter_terms`). Every coefficient depends on the
source within a few cells only, so the result is as local as a tiled least-squares fit.

The values sampled are the radially constant extension, N(φ, λ) at the direction of
each lattice point, read from a latitude/longitude lattice of the exact synthesis by
6 x 6-point Lagrange interpolation (error of order (k Δ)^6 at lattice spacing Δ; about
1e-7 relative at degree 360 on a 5' lattice), reflected across the poles.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from .._kernels import interpolation as kern
from ..bspline.basis import centred_bspline_samples
from ..bspline.keys import AXIS_STEPS, KEY_BITS, KEY_OFFSET, dilate_axis
from ..errors import FitError
from ..sphere.coordinates import latlon_of
from ..sphere.region import Region
from ..sphere.sample import NodeSample

__all__ = ["prefilter_taps", "sample_band", "LatticeLookup", "sample_nodes", "lattice_spacing", "interpolate_level",
           "prefilter_terms"]


log = logging.getLogger(__name__)


def prefilter_terms(order: int) -> int:
    """Default terms J of the prefilter's Neumann series for a spline order.

    ``1 - s`` reaches 2/3 at the Nyquist frequency for cubics but 0.87 for quintics, so
    higher orders need more terms. Measured on EGM96 at the millimetre level (region
    40..20S 80..60W, 5000 random points): cubic h = 0.003125, J = 4 and J = 8 both give
    max 3.2 mm; quintic h = 0.0045, J = 6: 1.13 mm, J = 8: 0.63 mm.
    """
    return 4 if order <= 4 else 8


#: Lattice rows/columns added around a lookup lattice for the 6-point Lagrange stencil.
_PAD = 3


def prefilter_taps(order: int, terms: int | None = None) -> np.ndarray:
    """Taps of the truncated inverse ``sum_{j<=terms} (1 - s)^j`` of the B-spline symbol."""
    terms = prefilter_terms(order) if terms is None else terms
    if terms < 0:
        raise ValueError(f"terms must be >= 0, got {terms}")
    s = centred_bspline_samples(order)
    one_minus_s = -s
    one_minus_s[s.size // 2] += 1.0
    taps = np.array([1.0])
    power = np.array([1.0])
    for _ in range(terms):
        power = np.convolve(power, one_minus_s)
        pad = (power.size - taps.size) // 2
        taps = np.pad(taps, pad) + power
    return taps


#: Steps the synthesis stage of a model is reported in (a few rows of its lattice each).
SYNTHESIS_STEPS = 40


def sample_nodes(source, region: Region, spacing_deg: float | None, progress=None) -> NodeSample:
    """``source.nodes(region, spacing_deg)``, a model's lattice synthesised a band of rows
    at a time and reported to ``progress`` (a :class:`~geoidspline.fitting.progress.Progress`)
    as the stage "synthesis". Rows are independent, so the values are those of one call."""
    from .progress import as_progress

    progress = as_progress(progress)
    if not hasattr(source, "lattice_step"):  # a grid: its nodes are read, not computed
        with progress.stage("read nodes", 1, "grid") as advance:
            sample = source.nodes(region, spacing_deg=spacing_deg)
            advance(1)
        return sample
    step = source.lattice_step(spacing_deg)
    k = round(180.0 / step)
    # the rows nodes() would take (its own rounding), split into bands of >= 2 rows
    i0 = max(0, math.floor((region.south + 90.0) / step + 1e-9))
    i1 = min(k, math.ceil((region.north + 90.0) / step - 1e-9))
    per_band = max(2, math.ceil((i1 - i0 + 1) / SYNTHESIS_STEPS))
    starts = list(range(i0, i1 + 1, per_band))
    if len(starts) > 1 and i1 + 1 - starts[-1] < 2:
        starts.pop()
    bands = [(a, (starts[n + 1] - 1) if n + 1 < len(starts) else i1) for n, a in enumerate(starts)]
    if len(bands) == 1 or i1 - i0 < 3:
        bands = [(i0, i1)]
    pieces = []
    with progress.stage("synthesis", len(bands), "band") as advance:
        for a, b in bands:
            south = max(-90.0, min(90.0, a * step - 90.0))
            north = max(-90.0, min(90.0, b * step - 90.0))
            pieces.append(source.nodes(Region(south, region.west, north, region.east) if (a, b) != (i0, i1)
                                       else region, spacing_deg=step))
            advance(1)
    if len(pieces) == 1:
        return pieces[0]
    return NodeSample(np.concatenate([p.latitude for p in pieces]), pieces[0].longitude,
                      np.concatenate([p.undulation for p in pieces], axis=0))


#: Lattice points a step of the lookup stage interpolates.
LOOKUP_CHUNK = 2_000_000


def sample_band(source, latitude_south: float, latitude_north: float, spacing_deg: float, progress=None):
    """The source on a full-circle latitude band, padded for the Lagrange lookups.

    Returns ``(LatticeLookup, NodeSample)``: the lookup's ``grid[i, j]`` is N at latitude
    ``lat0 + (first_row + i) step`` and longitude ``-180 + (j - 3) step`` (degrees),
    ``lat0 = -90 - 3 step`` the first padded row of the whole lattice, so that a band's
    lookups have the whole lattice's bits; rows beyond a pole are the rows inside it half
    a turn away; columns wrap. The NodeSample holds the unpadded lattice (the band's nodes).
    """
    step = source.lattice_step(spacing_deg)
    columns = round(360.0 / step)
    south = max(-90.0, latitude_south - _PAD * step)
    north = min(90.0, latitude_north + _PAD * step)
    sample = sample_nodes(source, Region(south, -180.0, north, 180.0), step, progress)
    lat = sample.latitude
    values = sample.undulation[:, :columns]  # the last column repeats the first (+360)
    if values.shape[1] != columns or not np.isclose(sample.longitude[0], -180.0):
        raise FitError(f"lattice of {source!r} does not start at -180 with {columns} columns")
    half_turn = columns // 2
    # beyond a pole: the rows inside it, half a turn away; elsewhere the band already
    # holds the stencil's rows, so the padding is never read
    below = (np.roll(values[_PAD:0:-1], -half_turn, axis=1) if lat[0] <= -90.0 + 1e-9
             else np.repeat(values[:1], _PAD, axis=0))
    above = (np.roll(values[-2:-2 - _PAD:-1], -half_turn, axis=1) if lat[-1] >= 90.0 - 1e-9
             else np.repeat(values[-1:], _PAD, axis=0))
    grid = np.concatenate([below, values, above], axis=0)
    grid = np.concatenate([grid[:, -_PAD:], grid, grid[:, :_PAD]], axis=1)
    first_row = round((float(lat[0]) + 90.0) / step)  # the band's first row on the whole lattice
    lookup = LatticeLookup(np.ascontiguousarray(grid), -90.0 - _PAD * step, step, first_row)
    return lookup, NodeSample(lat, sample.longitude, sample.undulation)


@dataclass(frozen=True)
class LatticeLookup:
    """``N`` (metres) by 6 x 6-point Lagrange lookups on the padded latitude band of an
    exact synthesis that :func:`sample_band` returns: ``grid`` row ``i`` at latitude
    ``lat0 + (first_row + i) step``, ``lat0`` the whole lattice's first padded row, so
    that every band gives a point the same bits; the one place that knows the band's
    layout (longitudes from -180 - ``_PAD`` steps)."""

    grid: np.ndarray
    lat0: float
    step: float
    first_row: int = 0

    def at(self, latitude, longitude, out):
        """``out[:] = N`` at contiguous ``latitude``, ``longitude`` (degrees)."""
        kern.lattice_lookup(self.grid, self.lat0, self.step, -180.0 - _PAD * self.step, self.step,
                            latitude, longitude, out, self.first_row)

    def __call__(self, points):
        """``G(x) = N(x / |x|)`` at points (M, 3) of the shell; a point outside the band is
        an error (its lookup would read the padding)."""
        latitude, longitude = latlon_of(np.asarray(points, dtype=float).reshape(-1, 3))
        out = np.empty(latitude.size)
        south = self.lat0 + self.first_row * self.step
        low, high = south + 2 * self.step, south + (self.grid.shape[0] - 4) * self.step
        if latitude.size and (latitude.min() < low - 1e-9 or latitude.max() > high + 1e-9):
            raise FitError(f"latitudes {latitude.min():.4f}..{latitude.max():.4f} outside the synthesised band")
        self.at(np.ascontiguousarray(latitude), np.ascontiguousarray(longitude), out)
        return out


def lattice_spacing(source, h: float, spacing_deg: float | None = None) -> float:
    """Spacing (degrees) of the lattice the lookups read: ``spacing_deg`` when given,
    else 30/N degrees for degree N (5' for degree 360: 6-point Lagrange error ~1e-7
    relative) and at most half the level spacing, so the nodes that measure the fit's
    error are denser than its cells."""
    if spacing_deg is None:
        spacing_deg = min(30.0 / source.max_degree, math.degrees(h) / 2.0)
    return source.lattice_step(spacing_deg)


def interpolate_level(source, keys, h: float, order: int, spacing_deg: float,
                      terms: int | None = None, progress=None):
    """Coefficients (metres) of B-splines ``keys`` (sorted) by quasi-interpolation.

    Returns ``(coefficients, band, lattice_points)``: ``band`` is the
    :class:`NodeSample` of the lattice synthesised for the lookups (every latitude the
    coefficients depend on, all longitudes), ``lattice_points`` the number of lattice
    points sampled. ``progress``: a :class:`~geoidspline.fitting.progress.Progress` told
    of the stages "synthesis", "lookups" and "prefilter".
    """
    from .progress import as_progress

    progress = as_progress(progress)
    start = time.perf_counter()
    taps = prefilter_taps(order, terms)
    half = (taps.size - 1) // 2
    steps = AXIS_STEPS
    # the key sets each pass writes: the coefficients, then dilated one axis at a time
    sets = [np.asarray(keys, dtype=np.int64)]
    for step in steps[::-1]:
        sets.append(dilate_axis(sets[-1], step, -half, half))
    lattice = sets[-1]
    lat = np.empty(lattice.size)
    lon = np.empty(lattice.size)
    # B-spline k lives on cells k .. k + order - 1: its centre is at (k + order/2) h
    kern.key_directions(lattice, KEY_OFFSET, KEY_BITS, order / 2.0, h, lat, lon)
    lookup, band = sample_band(source, float(lat.min()), float(lat.max()), spacing_deg, progress)
    t_synth = time.perf_counter()
    values = np.empty(lattice.size)
    # each point's lookup is independent: chunks give the values of one call
    bounds = list(range(0, lattice.size, LOOKUP_CHUNK)) + [lattice.size]
    with progress.stage("lookups", len(bounds) - 1, "chunk") as advance:
        for a, b in zip(bounds[:-1], bounds[1:]):
            lookup.at(lat[a:b], lon[a:b], values[a:b])
            advance(1)
    lookup_step = lookup.step
    del lat, lon, lookup
    with progress.stage("prefilter", len(steps), "axis") as advance:
        for axis, step_key in enumerate(steps):
            in_keys = sets[3 - axis]
            out_keys = sets[2 - axis]
            out = np.empty(out_keys.size)
            kern.filter_axis(in_keys, values, out_keys, step_key, taps, out)
            values = out
            advance(1)
    log.info(
        "quasi-interpolation at h=%.6g: %d coefficients from %d lattice points (%d taps an axis), "
        "band %.3f..%.3f deg at %.4g deg, %.1f s (synthesis and lookups %.1f s)",
        h, keys.size, lattice.size, taps.size, band.latitude[0], band.latitude[-1], lookup_step,
        time.perf_counter() - start, t_synth - start,
    )
    return values, band, int(lattice.size)
