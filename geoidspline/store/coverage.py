"""The coverage record of a manifest: where the store's source had data.

::

    "coverage": {"rule": "...", "parts": [
        {"region": [S, W, N, E], "source": "egm96_15.gtx", "lattice": null},
        {"region": [...], "source": "...", "lattice": {
            "lat0": -90.0, "dlat": 0.25, "nlat": 721, "lon0": -180.0, "dlon": 0.25, "nlon": 1440,
            "nodata_count": 1234, "encoding": "zlib+base64 of numpy.packbits (row-major, 1 = no data)",
            "nodata": "eJz..."}}]}

A part without a lattice has data everywhere in its region (a model, or a grid without
holes that spans the region). A format-1 store has no record: its coverage is its region.
See :class:`geoidspline.sphere.coverage.Coverage` for the rule.
"""

from __future__ import annotations

import base64
import binascii
import zlib

import numpy as np

from ..errors import StoreCorruptError
from ..sphere.coverage import Coverage, CoveragePart, NodataLattice
from ..sphere.region import Region

#: Most lattice nodes a coverage part may declare (checked before decoding: 2**30 nodes
#: is a 128 MiB mask; a global 1' grid has 2.3e8 nodes).
MAX_LATTICE_NODES = 2**30

#: Most parts a coverage may have (one per fit or regional update).
MAX_PARTS = 100_000

ENCODING = "zlib+base64 of numpy.packbits (row-major, 1 = no data)"

RULE = ("a point is covered when a part's region holds it and, for a part with a lattice, every node of the "
        "lattice cell holding it has data")


def coverage_record(coverage: Coverage, source: str | None = None) -> dict:
    """The manifest's ``coverage`` record of ``coverage`` (parts without a source name get ``source``)."""
    parts = []
    for part in coverage.parts:
        record = {"region": list(part.region.as_tuple()), "source": part.source or source, "lattice": None}
        lattice = part.lattice
        if lattice is not None:
            bits = np.packbits(lattice.nodata.ravel())
            record["lattice"] = {
                "lat0": float(lattice.lat0), "dlat": float(lattice.dlat), "nlat": lattice.nlat,
                "lon0": float(lattice.lon0), "dlon": float(lattice.dlon), "nlon": lattice.nlon,
                "nodata_count": int(lattice.nodata.sum()),
                "encoding": ENCODING,
                "nodata": base64.b64encode(zlib.compress(bits.tobytes(), 9)).decode("ascii"),
            }
        parts.append(record)
    return {"rule": RULE, "parts": parts}


def validate_coverage_record(schema, record):
    """Check the record's structure and declared sizes (the masks are decoded on opening)."""
    schema.mapping(record, "coverage")
    parts = schema.array(schema.get(record, "parts", "coverage"), "coverage.parts", 1, MAX_PARTS)
    for i, part in enumerate(parts):
        key = f"coverage.parts[{i}]"
        schema.mapping(part, key)
        schema.region(schema.get(part, "region", key), f"{key}.region")
        schema.string(part.get("source"), f"{key}.source", nullable=True)
        lattice = schema.get(part, "lattice", key)
        if lattice is None:
            continue
        key = f"{key}.lattice"
        schema.mapping(lattice, key)
        schema.number(schema.get(lattice, "lat0", key), f"{key}.lat0", -90.0, 90.0)
        schema.number(schema.get(lattice, "lon0", key), f"{key}.lon0", -1e4, 1e4)
        schema.number(schema.get(lattice, "dlat", key), f"{key}.dlat", 0.0, 180.0, open_lo=True)
        schema.number(schema.get(lattice, "dlon", key), f"{key}.dlon", 0.0, 360.0, open_lo=True)
        nlat = schema.integer(schema.get(lattice, "nlat", key), f"{key}.nlat", 1, MAX_LATTICE_NODES)
        nlon = schema.integer(schema.get(lattice, "nlon", key), f"{key}.nlon", 1, MAX_LATTICE_NODES)
        if nlat * nlon > MAX_LATTICE_NODES:
            schema.fail(key, f"declares {nlat} x {nlon} nodes, more than {MAX_LATTICE_NODES}")
        schema.integer(schema.get(lattice, "nodata_count", key), f"{key}.nodata_count", 0, nlat * nlon)
        if schema.string(schema.get(lattice, "encoding", key), f"{key}.encoding") != ENCODING:
            schema.fail(f"{key}.encoding", f"must be {ENCODING!r}")
        schema.string(schema.get(lattice, "nodata", key), f"{key}.nodata", max_len=2**31)


def _decode_mask(path, key, lattice) -> np.ndarray:
    nlat, nlon = lattice["nlat"], lattice["nlon"]
    want = (nlat * nlon + 7) // 8
    try:
        packed = base64.b64decode(lattice["nodata"], validate=True)
        inflate = zlib.decompressobj()
        raw = inflate.decompress(packed, want + 1)  # never more than the declared size
        complete = inflate.eof and not inflate.unconsumed_tail
    except (binascii.Error, ValueError, zlib.error) as exc:
        raise StoreCorruptError(f"{path}: manifest key '{key}.nodata' cannot be decoded ({exc})") from None
    if len(raw) != want or not complete:
        raise StoreCorruptError(f"{path}: manifest key '{key}.nodata' does not hold {nlat} x {nlon} bits")
    mask = np.unpackbits(np.frombuffer(raw, dtype=np.uint8), count=nlat * nlon).astype(bool).reshape(nlat, nlon)
    if int(mask.sum()) != lattice["nodata_count"]:
        raise StoreCorruptError(f"{path}: manifest key '{key}.nodata' holds {int(mask.sum())} no-data nodes, "
                                f"nodata_count says {lattice['nodata_count']}")
    return mask


def coverage_of(path, manifest: dict) -> Coverage:
    """The store's :class:`Coverage` (a format-1 store: its region)."""
    record = manifest.get("coverage")
    if record is None:
        return Coverage.of_region(Region(*manifest["region"]), manifest["provenance"].get("source"))
    parts = []
    for i, part in enumerate(record["parts"]):
        lattice = part["lattice"]
        if lattice is not None:
            key = f"coverage.parts[{i}].lattice"
            lattice = NodataLattice(float(lattice["lat0"]), float(lattice["dlat"]), float(lattice["lon0"]),
                                    float(lattice["dlon"]), _decode_mask(path, key, lattice))
        parts.append(CoveragePart(Region(*part["region"]), lattice, part.get("source")))
    return Coverage(tuple(parts))
