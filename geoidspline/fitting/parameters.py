"""The numerical parameters of a fit, checked once, with what each means."""

from __future__ import annotations

from dataclasses import asdict, dataclass

from ..bspline.keys import MAX_INDEX
from ..errors import FitError
from ..options import RULES, check_number

#: How level 0 is computed: by least squares on the data rays (any source), or by
#: quasi-interpolation of a source exact everywhere (:mod:`geoidspline.fitting.interpolation`).
FIT_METHODS = ("least-squares", "interpolation")

#: How levels are added: hierarchical overlays (§5.2, each level fitted to the residual
#: of the ones before) or one linearly independent hierarchical B-spline basis over all
#: levels, fitted at once (§5.3, :mod:`geoidspline.fitting.hierarchical`).
REFINEMENTS = ("overlays", "hierarchical")


#: Finest level spacing allowed, in units of the data's node spacing.
MIN_H_PER_DATA_SPACING = 0.5

#: Deepest level index a fit may reach.
MAX_LEVEL = RULES["max_level"].high


def finest_level(h0: float) -> int:
    """The finest level (≤ :data:`MAX_LEVEL`) whose coefficient indices stay in range for ``h0``."""
    level = 0
    while level < MAX_LEVEL and h0 / 2 ** (level + 1) * MAX_INDEX >= 1.5:
        level += 1
    return level


#: Site radii ``1 + ρ h`` of the rays (ρ in units of the level's spacing h) of each
#: refinement, when a fit does not give its own. Overlays fit a small residual with
#: B-splines reaching well off the sphere, so their sites span ±1.5 h and keep each
#: level constant along the rays. The hierarchical basis is thin (``SHELL`` of
#: :mod:`geoidspline.fitting.hierarchical`: two or three B-splines across the sphere) and
#: cannot stay constant along rays as long; its fine levels carry the whole undulation,
#: so that misfit along the rays shows on the sphere (Andes: 67,973 coefficients and the
#: tolerance not reached with ±1.5 h, 28,021 with ±0.15 h, 21,472 with 0): its sites are
#: on the sphere only, and the combinations that vanish there are left to the penalty (no
#: query sees them). Measured in benchmarks/README.md.
RADIAL_OFFSETS = {
    "overlays": (-1.5, -0.9, -0.3, 0.0, 0.3, 0.9, 1.5),
    "hierarchical": (0.0,),
}


@dataclass(frozen=True)
class FitParameters:
    """Parameters of a fit. Lengths are on the unit sphere (1 = Earth radius).

    ``h0`` is the level-0 grid spacing; level ℓ has ``h0 / 2**ℓ``. ``tolerance_m`` is the
    largest |error| accepted at the data nodes; refinement stops there or at
    ``max_level``. ``radial_offsets`` are the site radii ``1 + ρ h`` in units of the
    level's spacing (``None``: the refinement's own, :data:`RADIAL_OFFSETS`; the
    parameters then hold the values used). ``rays_per_cell`` caps how many data directions a cell width holds
    at coarse levels (more are thinned out: they would cost time, not accuracy).
    ``regularization`` weighs the second-difference penalty relative to the mean
    diagonal of the normal matrix. An overlay level takes the B-splines whose support
    centre is within ``refine_radius`` cells (per axis) of a node above the tolerance;
    ``None`` means ``order / 2``: every B-spline touching that node (thesis §5.2).
    ``sample_spacing_deg`` is the lattice spacing (degrees) at which a spherical-harmonic
    source is synthesised for the fit (``None``: 90/N degrees for degree N, at most a
    quarter of h0); grids always give their own nodes.
    ``method`` says how level 0 is computed: ``"least-squares"`` (thesis §5) or
    ``"interpolation"``, the quasi-interpolant of :mod:`geoidspline.fitting.interpolation`, for
    sources exact everywhere (harmonic models): no linear solve, every coefficient from
    the source within a few cells. Overlays, when the tolerance asks for them, are
    least squares either way.
    ``refinement`` says how levels are added: ``"overlays"`` (thesis §5.2) or
    ``"hierarchical"``, the linearly independent hierarchical B-splines of §5.3
    (:mod:`geoidspline.fitting.hierarchical`): with least squares the one basis is
    fitted at once; with ``"interpolation"`` every level's coefficients come from the
    hierarchical quasi-interpolant of §5.3.1
    (:mod:`geoidspline.fitting.hierarchical_interpolation`), no solve at all.
    Where the blocks are solved is not a parameter of the fit: see
    :class:`geoidspline.fitting.executors.Executor` (it never goes into a store).
    """

    order: int = 4
    h0: float = 0.1
    tolerance_m: float = 0.5
    max_level: int = 8
    tile_size: float = 0.4
    margin_cells: int = 10
    block_cells: int = 40
    radial_offsets: tuple | None = None
    rays_per_cell: float = 5.0
    regularization: float = 1e-6
    overlay_ridge: float = 0.3
    refine_radius: float | None = 1.0
    untiled_max_unknowns: int = 20_000
    sample_spacing_deg: float | None = None
    method: str = "least-squares"
    refinement: str = "overlays"

    def __post_init__(self):
        # the user's numbers by the rules every entry point shares (geoidspline.options)
        for name in ("order", "h0", "tolerance_m", "max_level", "sample_spacing_deg"):
            object.__setattr__(self, name, check_number(name, getattr(self, name)))
        if self.max_level > finest_level(self.h0):
            raise FitError("h0 / 2**max_level is too small for the coefficient index range")
        if not self.tile_size >= self.h0:
            raise FitError(f"tile size ({self.tile_size}) must be at least h0 ({self.h0})")
        if self.margin_cells < self.order:
            raise FitError(f"margin_cells must be at least the spline order ({self.order})")

        if self.method not in FIT_METHODS:
            raise FitError(f"fit method must be one of {FIT_METHODS}, got {self.method!r}")
        if self.refinement not in REFINEMENTS:
            raise FitError(f"refinement must be one of {REFINEMENTS}, got {self.refinement!r}")
        offsets = RADIAL_OFFSETS[self.refinement] if self.radial_offsets is None else self.radial_offsets
        object.__setattr__(self, "radial_offsets", tuple(float(rho) for rho in offsets))

    def spacing(self, level: int) -> float:
        return self.h0 / 2.0 ** level

    def as_dict(self) -> dict:
        data = asdict(self)
        data["radial_offsets"] = list(self.radial_offsets)
        return data
