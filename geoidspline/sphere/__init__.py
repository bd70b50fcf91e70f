"""The reference manifold, the unit sphere: regions, coordinates and directions (thesis §3.1),
and samples of undulations on a latitude/longitude lattice (:mod:`.sample`)."""

from .coordinates import check_coordinates, directions, latlon_of
from .region import GLOBAL, Region

__all__ = ["Region", "GLOBAL", "check_coordinates", "directions", "latlon_of"]
