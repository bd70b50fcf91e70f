"""Geographic regions: a latitude band times a longitude interval, in degrees."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import CoordinateError

__all__ = ["Region", "GLOBAL"]

#: Largest |west| or |east| a region accepts (degrees): any longitude interval can be
#: written within [-180, 360], so a bound beyond one and a half turns is a mistake (a
#: latitude typed as a longitude, a missing decimal point), not a region.
MAX_ABS_BOUND_LONGITUDE_DEG = 540.0

#: Largest |longitude| of a point that is wrapped modulo 360 rather than refused
#: (degrees). Up to here a float64 longitude keeps 1e-10° (10 µm) after wrapping; beyond
#: it, as for 1e308, the wrapped value is noise that would look like an answer.
MAX_ABS_POINT_LONGITUDE_DEG = 1e6

#: Rounding allowed on a full turn (degrees): 0 to 360.0000000001 is the whole circle.
_SPAN_TOL_DEG = 1e-9


@dataclass(frozen=True)
class Region:
    """A region ``south <= latitude <= north`` and ``west <= longitude <= east`` (degrees).

    Longitudes are taken modulo 360: ``west`` is normalised to [-180, 180) and ``east``
    to (west, west + 360], so a region may cross the antimeridian (west=170, east=-170
    is the 20° wide band across it). ``Region.from_bounds(-90, -180, 90, 180)`` is the
    whole sphere. Refused (:class:`CoordinateError`): non-finite bounds, south >= north
    or beyond ±90°, a west or east beyond ±540° (:data:`MAX_ABS_BOUND_LONGITUDE_DEG`),
    and ``east - west > 360`` (more than the whole circle: ``-72 1000`` is a mistake,
    not a band).
    """

    south: float
    west: float
    north: float
    east: float

    def __post_init__(self):
        values = (self.south, self.west, self.north, self.east)
        if not all(np.isfinite(v) for v in values):
            raise CoordinateError(f"region bounds must be finite numbers, got {values}")
        if not -90.0 <= self.south < self.north <= 90.0:
            raise CoordinateError(
                "region needs -90 <= south < north <= 90 (degrees), got "
                f"south={self.south}, north={self.north}"
            )
        for name, value in (("west", self.west), ("east", self.east)):
            if abs(value) > MAX_ABS_BOUND_LONGITUDE_DEG:
                raise CoordinateError(
                    f"region {name} longitude {value:g} is beyond ±{MAX_ABS_BOUND_LONGITUDE_DEG:g} degrees "
                    f"(a typing mistake? give west and east in [-180, 360])")
        if self.east - self.west > 360.0 + _SPAN_TOL_DEG:
            raise CoordinateError(
                f"region spans {self.east - self.west:g} degrees of longitude (west={self.west:g}, "
                f"east={self.east:g}): at most 360 (-180 180 is the whole circle)")
        west = (float(self.west) + 180.0) % 360.0 - 180.0
        east = float(self.east)
        span = 360.0 if (east - self.west) >= 360.0 - _SPAN_TOL_DEG else (east - self.west) % 360.0
        if span == 0.0:
            raise CoordinateError(f"region has zero longitude width: west={self.west}, east={self.east}")
        object.__setattr__(self, "west", west)
        object.__setattr__(self, "east", west + min(span, 360.0))
        object.__setattr__(self, "south", float(self.south))
        object.__setattr__(self, "north", float(self.north))

    @classmethod
    def from_bounds(cls, south, west, north, east) -> "Region":
        return cls(float(south), float(west), float(north), float(east))

    @property
    def is_global(self) -> bool:
        return self.south <= -90.0 and self.north >= 90.0 and self.east - self.west >= 360.0

    @property
    def longitude_span(self) -> float:
        return self.east - self.west

    def contains(self, latitude, longitude):
        """Boolean mask (or bool) of the points inside the region, edges included."""
        latitude = np.asarray(latitude, dtype=float)
        longitude = np.asarray(longitude, dtype=float)
        inside = (latitude >= self.south) & (latitude <= self.north)
        if self.longitude_span < 360.0:  # (only then: the modulo is most of a large batch's cost)
            with np.errstate(invalid="ignore"):  # an infinite longitude: NaN offset, not inside
                offset = (longitude - self.west) % 360.0
            inside &= offset <= self.longitude_span
        return inside

    def expanded(self, margin_deg: float) -> "Region":
        """The region grown by ``margin_deg`` on every side (clipped at the poles).

        The longitude margin is widened by 1/cos(latitude) so that it is at least
        ``margin_deg`` of arc everywhere in the band; it becomes global when it would
        wrap around.
        """
        south = max(-90.0, self.south - margin_deg)
        north = min(90.0, self.north + margin_deg)
        widest = max(abs(south), abs(north))
        if widest >= 89.0 or self.longitude_span >= 360.0:
            return Region(south, -180.0, north, 180.0)
        lon_margin = margin_deg / np.cos(np.radians(widest))
        if self.longitude_span + 2 * lon_margin >= 360.0:
            return Region(south, -180.0, north, 180.0)
        return Region(south, self.west - lon_margin, north, self.east + lon_margin)

    def as_tuple(self):
        return (self.south, self.west, self.north, self.east)

    def within(self, outer: "Region", tol: float = 1e-9) -> bool:
        """Whether this region lies inside ``outer`` (degrees; longitudes modulo 360;
        ``tol`` degrees of round-off allowed at the edges)."""
        if self.south < outer.south - tol or self.north > outer.north + tol:
            return False
        if outer.longitude_span >= 360.0:
            return True
        offset = (self.west - outer.west) % 360.0
        if offset > 360.0 - tol:
            offset -= 360.0
        return offset >= -tol and offset + self.longitude_span <= outer.longitude_span + tol

    def bounds_text(self) -> str:
        """``"S -42 W -77 N -18 E -53"``: the bounds in degrees for messages, without the
        float noise of bounds computed from a grid's nodes."""
        return " ".join(f"{name} {round(value, 9):g}" for name, value in zip("SWNE", self.as_tuple()))


GLOBAL = Region(-90.0, -180.0, 90.0, 180.0)
