"""The public operations: fit a source into a store, open a store, update a store.

:func:`build_store` is the one way the command line, the tests and :func:`fit` make a
store: fit, measure at check points that were not fit sites, write atomically.
"""

from __future__ import annotations

import dataclasses

from .fitting.check_points import check_points
from .fitting.driver import FitResult, fit_source
from .fitting.executors import Executor
from .fitting.parameters import FitParameters
from .fitting.progress import as_progress
from .sphere.region import GLOBAL, Region
from .store.reader import TileStore
from .store.writer import write_store

__all__ = ["build_store", "fit", "open_store", "update"]


def open_store(path, *, lazy: bool = True, verify: bool = True, key=None) -> TileStore:
    """Open a tile store read-only.

    ``lazy`` (default) reads a tile when a query first needs it; ``lazy=False`` reads and
    checks every tile now. ``verify`` checks each tile's sha256 as it is read (sizes are
    always checked). ``key``: the Ed25519 public key (PEM file or key object) that must
    have signed the store; an unsigned or forged store is refused
    (:class:`~geoidspline.store.signing.SignatureError`) and every tile is checked as it
    is read. See :class:`geoidspline.store.TileStore` and docs/signing.md.
    """
    return TileStore.open(path, verify=verify, lazy=lazy, key=key)


def build_store(source, path, region: Region | None = None, params: FitParameters | None = None,
                progress=None, overwrite=False, check_count=20_000,
                executor: Executor | None = None, extra: dict | None = None, sign=None) -> tuple[FitResult, dict]:
    """Fit ``source`` over ``region``, measure it and write the store at ``path``.

    ``progress``: a :class:`~geoidspline.fitting.progress.Progress` (every stage) or a
    callable given the number of blocks just solved. ``extra``: more entries of the
    manifest's ``fit`` section (``choices``: why the parameters are what they are).
    ``sign``: an Ed25519 private key (PEM file or key object) that signs the manifest.
    Returns the fit result and the store's summary (``TileStore.info()``).
    """
    region = region or GLOBAL
    params = params or FitParameters()
    progress = as_progress(progress)
    if sign is not None:
        from .store.signing import load_private_key

        sign = load_private_key(sign)  # a bad key file before the fit, not after it
    result = fit_source(source, region, params, progress=progress, executor=executor)
    if result.refinement_fallback:
        extra = {**(extra or {}), "refinement_fallback": result.refinement_fallback}
    check = check_points(source, region, count=check_count, progress=progress)
    with progress.stage("write", 1, "store") as advance:
        write_store(path, result, source.provenance, check=check, overwrite=overwrite, extra=extra, sign=sign)
        advance(1)
    return result, TileStore.open(path).info()


def _as_region(region) -> Region:
    if region is None:
        return GLOBAL
    return region if isinstance(region, Region) else Region.from_bounds(*region)


def fit(source, store, *, region=None, overwrite: bool = False, workers: int = 1, scheduler: str | None = None,
        correction=None, preset: str | None = None, progress=None, choose: bool = False, sign=None,
        **parameters) -> TileStore:
    """Fit a geoid source into a new tile store at ``store`` and open it.

    ``source``: a grid or model file path, a catalogue name (``"egm96-15"``) or a source
    object (:class:`~geoidspline.sources.grid.GeoidGrid`,
    :class:`~geoidspline.sources.harmonics.GeoidSynthesis`); ``correction`` and
    ``preset`` apply to a model file. ``region``: (south, west, north, east) degrees or a
    :class:`~geoidspline.sphere.Region` (default global). ``parameters``: any field of
    :class:`~geoidspline.fitting.parameters.FitParameters` (``tolerance_m``, ``h0``,
    ``max_level``, ``order``, ``method``, ...). ``workers``/``scheduler``: where blocks are
    solved (:class:`~geoidspline.fitting.executors.Executor`), never stored. ``choose``:
    the fields not in ``parameters`` are chosen from ``tolerance_m`` (default 0.5 m) for
    the fewest coefficients, as ``geoid-fit`` does
    (:func:`~geoidspline.fitting.choose.choose_parameters`; the reasons go into the
    manifest's ``fit.choices``); otherwise they keep FitParameters' defaults.
    ``sign``: an Ed25519 private key (PEM file or key object) that signs the store
    (docs/signing.md).
    """
    from .sources.resolve import open_source

    if isinstance(source, (str, bytes)) or hasattr(source, "__fspath__"):
        source = open_source(source, correction, preset)
    extra = None
    if choose:
        from .fitting.choose import choose_parameters

        tolerance = parameters.pop("tolerance_m", FitParameters().tolerance_m)
        choice = choose_parameters(source, tolerance, _as_region(region), given=parameters)
        params, extra = choice.parameters, {"choices": choice.as_manifest()}
    else:
        params = dataclasses.replace(FitParameters(), **parameters)
    build_store(source, store, _as_region(region), params, progress=progress, overwrite=overwrite,
                executor=Executor(workers=workers, scheduler=scheduler), extra=extra, sign=sign)
    return TileStore.open(store)


def update(store, source, region, *, blend_width_km: float = 100.0, tolerance_m: float | None = None,
           workers: int = 1, correction=None, preset: str | None = None, progress=None,
           wait_seconds: float = 0.0, sign=None) -> dict:
    """Replace the store's geoid inside ``region`` by ``source`` (a regional update,
    :func:`geoidspline.store.update.update_store`); returns the update's history record.

    ``tolerance_m``: this update's tolerance in metres (default: the store's);
    ``wait_seconds``: how long to wait for another process writing the store;
    ``sign``: an Ed25519 private key (PEM file or key object) that signs the new version."""
    from .sources.resolve import open_source
    from .store.update import update_store

    if isinstance(source, (str, bytes)) or hasattr(source, "__fspath__"):
        source = open_source(source, correction, preset)
    return update_store(store, source, _as_region(region), blend_width_km=blend_width_km,
                        executor=Executor(workers=workers), tolerance_m=tolerance_m, progress=progress,
                        wait_seconds=wait_seconds, sign=sign)
