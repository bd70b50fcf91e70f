"""Fit parameters chosen from the tolerance: the fewest coefficients that reach it.

A user gives a source and the largest error she accepts; :func:`choose_parameters`
picks the method, spline order, level-0 spacing h0, the number of levels and the
sample spacing, and says why for each. Every choice rests on a measured fit
(:data:`MEASURED`, rows of ``benchmarks/results/fits.jsonl`` and
``benchmarks/results/choose.jsonl``) and on two laws:

- convergence: level 0's max error at a spacing and order is predicted from the
  model's own degree variances on latitude rings (:mod:`.level0_error`: the
  prefilter's and the B-spline's transfer function weighted by the spectrum, the max
  from the RMS by a factor measured on EGM96), so a model whose spectrum differs from
  EGM96's (EGM2008 to degree 2190, a truncated model) gets its own spacing. A source
  that does not give its spectrum (``degree_power``) is taken to be EGM96-like: a
  model of degree N has the same relative resolution at the same ``h * N`` (its
  shortest wavelength is 2π/N on the unit sphere), and level 0's max error is read off
  EGM96's measured curve of ``h * N`` (:data:`LEVEL0_ERROR`, log-log interpolation,
  below its finest point extended by h^n). Measured, the error falls faster than the
  asymptotic h^n (about h^8-h^9 for order 6 at h N = 1.4-2.3: the spline is near the
  model's resolution there), which the spectral prediction reproduces. h0 is never
  chosen coarser than the curve's coarsest point;
- size: the B-splines touching the cells that meet the sphere number
  ``density * area / h**2`` (area in steradians); ``density`` grows with the order
  (the support is thicker radially) and is measured.

Grids are fitted the way the thesis's Andes headline is (least squares, cubic splines,
h0 = 0.1, overlays down to the grid's own resolution): quasi-interpolation needs a
source exact everywhere.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..errors import FitError
from ..options import check_number, check_numbers
from ..sphere.region import GLOBAL, Region
from .bands import uses_bands
from .level0_error import ModelSpectrum, predicted_level0, spacing_for_level0
from .parameters import MIN_H_PER_DATA_SPACING, FitParameters

__all__ = ["MEASURED", "ConvergencePoint", "Choice", "choose_parameters", "CHOSEN_FIELDS"]


#: The FitParameters fields :func:`choose_parameters` chooses (the rest keep their defaults).
CHOSEN_FIELDS = ("method", "refinement", "order", "h0", "max_level", "sample_spacing_deg", "tolerance_m")


@dataclass(frozen=True)
class ConvergencePoint:
    """One measured quasi-interpolated level 0 of a model fit.

    ``level0_max_m``: max |error| of level 0 alone; ``coefficients``: level 0's
    B-splines over the whole sphere; ``reference``: where it was measured.
    """

    model: str
    degree: int
    order: int
    h0: float
    level0_max_m: float
    coefficients: int
    reference: str

    @property
    def h_times_degree(self) -> float:
        return self.h0 * self.degree

    @property
    def density(self) -> float:
        """Coefficients per steradian times h0²."""
        return self.coefficients * self.h0**2 / (4.0 * math.pi)


#: The global anchors, one per spline order: coefficient counts (and, for order 6,
#: the global level-0 error that scales the regional curve).
MEASURED = {
    6: ConvergencePoint(
        "EGM96 (F477 + CORRCOEF)", 360, 6, 0.0045, 0.0026, 5_585_796,
        "benchmarks/README.md 'Millimetre stores from models', scenario egm96-mm "
        "(results/fits.jsonl 2026-11-23T21:36, 2a41d02): level 0 alone 2.6 mm at the 5' nodes",
    ),
    4: ConvergencePoint(
        "EGM96 (F477 + CORRCOEF)", 360, 4, 0.004, float("nan"), 4_712_294,
        "scenario egm96-cm (results/fits.jsonl 2026-11-23T22:26, 8cb19eb)",
    ),
}

#: Level 0's max |error| (metres) against h·N, per order: EGM96 (F477 + CORRCOEF),
#: quasi-interpolation alone, region 25..35N 80..95E (the Himalaya, the steepest
#: geoid), max over the 5' nodes (results/choose.jsonl, 2026-11-29). Global maxima are
#: larger by :data:`GLOBAL_OVER_REGIONAL`.
LEVEL0_ERROR = {
    6: ((1.44, 0.000841), (1.62, 0.002171), (1.98, 0.013498), (2.34, 0.063712)),
    4: ((1.08, 0.005020), (1.44, 0.017251), (1.80, 0.049309)),
}

#: Global level-0 max over the regional one at the same h: 2.6 mm (egm96-mm, every 5'
#: node of the sphere) against 2.17 mm (the region of LEVEL0_ERROR), order 6, h 0.0045.
GLOBAL_OVER_REGIONAL = 0.0026 / 0.002171

#: Level 0's max error relative to the tolerance asked for: egm96-mm's level 0 (2.6 mm)
#: against its node tolerance (1.5 mm, then taken as 0.8 of the 1.875 mm asked) left
#: 220 of 9.3 M nodes for the overlay (1,129 coefficients, 21 s). Many overlays on a
#: quasi-interpolated level are slow and were seen to make the worst node worse
#: (benchmarks/README.md), so level 0 does nearly all the work. The tolerance itself is
#: the one asked for, at the nodes and at random check points alike (check points
#: between the nodes were 0.74 (EGM96) and 0.90 (EGM2008 to 120) of the node max in
#: the measured fits): only level 0's spacing is chosen with this margin.
LEVEL0_OVER_TOLERANCE = 0.8 * 0.0026 / 0.0015

#: Level 0's predicted max error relative to the tolerance for a whole globe fitted band
#: by band (:mod:`geoidspline.fitting.bands`): level 0 alone keeps the tolerance, with
#: room for the store's rounding. A band bounds its neighbours' rounding at its edges
#: (it cannot know their step) by half the start step: with level 0 at 1.39 T and the
#: overlay bringing the worst nodes to 0.99 T there was no room for it, and the band
#: halved its step down to 1 µm and still reported 10.8 mm at 1 cm (EGM2008 synthetic,
#: band 0, 2026-12-03). At 0.7 T of the predicted max (measured level 0: 0.5-0.9 of the
#: prediction) the predicted RMS on the worst ring is 0.1 T too (the issue's 0.1 mm
#: at 1 mm), for about 15 % more level-0 coefficients than at 1.39 T.
BANDED_LEVEL0_OVER_TOLERANCE = 0.7

#: Level-0 coefficients above which h0 is not made finer (about 0.7 GB of peak memory
#: per million in the measured fits: 3.8 GB for 5.6 M); overlays take the rest. A whole
#: globe, fitted band by band, is not capped: its bands are sized by the memory.
MAX_LEVEL0_COEFFICIENTS = 12_000_000

#: Node lattice of a model: 5' (the measured fits) or 30/N degrees when finer (the
#: 6-point Lagrange lookups' accuracy, :func:`geoidspline.fitting.interpolation.lattice_spacing`).
NODE_SPACING_DEG = 1.0 / 12.0


#: Why a refinement is chosen (benchmarks/README.md, "Hierarchical B-splines (§5.3)
#: against overlays (§5.2)").
HIERARCHICAL_REASON = (
    "hierarchical (§5.3): fewer coefficients and closer to the grid between its nodes than overlays "
    "(Andes, 0.5 m: 21,472 against 28,968; global 0.1 m: 280,230 against 796,487, in 0.54 times the time); "
    "it holds each step's whole problem in memory, and a step that would not fit is fitted by overlays instead"
)
OVERLAYS_REASON = "overlays (§5.2)"


@dataclass(frozen=True)
class Choice:
    """The chosen parameters and, per field, why (``given`` when the caller fixed it)."""

    parameters: FitParameters
    reasons: dict
    tolerance_m: float  # the tolerance asked for

    def as_manifest(self) -> dict:
        """The ``fit.choices`` note of a store."""
        return {"tolerance_asked_m": self.tolerance_m, "reasons": dict(self.reasons)}


def region_area(region: Region) -> float:
    """Area of ``region`` on the unit sphere (steradians)."""
    span = math.radians(min(region.longitude_span, 360.0))
    return span * (math.sin(math.radians(region.north)) - math.sin(math.radians(region.south)))


def _level0_spacing(order: int, degree: int, level0_max_m: float) -> float:
    """h0 at which level 0's global max error is ``level0_max_m`` by :data:`LEVEL0_ERROR`."""
    points = LEVEL0_ERROR[order]
    h_n = np.log([p[0] for p in points])
    err = np.log([p[1] * GLOBAL_OVER_REGIONAL for p in points])
    target = math.log(level0_max_m)
    if target <= err[0]:  # finer than measured: the asymptotic rate h^order
        return math.exp(h_n[0] + (target - err[0]) / order) / degree
    return math.exp(float(np.interp(target, err, h_n))) / degree  # clamped at the coarsest


def _max_h_times_degree(order: int) -> float:
    return LEVEL0_ERROR[order][-1][0]


def _round_down(value: float, digits: int = 3) -> float:
    """``value`` rounded down to ``digits`` significant digits (h0 errs on the fine side)."""
    scale = 10.0 ** (digits - 1 - math.floor(math.log10(value)))
    return math.floor(value * scale) / scale


def choose_parameters(source, tolerance_m: float, region: Region | None = None, given: dict | None = None) -> Choice:
    """Parameters for the fewest coefficients that reach ``tolerance_m`` (metres).

    ``given``: FitParameters fields the caller fixed (an expert option); they are used
    as given and the rest chosen around them. Returns a :class:`Choice`.
    """
    region = region or GLOBAL
    # the user's numbers, before any is used in a formula (geoidspline.options)
    tolerance_m = check_number("tolerance_m", tolerance_m)
    given = check_numbers(dict(given or {}))
    everything_given = all(f in given for f in CHOSEN_FIELDS if f not in ("tolerance_m", "refinement"))
    if getattr(source.provenance, "kind", None) == "harmonic" and hasattr(source, "max_degree") \
            and given.get("method", "interpolation") == "interpolation" \
            and given.get("refinement", "overlays") == "overlays":
        values, reasons = _for_model(source, tolerance_m, region, given)
    else:
        values, reasons = _for_grid(source, tolerance_m, region, given)
        if not everything_given and given.get("method", "least-squares") == "least-squares":
            values["refinement"], reasons["refinement"] = "hierarchical", HIERARCHICAL_REASON
    for name in given:
        reasons[name] = "given"
    values.setdefault("refinement", "overlays")
    reasons.setdefault("refinement", OVERLAYS_REASON + (": the expert's command as before" if everything_given else ""))
    values.update(given)
    fields = {f.name for f in dataclasses.fields(FitParameters)}
    return Choice(FitParameters(**{k: v for k, v in values.items() if k in fields}), reasons, tolerance_m)


def _for_model(source, tolerance_m, region, given):
    degree = int(source.max_degree)
    values, reasons = {"method": "interpolation"}, {}
    reasons["method"] = ("quasi-interpolation: the model is exact everywhere, so level 0 needs no "
                         "linear solve; least-squares overlays only where nodes stay above the tolerance")
    values["tolerance_m"] = tolerance_m
    reasons["tolerance_m"] = (f"given: {tolerance_m:g} m at the sample lattice's nodes and at random check "
                              "points of the exact synthesis, in the store read back")
    # a whole globe is fitted band by band (fitting.bands), its bands made as small as
    # the memory allows (fitting.memory.banded_parameters): no cap on the globe's level 0
    banded = uses_bands(FitParameters(method="interpolation", refinement="overlays"), region)
    level0_target = (BANDED_LEVEL0_OVER_TOLERANCE if banded else LEVEL0_OVER_TOLERANCE) * tolerance_m
    area = region_area(region)
    # the whole sphere's spectrum and extreme, whatever the region: a region's rings hold
    # their average power, not the region's own (EGM96 over the Himalaya is three times
    # rougher at level 0 than its latitudes' average), and the global prediction is
    # calibrated on the Himalaya (benchmarks/README.md, "level 0 predicted from the
    # model's spectrum")
    spectrum = (ModelSpectrum.of(source)
                if hasattr(source, "degree_power") and not ("h0" in given and "order" in given) else None)
    # the order with the fewest level-0 coefficients at the error target
    candidates = {}
    for order in ([given["order"]] if "order" in given else sorted(MEASURED)):
        if order not in MEASURED and not given.get("h0"):
            raise FitError(f"no measured convergence for order {order} to choose h0 from: give h0 (--h0) too, "
                           f"or an order of {sorted(MEASURED)}")
        h0 = given.get("h0") or (
            spacing_for_level0(spectrum, order, level0_target, 4.0 * math.pi, _max_h_times_degree(order) / degree)
            if spectrum is not None else _level0_spacing(order, degree, level0_target))
        # an order not measured comes with its h0 given: no count to compare (nor needed)
        count = MEASURED[order].density * area / h0**2 if order in MEASURED else math.nan
        candidates[order] = (h0, count)
    order = min(candidates, key=lambda o: candidates[o][1])
    h0, count = candidates[order]
    if "order" not in given:
        others = ", ".join(f"order {o}: {c:,.0f}" for o, (_, c) in sorted(candidates.items()) if o != order)
        reasons["order"] = (f"{order}: fewest level-0 coefficients for {level0_target * 1e3:.2g} mm "
                            f"(about {count:,.0f}; {others}) by "
                            + ("the model's spectrum" if spectrum is not None else "the measured convergence"))
    values["order"] = order
    capped = False
    if "h0" not in given:
        ref = MEASURED[order]
        exact = h0
        if count > MAX_LEVEL0_COEFFICIENTS and not banded:
            h0 = math.sqrt(ref.density * area / MAX_LEVEL0_COEFFICIENTS)
            capped = True
        h0 = min(_round_down(h0), 0.1)
        if spectrum is not None:
            predicted_max, predicted_rms = predicted_level0(spectrum, h0, order, 4.0 * math.pi)
            law = (f"the model's degree variances (fitting.level0_error, max/RMS calibrated on the measured "
                   f"EGM96 curve): predicted level-0 max {predicted_max * 1e3:.3g} mm over the sphere, RMS "
                   f"{predicted_rms * 1e3:.3g} mm on the worst ring at h0 {h0:g}")
        else:
            law = "the measured level-0 error against h N (EGM96, fitting.choose.LEVEL0_ERROR)"
        if capped:
            reasons["h0"] = (f"{h0:g}: capped at {MAX_LEVEL0_COEFFICIENTS:,} level-0 coefficients (memory); "
                             f"{exact:.3g} would reach {level0_target * 1e3:.2g} mm by {law}; overlays take the rest")
        elif exact * degree >= _max_h_times_degree(order) - 1e-12:
            reasons["h0"] = (f"{h0:g}: h N = {h0 * degree:.3g}, the coarsest measured for order {order} "
                             f"(a coarser spline stops resolving degree {degree})")
        else:
            reasons["h0"] = (f"{h0:g}: h N = {h0 * degree:.3g} for a level-0 max error of "
                             f"{level0_target * 1e3:.2g} mm by {law}")
    values["h0"] = h0
    if "max_level" not in given:
        values["max_level"] = 2 if capped else 1
        reasons["max_level"] = (f"{values['max_level']}: " + (
            "level 0 is capped, two overlay levels" if capped else
            "one least-squares overlay (half spacing) for the few nodes level 0 leaves above the tolerance"))
    if "sample_spacing_deg" not in given:
        spacing = min(NODE_SPACING_DEG, 30.0 / degree)
        values["sample_spacing_deg"] = spacing
        reasons["sample_spacing_deg"] = (f"{spacing:.4g} deg: 5' nodes as in the measured fits (or 30/N when finer), "
                                         f"{math.degrees(h0) / spacing:.1f} nodes a level-0 cell to measure the error")
    return values, reasons


def _for_grid(source, tolerance_m, region, given):
    defaults = FitParameters()
    values = {"method": "least-squares", "order": defaults.order, "h0": defaults.h0}
    reasons = {
        "method": ("least squares: the hierarchical basis is fitted at once by least squares"
                   if given.get("refinement") == "hierarchical" and getattr(source, "max_degree", None)
                   else "least squares: a grid is known at its nodes only"),
        "order": f"{defaults.order} (cubic, C²), h0 {defaults.h0:g}: the thesis's Andes headline "
                 "(benchmarks scenario andes: < 0.5 m with 21,472 coefficients of the hierarchical basis, "
                 "results/fits.jsonl 2026-12-02T13:52)",
        "h0": f"{defaults.h0:g}: as the Andes headline",
    }
    h0 = given.get("h0", defaults.h0)
    spacing = _data_spacing_rad(source, region)
    if spacing is None:
        values["max_level"] = defaults.max_level
        reasons["max_level"] = f"{defaults.max_level}: the default (the source's node spacing is unknown)"
    else:
        finest = MIN_H_PER_DATA_SPACING * spacing
        level = max(0, min(12, math.floor(math.log2(h0 / finest) + 1e-9)))
        values["max_level"] = level
        reasons["max_level"] = (f"{level}: h = {h0 / 2**level:.4g} is the finest level at least {MIN_H_PER_DATA_SPACING:g} x "
                                f"the data spacing ({spacing:.4g} on the unit sphere); finer is not determined "
                                "between the nodes")
    values["tolerance_m"] = tolerance_m
    reasons["tolerance_m"] = f"given: {tolerance_m:g} m at the grid's nodes, in the store read back"
    reasons["sample_spacing_deg"] = ("the source's own nodes" if spacing is not None
                                     else "the default for a least-squares fit of a model: 90/N, at most h0/4")
    return values, reasons


def _data_spacing_rad(source, region: Region) -> float | None:
    """The node spacing the driver measures (:func:`geoidspline.fitting.driver.fit_nodes`)."""
    lat_step = getattr(source, "latitude_spacing", None)
    lon_step = getattr(source, "longitude_spacing", None)
    if lat_step is None or lon_step is None:
        return None
    south = max(region.south, source.extent.south)
    north = min(region.north, source.extent.north)
    lat = np.arange(south, north + 0.5 * lat_step, lat_step) if north > south else np.array([south])
    mean_cos = float(np.cos(np.radians(np.abs(lat))).mean())
    return max(math.radians(lat_step), math.radians(lon_step) * mean_cos)
