"""Is an update plausible? A source compared with the store over the update region, and
with its own neighbours, before anything is written.

A corrupt patch in a national grid (a node's 34.96 m stored as 0.3 m), a grid in the
wrong units or on another datum passes every reader check (the values are within the
geoid's ±150 m), yet it is no geoid revision. Two bounds, each derived from real geoids:

- **change** |N_new − N_store| at a node, at most :data:`MAX_CHANGE_M` = 10 m. Real
  revisions move decimetres where the old model had data and metres where it had
  little: EGM2008 and EGM96, both to degree 120, differ by up to 8.5 m (73.5°S 66°E,
  Antarctica) with 4.5 m at the 99.9th percentile (measured on a 1° lattice with the
  project's synthesis, NGA's coefficient files, the global mean difference removed).
  Tide systems, datums and quasi-geoids are converted or refused before this check
  (:mod:`~geoidspline.sources.reference`).
- **slope** between neighbouring nodes of the source, at most :data:`MAX_SLOPE` = 2e-3
  m/m (2 m per km). The geoid's slope is the deflection of the vertical: the steepest
  on PROJ's EGM96 15' grid ``egm96_15.gtx`` is 3.5e-4 m/m (measured: 72 arcsec, at an
  ocean trench), and deflections beyond 1 arcminute (2.9e-4) are rare anywhere; 2e-3 m/m
  (6.9 arcmin) leaves a factor 5.7 and still finds a metre-sized step between nodes
  500 m apart. East-west slopes are not measured within 3° of a pole, where the
  nodes of a row crowd together.

:func:`check_update` raises :class:`~geoidspline.errors.InputFileError` naming the worst
node (latitude, longitude, the values) and the way out (``--accept-implausible``,
``max_change_m=None`` / ``max_slope=None``).
"""

from __future__ import annotations

import numpy as np

from ..errors import InputFileError
from ..geodesy.ellipsoids import MEAN_EARTH_RADIUS_KM

__all__ = ["MAX_CHANGE_M", "MAX_SLOPE", "check_update", "steepest_slope"]

#: Largest |N_new − N_store| (metres) an update may bring without being asked.
MAX_CHANGE_M = 10.0
#: Largest slope (metres per metre) between neighbouring nodes of an update's source.
MAX_SLOPE = 2e-3
#: East-west slopes are measured where cos(latitude) is at least this (|latitude| <= 87°).
_MIN_COS = np.cos(np.radians(87.0))

_OVERRIDE = "give --accept-implausible (max_change_m=None, max_slope=None) if the data are right"


def steepest_slope(latitude, longitude, values):
    """(slope m/m, (i, j), (i2, j2)) of the steepest step between neighbouring nodes of a
    lattice (degrees, metres; NaN nodes skipped), or (0.0, None, None)."""
    lat = np.asarray(latitude, dtype=np.float64)
    lon = np.asarray(longitude, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    radius_m = MEAN_EARTH_RADIUS_KM * 1000.0
    best = (0.0, None, None)
    if lat.size > 1:
        north = np.abs(np.diff(v, axis=0)) / (radius_m * np.radians(np.diff(lat)))[:, None]
        if np.isfinite(north).any():
            k = int(np.nanargmax(north))
            i, j = np.unravel_index(k, north.shape)
            best = max(best, (float(north[i, j]), (int(i), int(j)), (int(i) + 1, int(j))), key=lambda b: b[0])
    if lon.size > 1:
        cos = np.cos(np.radians(lat))
        dx = radius_m * np.radians(np.diff(lon))[None, :] * cos[:, None]
        east = np.where(cos[:, None] >= _MIN_COS, np.abs(np.diff(v, axis=1)) / dx, np.nan)
        if np.isfinite(east).any():
            k = int(np.nanargmax(east))
            i, j = np.unravel_index(k, east.shape)
            best = max(best, (float(east[i, j]), (int(i), int(j)), (int(i), int(j) + 1)), key=lambda b: b[0])
    return best


def check_update(source_name, latitude, longitude, new, old, *, max_change_m: float | None = MAX_CHANGE_M,
                 max_slope: float | None = MAX_SLOPE) -> dict:
    """Refuse an update whose source ``new`` (metres, on the lattice ``latitude`` x
    ``longitude``, NaN: no data) changes the store's values ``old`` (NaN: not covered)
    by more than ``max_change_m``, or whose neighbouring nodes differ by more than
    ``max_slope`` metres per metre. None skips a check. Returns what was measured
    (``max_change_m``, ``max_slope``), for the update's record."""
    new = np.asarray(new, dtype=np.float64)
    old = np.asarray(old, dtype=np.float64)
    lat = np.asarray(latitude, dtype=np.float64)
    lon = np.asarray(longitude, dtype=np.float64)
    change = np.abs(new - old)
    measured = {"max_change_m": None, "max_slope": None}
    if np.isfinite(change).any():
        i, j = np.unravel_index(int(np.nanargmax(change)), change.shape)
        worst = float(change[i, j])
        measured["max_change_m"] = round(worst, 4)
        if max_change_m is not None and worst > max_change_m:
            raise InputFileError(
                source_name,
                f"implausible update: at latitude {lat[i]:.6g}, longitude {lon[j]:.6g} the source gives "
                f"{new[i, j]:.4f} m where the store holds {old[i, j]:.4f} m, a change of {worst:.4g} m, beyond the "
                f"{max_change_m:g} m a real geoid revision makes (a corrupt patch, wrong units or another datum?); "
                + _OVERRIDE,
            )
    slope, first, second = steepest_slope(lat, lon, new)
    measured["max_slope"] = float(f"{slope:.4g}")
    if max_slope is not None and slope > max_slope:
        (i, j), (k, m) = first, second
        raise InputFileError(
            source_name,
            f"implausible update: the source jumps from {new[i, j]:.4f} m at latitude {lat[i]:.6g}, longitude "
            f"{lon[j]:.6g} to {new[k, m]:.4f} m at its neighbour {lat[k]:.6g}, {lon[m]:.6g}, a slope of "
            f"{slope:.3g} m/m, beyond the {max_slope:g} m/m of the steepest real geoid (a corrupt node?); "
            + _OVERRIDE,
        )
    return measured
