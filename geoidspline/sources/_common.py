"""Checks and text-lattice helpers shared by the exchange-format readers (ISG, GSI, GeoTIFF).

(The plausibility of the values, ±150 m, is checked for every reader by
:func:`geoidspline.sources.files.finish_grid`.)

- :func:`parse_values`: the whitespace-separated numbers of a text grid, with an error
  naming the line of the first one that is not a number;
- :func:`snap_spacing` / :func:`snap_origin`: the lattice a header *means* when it
  writes 1/60 degree as ``0.016667`` (GSI, ISG ``deg``) or 39°50' as ``39.833333``:
  a value is snapped to 1/k degree, a whole number of arc-seconds, or a multiple of
  half the spacing only when that lies within half a unit of the last digit written.
"""

from __future__ import annotations

import re

import numpy as np

from ..errors import InputFileError

__all__ = [
    "MAX_TEXT_NODES",
    "decimals_tolerance",
    "parse_values",
    "snap_spacing",
    "snap_origin",
]

#: Largest number of nodes a text grid may declare (1e8 nodes: a 0.5' global grid
#: holds 9.3e8, no published text grid comes near 1e8). Checked before allocating.
MAX_TEXT_NODES = 100_000_000

_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")


def decimals_tolerance(text: str) -> float:
    """How far the value meant may lie from the number ``text`` says, in its units.

    Half a unit of the last decimal (``"0.016667"`` -> 5e-7) for a number written
    with at least 4 decimals, the fixed widths of ISG (4 or 6) and GSI (5 or 6) headers
    that round 1' to ``0.0167``/``0.016667``; 0 (exact as written) for fewer decimals
    (``"12.2"``, ``"40"``) and for exponent notation.
    """
    text = text.strip().lower()
    if "e" in text or "." not in text:
        return 0.0
    decimals = len(text.split(".")[1])
    return 0.5 * 10.0 ** -decimals if decimals >= 4 else 0.0


def snap_spacing(value: float, tolerance: float) -> float:
    """The spacing (degrees) meant by ``value`` written to within ``tolerance``.

    1/k degree (1/60 = 1', 1/3 = 20') first, then a whole number of arc-seconds; the
    value itself when neither lies within the tolerance (always for tolerance 0).
    """
    if tolerance <= 0.0:
        return value
    if 0.0 < value < 1.0:
        k = round(1.0 / value)
        if k > 0 and abs(1.0 / k - value) <= tolerance:
            return 1.0 / k
    seconds = round(value * 3600.0)
    if seconds > 0 and abs(seconds / 3600.0 - value) <= tolerance:
        return seconds / 3600.0
    return value


def snap_origin(value: float, spacing: float, tolerance: float) -> float:
    """``value`` snapped to a multiple of half the spacing when within ``tolerance``."""
    if tolerance <= 0.0:
        return value
    half = spacing / 2.0
    candidate = round(value / half) * half
    return candidate if abs(candidate - value) <= tolerance else value


def parse_values(path, text: str, first_line: int, what: str) -> np.ndarray:
    """The whitespace-separated numbers of ``text`` as float64.

    ``first_line`` is the file's line number of the first line of ``text`` (1-based),
    so that an error names the line of the first token that is not a number.
    """
    tokens = text.split()
    try:
        values = np.array(tokens, dtype=np.float64)
    except ValueError:
        for offset, line in enumerate(text.splitlines()):
            for column, token in enumerate(line.split(), start=1):
                if not _NUMBER.match(token):
                    raise InputFileError(
                        path,
                        f"{what}: line {first_line + offset}, value {column} is {token[:40]!r}, not a number",
                    ) from None
        raise InputFileError(path, f"{what}: a value is not a number") from None
    bad = ~np.isfinite(values)
    if bad.any():
        index = int(np.argmax(bad))
        raise InputFileError(
            path, f"{what}: value number {index + 1} is {tokens[index]!r}; a grid marks no data with its "
            "no-data value, not with nan or inf"
        )
    return values
