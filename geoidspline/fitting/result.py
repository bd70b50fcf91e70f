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
    """One level of a fit: its coefficients, sites and solves, and the node errors after
    it. A data-limited finest level may be fitted in more than one pass (the residual its
    first pass left, :func:`geoidspline.fitting.driver.fit_nodes`): the counts are the
    passes' totals, the errors those after the last, and ``pass_max_error_m`` /
    ``pass_nodes_above_tolerance`` the errors after each pass kept (empty when no second
    pass was tried; one entry when it was tried and dropped, not lowering the largest error)."""

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
    passes: int = 1
    pass_max_error_m: list = field(default_factory=list)
    pass_nodes_above_tolerance: list = field(default_factory=list)


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
    # why a hierarchical fit was fitted by overlays instead (its basis outgrew the memory)
    refinement_fallback: str | None = None

    @property
    def method(self) -> str:
        """The method actually used, in words (the manifest's ``fit.method``): the
        parameters are those the fit ran with (a hierarchical fit that fell back to
        overlays says overlays)."""
        return method_text(self.parameters)


def method_text(params: FitParameters) -> str:
    """How a fit with ``params`` computes its levels, citing the thesis (Lehmann 2013)."""
    if params.refinement == "hierarchical":
        if params.method == "interpolation":
            return "hierarchical B-spline basis by quasi-interpolation (Lehmann 2013, section 5.3)"
        return "hierarchical B-spline basis by least squares (Lehmann 2013, section 5.3)"
    if params.method == "interpolation":
        return "level 0 by quasi-interpolation, then hierarchical overlays (Lehmann 2013, section 5.2)"
    return "hierarchical overlays (Lehmann 2013, section 5.2)"
