"""What a fit reads from: geoid sources and their provenance.

A *source* gives geoid undulations N (metres, positive when the geoid is above the
ellipsoid) at geodetic latitude/longitude (degrees). Two kinds exist:

- grids (:class:`geoidspline.sources.grid.GeoidGrid`, read by :mod:`geoidspline.sources.formats`):
  values at their nodes; between nodes a bicubic interpolation, used only to place
  check points;
- spherical-harmonic models (:mod:`geoidspline.sources.harmonics`): an exact synthesis anywhere.

The fitter only needs the :class:`GeoidSource` protocol below.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from ..sphere.region import Region
from ..sphere.sample import NodeSample  # what a source's nodes() gives; fitting reads it from sphere

__all__ = ["Provenance", "NodeSample", "GeoidSource"]


@dataclass(frozen=True)
class Provenance:
    """Where the undulations came from; written into every store's manifest.

    ``zero_degree_term_m`` is the N0 already contained in the values (for NGA's EGM96
    products -0.53 m), ``None`` when unknown. ``tide_system`` is one of
    ``"tide_free"``, ``"zero_tide"``, ``"mean_tide"`` or ``None`` when unknown.
    """

    source: str
    sha256: str | None = None
    model: str = "unknown"
    kind: str = "grid"
    ellipsoid: str = "WGS84"
    tide_system: str | None = None
    zero_degree_term_m: float | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    def as_dict(self) -> dict:
        data = asdict(self)
        data["notes"] = list(self.notes)
        return data


@runtime_checkable
class GeoidSource(Protocol):
    provenance: Provenance

    @property
    def extent(self) -> Region:
        """The region the source has data for."""

    def nodes(self, region: Region, spacing_deg: float | None = None) -> NodeSample:
        """Data nodes covering ``region`` (inclusive).

        A grid returns its own nodes and ignores ``spacing_deg``; a harmonic model
        synthesises a lattice with at most that spacing.
        """

    def undulation(self, latitude, longitude) -> np.ndarray:
        """N in metres at arbitrary points: exact for models, interpolated for grids."""
