"""The one front door: fit a source into a store, update it, open it, query it in batches.

The packages below compose here (docs/ARCHITECTURE.md): :mod:`geoidspline.fitting`
fits, :mod:`geoidspline.store` persists, :mod:`geoidspline.sources` reads,
:mod:`geoidspline.query` evaluates; the command line (``geoidspline.cli``) only parses,
calls this module and prints. Importing it is light (neither the compiled kernels nor scipy): every
operation imports what it needs when called, and the names the command line needs for
its options (:data:`PRESETS`, :data:`FIT_METHODS`, ...) are re-exported on first access.

:func:`build_store` is the one way the command line, the tests and :func:`fit` make a
store: fit, measure at check points that were not fit sites, write atomically.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import time
from typing import TYPE_CHECKING

from ..sphere.region import GLOBAL, Region

if TYPE_CHECKING:  # annotations only
    from ..fitting.choose import Choice
    from ..fitting.driver import FitResult
    from ..fitting.executors import Executor
    from ..fitting.parameters import FitParameters
    from ..store.reader import TileStore

__all__ = ["build_store", "fit", "run_fit", "FitRun", "open_store", "update", "query_rows", "query_point",
           "BatchQuery"]

log = logging.getLogger("geoidspline.api")

#: Names re-exported from the layers below, imported on first access (PEP 562): what
#: the command line needs for its options and messages, without importing it all.
_EXPORTS = {
    "__version__": "geoidspline._version",
    "pin_mmap_threshold": "geoidspline._memory",
    "PRESETS": "geoidspline.sources.harmonics.presets",
    "FIT_METHODS": "geoidspline.fitting.parameters",
    "REFINEMENTS": "geoidspline.fitting.parameters",
    "FitParameters": "geoidspline.fitting.parameters",
    "for_terminal": "geoidspline.fitting.progress",
    "open_source": "geoidspline.sources.resolve",
    "load_synthesis": "geoidspline.sources.resolve",
    "resolve_source": "geoidspline.sources.resolve",
    "is_model_file": "geoidspline.sources.resolve",
    "verify_store": "geoidspline.store.reader",
    "generate_key": "geoidspline.store.signing",
    "key_fingerprint": "geoidspline.store.signing",
    "RULES": "geoidspline.options",
    "OptionError": "geoidspline.options",
    "check_number": "geoidspline.options",
    "upgrade_store": "geoidspline.store.upgrade",
    "check_against": "geoidspline.api.validation",
    "export_grid": "geoidspline.api.export",
    "plot_store": "geoidspline.query.plot",
    "crs_info": "geoidspline.query.crs",
    "BatchQuery": "geoidspline.query.batch",
    "HEIGHT_OUTPUT": "geoidspline.query.batch",
    "query_rows": "geoidspline.query.batch",
    "query_point": "geoidspline.query.batch",
    "TIDE_SYSTEM_NAMES": "geoidspline.geodesy.tides",
}


def __getattr__(name):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_EXPORTS[name]), name)
    globals()[name] = value
    return value


def open_store(path, *, lazy: bool = True, verify: bool = True, key=None, cache_bytes: int | None = None) -> TileStore:
    """Open a tile store read-only.

    ``lazy`` (default) reads a tile when a query first needs it; ``lazy=False`` reads and
    checks every tile now. ``verify`` checks each tile's sha256 as it is read (sizes are
    always checked). ``key``: the Ed25519 public key (PEM file or key object) that must
    have signed the store; an unsigned or forged store is refused
    (:class:`~geoidspline.store.signing.SignatureError`) and every tile is checked as it
    is read. ``cache_bytes``: how much the store keeps between queries short of reading
    it whole (default :data:`geoidspline.store.reader.CACHE_BYTES`, 512 MiB: decoded
    tiles, and how far the spline of the tiles queries needed may grow). See
    :class:`geoidspline.store.TileStore` (memory, caching, thread safety) and docs/signing.md.
    """
    from ..store.reader import CACHE_BYTES, TileStore

    return TileStore.open(path, verify=verify, lazy=lazy, key=key,
                          cache_bytes=CACHE_BYTES if cache_bytes is None else cache_bytes)


def build_store(source, path, region: Region | None = None, params: FitParameters | None = None,
                progress=None, overwrite=False, check_count=20_000,
                executor: Executor | None = None, extra: dict | None = None, sign=None,
                resume: bool = False) -> tuple[FitResult, dict]:
    """Fit ``source`` over ``region``, measure it and write the store at ``path``.

    A model's whole globe by quasi-interpolation and overlays is fitted band by band
    (:mod:`geoidspline.api.banded`): each band committed as it is done, so that
    ``resume=True`` continues an interrupted fit from its last committed band, and the
    bands farmed out to the executor's dask cluster when it has one.

    ``progress``: a :class:`~geoidspline.fitting.progress.Progress` (every stage) or a
    callable given the number of blocks just solved. ``extra``: more entries of the
    manifest's ``fit`` section (``choices``: why the parameters are what they are).
    ``sign``: an Ed25519 private key (PEM file or key object) that signs the manifest.
    Returns the fit result and the store's summary (``TileStore.info()``).
    """
    from ..fitting.check_points import check_points
    from ..fitting.driver import fit_source
    from ..fitting.executors import Executor
    from ..fitting.parameters import FitParameters
    from ..fitting.progress import as_progress
    from ..store.reader import TileStore
    from ..store.writer import write_store

    from ..fitting.bands import uses_bands

    region = region or GLOBAL
    params = params or FitParameters()
    progress = as_progress(progress)
    if uses_bands(params, region):
        from .banded import build_banded_store

        return build_banded_store(source, path, region, params, progress=progress, overwrite=overwrite,
                                  resume=resume, check_count=check_count, executor=executor, extra=extra, sign=sign)
    if sign is not None:
        from ..store.signing import load_private_key

        sign = load_private_key(sign)  # a bad key file before the fit, not after it
    from ..fitting.memory import check_plan
    from ..fitting.parameters import check_promise

    check_promise(params)  # a tolerance the store can keep, and the memory for it, before any work
    check_plan(source, region, params, (executor or Executor()).memory_budget)
    result = fit_source(source, region, params, progress=progress, executor=executor)
    if result.refinement_fallback:
        extra = {**(extra or {}), "refinement_fallback": result.refinement_fallback}
    check = check_points(source, region, count=check_count, progress=progress)
    with progress.stage("write", 1, "store") as advance:
        write_store(path, result, source.provenance, check=check, overwrite=overwrite, extra=extra, sign=sign)
        advance(1)
    return result, TileStore.open(path).info()


def _as_region(region, source=None) -> Region:
    """``region`` as a :class:`Region`; when not given, the source's own extent (a
    regional grid covers only part of the globe), else the globe."""
    if region is None:
        extent = getattr(source, "extent", None) if source is not None else None
        return GLOBAL if extent is None or extent.is_global else extent
    return region if isinstance(region, Region) else Region.from_bounds(*region)


def _is_path(source) -> bool:
    return isinstance(source, (str, bytes)) or hasattr(source, "__fspath__")


@dataclasses.dataclass
class FitRun:
    """A fit as :func:`run_fit` made it: what ``geoid-fit`` prints.

    ``source``: the source object fitted; ``region``; ``result``: the
    :class:`~geoidspline.fitting.result.FitResult`; ``info``: the store's summary
    (``TileStore.info()``); ``choice``: the :class:`~geoidspline.fitting.choose.Choice`
    of parameters and its reasons (None when ``choose=False``); ``seconds``: wall time of
    fitting, measuring and writing."""

    source: object
    region: Region
    result: FitResult
    info: dict
    choice: Choice | None
    seconds: float
    #: what the one rule of :func:`~geoidspline.sources.reference.for_new_store` converted
    #: or took in the source (also in the manifest's provenance notes)
    source_notes: list = dataclasses.field(default_factory=list)

    @property
    def parameters(self) -> FitParameters:
        return self.result.parameters if self.choice is None else self.choice.parameters

    @property
    def promise(self) -> dict:
        """Whether the store keeps the tolerance, from the store read back: at every node
        of the region; for a model (exact everywhere) at the random check points too; for
        a grid at every cell centre of the region too, within the tolerance of the interval
        its bilinear and bicubic interpolants span there (issue 21: its truth between the
        nodes is unknown but lies near them, so a store swinging away between the nodes
        does not keep the promise however well it meets them)."""
        tolerance = self.choice.tolerance_m if self.choice is not None else self.result.parameters.tolerance_m
        model = getattr(self.source.provenance, "kind", None) == "harmonic"
        node_max = self.info["node_max_error_m"]
        check_max = self.info["max_error_m"] if model and self.info["check_points"] else None
        centre_max = self.info.get("cell_centre_max_m")
        kept = (node_max is not None and node_max <= tolerance and (check_max is None or check_max <= tolerance)
                and (centre_max is None or centre_max <= tolerance))
        return {"tolerance_m": tolerance, "node_max_m": node_max, "check_max_m": check_max,
                "cell_centre_max_m": centre_max, "kept": bool(kept)}


def run_fit(source, store, *, region=None, overwrite: bool = False, workers: int = 1, scheduler: str | None = None,
            correction=None, preset: str | None = None, progress=None, choose: bool = True, sign=None,
            band: int | None = None, variable: str | None = None, tide_system: str | None = None,
            accept_datum: bool = False, accept_quasi_geoid: bool = False, max_memory_gb: float | None = None,
            resume: bool = False, **parameters) -> FitRun:
    """:func:`fit`, returning the whole account of it (:class:`FitRun`) instead of the store."""
    from ..fitting.executors import Executor
    from ..fitting.parameters import FitParameters
    from ..fitting.progress import as_progress
    from ..options import check_number
    from ..sources.reference import for_new_store

    max_memory_gb = check_number("max_memory_gb", max_memory_gb)
    executor = Executor(workers=workers, scheduler=scheduler,
                        max_memory_bytes=None if max_memory_gb is None else max_memory_gb * 1e9)
    if _is_path(source):
        from ..sources.resolve import open_source

        source = open_source(source, correction, preset, band=band, variable=variable,
                             progress=as_progress(progress))
    source, notes = for_new_store(source, tide_system=tide_system, accept_datum=accept_datum,
                                  accept_quasi_geoid=accept_quasi_geoid)
    fit_region = _as_region(region, source)
    choice, extra = None, None
    if choose:
        from ..fitting.choose import choose_parameters
        from ..fitting.driver import check_method

        tolerance = parameters.pop("tolerance_m", FitParameters().tolerance_m)
        choice = choose_parameters(source, tolerance, fit_region, given=parameters)
        params, extra = choice.parameters, {"choices": choice.as_manifest()}
        check_method(source, params)
    else:
        params = dataclasses.replace(FitParameters(), **parameters)
    log.info("source %s (%s), region %s", source.provenance.source, source.provenance.model, fit_region.as_tuple())
    started = time.perf_counter()
    result, info = build_store(source, store, fit_region, params, progress=progress, overwrite=overwrite,
                               executor=executor, extra=extra, sign=sign, resume=resume)
    return FitRun(source, fit_region, result, info, choice, time.perf_counter() - started, notes)


def fit(source, store, *, region=None, overwrite: bool = False, workers: int = 1, scheduler: str | None = None,
        correction=None, preset: str | None = None, progress=None, choose: bool = True, sign=None,
        band: int | None = None, variable: str | None = None, tide_system: str | None = None,
        accept_datum: bool = False, accept_quasi_geoid: bool = False, max_memory_gb: float | None = None,
        resume: bool = False, **parameters) -> TileStore:
    """Fit a geoid source into a new tile store at ``store`` and open it; the same store,
    coefficient for coefficient, as ``geoid-fit`` with the same arguments.

    ``source``: a grid or model file path, a catalogue name (``"egm96-15"``) or a source
    object (:class:`~geoidspline.sources.grid.GeoidGrid`,
    :class:`~geoidspline.sources.harmonics.GeoidSynthesis`); ``correction`` and
    ``preset`` apply to a model file. ``region``: (south, west, north, east) degrees or a
    :class:`~geoidspline.sphere.Region` (default: the source's extent, global for a
    global grid or a model). ``parameters``: any field of
    :class:`~geoidspline.fitting.parameters.FitParameters` (``tolerance_m``, ``h0``,
    ``max_level``, ``order``, ``method``, ...). ``workers``/``scheduler``: where blocks are
    solved (:class:`~geoidspline.fitting.executors.Executor`), never stored. ``choose``
    (default, as ``geoid-fit``): the fields not in ``parameters`` are chosen from
    ``tolerance_m`` (default 0.5 m) for the fewest coefficients
    (:func:`~geoidspline.fitting.choose.choose_parameters`; the reasons go into the
    manifest's ``fit.choices``); ``choose=False`` keeps FitParameters' defaults for them.
    ``sign``: an Ed25519 private key (PEM file or key object) that signs the store
    (docs/signing.md).
    ``band``/``variable``: the GeoTIFF band or netCDF variable of a file with several.
    The source is taken into the store by the one rule of
    :func:`geoidspline.sources.reference.for_new_store`: converted to ``tide_system``
    (default: its own) and to WGS 84 where a well-defined conversion exists, else
    refused unless ``accept_datum`` / ``accept_quasi_geoid``.
    ``max_memory_gb``: the memory the fit plans against (default: a share of the
    machine's, :data:`geoidspline._memory.MEMORY_FRACTION`); a fit that needs more is
    refused before any work, naming the figure.
    ``resume``: continue the unfinished fit of the same source and options at ``store``
    (a model's whole globe is fitted and committed band by band,
    :mod:`geoidspline.api.banded`); without one there, a new fit.
    """
    run_fit(source, store, region=region, overwrite=overwrite, workers=workers, scheduler=scheduler,
            correction=correction, preset=preset, progress=progress, choose=choose, sign=sign, band=band,
            variable=variable, tide_system=tide_system, accept_datum=accept_datum,
            accept_quasi_geoid=accept_quasi_geoid, max_memory_gb=max_memory_gb, resume=resume, **parameters)
    return open_store(store)


def update(store, source, region, *, blend_width_km: float = 100.0, tolerance_m: float | None = None,
           workers: int = 1, correction=None, preset: str | None = None, progress=None,
           wait_seconds: float = 0.0, sign=None, band: int | None = None, variable: str | None = None,
           accept_datum: bool = False, accept_quasi_geoid: bool = False, accept_implausible: bool = False) -> dict:
    """Replace the store's geoid inside ``region`` by ``source`` (a regional update,
    :func:`geoidspline.api.regional.update_store`); returns the update's history record,
    the same as ``geoid-update`` with the same arguments.

    ``tolerance_m``: this update's tolerance in metres (default: the store's);
    ``wait_seconds``: how long to wait for another process writing the store;
    ``sign``: an Ed25519 private key (PEM file or key object) that signs the new version;
    ``band``/``variable``: the GeoTIFF band or netCDF variable of a file with several;
    ``accept_datum``/``accept_quasi_geoid``: take such a source's values as they are;
    ``accept_implausible``: skip the plausibility check against the store."""
    from ..fitting.executors import Executor
    from .regional import update_store

    if _is_path(source):
        from ..sources.resolve import open_source

        source = open_source(source, correction, preset, band=band, variable=variable)
    bounds = {"max_change_m": None, "max_slope": None} if accept_implausible else {}
    return update_store(store, source, _as_region(region), blend_width_km=blend_width_km,
                        executor=Executor(workers=workers), tolerance_m=tolerance_m, progress=progress,
                        wait_seconds=wait_seconds, sign=sign, accept_datum=accept_datum,
                        accept_quasi_geoid=accept_quasi_geoid, **bounds)
