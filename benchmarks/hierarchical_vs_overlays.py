#!/usr/bin/env python3
"""Hierarchical B-splines (thesis §5.3) against hierarchical overlays (§5.2), in one run.

    python benchmarks/hierarchical_vs_overlays.py [SCENARIO ...] [--workers N] [--no-condition]
        [--condition-region S W N E] [--out-dir DIR]

Part 1, fits: each scenario runs ``geoid-fit ... --refinement overlays`` and then
``--refinement hierarchical`` (a ``-model`` scenario, EGM96 from its coefficients in
../shared/data, each with ``--method least-squares`` and ``--method interpolation``:
four fits) as subprocesses (``python -m geoidspline fit ... --json
-q``; wall time by ``time.perf_counter()`` around each, interpreter start included) and
records the coefficients, the node max |error| the store reports, whether the tolerance
was reached and the fit's own seconds. The two fits of a scenario run back to back so
that machine load hits them alike; the load averages before and after are recorded.

Part 2, condition numbers per number of levels, in this process, on a smaller region
(default -35 -80 -10 -60, a 25° x 20° part of the Andes: the matrices stay a few
thousand unknowns so their extreme eigenvalues are exact):

- hierarchical: after each refinement step L, the normal matrix AᵀA of the whole basis
  (levels 0..L, no penalty) at n³ + 3 random points filling every leaf cell (Ω, the
  setting of Theorems 5.3 and 5.6), scaled to unit diagonal;
- overlays, stacked: the overlay B-splines of levels 0..L taken as one basis, AᵀA at
  the sites of all those levels, scaled to unit diagonal: the system a joint least
  squares over overlays would have to solve (singular as soon as a level holds every
  child of a coarser B-spline);
- overlays, as solved: each level's own system (AᵀA + penalty + ridge) at its level.

Extreme eigenvalues by ``scipy.sparse.linalg.eigsh`` (the smallest by shift-invert
near 0); a matrix whose smallest eigenvalue is below 1e-15 of its largest is reported
as singular.

Every run appends one JSON row to benchmarks/results/hierarchical.jsonl (date, commit,
machine, load, figures) and prints markdown tables.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import git_commit, machine_info  # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results" / "hierarchical.jsonl"
DEFAULT_OUT = HERE / "out"

SHARED = REPO.parent / "shared" / "data" / "egm96"
#: EGM96 from its coefficients (F477 + CORRCOEF), every parameter fixed so that the four
#: fits of a model scenario share h0, order, levels and the 5' node lattice.
MODEL = [str(SHARED / "egm96_to360.ascii.gz"), "--correction", str(SHARED / "CORRCOEF.gz"),
         "--h0", "0.1", "--order", "4", "--max-level", "6", "--sample-spacing", str(1 / 12)]
#: The fits of a model scenario: (refinement, method); a grid scenario has only the first two.
MODEL_FITS = (("overlays", "least-squares"), ("hierarchical", "least-squares"), ("overlays", "interpolation"),
              ("hierarchical", "interpolation"))

SCENARIOS = {
    "andes": ["egm96-15", "--region", "-60", "-90", "15", "-30", "--tolerance", "0.5"],
    "andes-model": [*MODEL, "--region", "-60", "-90", "15", "-30", "--tolerance", "0.5"],
    "andes-part-model": [*MODEL, "--region", "-35", "-80", "-10", "-60", "--tolerance", "0.5"],
    "andes-part": ["egm96-15", "--region", "-35", "-80", "-10", "-60", "--tolerance", "0.5"],
    "global-0.1": ["egm96-15", "--tolerance", "0.1"],
}
TARGETS = {"andes": {"coefficients": 22_000}, "global-0.1": {"coefficients": 600_000}}


def run_fit(scenario, refinement, out_dir, workers, method=None):
    out = out_dir / f"{scenario}-{refinement}" if method is None else out_dir / f"{scenario}-{refinement}-{method}"
    cmd = [sys.executable, "-m", "geoidspline", "fit", *SCENARIOS[scenario], "--refinement", refinement,
           "--workers", str(workers), "--store", str(out), "--overwrite", "--json", "-q"]
    if method is not None:
        cmd += ["--method", method]
    load = os.getloadavg()
    start = time.perf_counter()
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    wall = time.perf_counter() - start
    if run.returncode not in (0, 3):
        raise SystemExit(f"{' '.join(cmd)} failed:\n{run.stderr}")
    info = json.loads(run.stdout)
    return {
        "scenario": scenario, "refinement": refinement, "method": method, "command": " ".join(cmd[1:]),
        "coefficients": info["coefficients"], "node_max_error_m": info["node_max_error_m"],
        "node_rms_error_m": info["node_rms_error_m"], "check_max_error_m": info.get("max_error_m"),
        "converged": run.returncode == 0, "wall_seconds": round(wall, 1),
        "levels": [lv["coefficients"] for lv in info["levels"]],
        "load_before": [round(v, 2) for v in load], "load_after": [round(v, 2) for v in os.getloadavg()],
    }


def condition(matrix):
    """Condition number of a symmetric positive semi-definite sparse matrix (inf if singular)."""
    import scipy.sparse.linalg as sla

    matrix = matrix.tocsc()
    largest = float(sla.eigsh(matrix, k=1, which="LA", return_eigenvectors=False)[0])
    try:
        smallest = float(sla.eigsh(matrix, k=1, sigma=-1e-12 * largest, which="LM", return_eigenvectors=False)[0])
    except RuntimeError:  # the shifted matrix is singular to working precision
        return math.inf
    return math.inf if smallest < 1e-15 * largest else largest / smallest


def unit_diagonal(matrix):
    import scipy.sparse as sp

    d = matrix.diagonal()
    scale = sp.diags(1.0 / np.sqrt(np.where(d > 0, d, 1.0)))
    return scale @ matrix @ scale


def condition_tables(region_bounds):
    import scipy.sparse as sp

    from geoidspline._kernels.fitting import normal_equations
    from geoidspline.bspline.domain import active_cells
    from geoidspline.bspline.keys import pack_keys, unpack_keys
    from geoidspline.fitting.driver import clip_to_extent, fit_nodes, support_margin_deg
    from geoidspline.fitting.hierarchical import fit_hierarchical
    from geoidspline.fitting.least_squares import _second_difference_penalty
    from geoidspline.fitting.parameters import FitParameters
    from geoidspline.fitting.sites import DataNodes, sites_for_level
    from geoidspline.hierarchy.hierarchical import design_matrix, normal_matrix
    from geoidspline.sources.resolve import open_source
    from geoidspline.sphere.region import Region

    region = Region.from_bounds(*region_bounds)
    source = open_source("egm96-15", None, None)
    params = FitParameters(tolerance_m=0.5)
    sample = source.nodes(clip_to_extent(region.expanded(support_margin_deg(params)), source))

    hierarchical = []

    rng = np.random.default_rng(0)

    def measure(basis, points, values, coefs):
        # the basis on Ω (the theorems' setting): n³ + 3 random points filling every leaf
        # (the fit's own sites lie on the sphere, where the thin basis leaves radial
        # combinations free for the penalty to decide)
        per = basis.order ** 3 + 3
        filled = []
        for lv, leaves in enumerate(basis.leaves):
            cells = unpack_keys(leaves)
            p = (cells[:, None, :] + rng.uniform(0, 1, (cells.shape[0], per, 3))) * basis.spacing(lv)
            filled.append((p.reshape(-1, 3), np.zeros(cells.shape[0] * per)))
        matrix, _ = normal_matrix(basis, filled)
        matrix = matrix + sp.triu(matrix, 1).T  # the whole symmetric matrix from its upper triangle
        hierarchical.append({"levels": basis.levels, "coefficients": basis.coefficient_count,
                             "condition": condition(unit_diagonal(matrix))})
        print(f"  hierarchical, levels 0-{basis.levels - 1}: {basis.coefficient_count} coefficients, "
              f"condition {hierarchical[-1]['condition']:.3g}", flush=True)

    nodes = DataNodes.from_sample(sample, region)
    fit_hierarchical(nodes, None, region, dataclasses.replace(params, refinement="hierarchical"), on_step=measure)

    result = fit_nodes(sample, region, params)
    stacked, solved = [], []
    points_so_far = []
    for lv, level in enumerate(result.spline.levels):
        h = level.h
        site_cells = np.unique(pack_keys(active_cells(h, region))) if lv == 0 else None
        ray_mask = nodes.thinned(h, params.rays_per_cell)
        pts, _ = sites_for_level(nodes, ray_mask, h, params.order, level.keys, params.radial_offsets, site_cells)
        points_so_far.append(pts)
        basis = _Stacked(params.order, [lv_.keys for lv_ in result.spline.levels[:lv + 1]],
                         [lv_.h for lv_ in result.spline.levels[:lv + 1]])
        a = design_matrix(basis, np.concatenate(points_so_far))
        stacked.append({"levels": lv + 1, "coefficients": basis.coefficient_count,
                        "condition": condition(unit_diagonal((a.T @ a).tocsc()))})
        # the level's own system, as the overlay fit solves it (penalty; ridge on overlays)
        indptr, indices, data, _ = normal_equations(np.ascontiguousarray(pts), np.zeros(pts.shape[0]),
                                                             h, params.order, level.keys)
        upper = sp.csc_matrix((data, indices, indptr), shape=(level.keys.size,) * 2)
        full = upper + sp.triu(upper, 1).T
        diagonal = full.diagonal()
        scale = float(diagonal[diagonal > 0].mean())
        ridge = params.overlay_ridge if lv > 0 else 1e-10
        system = full + params.regularization * scale * _second_difference_penalty(level.keys) \
            + ridge * scale * sp.identity(level.keys.size)
        solved.append({"level": lv, "coefficients": int(level.keys.size),
                       "condition": condition(unit_diagonal(system.tocsc()))})
        print(f"  overlays, levels 0-{lv}: {basis.coefficient_count} coefficients, stacked condition "
              f"{stacked[-1]['condition']:.3g}", flush=True)
    return {"region": list(region_bounds), "hierarchical": hierarchical, "overlays_stacked": stacked,
            "overlays_per_level": solved}


class _Stacked:
    """Overlay levels seen as one basis by ``design_matrix`` (keys and spacing per level)."""

    def __init__(self, order, active, spacings):
        self.order = order
        self.active = active
        self._h = spacings

    def spacing(self, level):
        return self._h[level]

    def offsets(self):
        return np.r_[0, np.cumsum([a.size for a in self.active])].astype(np.int64)

    @property
    def coefficient_count(self):
        return int(sum(a.size for a in self.active))


def fmt_condition(value):
    return "singular" if math.isinf(value) else f"{value:.3g}"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenarios", nargs="*", default=["andes"], choices=sorted(SCENARIOS))
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--out-dir", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--no-condition", action="store_true", help="skip the condition numbers")
    parser.add_argument("--condition-region", nargs=4, type=float, default=(-35, -80, -10, -60),
                        metavar=("S", "W", "N", "E"))
    args = parser.parse_args()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    row = {"date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
           "commit": git_commit(REPO), "machine": machine_info(), "fits": []}
    print("| scenario | refinement | method | coefficients | node max \\|error\\| | check max | reached | wall s "
          "| per level |")
    print("|---|---|---|---:|---:|---:|---|---:|---|")
    for scenario in args.scenarios:
        fits = MODEL_FITS if scenario.endswith("-model") else (("overlays", None), ("hierarchical", None))
        for refinement, method in fits:
            fit = run_fit(scenario, refinement, args.out_dir, args.workers, method)
            target = TARGETS.get(scenario, {}).get("coefficients")
            if target and refinement == "hierarchical":
                fit["target_coefficients"] = target
                fit["target_met"] = fit["coefficients"] <= target and fit["converged"]
            row["fits"].append(fit)
            check = fit["check_max_error_m"]
            print(f"| {scenario} | {refinement} | {method or ''} | {fit['coefficients']:,} | "
                  f"{fit['node_max_error_m']:.3f} m | {'' if check is None else f'{check:.3f} m'} | "
                  f"{'yes' if fit['converged'] else 'no'} | {fit['wall_seconds']} | "
                  f"{' / '.join(f'{c:,}' for c in fit['levels'])} |", flush=True)
    if not args.no_condition:
        print(f"\ncondition numbers on {tuple(args.condition_region)}:")
        row["condition"] = condition_tables(tuple(args.condition_region))
        cond = row["condition"]
        print("\n| levels | hierarchical: coefficients | condition | overlays stacked: coefficients | condition "
              "| overlay level's own system |")
        print("|---:|---:|---:|---:|---:|---:|")
        for i in range(max(len(cond["hierarchical"]), len(cond["overlays_stacked"]))):
            h = cond["hierarchical"][i] if i < len(cond["hierarchical"]) else None
            o = cond["overlays_stacked"][i] if i < len(cond["overlays_stacked"]) else None
            s = next((x for x in cond["overlays_per_level"] if x["level"] == i), None)
            print(f"| 0-{i} | {h['coefficients'] if h else ''} | {fmt_condition(h['condition']) if h else ''} | "
                  f"{o['coefficients'] if o else ''} | {fmt_condition(o['condition']) if o else ''} | "
                  f"{fmt_condition(s['condition']) if s else ''} |")
        for name, part in cond.items():
            if name != "region":
                for item in part:
                    item["condition"] = None if math.isinf(item["condition"]) else item["condition"]
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    with RESULTS.open("a", encoding="utf-8") as fh:
        fh.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
