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


#: Exact points a step of the check-point stage synthesises.
CHECK_CHUNK = 1_000


def check_points(source, region: Region, count: int = 20_000, seed: int = 0, progress=None) -> CheckPoints:
    """Points that were not fit sites, with the source's truth there.

    A grid's truth between its nodes is unknown: its check points are the centres of
    the grid cells inside the region, compared with the grid's bicubic interpolation.
    A model is exact everywhere: ``count`` random points uniform in area over the region,
    synthesised in chunks reported to ``progress`` as the stage "check points".
    """
    from .progress import as_progress

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
    truth = np.empty(count)
    with as_progress(progress).stage("check points", math.ceil(count / CHECK_CHUNK), "chunk") as advance:
        for start in range(0, count, CHECK_CHUNK):
            stop = min(count, start + CHECK_CHUNK)
            truth[start:stop] = source.undulation(lat[start:stop], lon[start:stop])
            advance(1)
    return CheckPoints(lat, lon, truth,
                       f"exact synthesis at {count} random points uniform in area (seed {seed})")
