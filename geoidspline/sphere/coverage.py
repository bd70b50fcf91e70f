"""Where a fit had data: regions, and the no-data holes of a source lattice.

A store answers only where its source had data (issue 10: "every answer is true or
refused"). :class:`Coverage` is a union of parts; a part is a region (degrees) and,
for a grid source, the source's lattice with a mask of the nodes holding no data.
A point is covered by a part when it lies in the part's region and every node of the
source lattice cell holding it has data (conservative: a point next to a hole is not
covered even where an interpolation would still give a number). A model source has
data everywhere: its part is its region alone.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .coordinates import COMPILED_FROM_POINTS
from .region import Region

__all__ = ["Coverage", "CoveragePart", "NodataLattice", "INSIDE", "OUTSIDE", "NO_DATA"]

#: Reasons :meth:`Coverage.reasons` gives per point.
INSIDE = "inside"
OUTSIDE = "outside the region"
NO_DATA = "no data in the source here"

#: Tolerance in lattice steps when deciding whether a point lies on the lattice's edge.
_EDGE_TOL = 1e-9

#: Relative tolerance on the spacing of a sample's axes (float64 round-off of lo + k·step).
_SPACING_RTOL = 1e-6


@dataclass(frozen=True, eq=False)
class NodataLattice:
    """An equally spaced latitude/longitude lattice and which of its nodes hold no data.

    Node (i, j) lies at latitude ``lat0 + i·dlat`` and longitude ``lon0 + j·dlon``
    (degrees; longitudes taken modulo 360); ``nodata`` is a boolean (nlat, nlon) array,
    True where the source had no value. A lattice with ``nlon·dlon = 360`` is periodic:
    its last column is followed by its first.
    """

    lat0: float
    dlat: float
    lon0: float
    dlon: float
    nodata: np.ndarray

    def __post_init__(self):
        mask = np.ascontiguousarray(self.nodata, dtype=bool)
        if mask.ndim != 2:
            raise ValueError(f"nodata must be a 2-D mask, got shape {mask.shape}")
        if not (self.dlat > 0 and self.dlon > 0 and np.isfinite(self.dlat) and np.isfinite(self.dlon)):
            raise ValueError(f"lattice spacings must be positive, got {self.dlat}, {self.dlon}")
        mask.setflags(write=False)
        object.__setattr__(self, "nodata", mask)

    @property
    def nlat(self) -> int:
        return int(self.nodata.shape[0])

    @property
    def nlon(self) -> int:
        return int(self.nodata.shape[1])

    @property
    def periodic(self) -> bool:
        return abs(self.dlon * self.nlon - 360.0) <= 1e-9 * max(1.0, self.nlon)

    @functools.cached_property
    def _cell_ok(self) -> np.ndarray:
        """Flat mask of the cells whose four nodes all have data, row-major over
        (nlat - 1) rows and nlon (periodic) or nlon - 1 columns: one lookup per point."""
        mask = self.nodata
        east = np.roll(mask, -1, axis=1) if self.periodic else mask[:, 1:]
        west = mask if self.periodic else mask[:, :-1]
        holes = west[:-1] | west[1:] | east[:-1] | east[1:]
        return _read_only(np.ascontiguousarray(~holes).ravel())

    def cells_have_data(self, latitude, longitude, region: Region | None = None):
        """Boolean mask: the lattice cell holding each point has data at all four nodes
        (and, with ``region``, the point lies in it: one pass for both).

        Points beyond the lattice (and NaN) give False. Batches of
        :data:`~geoidspline.sphere.coordinates.COMPILED_FROM_POINTS` points or more take
        one compiled pass (:mod:`geoidspline._kernels.coverage`), smaller ones numpy
        (no compiled kernels for a few points); both apply the same rule.
        """
        lat, lon = np.broadcast_arrays(np.asarray(latitude, dtype=float), np.asarray(longitude, dtype=float))
        shape = lat.shape
        lat, lon = np.ascontiguousarray(lat).ravel(), np.ascontiguousarray(lon).ravel()
        nlat, nlon = self.nodata.shape
        if nlat < 2 or nlon < 2:
            return np.zeros(shape, dtype=bool)
        if lat.size < COMPILED_FROM_POINTS:
            out = self._numpy_cells_have_data(lat, lon)
            return (out if region is None else out & region.contains(lat, lon)).reshape(shape)
        from .._kernels.coverage import cells_have_data

        bounds = (-np.inf, np.inf, 0.0, 360.0) if region is None else \
            (region.south, region.north, region.west, region.longitude_span)
        out = np.empty(lat.size, dtype=bool)
        # read-only views, whatever the caller's arrays: one compiled signature for all
        cells_have_data(_read_only(lat), _read_only(lon), *map(float, bounds), float(self.lat0), float(self.dlat),
                        float(self.lon0), float(self.dlon), nlat, nlon, bool(self.periodic), self._cell_ok,
                        _EDGE_TOL, out)
        return out.reshape(shape)

    def _numpy_cells_have_data(self, lat, lon):
        """:meth:`cells_have_data` of 1-D arrays in numpy (nlat, nlon >= 2)."""
        nlat, nlon = self.nodata.shape
        with np.errstate(invalid="ignore"):
            fi = (lat - self.lat0) / self.dlat
            ok = (fi >= -_EDGE_TOL) & (fi <= nlat - 1 + _EDGE_TOL)  # False for NaN
            offset = np.mod(lon - self.lon0, 360.0)
            fj = offset / self.dlon
            if self.periodic:
                columns = nlon
                ok &= fj <= nlon  # False for NaN
            else:
                columns = nlon - 1
                near = offset > 360.0 - _EDGE_TOL * self.dlon  # just west of lon0: round-off
                if near.any():
                    fj[near] = 0.0
                ok &= fj <= nlon - 1 + _EDGE_TOL
            # indices of the cell (garbage where not ok, kept in range by the clips)
            i = np.clip(np.where(ok, fi, 0.0), 0, nlat - 2).astype(np.int64)
            j = np.where(ok, fj, 0.0).astype(np.int64)
        if self.periodic:
            j %= nlon
        else:
            np.clip(j, 0, columns - 1, out=j)
        return ok & self._cell_ok[i * columns + j]

    def spans(self, region: Region) -> bool:
        """Whether every point of ``region`` lies within the lattice's cells."""
        tol = _EDGE_TOL
        lat_last = self.lat0 + (self.nlat - 1) * self.dlat
        if self.nlat < 2 or self.nlon < 2:
            return False
        if region.south < self.lat0 - tol * self.dlat or region.north > lat_last + tol * self.dlat:
            return False
        if self.periodic:
            return True
        offset = (region.west - self.lon0) % 360.0
        if offset > 360.0 - tol * self.dlon:
            offset -= 360.0
        return offset >= -tol * self.dlon and offset + region.longitude_span <= (self.nlon - 1 + tol) * self.dlon


@dataclass(frozen=True, eq=False)
class CoveragePart:
    """One piece of a coverage: a region, and the source lattice's holes (None: no holes)."""

    region: Region
    lattice: NodataLattice | None = None
    source: str | None = None

    def covers(self, latitude, longitude):
        if self.lattice is None and self.region.longitude_span >= 360.0:
            return self.region.contains(latitude, longitude)  # longitudes do not matter: no pole rule
        latitude, longitude = self._pole_inside(latitude, longitude)
        if self.lattice is not None and np.size(latitude) >= COMPILED_FROM_POINTS:
            return self.lattice.cells_have_data(latitude, longitude, region=self.region)
        inside = self.region.contains(latitude, longitude)
        if self.lattice is None:
            return inside
        count = int(np.count_nonzero(inside))
        if count == 0:
            return inside
        if count > inside.size // 2:  # mostly inside: no gather
            return inside & self.lattice.cells_have_data(latitude, longitude)
        out = inside.copy()
        out[inside] = self.lattice.cells_have_data(np.asarray(latitude)[inside], np.asarray(longitude)[inside])
        return out


    def _pole_inside(self, latitude, longitude):
        """A pole is one point, on every meridian: a point at latitude ±90 is tested at
        the middle longitude of this part's region, so a region reaching the pole covers
        it whatever longitude it is given with (a NaN longitude stays NaN)."""
        latitude = np.asarray(latitude, dtype=float)
        longitude = np.asarray(longitude, dtype=float)
        pole = (np.abs(latitude) == 90.0) & np.isfinite(longitude)
        if pole.any():
            longitude = np.where(pole, self.region.west + 0.5 * self.region.longitude_span, longitude)
        return latitude, longitude


@dataclass(frozen=True, eq=False)
class Coverage:
    """Where a store has data: the union of its parts (see the module docstring)."""

    parts: tuple

    @classmethod
    def of_region(cls, region: Region, source: str | None = None) -> Coverage:
        """Data everywhere in ``region`` (a model source; a store without a coverage record)."""
        return cls((CoveragePart(region, None, source),))

    @classmethod
    def from_sample(cls, sample, region: Region, source: str | None = None) -> Coverage:
        """The coverage of a :class:`~geoidspline.sphere.sample.NodeSample` (NaN: no data)
        over ``region``: the lattice cropped to the cells meeting the region, or the
        region alone when the lattice spans it without a hole."""
        lat = np.asarray(sample.latitude, dtype=float)
        lon = np.asarray(sample.longitude, dtype=float)
        nodata = ~np.isfinite(np.asarray(sample.undulation, dtype=float)).reshape(lat.size, lon.size)
        dlat = _spacing(lat, "latitude")
        dlon = _spacing(lon, "longitude")
        if dlat is None or dlon is None:
            # fewer than two nodes on an axis: no cell, no data
            return cls((CoveragePart(region, NodataLattice(0.0, 1.0, 0.0, 1.0, np.ones((1, 1), bool)), source),))
        # rows and columns of the cells that meet the region
        tol = _EDGE_TOL
        rows = np.flatnonzero((lat >= region.south - dlat * (1 + tol)) & (lat <= region.north + dlat * (1 + tol)))
        periodic = abs(dlon * lon.size - 360.0) <= 1e-9 * max(1.0, lon.size)
        span = region.longitude_span + 2.0 * dlon
        if span >= 360.0:
            cols = np.arange(lon.size)
        else:
            offset = np.mod(lon - (region.west - dlon), 360.0)
            selected = offset <= span + dlon * tol
            cols = np.flatnonzero(selected)
            if periodic and cols.size and cols.size < lon.size:
                # a cyclic run: start where the run starts
                starts = np.flatnonzero(selected & ~np.roll(selected, 1))
                cols = (starts[0] + np.arange(cols.size)) % lon.size
        if rows.size == 0 or cols.size == 0:
            return cls((CoveragePart(region, NodataLattice(0.0, 1.0, 0.0, 1.0, np.ones((1, 1), bool)), source),))
        if not periodic:
            cols = np.arange(cols.min(), cols.max() + 1)
        rows = np.arange(rows.min(), rows.max() + 1)
        lattice = NodataLattice(float(lat[rows[0]]), dlat, float(lon[cols[0]]), dlon, nodata[np.ix_(rows, cols)])
        if not lattice.nodata.any() and lattice.spans(region):
            return cls.of_region(region, source)
        return cls((CoveragePart(region, lattice, source),))

    @property
    def is_everywhere(self) -> bool:
        """Whether every point of the sphere is covered (a global store without holes):
        then only a NaN coordinate is outside."""
        return any(part.lattice is None and part.region.is_global for part in self.parts)

    def union(self, other: Coverage) -> Coverage:
        """Covered where either is (a regional update adds its source's data). A part
        inside the region of a part without holes adds nothing and is left out, so a
        store updated many times inside its region keeps one part."""
        parts = list(self.parts)
        for part in other.parts:
            if any(old.lattice is None and part.region.within(old.region) for old in parts):
                continue
            if part.lattice is None:
                parts = [old for old in parts if not old.region.within(part.region)]
            parts.append(part)
        return Coverage(tuple(parts))

    def covers(self, latitude, longitude):
        """Boolean mask (bool for scalars): points where the store has data."""
        lat, lon = np.broadcast_arrays(np.asarray(latitude, dtype=float), np.asarray(longitude, dtype=float))
        covered = np.asarray(self.parts[0].covers(lat, lon))
        for part in self.parts[1:]:
            covered = covered | part.covers(lat, lon)
        if covered.any():  # a NaN longitude is in every band spanning 360°: never covered
            covered = covered & ~np.isnan(lon)
        return covered[()] if covered.ndim == 0 else covered

    def reasons(self, latitude, longitude):
        """Per point one of :data:`INSIDE`, :data:`OUTSIDE` (no part's region holds it, or
        a NaN coordinate) and :data:`NO_DATA` (in a region, but the source had no data
        there); a str for scalars, else an array of str."""
        lat, lon = np.broadcast_arrays(np.asarray(latitude, dtype=float), np.asarray(longitude, dtype=float))
        covered = np.asarray(self.covers(lat, lon))
        in_region = np.zeros(lat.shape, dtype=bool)
        for part in self.parts:
            in_region |= part.region.contains(*part._pole_inside(lat, lon))
        in_region &= ~np.isnan(lon)  # a region spanning 360 degrees does not look at longitudes
        out = np.where(covered, INSIDE, np.where(in_region, NO_DATA, OUTSIDE)).astype(object)
        return str(out[()]) if out.ndim == 0 else out


def _read_only(array: np.ndarray) -> np.ndarray:
    view = array.view()
    view.flags.writeable = False
    return view


def _spacing(axis, name):
    """The spacing of an ascending equally spaced axis (degrees), None for fewer than 2 nodes."""
    if axis.size < 2:
        return None
    step = (axis[-1] - axis[0]) / (axis.size - 1)
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"{name} nodes are not ascending")
    worst = float(np.max(np.abs(axis - (axis[0] + step * np.arange(axis.size)))))
    if worst > _SPACING_RTOL * step:
        raise ValueError(f"{name} nodes are not equally spaced (a node is {worst:.3g} degrees off): "
                         "the coverage of the data cannot be recorded")
    return float(step)
