"""Reference ellipsoids, normal gravity and the permanent tide, as frozen values with their references."""

from .ellipsoids import (
                         GRS80,
                         KM_PER_DEGREE,
                         PERMANENT_TIDE,
                         TIDE_SYSTEMS,
                         WGS84,
                         Ellipsoid,
                         PermanentTide,
                         gaussian_mean_radius,
)

__all__ = ["Ellipsoid", "WGS84", "GRS80", "PermanentTide", "PERMANENT_TIDE", "TIDE_SYSTEMS",
           "gaussian_mean_radius", "KM_PER_DEGREE"]
