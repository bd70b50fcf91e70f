"""Geoid heights in the three tide systems: the offsets between them, for N.

The permanent tide changes C̄20 by ΔC̄20 (:class:`~geoidspline.geodesy.ellipsoids.PermanentTide`,
IERS Conventions 2010 §6.2.2: A0H0 = −1.39119e-8, NGA's k20 = 0.3), so N by
a·ΔC̄20·P̄20(sin φ) with P̄20 = √5 (3 sin²φ − 1)/2 (Bruns's formula, GM/(aγ) ≈ a):

- N_mean − N_zero = −0.1984 (3/2 sin²φ − 1/2) m = 9.9 − 29.8 sin²φ cm,
- N_zero − N_free = k20 times that, N_mean − N_free = (1 + k20) times that,

Ekman (1989), Bull. Géod. 63:281-296 (N_mean − N_free = (1 + k)(9.9 − 29.6 sin²φ) cm)
and Mäkinen & Ihde (2009), IAG Symposia 133:81-87, to 1 mm. The same numbers convert
harmonic models' C̄20, so a grid and a model convert alike.
"""

from __future__ import annotations

import math
import re

import numpy as np

from ..errors import GeoidSplineError, StoreError
from .ellipsoids import PERMANENT_TIDE, TIDE_SYSTEMS, WGS84, gaussian_mean_radius

__all__ = ["TIDE_SYSTEM_NAMES", "tide_offset_m", "tide_slope_north", "parse_tide_system", "tide_conversion"]

#: The tide-system names a command accepts: the library's and their hyphenated spellings.
TIDE_SYSTEM_NAMES = TIDE_SYSTEMS + tuple(t.replace("_", "-") for t in TIDE_SYSTEMS)


def _dc20(source: str, target: str) -> float:
    for system in (source, target):
        if system not in TIDE_SYSTEMS:
            raise ValueError(f"unknown tide system {system!r}; expected one of {', '.join(TIDE_SYSTEMS)}")
    return PERMANENT_TIDE.c20_offset(target) - PERMANENT_TIDE.c20_offset(source)


def tide_offset_m(latitude_deg, source: str, target: str):
    """N_target − N_source (metres) at geodetic latitude φ (degrees), for geoid heights."""
    phi = np.radians(np.asarray(latitude_deg, dtype=np.float64))
    return WGS84.a * _dc20(source, target) * math.sqrt(5.0) * (1.5 * np.sin(phi) ** 2 - 0.5)


def tide_slope_north(latitude_deg, source: str, target: str):
    """d(N_target − N_source)/dnorth (metres per metre) at geodetic latitude φ (degrees):
    the derivative of :func:`tide_offset_m` over the Gaussian mean radius, as
    :func:`geoidspline.query.derived.deflection` measures slopes."""
    phi = np.radians(np.asarray(latitude_deg, dtype=np.float64))
    return (WGS84.a * _dc20(source, target) * math.sqrt(5.0) * 3.0 * np.sin(phi) * np.cos(phi)
            / gaussian_mean_radius(latitude_deg))


def parse_tide_system(text: str | None) -> str | None:
    """``tide-free``/``tide_free``/``tide free`` -> ``tide_free``; None stays None."""
    if text is None:
        return None
    key = re.sub(r"[\s-]+", "_", str(text).strip().lower())
    if key not in TIDE_SYSTEMS:
        raise GeoidSplineError(f"unknown tide system {text!r}; expected one of {', '.join(TIDE_SYSTEMS)}")
    return key


def tide_conversion(own: str | None, asked: str | None, what) -> tuple[str, str] | None:
    """(own system, asked one) for answers asked in ``asked``; None when nothing is to
    convert; refused (naming ``what``, a store) when its own system is unknown."""
    target = parse_tide_system(asked)
    if target is None or target == own:
        return None
    if own is None:
        raise StoreError(f"{what}: the store's tide system is unknown, so it cannot be converted to {target} "
                         "(--tide-system needs a store that records its own)")
    return own, target
