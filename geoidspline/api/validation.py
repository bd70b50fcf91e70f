"""A store against the exact synthesis of a spherical-harmonic model at random points."""

from __future__ import annotations

import numpy as np

from ..errors import GeoidSplineError
from ..fitting.check_points import check_points
from ..sphere.region import Region

#: Seed of the random check points of :func:`check_against` (the fit's own check
#: points use seed 0, see :func:`geoidspline.fitting.check_points.check_points`).
CHECK_SEED = 1


def check_against(store, synthesis, points=20_000, seed=CHECK_SEED) -> dict:
    """|store − exact synthesis| at ``points`` random points of the store's region.

    The points are uniform in area over the store's region
    (:func:`geoidspline.fitting.check_points.check_points`, seed ``seed``); they are random, so not the
    fit's lattice nodes, and a different seed from the store's own check points.
    Returns a dict with ``points``, ``seed``, ``max_error_m``, ``rms_error_m``,
    ``p99_error_m``, ``mean_error_m`` (store − model), the point of the largest error and
    what was compared.
    """
    points = int(points)
    if points < 1:
        raise GeoidSplineError(f"points must be at least 1, got {points}")
    region = Region(*store.manifest["region"])
    check = check_points(synthesis, region, count=points, seed=seed)
    errors = store.undulation(check.latitude, check.longitude) - check.truth
    absolute = np.abs(errors)
    worst = int(np.argmax(absolute))
    prov = store.manifest.get("provenance", {})
    model = synthesis.model
    correction = synthesis.correction
    same_source = bool(prov.get("sha256")) and prov.get("sha256") == model.sha256
    return {
        "model": str(model.source_path or model.name),
        "model_name": model.name,
        "model_sha256": model.sha256,
        "correction": None if correction is None else str(correction.source_path or correction.name),
        "preset": synthesis.preset,
        "max_degree": synthesis.max_degree,
        "zero_degree_term_m": synthesis.zero_degree_term_m,
        "store_source_sha256": prov.get("sha256"),
        "same_source": same_source,
        "region": list(region.as_tuple()),
        "points": points,
        "seed": seed,
        "sampling": check.description,
        "max_error_m": float(absolute.max()),
        "rms_error_m": float(np.sqrt(np.mean(errors**2))),
        "p99_error_m": float(np.percentile(absolute, 99)),
        "mean_error_m": float(np.mean(errors)),
        "worst_point": [float(check.latitude[worst]), float(check.longitude[worst])],
        "units": "m",
    }
