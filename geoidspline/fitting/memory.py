"""The memory a fit will need, planned from the problem's size before any work.

A fit that cannot finish in the memory it is allowed should say so at once, naming the
figure it would need, rather than be killed by the system an hour later. The plan is a
lower bound from what is known before the fit: the source's nodes over the region, and
the first problem solved (level 0 by least squares, or by quasi-interpolation for a
model). A hierarchical fit measures each later step again before building it
(:func:`geoidspline.fitting.hierarchical.solve_basis`) and is fitted by overlays, block
by block, when a step would not fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import FitError
from ..sphere.region import Region
from .parameters import FitParameters

#: Peak bytes per level-0 coefficient of a quasi-interpolated model fit (the lattice
#: band, the coefficients, the node errors): EGM96 to 2 mm, 5,512,462 coefficients in
#: 2.49 GB peak, 0.44-0.45 kB each (issue 21's matrix, 2026-12-02).
INTERPOLATION_BYTES_PER_COEFFICIENT = 450

#: Peak bytes per lattice node of a quasi-interpolated model fit (the lattice, the nodes'
#: directions, values and errors, the sites of the overlays): the same fit, 9,331,200
#: 5' nodes in 2.49 GB, 267 each. The larger of the two figures plans a band.
INTERPOLATION_BYTES_PER_NODE = 270

#: Bytes per data node held through a least-squares fit: its direction (3 floats), value,
#: error, region mask and the rays of the coarsest levels (a few per node).
BYTES_PER_NODE = 200

def coefficient_density(order: int) -> float:
    """B-splines per steradian times h² of a level covering the sphere: measured for
    orders 4 and 6 (:data:`geoidspline.fitting.choose.MEASURED`), about 1.5 x the order
    otherwise (the support's radial thickness)."""
    from .choose import MEASURED

    return MEASURED[order].density if order in MEASURED else 1.5 * order


@dataclass(frozen=True)
class MemoryPlan:
    """The least memory a fit needs (bytes) and what it is for."""

    bytes: float
    what: str


def region_nodes(source, region: Region) -> float:
    """How many of a source's nodes lie in ``region`` (a model: its sample lattice)."""
    from .choose import region_area

    area = region_area(region)
    lat = getattr(source, "latitude_spacing", None)
    lon = getattr(source, "longitude_spacing", None)
    if lat and lon:
        return area / (math.radians(lat) * math.radians(lon))
    return 0.0


def plan(source, region: Region, params: FitParameters) -> MemoryPlan:
    """The least memory (bytes) a fit of ``source`` over ``region`` with ``params`` needs
    (a fit made band by band, :mod:`geoidspline.fitting.bands`: its largest band's)."""
    from .bands import Band, band_indices, uses_bands
    from .choose import region_area
    from .hierarchical import BYTES_PER_UNKNOWN, WHOLE_MAX_UNKNOWNS

    level0 = coefficient_density(params.order) * region_area(region) / params.h0 ** 2
    if uses_bands(params, region):
        # a band of one slab each: the least the tile size allows (band_slabs groups more)
        need, band0, nodes = max(band_need(source, params, Band(b, b)) for b in band_indices(params))
        return MemoryPlan(need, f"the largest band's about {band0:,.0f} level-0 coefficients by quasi-interpolation "
                                f"and {nodes:,.0f} lattice nodes (of {level0:,.0f} coefficients; tile_size "
                                f"{params.tile_size:g}: a smaller one makes smaller bands)")
    if params.method == "interpolation":
        return MemoryPlan(level0 * INTERPOLATION_BYTES_PER_COEFFICIENT,
                          f"about {level0:,.0f} level-0 coefficients by quasi-interpolation")
    nodes = region_nodes(source, region)
    node_bytes = nodes * BYTES_PER_NODE
    if params.refinement == "hierarchical" and level0 > WHOLE_MAX_UNKNOWNS:
        return MemoryPlan(level0 * BYTES_PER_UNKNOWN + node_bytes,
                          f"level 0's about {level0:,.0f} unknowns of the hierarchical basis"
                          f" and {nodes:,.0f} nodes")
    return MemoryPlan(node_bytes, f"{nodes:,.0f} nodes")


def band_need(source, params: FitParameters, band) -> tuple[float, float, float]:
    """(bytes, level-0 coefficients, lattice nodes) of a band's fit
    (:class:`~geoidspline.fitting.bands.Band`): its slabs' latitudes and margin, the
    lattice's rows full circles."""
    from .bands import band_margin_deg
    from .choose import region_area
    from .interpolation import lattice_spacing

    margin = band_margin_deg(params)
    south, north = band.latitudes(params.tile_size)
    reach = Region(max(-90.0, south - margin), -180.0, min(90.0, north + margin), 180.0)
    coefficients = coefficient_density(params.order) * region_area(reach) / params.h0 ** 2
    spacing = lattice_spacing(source, params.h0, params.sample_spacing_deg)
    nodes = ((reach.north - reach.south) / spacing + 1.0) * 360.0 / spacing
    return (max(coefficients * INTERPOLATION_BYTES_PER_COEFFICIENT, nodes * INTERPOLATION_BYTES_PER_NODE),
            coefficients, nodes)


def band_slabs(source, params: FitParameters) -> list:
    """The bands of a whole-globe fit (:class:`~geoidspline.fitting.bands.Band`): runs
    of consecutive tile slabs from the south, each as long as its :func:`band_need`
    stays within the largest one-slab band's (the one :func:`banded_parameters` sized
    the tiles for, within the memory): near the poles a slab each (their lattice rows
    are many), near the equator several, so that fewer margins are synthesised and
    quasi-interpolated twice. A function of the parameters alone, as the tiles are."""
    from .bands import Band, band_indices

    slabs = band_indices(params)
    limit = max(band_need(source, params, Band(b, b))[0] for b in slabs)
    bands = [Band(slabs[0], slabs[0])]
    for slab in slabs[1:]:
        longer = Band(bands[-1].first, slab)
        if band_need(source, params, longer)[0] <= limit:
            bands[-1] = longer
        else:
            bands.append(Band(slab, slab))
    return bands


def check_plan(source, region: Region, params: FitParameters, budget: float | None) -> MemoryPlan:
    """:func:`plan`, refused with a one-line :class:`FitError` naming the figure when it
    exceeds ``budget`` (bytes; ``None``: not known, nothing refused)."""
    need = plan(source, region, params)
    if budget is not None and need.bytes > budget:
        raise FitError(f"this fit needs at least {need.bytes / 1e9:.3g} GB ({need.what}); "
                       f"{budget / 1e9:.3g} GB are allowed: give max_memory_gb {math.ceil(need.bytes / 1e8) / 10:g}"
                       " if the machine has it, or a smaller region, or a coarser tolerance")
    return need


#: The smallest tile side (unit sphere) :func:`banded_parameters` makes bands of.
SMALLEST_BAND_TILE = 0.025


def banded_parameters(source, region: Region, params: FitParameters, budget: float | None) -> FitParameters:
    """``params`` with the tile size (a band's height, :mod:`geoidspline.fitting.bands`)
    halved until the largest band's :func:`plan` fits ``budget`` (bytes), down to
    :data:`SMALLEST_BAND_TILE`; unchanged when it fits already, or the fit is not made
    by bands. The store's tiles are then that size (the layout follows the memory
    given, and is recorded with the parameters)."""
    import dataclasses

    from .bands import uses_bands

    if budget is None or not uses_bands(params, region):
        return params
    while plan(source, region, params).bytes > budget and params.tile_size / 2.0 >= max(SMALLEST_BAND_TILE,
                                                                                         params.h0):
        params = dataclasses.replace(params, tile_size=params.tile_size / 2.0)
    return params
