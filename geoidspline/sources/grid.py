"""Geoid undulations on a regular latitude/longitude grid.

:class:`GeoidGrid` holds N (metres) at the nodes of an equally spaced lattice (degrees)
and implements the :class:`~geoidspline.sources.base.GeoidSource` protocol: its ``nodes`` are
the data the fitter uses; ``undulation`` interpolates between nodes (bilinear as in
PROJ/GeographicLib, or Catmull-Rom bicubic) and is only meant to place check points.
"""

from __future__ import annotations

import numpy as np

from ..errors import CoordinateError, InputFileError, ParameterError
from ..sphere.region import Region
from ..sphere.sample import lattice_interpolation
from .base import NodeSample, Provenance

__all__ = ["GeoidGrid"]


#: Tolerance (degrees) when deciding whether a node lies on a region edge.
NODE_TOL_DEG = 1e-9


#: Tolerance (degrees) on the lattice: coordinates may deviate this much from
#: ``origin + k * spacing`` (float64 round-off on up to ~1e5 nodes).
_LATTICE_TOL_DEG = 1e-9


class GeoidGrid:
    """Undulations N (metres) on an equally spaced latitude/longitude lattice.

    Parameters
    ----------
    latitude : (nlat,) ascending, equally spaced, within [-90, 90] degrees.
    longitude : (nlon,) ascending, equally spaced degrees, spanning less than 360°.
        A grid with ``spacing * nlon == 360`` is periodic (global in longitude); a
        repeated 360° column is not allowed here (the readers drop it).
    undulation : (nlat, nlon) metres; NaN marks a node without data.
    provenance : where the values come from; its ``source`` names the grid in errors.

    Invariants are checked once here; a violation raises :class:`InputFileError`
    (a ``ValueError``) naming ``provenance.source``.
    """

    def __init__(self, latitude, longitude, undulation, provenance: Provenance):
        self.provenance = provenance
        lat = np.array(latitude, dtype=np.float64)
        lon = np.array(longitude, dtype=np.float64)
        values = np.array(undulation, dtype=np.float64)
        if lat.ndim != 1 or lon.ndim != 1:
            self._fail(f"latitude and longitude must be 1-D, got shapes {lat.shape} and {lon.shape}")
        if lat.size < 2 or lon.size < 2:
            self._fail(f"a grid needs at least 2 x 2 nodes, got {lat.size} x {lon.size}")
        if values.shape != (lat.size, lon.size):
            self._fail(
                f"undulation has shape {values.shape}, expected (nlat, nlon) = ({lat.size}, {lon.size})"
            )
        self._dlat = self._check_axis(lat, "latitude")
        self._dlon = self._check_axis(lon, "longitude")
        if lat[0] < -90.0 - NODE_TOL_DEG or lat[-1] > 90.0 + NODE_TOL_DEG:
            self._fail(f"latitudes {lat[0]}..{lat[-1]} degrees go beyond [-90, 90]")
        if np.isinf(values).any():
            self._fail(f"{int(np.isinf(values).sum())} undulation values are infinite")
        periodic = abs(self._dlon * lon.size - 360.0) <= 1e-9
        if not periodic and (lon.size - 1) * self._dlon >= 360.0 - 1e-9:
            self._fail(
                f"{lon.size} longitudes at {self._dlon} degrees span {(lon.size - 1) * self._dlon} "
                "degrees: a grid may not repeat its first column (drop the 360° duplicate)"
            )
        self._periodic = periodic
        # Keep the lattice exact so index arithmetic and node coordinates agree.
        self.latitude = lat[0] + self._dlat * np.arange(lat.size)
        self.longitude = lon[0] + self._dlon * np.arange(lon.size)
        self.values = values
        for array in (self.latitude, self.longitude, self.values):
            array.setflags(write=False)

    # -- invariants ---------------------------------------------------------------
    def _fail(self, rule: str):
        raise InputFileError(self.provenance.source, rule)

    def _check_axis(self, coord: np.ndarray, name: str) -> float:
        """Spacing (degrees) of an ascending equally spaced axis, or raise."""
        if not np.isfinite(coord).all():
            self._fail(f"{name} contains {int((~np.isfinite(coord)).sum())} non-finite values")
        step = np.diff(coord)
        if not (step > 0).all():
            self._fail(f"{name} must be strictly ascending")
        spacing = (coord[-1] - coord[0]) / (coord.size - 1)
        if not np.isfinite(spacing) or spacing <= 0:
            self._fail(f"{name} spacing {spacing} is not a positive finite number of degrees")
        lattice = coord[0] + spacing * np.arange(coord.size)
        worst = float(np.max(np.abs(coord - lattice)))
        if worst > _LATTICE_TOL_DEG + 1e-12 * np.max(np.abs(coord)):
            self._fail(
                f"{name} is not equally spaced: a node is {worst:.3g} degrees off the "
                f"{spacing:.12g}-degree lattice"
            )
        return float(spacing)

    # -- description --------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return self.values.shape

    @property
    def latitude_spacing(self) -> float:
        """Node spacing in latitude, degrees."""
        return self._dlat

    @property
    def longitude_spacing(self) -> float:
        """Node spacing in longitude, degrees."""
        return self._dlon

    @property
    def is_global_in_longitude(self) -> bool:
        """True when the columns wrap around (spacing * nlon == 360 within 1e-9)."""
        return self._periodic

    @property
    def extent(self) -> Region:
        """The region covered by the nodes (the whole longitude circle if periodic)."""
        lon0 = float(self.longitude[0])
        east = lon0 + 360.0 if self._periodic else float(self.longitude[-1])
        return Region(float(self.latitude[0]), lon0, float(self.latitude[-1]), east)

    def __repr__(self):
        nlat, nlon = self.shape
        return (
            f"GeoidGrid({self.provenance.source!r}, {nlat} x {nlon} nodes, "
            f"lat {self.latitude[0]:g}..{self.latitude[-1]:g} step {self._dlat:g}, "
            f"lon {self.longitude[0]:g}..{self.longitude[-1]:g} step {self._dlon:g}"
            f"{', periodic' if self._periodic else ''})"
        )

    # -- nodes --------------------------------------------------------------------
    def nodes(self, region: Region, spacing_deg: float | None = None) -> NodeSample:
        """The grid's own nodes inside ``region`` (edges included, tolerance 1e-9°).

        ``spacing_deg`` is ignored (a grid has its own spacing). Longitudes come back
        ascending in the frame of ``region.west`` (so a region crossing the
        antimeridian gives e.g. 170..190); a global region gives each column once.
        Raises :class:`CoordinateError` when the region is not inside :attr:`extent`.
        """
        tol = NODE_TOL_DEG
        lat0, lon0 = float(self.latitude[0]), float(self.longitude[0])
        nlat, nlon = self.shape
        if region.south < lat0 - tol or region.north > float(self.latitude[-1]) + tol:
            raise CoordinateError(
                f"region latitudes {region.south}..{region.north} are outside the grid "
                f"{self.provenance.source} ({lat0}..{self.latitude[-1]} degrees)"
            )
        i_lo = max(0, int(np.ceil((region.south - lat0 - tol) / self._dlat)))
        i_hi = min(nlat - 1, int(np.floor((region.north - lat0 + tol) / self._dlat)))
        rows = np.arange(i_lo, i_hi + 1)

        # Work in lattice steps k counted from lon0, with region.west shifted by a
        # whole number of turns so that it lies at or after lon0 (or just before it).
        turns = np.ceil((lon0 - tol - region.west) / 360.0)
        west = region.west + 360.0 * turns
        east = west + region.longitude_span
        k_lo = int(np.ceil((west - lon0 - tol) / self._dlon))
        k_hi = int(np.floor((east - lon0 + tol) / self._dlon))
        if self._periodic:
            k_hi = min(k_hi, k_lo + nlon - 1)  # each column once for a global region
        elif k_lo < 0 or east > float(self.longitude[-1]) + tol:
            raise CoordinateError(
                f"region longitudes {region.west}..{region.east} are outside the grid "
                f"{self.provenance.source} ({lon0}..{self.longitude[-1]} degrees)"
            )
        steps = np.arange(k_lo, k_hi + 1)
        cols = steps % nlon
        longitude = lon0 + self._dlon * steps - 360.0 * turns
        return NodeSample(
            latitude=self.latitude[rows].copy(),
            longitude=longitude,
            undulation=self.values[np.ix_(rows, cols)],
        )

    # -- interpolation ------------------------------------------------------------
    def _fractional_index(self, lat, lon):
        """Fractional row/column indices of finite points; raises for points off the grid."""
        if np.isinf(lon).any():
            raise CoordinateError("longitude must be finite (degrees)")
        if (np.abs(lat) > 90.0).any():
            bad = lat[np.abs(lat) > 90.0]
            raise CoordinateError(f"latitude must be within [-90, 90] degrees, got {bad[:5].tolist()}")
        tol = NODE_TOL_DEG
        lat0, lat1 = float(self.latitude[0]), float(self.latitude[-1])
        if ((lat < lat0 - tol) | (lat > lat1 + tol)).any():
            raise CoordinateError(
                f"latitude outside the grid {self.provenance.source} ({lat0}..{lat1} degrees)"
            )
        y = np.clip((lat - lat0) / self._dlat, 0.0, self.shape[0] - 1)
        offset = np.mod(lon - self.longitude[0], 360.0)
        if not self._periodic:
            span = (self.shape[1] - 1) * self._dlon
            offset = np.where(offset > 360.0 - tol, offset - 360.0, offset)
            if (offset > span + tol).any():
                raise CoordinateError(
                    f"longitude outside the grid {self.provenance.source} "
                    f"({self.longitude[0]}..{self.longitude[-1]} degrees)"
                )
            offset = np.clip(offset, 0.0, span)
        x = offset / self._dlon
        if self._periodic:
            x = np.where(x >= self.shape[1], 0.0, x)  # mod can round up to exactly 360
        return y, x

    def undulation(self, latitude, longitude, method: str = "bicubic"):
        """Interpolated N (metres) at ``latitude``/``longitude`` (degrees, broadcast).

        ``method="bilinear"`` is PROJ's and GeographicLib's bilinear interpolation.
        ``method="bicubic"`` is Catmull-Rom cubic convolution (a = -0.5) on the 4x4
        neighbourhood: it passes through the nodes and reproduces quadratics. Columns
        wrap for a periodic grid; rows beyond the first/last are clamped to the edge
        row (no crossing of the poles), so near the edges it is less accurate.

        Scalar input gives a ``np.float64``; NaN coordinates give NaN; a node without
        data (NaN) makes every point that uses it NaN. Latitude beyond ±90° (or beyond a
        regional grid) raises :class:`CoordinateError`; any finite longitude is wrapped.
        """
        if method not in ("bilinear", "bicubic"):
            raise ParameterError(f"method must be 'bilinear' or 'bicubic', got {method!r}")
        lat, lon = np.broadcast_arrays(
            np.asarray(latitude, dtype=np.float64), np.asarray(longitude, dtype=np.float64)
        )
        shape = lat.shape
        lat = lat.ravel()
        lon = lon.ravel()
        ok = ~(np.isnan(lat) | np.isnan(lon))
        y, x = self._fractional_index(lat[ok], lon[ok])
        nlat, nlon = self.shape
        i = np.minimum(np.floor(y).astype(np.intp), nlat - 2)
        fy = y - i
        if self._periodic:
            j = np.floor(x).astype(np.intp)
        else:
            j = np.minimum(np.floor(x).astype(np.intp), nlon - 2)
        fx = x - j
        inside = lattice_interpolation(self.values, i, fy, j, fx, method, self._periodic)
        result = np.full(lat.shape, np.nan)
        result[ok] = inside
        if shape == ():
            return np.float64(result[0])
        return result.reshape(shape)
