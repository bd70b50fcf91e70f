"""What a source's values are, and the one rule for a source that differs from its store.

Every reader states in the :class:`~.base.Provenance` what the file (or the catalogue)
says: the datum (``datum``: the nodes' geographic CRS, or only an ``ellipsoid`` name),
the quantity (geoid undulations N or height anomalies ζ of a quasi-geoid), the unit
(metres: readers convert or refuse others) and the tide system. :func:`conform` then
applies ONE rule, whatever the format, when a source goes into a store (``geoid-fit``,
``geoid-update``) or a grid leaves it in another tide system (``--tide-system``):

- **the same**: taken as it is;
- **not stated** (a GTX, a DAC, an NGS ``.bin``, a netCDF without ``grid_mapping``):
  taken as the store's, and the provenance says so;
- **a well-defined conversion exists**: converted, and the provenance (so the manifest
  and the command's output) says from what, how, and to what:

  - tide systems (tide-free, zero-tide, mean-tide) by :func:`tide_offset_m`;
  - a geographic datum other than the store's, through pyproj: only when PROJ has a
    transformation that is not a "ballpark" guess and needs no grid that is missing
    (:func:`datum_transformer`). The nodes' heights change with the datum as much as their
    positions (a geoid height refers to its ellipsoid), so each node is moved in 3D
    (φ, λ, h = N) and the grid resampled on the store's lattice;
  - the GRS80 and WGS84 ellipsoids, both geocentric, differ by 0.105 mm in the semi-minor
    axis: N on one is N on the other to 0.1 mm;

- **otherwise refused**, naming both sides and the option that takes the values as
  they are: ``--accept-datum`` (a non-geocentric ellipsoid such as Bessel 1841 with no
  datum, or a datum PROJ can only guess at), ``--accept-quasi-geoid`` (height anomalies
  into a geoid store, or undulations into a quasi-geoid one: ζ and N differ by up to
  ~3 m in high mountains), and a source of unknown tide system asked to be converted.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass

import numpy as np

from ..errors import InputFileError
from ..geodesy.ellipsoids import PERMANENT_TIDE
from ..geodesy.tides import TIDE_SYSTEM_NAMES, parse_tide_system, tide_conversion, tide_offset_m, tide_slope_north
from .base import NodeSample, Provenance

__all__ = ["QUANTITIES", "Target", "for_new_store", "canonical_ellipsoid", "crs_datum", "datum_transformer",
           "conform", "converted_grid",
           # the tide systems' offsets live in geodesy.tides; re-exported for the sources' users
           "TIDE_SYSTEM_NAMES", "tide_offset_m", "tide_slope_north", "parse_tide_system", "tide_conversion"]

QUANTITIES = ("geoid", "quasi-geoid")

# Ellipsoid names as files spell them -> one name each (ISG "ref ellipsoid", netCDF
# attributes, PROJ's names).
_ELLIPSOIDS = {
    "wgs84": "WGS84", "wgs 84": "WGS84", "wgs-84": "WGS84", "wgs 1984": "WGS84", "world geodetic system 1984": "WGS84",
    "grs80": "GRS80", "grs 80": "GRS80", "grs 1980": "GRS80", "grs-80": "GRS80", "geodetic reference system 1980": "GRS80",
    "bessel": "Bessel 1841", "bessel 1841": "Bessel 1841", "bessel1841": "Bessel 1841",
    "clarke 1866": "Clarke 1866", "clarke1866": "Clarke 1866", "clrk66": "Clarke 1866",
    "clarke 1880": "Clarke 1880", "clrk80": "Clarke 1880",
    "international 1924": "International 1924", "intl": "International 1924", "hayford": "International 1924",
    "krassowsky 1940": "Krassowsky 1940", "krass": "Krassowsky 1940", "krassovsky": "Krassowsky 1940",
    "airy 1830": "Airy 1830", "airy": "Airy 1830",
}
#: Geocentric ellipsoids: same centre and axes as WGS 84 in every modern frame. The
#: GRS80 and WGS84 ellipsoids differ by 0.105 mm in b (a equal, 1/f 298.257222101 vs
#: 298.257223563): N on one is N on the other to 0.1 mm, far below any geoid's accuracy.
GEOCENTRIC = ("WGS84", "GRS80")
_UNSTATED = (None, "", "unknown", "---")


def canonical_ellipsoid(name) -> str | None:
    """One name per ellipsoid (``"GRS 1980"`` -> ``"GRS80"``); None when not stated."""
    if name is None or str(name).strip().lower() in _UNSTATED:
        return None
    key = " ".join(str(name).replace("_", " ").split()).lower()
    return _ELLIPSOIDS.get(key, _ELLIPSOIDS.get(key.replace(" ", ""), str(name).strip()))


# -- datums ----------------------------------------------------------------------------
def crs_datum(crs_text) -> tuple[str | None, str | None]:
    """(datum, ellipsoid) of a geographic CRS given as WKT/EPSG/PROJ text: datum as
    ``"EPSG:xxxx"`` when PROJ knows the code (else the WKT), ellipsoid's one name.
    Text PROJ cannot read raises ValueError (the reader names its file)."""
    if not crs_text:
        return None, None
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        crs = CRS.from_user_input(crs_text)
    except CRSError as exc:
        raise ValueError(f"PROJ cannot read the CRS {str(crs_text)[:60]!r} ({str(exc)[:80]})") from None
    if crs.is_compound:
        crs = crs.sub_crs_list[0]
    if not crs.is_geographic:
        return None, None  # a vertical or projected code says nothing of the nodes' datum
    code = crs.to_authority(min_confidence=90)
    ellipsoid = canonical_ellipsoid(crs.ellipsoid.name) if crs.ellipsoid else None
    return (f"{code[0]}:{code[1]}" if code else crs.to_wkt()), ellipsoid


def _datum_label(datum: str | None, ellipsoid: str | None) -> str:
    if datum is None:
        return f"the {ellipsoid} ellipsoid (no datum stated)" if ellipsoid else "no stated datum"
    try:
        from pyproj import CRS

        crs = CRS.from_user_input(datum)
        name = crs.name  # "NAD27", "JGD2011": the short name
        return f"{name} ({datum if len(datum) < 20 else 'WKT'}, {crs.ellipsoid.name if crs.ellipsoid else '?'})"
    except Exception:  # a label only
        return datum[:60]


def _is_wgs84(crs) -> bool:
    """Whether a geographic CRS is on WGS 84 (any realisation: EPSG's ensemble)."""
    name = (crs.datum.name if crs.datum else "").lower()
    return "world geodetic system 1984" in name or name in ("wgs 84", "wgs84")


#: Worst stated accuracy (metres) of a datum transformation applied without being asked:
#: EPSG's own accuracy of the WGS 84 datum ensemble (2 m), so a conversion no worse
#: than that is as good as "WGS 84" itself is defined (ETRS89 1 m, JGD2011 1 m,
#: NAD83(2011) 2 m). Worse ones (NAD27's Helmert 7 m without NADCON grids, DHDN's 3 m
#: without BETA2007) move geoid heights by tens of metres to within metres: refused
#: unless --accept-datum.
MAX_DATUM_ACCURACY_M = 2.0


def datum_transformer(datum: str, target_datum: str | None = None, area=None):
    """(transformer, description, accuracy in metres or None) from ``datum`` (3D) to the
    target (WGS 84 3D, EPSG:4979, by default): PROJ's best available transformation that
    is not a "ballpark" guess, or (None, why, None) when there is none. ``area`` is
    (S, W, N, E) degrees, so that PROJ picks the transformation for that area."""
    import warnings

    from pyproj import CRS
    from pyproj.aoi import AreaOfInterest
    from pyproj.transformer import TransformerGroup

    source = CRS.from_user_input(datum)
    target = CRS.from_user_input(target_datum) if target_datum else CRS.from_epsg(4979)
    aoi = None
    if area is not None:
        south, west, north, east = area
        span = min(east - west, 359.999)
        west = (west + 180.0) % 360.0 - 180.0
        aoi = AreaOfInterest(west, max(south, -90.0), min(west + span, 180.0), min(north, 90.0))
    with warnings.catch_warnings():  # pyproj warns of a missing grid: said in the description instead
        warnings.simplefilter("ignore")
        group = TransformerGroup(source.to_3d(), target.to_3d(), always_xy=True, allow_ballpark=False,
                                 area_of_interest=aoi)
    missing = ""
    if group.unavailable_operations:
        missing = f" (PROJ's better '{group.unavailable_operations[0].name}' needs a grid not installed: projsync)"
    if not group.transformers:
        return None, "PROJ knows no transformation but a ballpark guess" + missing, None
    best = group.transformers[0]
    accuracy = best.accuracy if best.accuracy is not None and best.accuracy >= 0 else None
    name = " + ".join(p for p in best.description.split(" + ") if "axis order change" not in p)
    stated = f"accuracy {accuracy:g} m" if accuracy is not None else "accuracy not stated"
    return best, f"'{name}' ({stated}){missing}", accuracy


@dataclass(frozen=True)
class Target:
    """What a store holds: its ellipsoid, datum, quantity and tide system (None: unknown,
    or, for a new store, the source's own), and a label for messages."""

    label: str = "the store"
    ellipsoid: str | None = "WGS84"
    datum: str | None = None
    quantity: str = "geoid"
    tide_system: str | None = None

    @classmethod
    def of_store(cls, manifest: dict, path) -> "Target":
        prov = manifest.get("provenance", {})
        return cls(f"the store {path}", canonical_ellipsoid(prov.get("ellipsoid")) or "WGS84", prov.get("datum"),
                   prov.get("quantity") or "geoid", prov.get("tide_system"))


def _refuse(source: Provenance, what: str, option: str):
    raise InputFileError(source.source, f"{what}; convert the source first, or give {option} to take its values "
                                        "as they are")


def conform(source, target: Target, *, accept_datum: bool = False, accept_quasi_geoid: bool = False,
            asked_tide: bool = False):
    """``(source, notes)``: ``source`` as ``target`` holds it (the same object when nothing
    differs, else a converted copy) and what was done (also added to its provenance's
    notes, so to the manifest), or :class:`InputFileError` naming both sides and the
    option that accepts the values as they are.

    ``target.tide_system`` None keeps the source's; a source that states none is taken
    as in the target's (an update into a store), or refused when the conversion was
    ``asked_tide`` (``--tide-system``). The order: quantity, datum, tide.
    """
    prov = source.provenance
    notes: list[str] = []
    changes: dict = {}
    # quantity: N and ζ differ by up to ~3 m in high mountains (ζ − N ≈ Δg_B/γ · H)
    quantity = prov.quantity or "geoid"
    if quantity != target.quantity:
        if not accept_quasi_geoid:
            _refuse(prov, f"the source holds {_quantity_label(quantity)}, {target.label} {_quantity_label(target.quantity)}",
                    "--accept-quasi-geoid (accept_quasi_geoid=True)")
        notes.append(f"{_quantity_label(quantity)} taken as {_quantity_label(target.quantity)} "
                     "as asked (--accept-quasi-geoid)")
        changes["quantity"] = target.quantity
    shift = _datum_rule(source, target, accept_datum, notes, changes)
    offset = None
    tide = prov.tide_system
    if target.tide_system is not None and target.tide_system != tide:
        if tide is None and asked_tide:
            raise InputFileError(prov.source, f"the source states no tide system, so it cannot be converted to "
                                              f"{target.tide_system}; drop --tide-system (tide_system=None)")
        if tide is None:
            notes.append(f"tide system not stated by the source: taken as {target.tide_system}, {target.label}'s")
        else:
            offset = (tide, target.tide_system)
            notes.append(f"converted from {tide} to {target.tide_system}: N += a·ΔC̄20·P̄20(sin φ) "
                         f"(Ekman 1989; IERS 2010 §6.2.2, k20={PERMANENT_TIDE.love_k20}), "
                         f"{float(tide_offset_m(0.0, tide, target.tide_system)):+.4f} m at the equator, "
                         f"{float(tide_offset_m(90.0, tide, target.tide_system)):+.4f} m at the poles")
        changes["tide_system"] = target.tide_system
    if not notes and not changes:
        return source, []
    new_prov = dataclasses.replace(prov, notes=tuple(prov.notes) + tuple(notes), **changes)
    if shift is None and offset is None:
        relabelled = copy.copy(source)  # a label only: the values are the same (and the caller's object too)
        relabelled.provenance = new_prov
        return relabelled, notes
    if hasattr(source, "latitude_spacing"):
        return converted_grid(source, new_prov, shift, offset), notes
    return _Converted(source, new_prov, shift, offset), notes


def for_new_store(source, *, tide_system: str | None = None, accept_datum: bool = False,
                  accept_quasi_geoid: bool = False):
    """``(source, notes)`` for a new store (``geoid-fit``): on WGS 84, geoid undulations
    (height anomalies only with ``accept_quasi_geoid``: the store then says it holds a
    quasi-geoid), in ``tide_system`` (None: the source's own)."""
    quantity = source.provenance.quantity if accept_quasi_geoid else "geoid"
    source, notes = conform(source, Target("a new store", "WGS84", None, quantity, parse_tide_system(tide_system)),
                            accept_datum=accept_datum, accept_quasi_geoid=accept_quasi_geoid,
                            asked_tide=tide_system is not None)
    if quantity == "quasi-geoid":
        notes = notes + ["the store holds height anomalies (a quasi-geoid), as asked (--accept-quasi-geoid)"]
    return source, notes


def _quantity_label(quantity: str) -> str:
    return "height anomalies (a quasi-geoid)" if quantity == "quasi-geoid" else "geoid undulations N"


def _datum_rule(source, target: Target, accept: bool, notes: list, changes: dict):
    """Apply the datum part of the rule; the transformer when the values must move."""
    prov = source.provenance
    src_ell = canonical_ellipsoid(prov.ellipsoid)
    tgt_ell = target.ellipsoid or "WGS84"
    if prov.datum is None:
        if src_ell is None or src_ell == tgt_ell:
            if src_ell is None:
                notes.append(f"datum not stated by the source: taken as {tgt_ell}, {target.label}'s")
                changes["ellipsoid"] = tgt_ell
            return None
        if src_ell in GEOCENTRIC and tgt_ell in GEOCENTRIC:
            notes.append(f"{src_ell} ellipsoid taken as {tgt_ell}: both geocentric, N differs by at most 0.1 mm")
            changes["ellipsoid"] = tgt_ell
            return None
        what = (f"the source is on {_datum_label(None, src_ell)}, {target.label} on {tgt_ell}: without a datum "
                "the position of a non-geocentric ellipsoid is unknown, so no conversion is defined")
        if not accept:
            _refuse(prov, what, "--accept-datum (accept_datum=True)")
        notes.append(f"values on the {src_ell} ellipsoid taken as {tgt_ell} without conversion, as asked (--accept-datum)")
        changes["ellipsoid"] = tgt_ell
        return None
    from pyproj import CRS

    src_crs = CRS.from_user_input(prov.datum)
    same = (_is_wgs84(src_crs) and target.datum is None and tgt_ell == "WGS84") or (
        target.datum is not None and CRS.from_user_input(target.datum).datum == src_crs.datum)
    if same:
        return None
    extent = source.extent
    transformer, how, accuracy = datum_transformer(prov.datum, target.datum, area=(
        extent.south, extent.west, extent.north, extent.east))
    label = _datum_label(prov.datum, src_ell)
    target_label = _datum_label(target.datum, tgt_ell) if target.datum else "WGS 84"
    if transformer is not None and (accuracy is None or accuracy > MAX_DATUM_ACCURACY_M):
        what = (f"the source is on {label}, {target.label} on {target_label}: PROJ's best transformation {how} is "
                f"not within {MAX_DATUM_ACCURACY_M:g} m (EPSG's accuracy of WGS 84 itself)")
        if not accept:
            raise InputFileError(prov.source, f"{what}; convert the source with a better transformation first, or "
                                              "give --accept-datum (accept_datum=True) to convert with this one")
        notes.append(f"conversion accuracy beyond {MAX_DATUM_ACCURACY_M:g} m accepted as asked (--accept-datum)")
    if transformer is None:
        if not accept:
            _refuse(prov, f"the source is on {label}, {target.label} on {target_label}: {how}", "--accept-datum "
                    "(accept_datum=True)")
        notes.append(f"values on {label} taken as {target_label} without conversion, as asked (--accept-datum)")
        changes.update(ellipsoid=tgt_ell, datum=target.datum)
        return None
    notes.append(f"converted from {label} to {target_label} by {how}: each node moved in 3D (φ, λ, N) and "
                 "resampled on the same lattice")
    changes.update(ellipsoid=tgt_ell, datum=target.datum)
    return transformer


def _shifted(source, latitude, longitude, transformer) -> np.ndarray:
    """N in the target datum at target-datum points: each point taken back to the source
    datum (at height 0), N read there, the geoid point (φ, λ, N) carried forward."""
    lon_s, lat_s, _ = transformer.transform(longitude, latitude, np.zeros_like(latitude), direction="INVERSE")
    n_source = source.undulation(lat_s, lon_s)
    _, _, height = transformer.transform(lon_s, lat_s, n_source)
    return np.asarray(height, dtype=np.float64)


def _apply(source, latitude, longitude, shift, offset):
    latitude = np.asarray(latitude, dtype=np.float64)
    longitude = np.asarray(longitude, dtype=np.float64)
    values = _shifted(source, latitude, longitude, shift) if shift is not None else source.undulation(latitude, longitude)
    if offset is not None:
        values = values + tide_offset_m(latitude, *offset)
    return values


def converted_grid(grid, provenance: Provenance, shift=None, offset=None):
    """A :class:`~.grid.GeoidGrid` on ``grid``'s lattice with the datum ``shift`` (a pyproj
    transformer) and the tide ``offset`` (source, target) applied, labelled ``provenance``.

    A shifted node's value comes from the source's bicubic interpolation a few metres to
    a few hundred metres away (a datum shift), a node near the edge or a hole whose
    source point falls off the grid or on no data becomes NaN (no data).
    """
    from ..errors import CoordinateError
    from .grid import GeoidGrid

    lat2, lon2 = np.meshgrid(grid.latitude, grid.longitude, indexing="ij")
    if shift is None:
        values = np.array(grid.values, dtype=np.float64)
        if offset is not None:
            values = values + tide_offset_m(lat2, *offset)
    else:
        values = np.full(lat2.shape, np.nan)
        flat_lat, flat_lon = lat2.ravel(), lon2.ravel()
        lon_s, lat_s, _ = shift.transform(flat_lon, flat_lat, np.zeros_like(flat_lat), direction="INVERSE")
        lat_s, lon_s = np.asarray(lat_s), np.asarray(lon_s)
        extent = grid.extent
        inside = (lat_s >= extent.south) & (lat_s <= extent.north)
        if not grid.is_global_in_longitude:
            inside &= ((lon_s - extent.west) % 360.0) <= extent.longitude_span
        try:
            n_source = grid.undulation(lat_s[inside], lon_s[inside])
        except CoordinateError:  # rounding at the very edge: those nodes get no data
            n_source = np.full(int(inside.sum()), np.nan)
        _, _, height = shift.transform(lon_s[inside], lat_s[inside], n_source)
        out = np.full(flat_lat.shape, np.nan)
        out[inside] = height
        if offset is not None:
            out += tide_offset_m(flat_lat, *offset)
        values = out.reshape(lat2.shape)
        values[~np.isfinite(values)] = np.nan
    return GeoidGrid(grid.latitude, grid.longitude, values, provenance)


class _Converted:
    """A source (a harmonic model) with a tide offset or datum shift applied to its values."""

    def __init__(self, source, provenance, shift, offset):
        self._source, self.provenance, self._shift, self._offset = source, provenance, shift, offset

    def __getattr__(self, name):  # lattice_step, max_degree, extent, ...: the model's own
        return getattr(self._source, name)

    @property
    def extent(self):
        return self._source.extent

    def undulation(self, latitude, longitude):
        if self._shift is None and self._offset is None:
            return self._source.undulation(latitude, longitude)
        lat, lon = np.broadcast_arrays(np.asarray(latitude, float), np.asarray(longitude, float))
        return _apply(self._source, lat, lon, self._shift, self._offset)

    def nodes(self, region, spacing_deg=None) -> NodeSample:
        sample = self._source.nodes(region, spacing_deg)
        if self._shift is None and self._offset is None:
            return sample
        lat2, lon2 = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")
        if self._shift is None:
            values = sample.undulation + tide_offset_m(lat2, *self._offset)
        else:
            values = _apply(self._source, lat2, lon2, self._shift, self._offset)
        return NodeSample(sample.latitude, sample.longitude, values)


