"""Store format 2 against format 1 on the same fit: bytes, errors, nodes (issue 12).

    python benchmarks/compact_stores.py egm96-2mm global-0.5 [--out-dir DIR]

Each scenario fits once, as ``geoid-fit SOURCE --tolerance T`` does (parameters chosen
from the tolerance), then writes the same fit twice: format 2 (``DIR/NAME-v2``, what
``geoid-fit`` writes) and format 1 (``DIR/NAME-v1``, float64 netCDF4 tiles). For each:
bytes (manifest plus tiles), bytes per coefficient, the step and its stated bound, the
largest |error| at the fit's nodes of what the store holds (read back from the store
and evaluated at every node, independently of the manifest's figures), and for a model
the errors at 20,000 random points against the exact synthesis
(:func:`geoidspline.api.validation.check_against`, seed 1, as ``geoid-info
--check-against``). One JSON row per scenario goes to ``results/compact.jsonl``.
Run it under the shared lock: the 2 mm fit needs about 3 GB.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import git_commit, machine_info  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("GEOIDSPLINE_DATA", "/work/shared/data/egm96"))

SCENARIOS = {
    "egm96-2mm": {"source": DATA / "egm96_to360.ascii.gz", "correction": DATA / "CORRCOEF.gz",
                  "tolerance_m": 0.002, "targets": {"max_error_m": 0.002, "rms_error_m": 0.0003,
                                                    "bytes": 8_000_000}},
    "global-0.5": {"source": Path("/usr/share/proj/egm96_15.gtx"), "correction": None,
                   "tolerance_m": 0.5, "targets": {"bytes": 1_000_000}},
}


def _store_figures(path: Path, result, synthesis) -> dict:
    from geoidspline.api.validation import check_against
    from geoidspline.store.reader import TileStore

    store = TileStore.open(path, lazy=False)
    m = store.manifest
    size = (path / "manifest.json").stat().st_size + sum(e["bytes"] for e in m["tiles"])
    stored_at_nodes = store.spline.evaluate_points(result.node_directions)
    fitted_at_nodes = result.spline.evaluate_points(result.node_directions)
    node_errors = result.node_errors - (stored_at_nodes - fitted_at_nodes)  # truth − stored
    row = {
        "format_version": m["format_version"],
        "bytes": size,
        "tiles": len(m["tiles"]),
        "bytes_per_coefficient": round(size / m["spline"]["coefficients"], 3),
        "value_step_m": m["spline"].get("value_step_m"),
        "value_error_bound_m": m["spline"].get("value_error_bound_m"),
        "node_max_error_m": float(np.abs(node_errors).max()),
        "node_rms_error_m": float(np.sqrt(np.mean(node_errors**2))),
        "manifest_node_max_error_m": m["accuracy"]["node_max_error_m"],
        "fit_check_max_error_m": m["accuracy"]["max_error_m"],
    }
    if synthesis is not None:
        check = check_against(store, synthesis, points=20_000)
        row.update({f"exact_{k}": check[k] for k in ("points", "max_error_m", "rms_error_m", "p99_error_m")})
    return row


def run(name: str, out_dir: Path) -> dict:
    from geoidspline.api import _as_region
    from geoidspline.fitting.check_points import check_points
    from geoidspline.fitting.choose import choose_parameters
    from geoidspline.fitting.driver import fit_source
    from geoidspline.sources.resolve import open_source
    from geoidspline.store.writer import write_store

    spec = SCENARIOS[name]
    source = open_source(str(spec["source"]), str(spec["correction"]) if spec["correction"] else None, None)
    region = _as_region(None)
    t0 = time.perf_counter()
    choice = choose_parameters(source, spec["tolerance_m"], region)
    result = fit_source(source, region, choice.parameters)
    check = check_points(source, region, count=20_000)
    fit_s = time.perf_counter() - t0
    extra = {"choices": choice.as_manifest()}
    rows = {}
    for version in (2, 1):
        path = out_dir / f"{name}-v{version}"
        t1 = time.perf_counter()
        write_store(path, result, source.provenance, check=check, overwrite=True, extra=extra,
                    format_version=version)
        write_s = time.perf_counter() - t1
        rows[f"v{version}"] = {"path": str(path), "write_s": round(write_s, 1),
                               **_store_figures(path, result, source if spec["correction"] else None)}
    v2 = rows["v2"]
    targets = dict(spec["targets"])
    met = {"bytes": v2["bytes"] <= targets["bytes"],
           "nodes_within_tolerance": v2["node_max_error_m"] <= spec["tolerance_m"]}
    if "max_error_m" in targets:
        met["max_error_m"] = v2["exact_max_error_m"] <= targets["max_error_m"]
        met["rms_error_m"] = v2["exact_rms_error_m"] <= targets["rms_error_m"]
    return {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "commit": git_commit(REPO),
        "machine": machine_info(),
        "load_average": os.getloadavg(),
        "scenario": name,
        "tolerance_m": spec["tolerance_m"],
        "parameters": choice.parameters.as_dict(),
        "coefficients": result.spline.coefficient_count,
        "levels": [len(lv) for lv in result.spline.levels],
        "fit_node_max_error_m": result.node_max_error_m,
        "fit_and_check_points_s": round(fit_s, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "targets": targets,
        "met": met,
        **rows,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenarios", nargs="+", choices=sorted(SCENARIOS))
    parser.add_argument("--out-dir", type=Path, default=REPO / "benchmarks" / "out")
    parser.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "compact.jsonl")
    args = parser.parse_args(argv)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    failed = False
    for name in args.scenarios:
        row = run(name, args.out_dir)
        print(json.dumps(row), flush=True)
        with open(args.json, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(row) + "\n")
        failed |= not all(row["met"].values())
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
