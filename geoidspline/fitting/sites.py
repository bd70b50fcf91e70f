"""Data nodes and the sites of a level: rays through the nodes within the shell.

Because the extension is constant along rays, each data direction ``u`` is sampled at
radii ``1 + ρ h`` within the shell, all carrying the value N(u) (METHOD.md §1). Sites
outside the level's active cells are dropped.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .._kernels.fitting import cells_meet_sphere
from ..bspline.keys import covered_cell_keys, dilate_keys, isin_sorted, pack_keys
from ..sphere.coordinates import directions
from ..sphere.region import Region


@dataclass
class DataNodes:
    """Data nodes of a fit: directions, values, region mask and thinning strides."""

    latitude: np.ndarray
    longitude: np.ndarray
    values: np.ndarray
    directions: np.ndarray
    in_region: np.ndarray
    row: np.ndarray
    col: np.ndarray
    dlat_rad: float
    dlon_rad: float

    @classmethod
    def from_sample(cls, sample, region: Region):
        rows, cols = sample.latitude.size, sample.longitude.size
        values = np.asarray(sample.undulation, dtype=float).ravel()
        keep = np.isfinite(values)
        # a pole row holds one point: keep a single node there
        for pole_row in np.flatnonzero(np.abs(sample.latitude) >= 90.0):
            keep[pole_row * cols + 1:(pole_row + 1) * cols] = False
        # the lattice's rows and columns, flat, row by row: taken whole when every
        # point is kept (a band of tens of millions of nodes: no masked copies)
        every = bool(keep.all())

        def kept(flat):
            return flat if every else flat[keep]

        lat = kept(np.repeat(sample.latitude, cols))
        lon = kept(np.tile(sample.longitude, rows))
        dlat = np.radians(np.diff(sample.latitude).min()) if rows > 1 else np.pi
        dlon = np.radians(np.diff(sample.longitude).min()) if cols > 1 else 2 * np.pi
        return cls(
            latitude=lat,
            longitude=lon,
            values=np.array(values, copy=True) if every else values[keep],  # not the sample's array
            directions=directions(lat, lon),
            in_region=region.contains(lat, lon),
            row=kept(np.repeat(getattr(sample, "first_row", 0) + np.arange(rows), cols)),
            col=kept(np.tile(np.arange(cols), rows)),
            dlat_rad=float(dlat),
            dlon_rad=float(dlon),
        )

    def subset(self, mask) -> "DataNodes":
        """The nodes of ``mask`` (bool over the nodes), same spacing."""
        return dataclasses.replace(self, **{f.name: getattr(self, f.name)[mask] for f in dataclasses.fields(self)
                                            if isinstance(getattr(self, f.name), np.ndarray)})

    def joined(self, other: "DataNodes") -> "DataNodes":
        """These nodes and ``other``'s (same spacing) as one set of data nodes."""
        return DataNodes(**{f.name: np.concatenate([getattr(self, f.name), getattr(other, f.name)])
                            if isinstance(getattr(self, f.name), np.ndarray) else getattr(self, f.name)
                            for f in dataclasses.fields(DataNodes)})

    @property
    def spacing_rad(self) -> float:
        """The nodes' spacing on the unit sphere: the larger of the latitude step and the
        longitude step at the nodes' mean |cos φ| (levels finer than half of it are not
        determined between the nodes)."""
        return max(self.dlat_rad, self.dlon_rad * float(np.cos(np.radians(np.abs(self.latitude))).mean()))

    def thinned(self, h, rays_per_cell):
        """Mask of the nodes kept as rays at spacing h (about rays_per_cell per cell width)."""
        target = h / rays_per_cell
        lat_stride = max(1, int(target // self.dlat_rad))
        cos_lat = np.maximum(np.cos(np.radians(self.latitude)), 1e-6)
        lon_stride = np.maximum(1, np.floor(target / (self.dlon_rad * cos_lat))).astype(np.int64)
        return (self.row % lat_stride == 0) & (self.col % lon_stride == 0)


def sites_for_level(nodes: DataNodes, ray_mask, h, order, keys, radial_offsets, site_cells=None):
    """Site positions and node indices for one level (rays through the kept nodes)."""
    covered = covered_cell_keys(keys, order) if site_cells is None else site_cells
    node_idx = np.flatnonzero(ray_mask)
    # a site is at most max |offset| h from its node, so its cell at most that many cells
    # (+1 for the floor) from the node's own per axis: nodes whose own cell is farther
    # from every covered cell have no site (an overlay covers a few cells of millions)
    reach = math.ceil(max(abs(rho) for rho in radial_offsets)) + 1
    near = isin_sorted(pack_keys(np.floor(nodes.directions[node_idx] / h).astype(np.int64)),
                       dilate_keys(covered, -reach, reach))
    node_idx = node_idx[near]
    pts_all, idx_all = [], []
    for rho in radial_offsets:
        pts = nodes.directions[node_idx] * (1.0 + rho * h)
        cells = np.floor(pts / h).astype(np.int64)
        inside = isin_sorted(pack_keys(cells), covered)
        if rho != 0.0:
            # sites off the sphere count only inside cells that meet the sphere (Ω)
            inside[inside] = cells_meet_sphere(cells[inside], h, 1.0)
        pts_all.append(pts[inside])
        idx_all.append(node_idx[inside])
    return np.concatenate(pts_all), np.concatenate(idx_all)
