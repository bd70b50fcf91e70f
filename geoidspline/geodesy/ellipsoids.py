"""Reference ellipsoids and their normal gravity fields, as frozen value objects.

Every number here is either a defining constant (with its reference in a comment) or
derived from those with the closed formulas of Heiskanen & Moritz (1967) "Physical
Geodesy" §2-7..2-10, restated in Moritz (2000) "Geodetic Reference System 1980",
J. Geodesy 74:128-133 and NIMA TR8350.2 (3rd ed., 2000) ch. 3. The derived values are
checked in the tests against the published ones (WGS84: J2 = 0.108262982131e-2,
C̄20 = -0.484166774985e-3, γe = 9.7803253359 m/s², k = 0.00193185265246).

Units: metres, m³/s², rad/s, m/s².
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError

__all__ = ["Ellipsoid", "WGS84", "GRS80", "PermanentTide", "PERMANENT_TIDE", "TIDE_SYSTEMS", "gaussian_mean_radius", "MEAN_EARTH_RADIUS_KM", "KM_PER_DEGREE"]


def _q0_series(ep: float) -> float:
    """q0 = ½[(1 + 3/e'²) arctan e' − 3/e'] (H&M 2-58) as its series.

    The closed form loses ~6 digits to cancellation for e' ≈ 0.08; the series
    q0 = 2 Σ (−1)^(j+1) j e'^(2j+1) / ((2j+1)(2j+3)) (Moritz 2000 eq. 11) does not.
    Summed from the small terms up.
    """
    total = 0.0
    for j in range(40, 0, -1):
        total += (-1) ** (j + 1) * j * ep ** (2 * j + 1) / ((2 * j + 1) * (2 * j + 3))
    return 2.0 * total


def _q0_prime_series(ep: float) -> float:
    """q0' = 3(1 + 1/e'²)(1 − arctan(e')/e') − 1 (H&M 2-67) as its series
    6 Σ (−1)^(j+1) e'^(2j) / ((2j+1)(2j+3)), for the same reason as :func:`_q0_series`."""
    total = 0.0
    for j in range(40, 0, -1):
        total += (-1) ** (j + 1) * ep ** (2 * j) / ((2 * j + 1) * (2 * j + 3))
    return 6.0 * total


@dataclass(frozen=True)
class Ellipsoid:
    """A level ellipsoid: geometry (a, f) plus GM and ω define its normal field.

    ``a`` semi-major axis (m), ``f`` flattening, ``gm`` geocentric gravitational
    constant (m³/s²), ``omega`` angular velocity (rad/s). Everything else is derived.
    """

    name: str
    a: float
    f: float
    gm: float
    omega: float

    # --- geometry -------------------------------------------------------------------
    @property
    def b(self) -> float:
        """Semi-minor axis (m)."""
        return self.a * (1.0 - self.f)

    @property
    def e2(self) -> float:
        """First eccentricity squared e² = f(2 − f)."""
        return self.f * (2.0 - self.f)

    @property
    def ep2(self) -> float:
        """Second eccentricity squared e'² = e²/(1 − e²)."""
        return self.e2 / (1.0 - self.e2)

    @property
    def linear_eccentricity(self) -> float:
        """E = √(a² − b²) (m)."""
        return self.a * math.sqrt(self.e2)

    # --- normal field ---------------------------------------------------------------
    @property
    def m(self) -> float:
        """m = ω²a²b/GM (H&M 2-70)."""
        return self.omega**2 * self.a**2 * self.b / self.gm

    @property
    def _ratio(self) -> float:
        # e' q0'/q0, the factor shared by γe, γp (H&M 2-73, 2-74)
        ep = math.sqrt(self.ep2)
        return ep * _q0_prime_series(ep) / _q0_series(ep)

    @property
    def gamma_e(self) -> float:
        """Normal gravity at the equator (m/s²), H&M 2-73 / TR8350.2 eq. 3-33."""
        return self.gm / (self.a * self.b) * (1.0 - self.m - self.m / 6.0 * self._ratio)

    @property
    def gamma_p(self) -> float:
        """Normal gravity at the poles (m/s²), H&M 2-74 / TR8350.2 eq. 3-34."""
        return self.gm / self.a**2 * (1.0 + self.m / 3.0 * self._ratio)

    @property
    def k(self) -> float:
        """Somigliana's constant k = bγp/(aγe) − 1 (H&M 2-78)."""
        return self.b * self.gamma_p / (self.a * self.gamma_e) - 1.0

    @property
    def u0(self) -> float:
        """Normal potential on the ellipsoid U0 = GM/E·arctan(e') + ω²a²/3 (m²/s², H&M 2-61)."""
        ep = math.sqrt(self.ep2)
        return self.gm / self.linear_eccentricity * math.atan(ep) + self.omega**2 * self.a**2 / 3.0

    def normal_gravity(self, sin2_lat):
        """Somigliana's closed formula on the ellipsoid (m/s²) for sin²(geodetic latitude).

        γ = γe (1 + k sin²φ) / √(1 − e² sin²φ) (H&M 2-78; TR8350.2 eq. 4-1). Works on
        NumPy arrays.
        """
        return self.gamma_e * (1.0 + self.k * sin2_lat) / (1.0 - self.e2 * sin2_lat) ** 0.5

    def J(self, degree: int) -> float:
        """Unnormalised even zonal J_2n of the normal field (dimensionless).

        J2 = (e²/3)(1 − (2/15) m e'/q0)  (H&M 2-90 with 2-72),
        J2n = (−1)^(n+1) 3 e^(2n) / ((2n+1)(2n+3)) · (1 − n + 5n J2/e²)  (H&M 2-92;
        TR8350.2 eq. 3-61). Odd degrees and degree 0 of the disturbing part are zero.
        """
        if degree < 2 or degree % 2:
            raise ValueError(f"J is defined here for even degrees >= 2, got {degree}")
        e2 = self.e2
        ep = math.sqrt(self.ep2)
        j2 = e2 / 3.0 * (1.0 - 2.0 / 15.0 * self.m * ep / _q0_series(ep))
        n = degree // 2
        if n == 1:
            return j2
        return (-1) ** (n + 1) * 3.0 * e2**n / ((2 * n + 1) * (2 * n + 3)) * (1.0 - n + 5.0 * n * j2 / e2)

    def zonal_cbar(self, degree: int) -> float:
        """Fully normalised C̄n0 of the normal field: C̄n0 = −Jn/√(2n+1) (0 for odd n)."""
        if degree >= 2 and degree % 2 == 0:
            return -self.J(degree) / math.sqrt(2 * degree + 1)
        return 0.0


# WGS84: a = 6378137 m, 1/f = 298.257223563, GM = 3.986004418e14 m³/s² and
# ω = 7.292115e-5 rad/s are the defining constants of NIMA TR8350.2 (3rd ed., 2000),
# Table 3.1 (a and f are PROJ's too, tested). Written out rather than asked of PROJ, so
# that importing them does not import pyproj (a one-point query never needs it).
WGS84 = Ellipsoid("WGS84", 6378137.0, 1.0 / 298.257223563, gm=3.986004418e14, omega=7.292115e-5)


# GRS80: a = 6378137 m, 1/f = 298.257222101 (derived from J2 = 108263e-8, as PROJ stores
# it); GM = 3.986005e14 m³/s², ω = 7.292115e-5 rad/s: Moritz (2000), J. Geodesy 74:128-133.
GRS80 = Ellipsoid("GRS80", 6378137.0, 1.0 / 298.257222101, gm=3.986005e14, omega=7.292115e-5)


TIDE_SYSTEMS = ("tide_free", "zero_tide", "mean_tide")


@dataclass(frozen=True)
class PermanentTide:
    """The permanent-tide part of C̄20 and the conversions between tide systems.

    IERS Conventions (2010), IERS TN 36, §6.2.2: the time-independent part of the degree-2
    tide adds ⟨ΔC̄20⟩ = A0 H0 k20 to C̄20, with A0 H0 = −1.39119e-8 (the same number is
    −3.11080e-8/√5 of the EGM96 report, Lemoine et al. 1998, §11.2). NGA uses k20 = 0.3
    for EGM96 and EGM2008 (IERS's nominal value is 0.30190), which reproduces EGM2008's
    published pair C̄20 = −0.484165143790815e-3 (tide free) and −0.484169317366974e-3
    (zero tide) to 6e-15.

    - zero tide = tide free + k20·A0H0       (indirect effect of the permanent tide kept)
    - mean tide = tide free + (1 + k20)·A0H0 (direct + indirect effect kept)

    The zero-tide Earth is the more flattened one: its C̄20 is the more negative.
    """

    a0h0: float = -1.39119e-8
    love_k20: float = 0.3

    def c20_offset(self, system: str) -> float:
        """ΔC̄20 of ``system`` relative to the tide-free value."""
        if system == "tide_free":
            return 0.0
        if system == "zero_tide":
            return self.love_k20 * self.a0h0
        if system == "mean_tide":
            return (1.0 + self.love_k20) * self.a0h0
        raise ParameterError(f"unknown tide system {system!r}; expected one of {TIDE_SYSTEMS}")

    def convert_c20(self, c20: float, source: str, target: str) -> float:
        """C̄20 of ``source`` tide system expressed in the ``target`` one."""
        return c20 - self.c20_offset(source) + self.c20_offset(target)


PERMANENT_TIDE = PermanentTide()


def gaussian_mean_radius(latitude, ellipsoid=WGS84):
    """Gaussian mean radius of curvature √(M N) (metres) at geodetic latitude (degrees).

    M = a(1 − e²)/W³ (meridian) and N = a/W (prime vertical), W = √(1 − e² sin²φ), so
    √(M N) = a √(1 − e²) / W². On WGS84 it runs from 6,356,752 m (= b, at the equator)
    to 6,399,594 m (= a²/b, at the poles).
    """
    phi = np.radians(np.asarray(latitude, dtype=np.float64))
    e2 = ellipsoid.e2
    w2 = 1.0 - e2 * np.sin(phi) ** 2
    return ellipsoid.a * math.sqrt(1.0 - e2) / w2


#: The mean Earth radius R1 = (2a + b)/3 of WGS84, rounded (km), and the length of one
#: degree of arc on that sphere: how a width in km becomes degrees (blend zones).
MEAN_EARTH_RADIUS_KM = 6371.0
KM_PER_DEGREE = MEAN_EARTH_RADIUS_KM * 3.141592653589793 / 180.0
