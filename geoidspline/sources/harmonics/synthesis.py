"""Geoid undulations N (metres) from a spherical-harmonic model, as NGA computes them.

:class:`GeoidSynthesis` implements ../reference/METHOD.md §6 for a point on the
ellipsoid (h = 0) at geodetic latitude φ and longitude λ (degrees):

1. geocentric radius r and latitude ψ of the ellipsoid point;
2. T = (GM/r) Σ_{n=2}^{N} (a/r)^n Σ_m (ΔC̄nm cos mλ + S̄nm sin mλ) P̄nm(sin ψ), with the
   even zonals of the reference ellipsoid's normal field subtracted;
3. ζ = T/γ(φ), Somigliana normal gravity on the ellipsoid;
4. N = ζ + C(φ, λ) + N0, C the ζ-to-N correction series (no (a/r)^n factor), N0 the
   zero-degree term.

Presets (the constants each uses are in :class:`Conventions`):

- ``"nga-f477"``: NGA's F477.F for EGM96 (source read: the NIMA routines ``hundu``,
  ``radgra``, ``dhcsin``). The sum is scaled by the **WGS84** GM = 3.986004418e14 and
  a = 6378137 m whatever the model's constants; C̄n0 += Jn/√(2n+1) with NGA's literal
  WGS84 J2..J10; γ from geqt = 9.7803253359, k = 0.00193185265246,
  e² = 0.00669437999013; CORRCOEF/100 summed over n = 0..N; N0 = −0.53 m.
- ``"nga-hsynth"``: NGA's hsynth_WGS84 for EGM2008: the model's own GM and a scale the
  sum; the WGS84 zonals are rescaled to them, ΔC̄n0 = C̄n0 + (GM84/GM)(a84/a)^n Jn/√(2n+1);
  same γ and point geometry as F477; N0 = −0.41 m. (Not checked against NGA output: the
  EGM2008 files for that are not available here.)
- ``"generic"``: like hsynth but every constant derived from ``ellipsoid``
  (:mod:`geoidspline.geodesy`), even zonals to degree min(N, 20), N0 = 0 unless given.

Degrees 0 and 1 of the model never enter T (their effect is what N0 stands for). A
``max_degree`` below the model's truncates the model, the normal zonals and the
correction alike.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass

import numpy as np

from ..._kernels import legendre
from ...errors import CoordinateError, InputFileError, ParameterError
from ...geodesy.ellipsoids import WGS84, Ellipsoid
from ...geodesy.limits import MAX_ABS_UNDULATION_M
from ...sphere.region import GLOBAL, Region
from ..base import NodeSample, Provenance
from .models import CorrectionModel, HarmonicModel
from .presets import DEFAULT_PRESET, PRESETS

__all__ = ["GeoidSynthesis", "Conventions", "PRESETS", "NGA_WGS84_J"]


# NGA's WGS84 (G873) even zonals, F477.F subroutine dhcsin ("computed using subroutine
# GRS written by N.K. Pavlis"); they equal Ellipsoid.J(n) of WGS84 to 12 digits.
NGA_WGS84_J = {
    2: 0.108262982131e-2,
    4: -0.237091120053e-05,
    6: 0.608346498882e-8,
    8: -0.142681087920e-10,
    10: 0.121439275882e-13,
}


@dataclass(frozen=True)
class Conventions:
    """The constants one preset uses (SI units).

    ``scale_gm``/``scale_a`` scale the potential sum; ``zonal_terms`` maps n to the
    amount added to C̄n0 (= −C̄n0 of the normal field in that scaling); ``gamma_e``,
    ``gamma_k``, ``gamma_e2`` give Somigliana's γ; ``point_a``/``point_e2`` place the
    ellipsoid point; ``n0_m`` is the default zero-degree term (m).
    """

    preset: str
    scale_gm: float
    scale_a: float
    zonal_terms: tuple[tuple[int, float], ...]
    gamma_e: float
    gamma_k: float
    gamma_e2: float
    point_a: float
    point_e2: float
    n0_m: float


# F477.F radgra: a = 6378137, e2 = .00669437999013, geqt = 9.7803253359,
# k = .00193185265246; hundu: gm = .3986004418d15, ae = 6378137, N0 = -0.53 m.
_NGA_GAMMA = dict(gamma_e=9.7803253359, gamma_k=0.00193185265246, gamma_e2=0.00669437999013)
_NGA_POINT = dict(point_a=6378137.0, point_e2=0.00669437999013)
_NGA_GM, _NGA_A = 3.986004418e14, 6378137.0


def _conventions(preset: str, model: HarmonicModel, ellipsoid: Ellipsoid, nmax: int) -> Conventions:
    if preset == "nga-f477":
        terms = tuple((n, j / math.sqrt(2 * n + 1)) for n, j in NGA_WGS84_J.items() if n <= nmax)
        return Conventions(preset, _NGA_GM, _NGA_A, terms, **_NGA_GAMMA, **_NGA_POINT, n0_m=-0.53)
    if preset == "nga-hsynth":
        terms = tuple(
            (n, (_NGA_GM / model.gm) * (_NGA_A / model.radius) ** n * j / math.sqrt(2 * n + 1))
            for n, j in NGA_WGS84_J.items()
            if n <= nmax
        )
        return Conventions(preset, model.gm, model.radius, terms, **_NGA_GAMMA, **_NGA_POINT, n0_m=-0.41)
    terms = tuple(
        (n, (ellipsoid.gm / model.gm) * (ellipsoid.a / model.radius) ** n * -ellipsoid.zonal_cbar(n))
        for n in range(2, min(nmax, 20) + 1, 2)
    )
    return Conventions(
        preset,
        model.gm,
        model.radius,
        terms,
        gamma_e=ellipsoid.gamma_e,
        gamma_k=ellipsoid.k,
        gamma_e2=ellipsoid.e2,
        point_a=ellipsoid.a,
        point_e2=ellipsoid.e2,
        n0_m=0.0,
    )


#: NGA publishes EGM2008's zeta-to-N correction to degree 2160 only
#: (Zeta-to-N_to2160_egm2008), and its hsynth_WGS84 sums it beside the degree-2190
#: model: that correction is accepted for a synthesis up to degree 2190.
NGA_EGM2008_CORRECTION_DEGREE = 2160
NGA_EGM2008_DEGREE = 2190


def _check_correction_degree(correction: CorrectionModel | None, nmax: int, explicit: bool) -> None:
    """Refuse a correction that stops below the synthesis degree (its missing degrees
    would silently be zero): a degree-60 CORRCOEF beside a degree-360 model."""
    if correction is None or correction.max_degree >= nmax:
        return
    if correction.max_degree == NGA_EGM2008_CORRECTION_DEGREE and nmax <= NGA_EGM2008_DEGREE:
        return
    where = "asked for" if explicit else "the model's degree"
    raise InputFileError(
        correction.source_path or correction.name,
        f"the zeta-to-N correction stops at degree {correction.max_degree}, but the synthesis goes to degree "
        f"{nmax} ({where}): its degrees {correction.max_degree + 1}..{nmax} would be missing. Use the "
        f"correction that belongs to the model, or truncate both on purpose with max_degree="
        f"{correction.max_degree}",
    )


def _check_range(values, latitude, longitude, source: str, quantity: str) -> None:
    """Refuse a synthesis whose N (or ζ) leaves the geoid's physical range: the model's
    coefficients are not a geoid model's (or the preset or units are wrong)."""
    if values.size == 0:
        return
    # largest and smallest without NaN and without a temporary of the values' size (a
    # global lattice at degree 2190 is 307 MB); the position only when refused
    flat = values.reshape(-1)
    if not max(abs(np.fmax.reduce(flat)), abs(np.fmin.reduce(flat))) > MAX_ABS_UNDULATION_M:
        return
    magnitude = np.abs(np.where(np.isnan(values), 0.0, values))
    k = int(np.argmax(magnitude))
    lat = np.broadcast_to(latitude, values.shape).flat[k]
    lon = np.broadcast_to(longitude, values.shape).flat[k]
    raise InputFileError(
        source,
        f"the synthesis gives {quantity} = {values.flat[k]:.6g} m at latitude {lat:.6g}, longitude {lon:.6g}, "
        f"beyond ±{MAX_ABS_UNDULATION_M:g} m, the physical range of the geoid: the coefficients are not "
        "those of a geoid model (a corrupt value, a wrong unit or a wrong normalisation)",
    )


@functools.lru_cache(maxsize=2)
def _tables(nmax: int):
    """Recursion tables shared by syntheses of the same degree (read-only)."""
    AT, BT = legendre.recursion_tables(nmax)
    AT.flags.writeable = False
    BT.flags.writeable = False
    return AT, BT


def _as_points(latitude, longitude):
    """Validated float arrays (broadcast) and whether both inputs were scalars."""
    try:
        lat = np.asarray(latitude, dtype=np.float64)
        lon = np.asarray(longitude, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CoordinateError(f"latitude/longitude must be numbers: {exc}") from None
    scalar = lat.ndim == 0 and lon.ndim == 0
    try:
        lat, lon = np.broadcast_arrays(lat, lon)
    except ValueError:
        raise CoordinateError(
            f"latitude and longitude shapes {lat.shape} and {lon.shape} do not broadcast"
        ) from None
    with np.errstate(invalid="ignore"):
        bad = np.abs(lat) > 90.0
    if bad.any():
        raise CoordinateError(f"latitude must be within [-90, 90] degrees, got {lat[bad].flat[0]!r}")
    if np.isinf(lon).any():
        raise CoordinateError("longitude must be finite (NaN marks a missing point)")
    return lat, lon, scalar


class GeoidSynthesis:
    """Exact spherical-harmonic geoid undulations N (metres) on WGS84-like ellipsoids.

    Parameters
    ----------
    model : HarmonicModel
        Fully normalised potential coefficients (e.g. :func:`read_nga` of EGM96).
    correction : CorrectionModel, optional
        ζ-to-N correction (NGA CORRCOEF for EGM96). Without it the result is ζ + N0.
    ellipsoid : Ellipsoid
        Reference ellipsoid; the NGA presets require WGS84 (they use NGA's literals).
    preset : {"nga-f477", "nga-hsynth", "generic"}
    zero_degree_term_m : float, optional
        N0 in metres; default per preset (−0.53, −0.41, 0).
    max_degree : int, optional
        Truncation degree N (default: the model's). A correction that stops below N is
        refused (its missing degrees would silently be zero), except NGA's EGM2008
        correction to 2160 beside a model of degree up to 2190; pass its degree as
        ``max_degree`` to truncate both on purpose.

    Implements the :class:`geoidspline.sources.base.GeoidSource` protocol.
    """

    def __init__(
        self,
        model: HarmonicModel,
        correction: CorrectionModel | None = None,
        ellipsoid: Ellipsoid = WGS84,
        preset: str = DEFAULT_PRESET,
        zero_degree_term_m: float | None = None,
        max_degree: int | None = None,
    ):
        if not isinstance(model, HarmonicModel):
            raise TypeError(f"model must be a HarmonicModel, got {type(model).__name__}")
        if correction is not None and not isinstance(correction, CorrectionModel):
            raise TypeError(f"correction must be a CorrectionModel or None, got {type(correction).__name__}")
        if preset not in PRESETS:
            raise ParameterError(f"preset must be one of {PRESETS}, got {preset!r}")
        if preset.startswith("nga-") and (ellipsoid.a, ellipsoid.f, ellipsoid.gm) != (WGS84.a, WGS84.f, WGS84.gm):
            raise ParameterError(f"preset {preset!r} is defined for WGS84 only, got {ellipsoid.name}")
        nmax = model.max_degree if max_degree is None else int(max_degree)
        if not 2 <= nmax <= model.max_degree:
            raise ParameterError(f"max_degree must be in 2..{model.max_degree}, got {max_degree}")
        if zero_degree_term_m is not None and not math.isfinite(zero_degree_term_m):
            raise ParameterError(f"zero_degree_term_m must be finite, got {zero_degree_term_m}")
        _check_correction_degree(correction, nmax, max_degree is not None)

        engine = os.environ.get("GEOIDSPLINE_LATTICE_ENGINE", "").strip() or type(self).lattice_engine
        if engine not in ("exact", "sht"):
            raise ParameterError(f"GEOIDSPLINE_LATTICE_ENGINE must be 'exact' or 'sht', got {engine!r}")
        self.lattice_engine = engine
        self.model = model.truncated(nmax)
        self.max_degree = nmax
        self.ellipsoid = ellipsoid
        self.preset = preset
        self.conventions = _conventions(preset, model, ellipsoid, nmax)
        self.zero_degree_term_m = float(self.conventions.n0_m if zero_degree_term_m is None else zero_degree_term_m)
        self.correction = None if correction is None else correction.truncated(min(nmax, correction.max_degree))

        # Order-major coefficient sets (k, m, n): set 0 the model with n < 2 removed and
        # the normal zonals subtracted; set 1 the correction (all degrees, no (a/r)^n).
        nsets = 1 if self.correction is None else 2
        size = nmax + 1
        CT = np.zeros((nsets, size, size))
        ST = np.zeros((nsets, size, size))
        C = np.array(self.model.C)
        for n, term in self.conventions.zonal_terms:
            C[n, 0] = C[n, 0] + term
        C[:2, :] = 0.0
        CT[0] = C.T
        ST[0] = self.model.S.T
        ST[0, :, :2] = 0.0
        if self.correction is not None:
            nc = self.correction.max_degree + 1
            CT[1, :nc, :nc] = self.correction.C.T
            ST[1, :nc, :nc] = self.correction.S.T
        self._CT = CT
        self._ST = ST
        self._radial = np.array([True, False][:nsets])
        self._AT, self._BT = _tables(nmax)

        notes = [
            f"preset {preset}: sum scaled by GM={self.conventions.scale_gm!r} m^3/s^2, a={self.conventions.scale_a!r} m",
            f"synthesis to degree {nmax}; normal-field zonals subtracted for n in "
            f"{[n for n, _ in self.conventions.zonal_terms]}",
            f"zero-degree term N0 = {self.zero_degree_term_m} m",
        ]
        if self.correction is None:
            notes.append("no zeta-to-N correction: values are height anomalies plus N0")
        else:
            unit = {0.01: "cm", 1.0: "m", 0.001: "mm"}.get(self.correction.unit_m, f"{self.correction.unit_m} m")
            notes.append(
                f"zeta-to-N correction {self.correction.name} to degree {self.correction.max_degree}, in {unit} "
                f"(sha256 {self.correction.sha256})"
            )
        notes.extend(model.notes)
        self.provenance = Provenance(
            source=str(model.source_path or model.name),
            sha256=model.sha256,
            model=model.name,
            kind="harmonic",
            ellipsoid=ellipsoid.name,
            tide_system=model.tide_system,
            zero_degree_term_m=self.zero_degree_term_m,
            notes=tuple(notes),
        )

    # ------------------------------------------------------------------ protocol
    @property
    def extent(self) -> Region:
        """The whole sphere: a model has values everywhere."""
        return GLOBAL

    def __repr__(self):
        return (
            f"GeoidSynthesis({self.model.name}, degree={self.max_degree}, preset={self.preset!r}, "
            f"correction={None if self.correction is None else self.correction.name!r})"
        )

    # ------------------------------------------------------------------ geometry
    def _geometry(self, lat_deg):
        """sin ψ, cos ψ, r (m) and γ (m/s²) of the ellipsoid point at geodetic latitude."""
        cv = self.conventions
        phi = np.radians(lat_deg)
        s = np.sin(phi)
        c = np.cos(phi)
        s2 = s * s
        w = np.sqrt(1.0 - cv.point_e2 * s2)
        nu = cv.point_a / w  # prime-vertical radius of curvature
        p = nu * c
        z = nu * (1.0 - cv.point_e2) * s
        r = np.hypot(p, z)
        gamma = cv.gamma_e * (1.0 + cv.gamma_k * s2) / np.sqrt(1.0 - cv.gamma_e2 * s2)
        return z / r, p / r, r, gamma

    def _scales(self, r, gamma, quantity):
        """Per-point weights of the coefficient sets for 'N', 'zeta' or 'T'."""
        cv = self.conventions
        scale = np.zeros((r.shape[0], self._CT.shape[0]))
        if quantity == "T":
            scale[:, 0] = cv.scale_gm / r
        else:
            scale[:, 0] = cv.scale_gm / (r * gamma)
        if quantity == "N" and scale.shape[1] > 1:
            scale[:, 1] = self.correction.unit_m
        return scale

    def _points(self, latitude, longitude, quantity):
        lat, lon, scalar = _as_points(latitude, longitude)
        shape = lat.shape
        lat = np.ascontiguousarray(lat, dtype=np.float64).ravel()
        lon = np.ascontiguousarray(lon, dtype=np.float64).ravel()
        lam = np.radians(np.mod(lon, 360.0))
        rings, ring_of = (np.unique(lat, return_inverse=True) if np.isfinite(lat).all()
                          else (lat, None))
        if ring_of is not None and rings.size * self.RING_SHARING <= lat.size:
            out = self._ring_points(rings, ring_of.ravel(), lam, quantity)
        else:
            t, u, r, gamma = self._geometry(lat)
            q = self.conventions.scale_a / r
            out = np.empty(lat.shape[0])
            legendre.point_sums(
                self.max_degree, t, u, q, lam, self._scales(r, gamma, quantity), self._radial,
                self._CT, self._ST, self._AT, self._BT, out,
            )
        if quantity == "N":
            out += self.zero_degree_term_m
        if quantity != "T":
            _check_range(out, lat, lon, self.provenance.source, "N" if quantity == "N" else "zeta")
        out = out.reshape(shape)
        return float(out) if scalar else out

    #: Points a latitude must hold on average for :meth:`_points` to sum each latitude's
    #: Legendre functions once (a ring's row sums cost about one point's synthesis;
    #: check points come 10 a latitude, :func:`geoidspline.fitting.check_points.random_positions`).
    RING_SHARING = 2
    #: Latitudes (rings) whose sums one step of :meth:`_ring_points` holds, and points
    #: whose longitude sums it takes at a time (their cos/sin tables): tens of MB at degree 2190.
    _RING_CHUNK = 1_000
    _RING_POINT_CHUNK = 2_000

    def _ring_points(self, rings, ring_of, lam, quantity):
        """Values at points on few latitudes: ``rings`` (sorted geodetic latitudes,
        degrees), point i on ring ``ring_of[i]`` at longitude ``lam[i]`` (radians): each
        ring's sums A_m, B_m once (the lattice's row sums), then Σ_m A_m cos mλ + B_m sin mλ
        a point (the point synthesis's sum, within rounding)."""
        orders = np.arange(self.max_degree + 1, dtype=np.float64)
        by_ring = np.argsort(ring_of, kind="stable")
        firsts = np.searchsorted(ring_of[by_ring], np.arange(rings.size + 1))
        out = np.empty(lam.size)
        for first in range(0, rings.size, self._RING_CHUNK):
            last = min(rings.size, first + self._RING_CHUNK)
            t, u, r, gamma = self._geometry(rings[first:last])
            A = np.empty((last - first, self.max_degree + 1))
            B = np.empty((last - first, self.max_degree + 1))
            legendre.row_sums(self.max_degree, t, u, self.conventions.scale_a / r, self._scales(r, gamma, quantity),
                              self._radial, self._CT, self._ST, self._AT, self._BT, A, B)
            points = by_ring[firsts[first]:firsts[last]]
            for a in range(0, points.size, self._RING_POINT_CHUNK):
                part = points[a:a + self._RING_POINT_CHUNK]
                angle = lam[part, None] * orders[None, :]
                rows = ring_of[part] - first
                out[part] = (np.einsum("ij,ij->i", A[rows], np.cos(angle))
                             + np.einsum("ij,ij->i", B[rows], np.sin(angle)))
        return out

    # ------------------------------------------------------------------ public values
    def undulation(self, latitude, longitude):
        """Geoid undulation N (metres) at geodetic latitude/longitude (degrees, WGS84).

        Vectorised with NumPy broadcasting; scalars give a float; NaN in gives NaN out;
        |latitude| > 90 raises :class:`~geoidspline.errors.CoordinateError`. A result
        beyond the geoid's physical range (±150 m, :mod:`geoidspline.geodesy.limits`)
        raises :class:`~geoidspline.errors.InputFileError` naming the model: its
        coefficients are not a geoid model's.
        """
        return self._points(latitude, longitude, "N")

    def height_anomaly(self, latitude, longitude):
        """ζ = T/γ (metres) at the ellipsoid point: N without correction and N0."""
        return self._points(latitude, longitude, "zeta")

    def disturbing_potential(self, latitude, longitude):
        """T (m²/s²) at the ellipsoid point (h = 0), degrees 2..N, normal zonals removed."""
        return self._points(latitude, longitude, "T")

    def degree_power(self, latitude, directions: int = 1) -> np.ndarray:
        """Mean square (m²) of each degree's part of N along latitude rings, by the
        direction its waves run in.

        ``latitude``: geodetic latitudes (degrees). ``out[i, n, b]``: on ring i, the mean
        over the ring's longitudes of (degree n of ζ)² plus (degree n of the correction)²,
        on the ellipsoid ((a/r)^n at the ring's radius): Σ_m w_m (ΔC̄nm² + S̄nm²) P̄nm²
        times the ring's scale², w_0 = 1, w_m = 1/2, of the orders m whose waves run at
        an angle from east in bin b of ``directions`` equal bins of [0°, 90°]. Locally
        (large n) the term of order m is a wave of n + 1/2 radians per unit length on the
        unit sphere with m / cos ψ of them eastwards (ψ geocentric latitude), the rest
        north-south; poleward of its turning latitude (m / cos ψ > n + 1/2) it is small
        and counted as running east. Degrees are summed incoherently: terms of distinct m
        vanish in the mean along the ring, those of distinct degrees (and of ζ and the
        correction) are left out, as they average out over latitude. The spectrum the
        fit's parameter choice reads (:mod:`geoidspline.fitting.level0_error`).
        """
        lat = np.atleast_1d(np.asarray(latitude, dtype=np.float64))
        if lat.ndim != 1 or not np.all(np.abs(lat) <= 90.0):
            raise CoordinateError(f"latitudes must be a list within [-90, 90] degrees, got {latitude!r}")
        if int(directions) != directions or directions < 1:
            raise ParameterError(f"directions must be a positive integer, got {directions!r}")
        nmax = self.max_degree
        size = nmax + 1
        t, u, r, gamma = self._geometry(lat)
        scale = self._scales(r, gamma, "N")
        weight = np.full(size, 0.5)
        weight[0] = 1.0
        # order-major power of each set, the order weight folded in: (k, m, n)
        power = (self._CT**2 + self._ST**2) * weight[None, :, None]
        m, n = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
        below = m <= n
        degree = np.arange(size)
        plm = np.zeros((size, size))
        out = np.zeros((lat.size, size, directions))
        for i in range(lat.size):
            legendre.plm_bar(nmax, float(t[i]), float(u[i]), self._AT, self._BT, plm)
            plm_squared = np.where(below, plm.T, 0.0) ** 2  # [m, n]; plm_bar leaves m > n untouched
            east = m / max(float(u[i]), 1e-300)
            north = np.sqrt(np.maximum((n + 0.5) ** 2 - east**2, 0.0))
            angle = np.arctan2(north, east)  # from east, 0..π/2
            bins = np.minimum((angle / (0.5 * math.pi) * directions).astype(np.int64), directions - 1)
            ring = np.zeros((size, size))
            for k in range(power.shape[0]):
                part = power[k] * plm_squared * scale[i, k] ** 2
                if self._radial[k]:
                    part *= ((self.conventions.scale_a / r[i]) ** (2 * degree))[None, :]
                ring += part
            out[i] = np.bincount((n * directions + bins)[below], ring[below],
                                 minlength=size * directions).reshape(size, directions)
        return out

    # ------------------------------------------------------------------ lattices
    def lattice_step(self, spacing_deg: float | None = None) -> float:
        """The lattice spacing (degrees) used for ``spacing_deg``: 180/k for the smallest
        integer k with 180/k ≤ spacing_deg, so it divides 180 and 360. Default: 90/N
        (15' for degree 360)."""
        if spacing_deg is None:
            spacing_deg = 90.0 / self.max_degree
        spacing_deg = float(spacing_deg)
        if not (math.isfinite(spacing_deg) and spacing_deg > 0):
            raise ParameterError(f"spacing_deg must be a positive number, got {spacing_deg}")
        k = max(1, math.ceil(180.0 / spacing_deg - 1e-9))
        return 180.0 / k

    def nodes(self, region: Region, spacing_deg: float | None = None) -> NodeSample:
        """N (metres) on the lattice of :meth:`lattice_step` nodes covering ``region``.

        Latitudes −90 + i·Δ and longitudes j·Δ, from the last node at or before each
        lower edge to the first node at or after each upper edge (clipped at the poles);
        longitudes stay monotonic across the antimeridian (may exceed 180).

        Computed row by row: the Legendre sums of every latitude by ducc0's transforms,
        band by band with the (a/r)^n factor expanded (:mod:`.sht`; ``lattice_engine =
        "exact"``: the point synthesis's sums, row by row), then the longitude sum by a
        real FFT over the full circle (or a direct product for few columns).
        """
        if not isinstance(region, Region):
            raise TypeError(f"region must be a Region, got {type(region).__name__}")
        step = self.lattice_step(spacing_deg)
        k = round(180.0 / step)
        eps = 1e-9
        i0 = max(0, math.floor((region.south + 90.0) / step + eps))
        i1 = min(k, math.ceil((region.north + 90.0) / step - eps))
        j0 = math.floor(region.west / step + eps)
        j1 = math.ceil(region.east / step - eps)
        rows = np.arange(i0, i1 + 1)
        cols = np.arange(j0, j1 + 1)
        latitude = rows * 180.0 / k - 90.0
        longitude = cols * 180.0 / k
        values = self._lattice(latitude, cols, 2 * k)
        return NodeSample(latitude=latitude, longitude=longitude, undulation=values)

    #: How lattices are synthesised: "exact" (the per-row Legendre sums of the point
    #: synthesis; the default) or "sht" (ducc0's transforms in canonical groups of rows,
    #: band by band, see :mod:`.sht`, the ``sht`` extra: within 1e-7 m of exact; a row has
    #: the same bits whatever rows a call asks for; timings in benchmarks/README.md).
    #: The environment variable GEOIDSPLINE_LATTICE_ENGINE sets it for new syntheses
    #: (the command line's fits).
    lattice_engine = "exact"
    #: Threads ducc0 may use for a lattice.
    lattice_threads = 1

    def _sht(self):
        if getattr(self, "_sht_rows", None) is None:
            from .sht import ShtRows

            self._sht_rows = ShtRows(self._CT, self._ST, self._radial, self.max_degree)
        return self._sht_rows

    # Rows by ducc0 are computed in canonical groups: a row's sums are those of its group
    # (the same rows, the same call, the same bands) whatever rows a call asks for, so a
    # lattice in bands has the bits of one call. A group: the rows within G of a pole's
    # distance band, north and south together (one radius: one band of the expansion).
    _GROUP_DEGREES = 5.0  # a group spans about this much latitude a hemisphere
    _CACHE_BYTES = 512 << 20  # group sums kept (a global lattice at degree 2190: 154 MB)

    def _group_size(self, k: int) -> int:
        return max(1, min(128, int(self._GROUP_DEGREES * k / 180.0)))

    def _group_of(self, index, k: int):
        return np.minimum(index, k - index) // self._group_size(k)

    def _group_sums(self, k: int, g: int):
        """(lattice row indices, A, B) of group g of the lattice of k + 1 rows, cached."""
        import collections

        cache = self.__dict__.setdefault("_sht_cache", collections.OrderedDict())
        key = (k, g)
        if key in cache:
            cache.move_to_end(key)
            return cache[key]
        size = self._group_size(k)
        south = np.arange(g * size, min((g + 1) * size, k // 2 + 1))
        rows = np.unique(np.concatenate([south, k - south]))
        latitude = rows * 180.0 / k - 90.0
        t, u, r, gamma = self._geometry(latitude)
        scale = self._scales(r, gamma, "N")
        log_q = np.log(self.conventions.scale_a / r)
        theta = np.arctan2(u, t)  # colatitude of the geocentric latitude
        sht = self._sht()
        A = np.empty((rows.size, self.max_degree + 1))
        B = np.empty((rows.size, self.max_degree + 1))
        for band in sht.plan(log_q, scale[:, 0]):
            A[band[0]], B[band[0]] = sht.band_sums(theta, log_q, scale, band, self.lattice_threads)
        cache[key] = (rows, A, B)
        while len(cache) > 1 and sum(a.nbytes + b.nbytes for _, a, b in cache.values()) > self._CACHE_BYTES:
            cache.popitem(last=False)
        return cache[key]

    def _lattice(self, latitude, cols, L):
        """N at latitudes × longitudes cols·360/L (degrees)."""
        nmax = self.max_degree
        t, u, r, gamma = self._geometry(latitude)
        q = self.conventions.scale_a / r
        scale = self._scales(r, gamma, "N")
        ncol = cols.size
        use_fft = (nmax + 1) * ncol > 2 * L * max(1.0, math.log2(L))
        out = np.empty((latitude.size, ncol))
        if use_fft:
            index = np.mod(cols, L)
        else:
            lam = np.radians(np.mod(cols * (360.0 / L), 360.0))
            mm = np.arange(nmax + 1)[:, None]
            cos_ml = np.cos(mm * lam[None, :])
            sin_ml = np.sin(mm * lam[None, :])

        def emit(rows, A, B):
            if use_fft:
                out[rows] = legendre.fold_to_circle(A, B, L)[:, index]
            else:
                out[rows] = A @ cos_ml + B @ sin_ml

        if self.lattice_engine == "sht":
            k = L // 2
            row_index = np.rint((latitude + 90.0) * k / 180.0).astype(np.int64)
            group = self._group_of(row_index, k)
            for g in np.unique(group):
                mine = np.flatnonzero(group == g)
                rows, A, B = self._group_sums(k, int(g))
                at = np.searchsorted(rows, row_index[mine])
                emit(mine, A[at], B[at])
        else:
            rows_per_chunk = max(1, min(latitude.size, 4_000_000 // (L if use_fft else max(ncol, nmax + 1))))
            for start in range(0, latitude.size, rows_per_chunk):
                sl = slice(start, min(latitude.size, start + rows_per_chunk))
                nrow = sl.stop - sl.start
                A = np.empty((nrow, nmax + 1))
                B = np.empty((nrow, nmax + 1))
                legendre.row_sums(
                    nmax, np.ascontiguousarray(t[sl]), np.ascontiguousarray(u[sl]), np.ascontiguousarray(q[sl]),
                    np.ascontiguousarray(scale[sl]), self._radial, self._CT, self._ST, self._AT, self._BT, A, B,
                )
                emit(np.arange(sl.start, sl.stop), A, B)
        out += self.zero_degree_term_m
        lon = cols * (360.0 / L)
        _check_range(out, latitude[:, None], lon[None, :], self.provenance.source, "N")
        return out
