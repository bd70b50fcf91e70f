"""The one way a store's manifest is made: by a fit, an update or an upgrade.

Every write ends in :func:`build_manifest`: the history record of what was done, the
tile entries written, and the sections that changed. The schema and its checks are
:mod:`.format`'s (:func:`~.format.validate_manifest`).
"""

from __future__ import annotations

from .._version import __version__
from .format import FORMAT_NAME, FORMAT_VERSION

__all__ = ["build_manifest"]


def build_manifest(record: dict, tiles: list, previous: dict | None = None, **sections) -> dict:
    """The manifest of store version ``record["store_version"]``, written at ``record["time"]``.

    A fit (``sections`` holds ``fit``) starts a new manifest from its sections
    (``format_version``, ``store_id``, ``provenance``, ``region``, ``coverage``, ``spline``,
    ``fit``, ``accuracy``), keeping only the creation time and history of the store it
    replaces (``previous``, if any). An update or an upgrade is the next version of
    ``previous``: the sections given replace its own, the others are kept. Either way
    ``tiles`` are the tile entries and ``record`` joins the history.
    """
    history = (previous.get("history", []) if previous else []) + [record]
    if "fit" in sections:
        manifest = {
            "format": FORMAT_NAME,
            "format_version": sections.pop("format_version", FORMAT_VERSION),
            "store_version": record["store_version"],
            "store_id": sections.pop("store_id"),
            "created": previous["created"] if previous else record["time"],
            "updated": record["time"],
            "software": f"geoidspline {__version__}",
            **sections,
        }
    else:
        manifest = dict(previous)
        manifest.pop("integrity", None)  # recomputed when written
        manifest.update({"format_version": FORMAT_VERSION, "store_version": record["store_version"],
                         "updated": record["time"], **sections})
    manifest["tiles"] = tiles
    manifest["history"] = history
    return manifest
