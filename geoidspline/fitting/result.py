"""What a fit returns, whichever way its levels were made (overlays or one hierarchical basis)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..hierarchy.ambient import AmbientSpline
from ..sphere.coverage import Coverage
from ..sphere.region import Region
from .parameters import FitParameters


@dataclass
class LevelReport:
    level: int
    h: float
    coefficients: int
    marked_cells: int
    sites: int
    blocks_solved: int
    max_error_m: float
    rms_error_m: float
    nodes_above_tolerance: int
    seconds: float


@dataclass
class FitResult:
    spline: AmbientSpline
    parameters: FitParameters
    region: Region
    levels: list = field(default_factory=list)
    node_count: int = 0
    node_max_error_m: float = float("nan")
    node_rms_error_m: float = float("nan")
    converged: bool = False
    seconds: float = 0.0
    # per-node arrays kept for tile statistics (sphere directions and errors)
    node_directions: np.ndarray | None = None
    node_errors: np.ndarray | None = None
    # refinement stopped because the next level would be finer than the data resolve
    data_limited: bool = False
    # where the source had data (region and no-data holes): the store answers only there
    coverage: Coverage | None = None
    # refinement "hierarchical": the basis the spline is written in
    # (:class:`geoidspline.hierarchy.hierarchical.HierarchicalBasis`), for inspection
    basis: object = None
