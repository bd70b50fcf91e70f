"""Every number a user can give, checked in one place: finite, in range, the range in the message.

Each numeric parameter of the public API (and the command-line option that sets it) has
one :class:`NumberRule` in :data:`RULES`, keyed by its Python name. :func:`check_number`
is the one check: the API functions call it on their keyword arguments,
:class:`~geoidspline.fitting.parameters.FitParameters` on its fields, and the commands'
options through a click type that calls it too (``cli/_common.py``), so that ``--h0 0``,
``h0=0`` and ``FitParameters(h0=0)`` are refused with the same sentence.

The ranges are what the method and the formats can honour, not taste: a tolerance
beyond 1000 m is larger than the geoid itself; an ``h0`` below 1e-4 (0.64 km at the
Earth's surface) is finer than any published grid's nodes, and below ~2e-6 the
coefficient indices would not fit their 21 bits.
"""

from __future__ import annotations

import math
import numbers
import re
from dataclasses import dataclass

from .errors import ParameterError

__all__ = ["DECIMAL", "NumberRule", "OptionError", "RULES", "check_number", "check_numbers", "parse_decimal"]


class OptionError(ParameterError):
    """A numeric parameter that is not a finite number in its range.

    ``name`` is the Python parameter, ``requirement`` the rule in words ("a finite
    number in (0, 1000] metres"), ``value`` what was given.
    """

    def __init__(self, name: str, requirement: str, value):
        self.name = name
        self.requirement = requirement
        self.value = value
        super().__init__(f"{name} must be {requirement}, got {value!r}")


@dataclass(frozen=True)
class NumberRule:
    """A numeric parameter's range: ``low``/``high`` (inclusive unless ``*_open``),
    ``integer`` for counts, ``unit`` for the message."""

    low: float
    high: float
    unit: str = ""
    integer: bool = False
    low_open: bool = False
    high_open: bool = False
    optional: bool = False  # None is a value ("chosen", "the store's")

    @property
    def requirement(self) -> str:
        kind = "a whole number" if self.integer else "a finite number"
        left = "(" if self.low_open else "["
        right = ")" if self.high_open else "]"
        unit = f" {self.unit}" if self.unit else ""
        return f"{kind} in {left}{self.low:g}, {self.high:g}{right}{unit}"

    def check(self, name: str, value):
        """``value`` as an int or float when it keeps the rule, else :class:`OptionError`.

        Strings are read as Python reads numbers only for the command line's sake (click
        hands over text); bools are refused (``True`` is not a count)."""
        if value is None and self.optional:
            return None
        number = _as_number(value, self.integer)
        if number is None:
            raise OptionError(name, self.requirement, value)
        low_ok = number > self.low if self.low_open else number >= self.low
        high_ok = number < self.high if self.high_open else number <= self.high
        if not (low_ok and high_ok):
            raise OptionError(name, self.requirement, value)
        return number


#: A plain decimal number in ASCII: optional sign, digits with an optional fraction (or
#: a fraction alone), optional exponent. Not Python's wider float(): no ``1_000``, no
#: non-ASCII digits, no ``nan``/``inf``, no hexadecimal.
DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def parse_decimal(text: str) -> float:
    """The float a plain ASCII decimal (:data:`DECIMAL`, blanks around it allowed)
    spells; ValueError for anything else, and for a number beyond float's range."""
    text = text.strip(" \t\r\n")
    if not DECIMAL.fullmatch(text):
        raise ValueError(f"not a plain decimal number: {text!r}")
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"beyond the range of a float: {text!r}")
    return value


def _as_number(value, integer: bool):
    """The int/float in ``value`` (a number or its text), None when there is none or it
    is not finite."""
    if isinstance(value, bool):
        return None
    if isinstance(value, str):
        try:
            value = parse_decimal(value)
        except ValueError:
            return None
    if isinstance(value, numbers.Integral):
        value = int(value)
        return value if integer or abs(value) < 2 ** 63 else None
    if isinstance(value, numbers.Real):
        value = float(value)
        if not math.isfinite(value):
            return None
        if integer:
            return int(value) if value.is_integer() else None
        return value
    return None


#: Python parameter name -> its rule. The command-line option that sets each one is
#: named in ``cli/_common.OPTION_NAMES`` where the names differ.
RULES: dict[str, NumberRule] = {
    # fitting (geoid-fit, fit(), FitParameters)
    "tolerance_m": NumberRule(1e-9, 1000.0, "metres"),
    "h0": NumberRule(1e-4, 0.5, "(unit-sphere spacing of level 0; 0.1 is 637 km)"),
    "max_level": NumberRule(0, 12, integer=True),
    "order": NumberRule(2, 8, "(4 = cubic, C²)", integer=True),
    # a model synthesised finer than 3.6" (degree ~50 000) is beyond any published model
    "sample_spacing_deg": NumberRule(1e-3, 5.0, "degrees", optional=True),
    "workers": NumberRule(1, 1024, "processes", integer=True),
    "max_memory_gb": NumberRule(0.01, 1e6, "GB", optional=True),
    # regional updates (geoid-update, update())
    "blend_width_km": NumberRule(0.0, 20_000.0, "km"),
    "update_tolerance_m": NumberRule(1e-9, 1000.0, "metres", optional=True),
    "wait_seconds": NumberRule(0.0, 86_400.0, "seconds"),
    # geoid-info --check-against
    "points": NumberRule(1, 10_000_000, "points", integer=True),
    # geoid-export, geoid-plot
    # 1e-6 degrees is 0.1 m: finer grids than that are no geoid product
    "spacing_deg": NumberRule(1e-6, 180.0, "degrees"),
    "plot_spacing_deg": NumberRule(1e-6, 180.0, "degrees", optional=True),
    "dpi": NumberRule(30, 1200, "dots per inch", integer=True),
    # geoid-query
    "precision": NumberRule(0, 15, "decimals", integer=True),
    # a far column is a row's error ("expected at least N columns"), not the option's
    "height_column": NumberRule(0, 2**53, "(0-based column)", integer=True, optional=True),
    # a region's bound: a plain finite number here; the region's own rules
    # (:class:`~geoidspline.sphere.region.Region`: latitudes within ±90, longitudes within
    # ±540, at most one turn) then say what is wrong with the bounds together
    "region_bound_deg": NumberRule(-1e6, 1e6, "degrees"),
}

def check_number(name: str, value, rule: str | None = None):
    """``value`` checked by the rule of parameter ``name`` (or of ``rule``); returns it as
    an int or float, raises :class:`OptionError` naming ``name`` and the range."""
    key = rule or name
    return RULES[key].check(name, value)


def check_numbers(values: dict, **rules) -> dict:
    """Every entry of ``values`` that has a rule, checked (``rules``: parameter name ->
    rule key where they differ); the others are returned as they are."""
    out = dict(values)
    for name, value in values.items():
        key = rules.get(name, name)
        if key in RULES:
            out[name] = check_number(name, value, key)
    return out
