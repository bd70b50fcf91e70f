"""Check points: where a fit is measured that were not its sites, with the truth there."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..sphere.region import Region
from ..sphere.sample import interval_distance

__all__ = ["CheckPoints", "check_points", "random_positions", "random_description", "exact_values"]


@dataclass(frozen=True)
class CheckPoints:
    """Points that were not fit sites, with their true undulations (metres)."""

    latitude: np.ndarray
    longitude: np.ndarray
    truth: np.ndarray
    description: str
    #: a grid's (low, high) at each point: the interval its bilinear and bicubic
    #: interpolants span (its truth between the nodes is unknown but lies near them);
    #: None for a model, exact everywhere
    interval: tuple | None = None

    def interval_distance(self, values) -> np.ndarray | None:
        """How far ``values`` at the points lie outside :attr:`interval` (0 inside), metres."""
        if self.interval is None:
            return None
        return interval_distance(values, *self.interval)


#: Exact points a step of the check-point stage synthesises.
CHECK_CHUNK = 1_000


def check_points(source, region: Region, count: int = 20_000, seed: int = 0, progress=None) -> CheckPoints:
    """Points that were not fit sites, with the source's truth there.

    A grid's truth between its nodes is unknown: its check points are the centres of
    the grid cells inside the region, compared with the grid's bicubic interpolation
    (and with the interval its bilinear and bicubic interpolants span there).
    A model is exact everywhere: ``count`` random points uniform in area over the region,
    synthesised in chunks reported to ``progress`` as the stage "check points".
    """
    if hasattr(source, "latitude_spacing"):  # a GeoidGrid
        sample = source.nodes(region)
        lat = sample.latitude[:-1] + 0.5 * np.diff(sample.latitude)
        lon = sample.longitude[:-1] + 0.5 * np.diff(sample.longitude)
        lat2, lon2 = np.meshgrid(lat, lon, indexing="ij")
        lat2, lon2 = lat2.ravel(), lon2.ravel()
        truth = source.undulation(lat2, lon2)
        bilinear = source.undulation(lat2, lon2, method="bilinear")
        keep = np.isfinite(truth) & np.isfinite(bilinear)
        truth, bilinear = truth[keep], bilinear[keep]
        return CheckPoints(
            lat2[keep], lon2[keep], truth,
            "bicubic (Catmull-Rom) interpolation of the source grid at the centres of its cells",
            interval=(np.minimum(truth, bilinear), np.maximum(truth, bilinear)),
        )
    lat, lon = random_positions(region, count, seed)
    truth = exact_values(source, lat, lon, progress)
    return CheckPoints(lat, lon, truth, random_description(count, seed))


#: Check points a random latitude holds (a ring): the synthesis sums a latitude's
#: Legendre functions once for all of them (:meth:`~geoidspline.sources.harmonics.synthesis.GeoidSynthesis.undulation`),
#: so 10 points cost about what 1.2 scattered ones did.
RING_POINTS = 10


def random_positions(region: Region, count: int, seed: int = 0):
    """(latitude, longitude) degrees of a model's ``count`` check points: uniform in area
    over ``region``, in rings of :data:`RING_POINTS` (a random latitude, uniform in
    ``sin``, with that many random longitudes), the same for the same seed (a fit made
    band by band measures each band's share of them: a ring's points share its band)."""
    rng = np.random.default_rng(seed)
    z_lo, z_hi = math.sin(math.radians(region.south)), math.sin(math.radians(region.north))
    rings = -(-count // RING_POINTS)
    lat = np.repeat(np.degrees(np.arcsin(rng.uniform(z_lo, z_hi, rings))), RING_POINTS)[:count]
    lon = region.west + rng.uniform(0.0, region.longitude_span, rings * RING_POINTS)[:count]
    return lat, lon


def random_description(count: int, seed: int = 0) -> str:
    """What a model's check points are, in the manifest's words."""
    return (f"exact synthesis at {count} random points uniform in area, {RING_POINTS} a random latitude "
            f"(seed {seed})")


def exact_values(source, latitude, longitude, progress=None) -> np.ndarray:
    """The model's undulation (metres) at points, synthesised in chunks of
    :data:`CHECK_CHUNK` reported to ``progress`` as the stage "check points"."""
    from .progress import as_progress

    truth = np.empty(np.size(latitude))
    with as_progress(progress).stage("check points", math.ceil(truth.size / CHECK_CHUNK), "chunk") as advance:
        for start in range(0, truth.size, CHECK_CHUNK):
            stop = min(truth.size, start + CHECK_CHUNK)
            truth[start:stop] = source.undulation(latitude[start:stop], longitude[start:stop])
            advance(1)
    return truth
