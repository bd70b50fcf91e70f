"""A whole-globe fit of a model made band by band into its store (issue 22).

:func:`build_banded_store` is what :func:`geoidspline.api.build_store` does for a fit
that :func:`~geoidspline.fitting.bands.uses_bands`: the memory of its largest band is
planned (and a fit that cannot have it refused) before any work; then every band not
committed yet is fitted (:func:`~geoidspline.fitting.bands.fit_band`: here, or as a task
on a dask cluster) and committed to the store as it comes back
(:class:`~geoidspline.store.writer.BandedWrite`); the manifest, written last, sums
the bands. An interrupted fit continues with ``resume=True`` from its last committed band.
"""

from __future__ import annotations

import json
import logging
import time

import numpy as np

log = logging.getLogger("geoidspline.api")

#: The seed of a model's check points (:func:`geoidspline.fitting.check_points.random_positions`).
CHECK_SEED = 0


def _fitted_bands(bands, shared, executor, progress):
    """``(band, BandResult)`` as each band is fitted: on the executor's dask cluster when
    it has one (a band a task), else here one after the other (the executor's workers
    solving each band's overlay blocks, the stages reported to ``progress``)."""
    from ..fitting.executors import run_tasks

    if executor.scheduler:
        yield from run_tasks(_band_task, bands, executor, shared)
    else:
        for band in bands:
            yield band, _band_in_process(shared, band, executor, progress)


def _band_task(shared, band):
    """One band's fit (a module-level function: what a dask worker runs)."""
    return _band_in_process(shared, band)


def _band_in_process(shared, band, executor=None, progress=None):
    """A band fitted here, its overlay blocks solved by ``executor``'s workers; its large
    temporaries reuse each other's memory (:func:`~geoidspline._kernels.array_cache.reused_array_memory`),
    released when it ends: blocks kept from one band to the next would sit beside the
    next band's synthesis and the previous band's commit, which allocate outside the
    cache, and raise the fit's peak (benchmarks/README.md)."""
    from .._kernels.array_cache import reused_array_memory
    from ..fitting.bands import fit_band

    source, params, rounding, check_lat, check_lon, margin = shared
    with reused_array_memory():
        return fit_band(source, params, band, check_lat, check_lon, rounding, margin, executor=executor,
                        progress=progress)


def _plain(value):
    """JSON for numpy scalars in a band's summary."""
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON")


def global_lattice_engine(source):
    """``source`` as a whole globe is fitted from: a model's lattices by ducc0's
    transforms ('sht': each group of rows, north and south together, is computed once
    for the bands that read it; 2.5x less CPU than the row sums at degree 2190, within
    1e-9 m: benchmarks/README.md) when ducc0 is installed and ``GEOIDSPLINE_LATTICE_ENGINE``
    does not name an engine; a copy, the caller's source is left as it is. Regions keep
    the row sums: their few rows do not pay for whole groups."""
    import copy
    import importlib.util
    import os

    if (getattr(source, "lattice_engine", "sht") == "sht" or os.environ.get("GEOIDSPLINE_LATTICE_ENGINE", "").strip()
            or importlib.util.find_spec("ducc0") is None):
        return source
    source = copy.copy(source)
    source.lattice_engine = "sht"
    return source


def _commit_behind(fitted, commit, committed):
    """``commit(band, result)`` of each ``(band, result)`` of ``fitted`` in order, on one
    thread of its own while the next band is fitted (a band's tiles are encoded and
    written in 12-25 s at 1 cm: the codec, zstd and the files release the GIL); at most
    one band waits, each committed before the next is handed over, and none is left
    writing when this returns or raises (``committed()`` after each)."""
    from concurrent.futures import ThreadPoolExecutor

    pending = None
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="band-commit") as writer:
        try:
            for band, result in fitted:
                if pending is not None:
                    pending.result()
                    committed()
                pending = writer.submit(commit, band, result)
                del result  # the writer holds it until committed
            if pending is not None:
                pending.result()
                committed()
                pending = None
        finally:
            if pending is not None:  # a fit failed: its predecessor's commit still completes
                pending.exception()


def build_banded_store(source, path, region, params, progress=None, overwrite=False, resume=False,
                       check_count=20_000, executor=None, extra=None, sign=None, margin_deg=None):
    """Fit ``source`` over the globe band by band into the store at ``path`` (see the
    module's docstring); returns ``(FitResult, store info)`` as
    :func:`~geoidspline.api.build_store` does (the result's ``spline`` is None: the
    store holds it, read it with :func:`~geoidspline.api.open_store`)."""
    from ..bspline.level import LevelSpline
    from ..fitting.bands import ROUNDING_RMS_OVER_TOLERANCE, Rounding, band_margin_deg
    from ..fitting.check_points import RING_POINTS, random_positions
    from ..fitting.executors import Executor
    from ..fitting.memory import band_slabs, banded_parameters, check_plan
    from ..fitting.parameters import check_promise
    from ..fitting.progress import as_progress
    from ..hierarchy.ambient import AmbientSpline
    from ..store.codec import first_step, stored_values
    from ..store.reader import TileStore
    from ..store.writer import BandedWrite, tile_groups, tile_stats, tolerance_asked

    started = time.perf_counter()
    executor = executor or Executor()
    progress = as_progress(progress)
    source = global_lattice_engine(source)
    check_promise(params)
    params = banded_parameters(source, region, params, executor.memory_budget)
    check_plan(source, region, params, executor.memory_budget)
    margin = band_margin_deg(params) if margin_deg is None else float(margin_deg)
    asked = tolerance_asked({"tolerance_m": params.tolerance_m, **(extra or {})})
    # the store's step: 4x the proven bound's (first_step); each band corrects its
    # rounding at its nodes and halves the step as often as they need (tiles of finer
    # steps nest in the store's)
    step = first_step(asked, params.max_level + 1)
    rounding = Rounding(step, asked, stored_values, ROUNDING_RMS_OVER_TOLERANCE * asked)
    check_lat, check_lon = random_positions(region, check_count, CHECK_SEED)
    bands = band_slabs(source, params)
    identity = json.loads(json.dumps({
        "source": source.provenance.source, "sha256": source.provenance.sha256, "parameters": params.as_dict(),
        "value_step_m": step, "check_points": check_count, "check_seed": CHECK_SEED,
        "check_ring_points": RING_POINTS, "margin_deg": margin,
        "lattice_engine": getattr(source, "lattice_engine", None),  # the lattice's bits
        "region": list(region.as_tuple()), "extra": extra or {},
        "bands": [list(band) for band in bands],  # the slabs of each: part of the fit, as the tile size
    }, default=_plain))
    spline_meta = {"order": params.order, "h0": params.h0, "tile_size": params.tile_size}
    with BandedWrite(path, identity, overwrite=overwrite, resume=resume, sign=sign) as write:
        done = write.done()
        if done:
            log.info("resuming: %d of %d bands committed already", len(done), len(bands))
        todo = [band for band in bands if band.first not in done]
        shared = (source, params, rounding, check_lat, check_lon, margin)

        def commit(band, result):
            levels = [LevelSpline(level, h, params.order, keys, coefs)
                      for level, h, keys, coefs in result.levels if keys.size]
            groups = tile_groups(AmbientSpline(levels), params.tile_size)
            stats = {key: tile_stats(*result.tile_stats[key]) for key in groups}
            summary = json.loads(json.dumps({
                "levels": {str(level): int(keys.size) for level, _, keys, _ in result.levels},
                "node_count": result.node_count, "node_max_error_m": result.node_max_error_m,
                "node_sum_squares": result.node_sum_squares,
                "fit_node_max_error_m": result.fit_node_max_error_m,
                "check_errors": result.check_errors, "level_reports": result.level_reports,
                "converged": result.converged, "data_limited": result.data_limited,
                "seconds": round(result.seconds, 3), "rows": result.sample_rows,
                "value_step_m": result.value_step_m,
            }, default=_plain))
            write.commit_band(band.first, groups, stats, {**spline_meta, "value_step_m": result.value_step_m},
                              summary)
            log.info("band %d..%d: %d coefficients, node max %.4f m, %.1f s", band.first, band.last,
                     sum(summary["levels"].values()), summary["node_max_error_m"], summary["seconds"])

        with progress.stage("bands", len(bands), "band") as advance:
            advance(len(done))
            _commit_behind(_fitted_bands(todo, shared, executor, progress), commit, lambda: advance(1))
        manifest, result = _banded_manifest(write, source, region, params, step, extra, started, check_count)
        with progress.stage("write", 1, "store") as advance:
            write.finish(manifest)
            advance(1)
    return result, TileStore.open(path).info()


def _banded_manifest(write, source, region, params, step, extra, started, check_count):
    """The store's manifest from the bands' records, and the fit's account."""
    from ..fitting.bands import level_reports
    from ..fitting.check_points import random_description
    from ..fitting.result import FitResult, LevelReport, method_text
    from ..sphere.coverage import Coverage
    from ..store.format import error_stats
    from ..store.writer import fit_manifest, quantisation_meta

    records = write.done()
    bands = [records[band] for band in sorted(records)]
    entries = sorted((entry for record in bands for entry in record["tiles"]), key=lambda e: e["tile"])
    counts: dict[int, int] = {}
    for record in bands:
        for level, count in record["levels"].items():
            counts[int(level)] = counts.get(int(level), 0) + int(count)
    level_counts = [{"level": level, "h": params.spacing(level), "coefficients": counts[level]}
                    for level in sorted(counts) if counts[level]]
    reports = level_reports([(record["level_reports"], record["levels"]) for record in bands])
    nodes = sum(record["node_count"] for record in bands)
    node_stats = {"count": nodes, "max_error_m": max(record["node_max_error_m"] for record in bands),
                  "rms_error_m": float(np.sqrt(sum(record["node_sum_squares"] for record in bands) / max(nodes, 1))),
                  "p99_error_m": None}  # not kept per band
    check_errors = np.concatenate([np.asarray(record["check_errors"], dtype=float) for record in bands])
    converged = all(record["converged"] for record in bands)
    seconds = time.perf_counter() - started
    fit = {"method": method_text(params), "converged": converged, "seconds": round(seconds, 3),
           "level_reports": reports,
           "bands": {"count": len(bands), "tile_size": params.tile_size, "margin_deg": write.identity["margin_deg"],
                     "seconds": [record["seconds"] for record in bands],
                     "value_steps_m": [record["value_step_m"] for record in bands]},
           **(extra or {})}
    coverage = Coverage.of_region(region)
    manifest = fit_manifest(entries, write.previous, write.version, write.store_id, source.provenance, region,
                            coverage, params, quantisation_meta(step, len(level_counts), nudged=True), level_counts, fit,
                            node_stats, max(record["fit_node_max_error_m"] for record in bands),
                            error_stats(check_errors), random_description(check_count, CHECK_SEED))
    result = FitResult(
        spline=None, parameters=params, region=region,
        levels=[LevelReport(**{k: v for k, v in r.items() if k in LevelReport.__dataclass_fields__})
                for r in reports],
        node_count=nodes, node_max_error_m=node_stats["max_error_m"], node_rms_error_m=node_stats["rms_error_m"],
        converged=converged, seconds=seconds, data_limited=any(record["data_limited"] for record in bands),
        coverage=coverage,
    )
    return manifest, result
