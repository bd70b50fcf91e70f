"""Check points: where a fit is measured that were not its sites, with the truth there."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..sphere.region import Region


@dataclass(frozen=True)
class CheckPoints:
    """Points that were not fit sites, with their true undulations (metres)."""

    latitude: np.ndarray
    longitude: np.ndarray
    truth: np.ndarray
    description: str


def check_points(source, region: Region, count: int = 20_000, seed: int = 0) -> CheckPoints:
    """Points that were not fit sites, with the source's truth there.

    A grid's truth between its nodes is unknown: its check points are the centres of
    the grid cells inside the region, compared with the grid's bicubic interpolation.
    A model is exact everywhere: ``count`` random points uniform in area over the region.
    """
    if hasattr(source, "latitude_spacing"):  # a GeoidGrid
        sample = source.nodes(region)
        lat = sample.latitude[:-1] + 0.5 * np.diff(sample.latitude)
        lon = sample.longitude[:-1] + 0.5 * np.diff(sample.longitude)
        lat2, lon2 = np.meshgrid(lat, lon, indexing="ij")
        lat2, lon2 = lat2.ravel(), lon2.ravel()
        truth = source.undulation(lat2, lon2)
        keep = np.isfinite(truth)
        return CheckPoints(
            lat2[keep], lon2[keep], truth[keep],
            "bicubic (Catmull-Rom) interpolation of the source grid at the centres of its cells",
        )
    rng = np.random.default_rng(seed)
    z_lo, z_hi = math.sin(math.radians(region.south)), math.sin(math.radians(region.north))
    lat = np.degrees(np.arcsin(rng.uniform(z_lo, z_hi, count)))
    lon = region.west + rng.uniform(0.0, region.longitude_span, count)
    return CheckPoints(lat, lon, source.undulation(lat, lon),
                       f"exact synthesis at {count} random points uniform in area (seed {seed})")
