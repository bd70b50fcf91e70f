#!/usr/bin/env python3
"""Dask scaling benchmark: one fit serially, then with its blocks solved on dask.

    python benchmarks/dask_scaling.py [--region S W N E] [--tolerance M] [--workers N]
                                      [--modes serial,pool,local,cluster] [--source NAME]

The same fit (default: EGM96 15' over the Andes region -60 -90 15 -30 at 0.1 m) runs
in this process once per mode:

- ``serial``: ``Executor(workers=1)``, every block solved here;
- ``pool``: ``workers=N``, the spawned process pool (``geoid-fit --workers N``);
- ``local``: ``scheduler="local", workers=N``: a dask LocalCluster of N single-threaded
  worker processes started and closed for every level (``geoid-fit --scheduler local``);
- ``cluster``: one LocalCluster of N single-threaded worker processes started by this
  script before the fit and passed by its ``tcp://`` address (``geoid-fit --scheduler
  tcp://...``): the set-up a real cluster has, without the per-level start-up.

Recorded per mode: wall time of ``fit_source`` (reading the source's nodes included),
the speed-up over ``serial``, whether the coefficients equal the serial ones bit for
bit, and per level the blocks, unknowns and sites per block and the per-block solve
seconds (measured inside the task, from ``solve_local_problem``; taken by wrapping
``geoidspline.fitting.executors.solve_problems``). Memory: every 0.25 s the RSS of each child
process of this one (the pool's or the cluster's workers; psutil), keeping the largest
single worker and the largest sum; in ``cluster`` mode also the workers' own report
(``client.run(psutil.Process().memory_info().rss)``) every 0.5 s, and their idle RSS
before the fit. A sample can miss a short peak.

Appends one JSON row to benchmarks/results/dask.jsonl and prints a summary table.
Run with at most 2 workers on a shared 2-core machine.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import statistics
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import git_commit, machine_info  # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results" / "dask.jsonl"
MODES = ("serial", "pool", "local", "cluster")


class ChildRSS:
    """Peak RSS of the largest child process and of all children together (psutil)."""

    def __init__(self, interval=0.25):
        import psutil

        self.peak_single_mb = 0.0
        self.peak_total_mb = 0.0
        self._stop = threading.Event()
        me = psutil.Process()

        def sample():
            while not self._stop.is_set():
                sizes = []
                for child in me.children(recursive=True):
                    try:
                        sizes.append(child.memory_info().rss / 2**20)
                    except psutil.Error:
                        pass
                if sizes:
                    self.peak_single_mb = max(self.peak_single_mb, max(sizes))
                    self.peak_total_mb = max(self.peak_total_mb, sum(sizes))
                self._stop.wait(interval)

        self._thread = threading.Thread(target=sample, daemon=True)
        self._thread.start()

    def stop(self):
        self._stop.set()
        self._thread.join()


def _rss():
    import psutil

    return psutil.Process().memory_info().rss


class WorkerRSS:
    """Peak RSS per dask worker as the workers report it (client.run every interval)."""

    def __init__(self, address, interval=0.5):
        from dask.distributed import Client

        self.client = Client(address)
        self.idle_mb = {w: v / 2**20 for w, v in self.client.run(_rss).items()}
        self.peak_mb = dict(self.idle_mb)
        self._stop = threading.Event()

        def sample():
            while not self._stop.is_set():
                try:
                    for w, v in self.client.run(_rss).items():
                        self.peak_mb[w] = max(self.peak_mb.get(w, 0.0), v / 2**20)
                except Exception:  # a worker restarting: skip the sample
                    pass
                self._stop.wait(interval)

        self._thread = threading.Thread(target=sample, daemon=True)
        self._thread.start()

    def stop(self):
        self._stop.set()
        self._thread.join()
        self.client.close()


class Recorder:
    """Wraps geoidspline.fitting.executors.solve_problems to keep per-level block figures."""

    def __init__(self):
        import geoidspline.fitting.executors as module

        self.module = module
        self.real = module.solve_problems
        self.levels = []

    def __enter__(self):
        def solve_problems(problems, *args, **kwargs):
            problems = list(problems)
            start = time.perf_counter()
            results = self.real(problems, *args, **kwargs)
            wall = time.perf_counter() - start
            seconds = [r[2] for r in results]
            unknowns = [p.keys.size for p in problems]
            sites = [p.points.shape[0] for p in problems]
            self.levels.append({
                "h": problems[0].h if problems else None,
                "blocks": len(problems),
                "own_coefficients": int(sum(r[0].size for r in results)),
                "unknowns_median": statistics.median(unknowns) if unknowns else 0,
                "unknowns_max": max(unknowns, default=0),
                "sites_median": statistics.median(sites) if sites else 0,
                "sites_max": max(sites, default=0),
                "block_seconds_median": round(statistics.median(seconds), 4) if seconds else 0,
                "block_seconds_max": round(max(seconds, default=0), 4),
                "block_seconds_sum": round(sum(seconds), 3),
                "solve_wall_seconds": round(wall, 3),
                # every block: [unknowns, sites, own coefficients, solve seconds]
                "block_table": [[int(u), int(n), int(r[0].size), round(float(r[2]), 4)]
                                for u, n, r in zip(unknowns, sites, results)],
            })
            return results

        self.module.solve_problems = solve_problems
        return self

    def __exit__(self, *exc):
        self.module.solve_problems = self.real


def run_mode(mode, source, region, base_params, workers):
    from geoidspline.fitting.driver import fit_source
    from geoidspline.fitting.executors import Executor

    cluster = worker_rss = None
    if mode == "serial":
        executor = Executor(workers=1)
    elif mode == "pool":
        executor = Executor(workers=workers)
    elif mode == "local":
        executor = Executor(workers=workers, scheduler="local")
    else:
        from dask.distributed import LocalCluster

        started = time.perf_counter()
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               env={"GEOIDSPLINE_THREADS": "1"},  # as geoidspline.fitting.executors starts them
                               dashboard_address=":0", scheduler_kwargs={"dashboard": False})
        cluster_start = time.perf_counter() - started
        executor = Executor(workers=workers, scheduler=cluster.scheduler_address)
        worker_rss = WorkerRSS(cluster.scheduler_address)
    children = ChildRSS()
    try:
        with Recorder() as rec:
            start = time.perf_counter()
            result = fit_source(source, region, base_params, executor=executor)
            wall = time.perf_counter() - start
    finally:
        children.stop()
        if worker_rss is not None:
            worker_rss.stop()
        if cluster is not None:
            cluster.close()
    row = {
        "mode": mode,
        "workers": 1 if mode == "serial" else workers,
        "scheduler": "address of a LocalCluster started before the fit" if mode == "cluster" else executor.scheduler,
        "wall_seconds": round(wall, 2),
        "fit_seconds": round(result.seconds, 2),
        "coefficients": int(sum(len(lv) for lv in result.spline.levels)),
        "node_max_error_m": result.node_max_error_m,
        "converged": result.converged,
        # sites of each level (each counted once; blocks share the ones in their margins)
        "level_sites": [r.sites for r in result.levels],
        # everything but the block solves: nodes, sites, residuals, building the blocks
        "driver_seconds": round(result.seconds - sum(lv["solve_wall_seconds"] for lv in rec.levels), 2),
        "levels": rec.levels,
        "block_seconds_median": round(statistics.median(
            [lv["block_seconds_median"] for lv in rec.levels]), 4) if rec.levels else None,
        "block_seconds_max": max((lv["block_seconds_max"] for lv in rec.levels), default=None),
        "block_seconds_total": round(sum(lv["block_seconds_sum"] for lv in rec.levels), 2),
        "peak_child_rss_mb": round(children.peak_single_mb, 1) or None,
        "peak_children_total_rss_mb": round(children.peak_total_mb, 1) or None,
    }
    if cluster is not None:
        row["cluster_start_seconds"] = round(cluster_start, 2)
        row["worker_idle_rss_mb"] = round(max(worker_rss.idle_mb.values()), 1)
        row["worker_peak_rss_mb"] = round(max(worker_rss.peak_mb.values()), 1)
    return row, result


_MEMORY_PROBE = r"""
import pickle, resource, sys, psutil
from geoidspline.fitting.least_squares import solve_local_problem
with open(sys.argv[1], "rb") as fh:
    small, big = pickle.load(fh)
solve_local_problem(small)  # kernel library load and qdldl import, outside the measurement
before = psutil.Process().memory_info().rss
seconds = solve_local_problem(big)[2]
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(before, peak, seconds)
"""


def full_block_probe(h, node_spacing_deg, centre=(30.0, 45.0), width_blocks=4, solve=6):
    """Full-coverage blocks of an overlay level of spacing ``h``, measured.

    Every data node of a square ``width_blocks`` blocks wide around ``centre`` is marked as above the
    tolerance, so the level covers it completely (what the finest level of a fit to a
    field with detail everywhere looks like); nodes on a lattice of ``node_spacing_deg``.
    The blocks of that level are built exactly as the fit builds them; the ``solve``
    blocks owning most coefficients (interior, full-coverage blocks) are solved here,
    and the largest of them once more in a fresh process for its memory: peak RSS
    (ru_maxrss) minus the RSS just before the solve, after a warm-up solve of a small
    block. Also measured: coefficients per surface cell (h²) of the level, counting
    B-splines whose support centre lies over the square, and how many blocks of
    ``block_cells`` cells meet the unit sphere (the block count of a global level with
    full coverage).
    """
    import math
    import pickle
    import subprocess
    import tempfile

    import numpy as np

    from geoidspline.bspline.domain import active_cells
    from geoidspline.fitting.least_squares import local_problems as _local_problems
    from geoidspline.fitting.least_squares import solve_local_problem
    from geoidspline.fitting.parameters import FitParameters
    from geoidspline.fitting.sites import DataNodes as _Nodes
    from geoidspline.fitting.sites import sites_for_level as _sites_for_level
    from geoidspline.hierarchy.overlays import OverlayRefinement
    from geoidspline.sources.base import NodeSample
    from geoidspline.sphere.region import GLOBAL, Region

    params = FitParameters(h0=h, max_level=0, untiled_max_unknowns=0, tile_size=max(0.4, h))
    order = params.order
    width_deg = math.degrees(width_blocks * params.block_cells * h)
    lat0, lon0 = centre
    region = Region(lat0 - width_deg / 2, lon0 - width_deg / 2, lat0 + width_deg / 2, lon0 + width_deg / 2)
    reach = math.degrees((params.margin_cells + 2 * order) * h)
    data = region.expanded(reach)
    lat = np.arange(data.south, data.north + 1e-12, node_spacing_deg)
    lon = np.arange(data.west, data.east + 1e-12, node_spacing_deg)
    lat2, lon2 = np.meshgrid(lat, lon, indexing="ij")
    # metres; ~1 m of detail at ~2 km wavelength on a smooth background
    field = 30 * np.sin(np.radians(2 * lat2)) + np.sin(lat2 * 180) * np.cos(lon2 * 170)
    nodes = _Nodes.from_sample(NodeSample(lat, lon, field), region)
    started = time.perf_counter()
    keys, _, _ = OverlayRefinement(params.refine_radius).level_keys(
        1, h, order, region, nodes.directions[nodes.in_region])
    points, node_of_site = _sites_for_level(nodes, nodes.thinned(h, params.rays_per_cell), h, order, keys,
                                            params.radial_offsets)
    problems = list(_local_problems(1, h, params, keys, points, nodes.values[node_of_site]))
    setup = time.perf_counter() - started
    centres = (_unpack(keys) + order / 2.0) * h
    norm = np.linalg.norm(centres, axis=1)
    c_lat = np.degrees(np.arcsin(centres[:, 2] / norm))
    c_lon = np.degrees(np.arctan2(centres[:, 1], centres[:, 0]))
    over = int(region.contains(c_lat, c_lon).sum())
    area = math.radians(region.longitude_span) * (math.sin(math.radians(region.north))
                                                  - math.sin(math.radians(region.south)))
    own = np.array([int(p.own.sum()) for p in problems])
    chosen = np.argsort(own)[::-1][:solve]
    table = []
    for i in chosen:
        p = problems[i]
        table.append([int(p.keys.size), int(p.points.shape[0]), int(own[i]),
                      round(solve_local_problem(p)[2], 3)])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "blocks.pkl"
        with open(path, "wb") as fh:
            pickle.dump((problems[int(np.argmin(own))], problems[int(chosen[0])]), fh)
        out = subprocess.run([sys.executable, "-c", _MEMORY_PROBE, str(path)], capture_output=True, text=True,
                             check=True).stdout.split()
    before, peak, seconds = int(out[0]), int(out[1]), float(out[2])
    blocks_global = int(len(active_cells(params.block_cells * h, GLOBAL)))
    return {
        "h": h,
        "node_spacing_deg": node_spacing_deg,
        "square": {"centre": list(centre), "width_deg": width_deg},
        "nodes": int(nodes.values.size),
        "level_coefficients": int(keys.size),
        "coefficients_per_surface_cell": round(over / (area / h**2), 3),
        "sites_per_surface_cell": round(points.shape[0] / ((math.radians(data.longitude_span) * (
            math.sin(math.radians(data.north)) - math.sin(math.radians(data.south)))) / h**2), 3),
        "blocks": len(problems),
        "setup_seconds": round(setup, 2),
        "full_blocks": [dict(zip(("unknowns", "sites", "own", "seconds"), row)) for row in table],
        "memory_block": {"unknowns": int(problems[int(chosen[0])].keys.size),
                         "sites": int(problems[int(chosen[0])].points.shape[0]),
                         "own": int(own[chosen[0]]), "seconds": round(seconds, 3),
                         "rss_before_mb": round(before / 2**20, 1), "peak_rss_mb": round(peak / 2**20, 1),
                         "solve_extra_mb": round((peak - before) / 2**20, 1)},
        "global_blocks_meeting_sphere": blocks_global,
    }


def _unpack(keys):
    from geoidspline.bspline.keys import unpack_keys

    return unpack_keys(keys)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", default="egm96-15")
    parser.add_argument("--region", nargs=4, type=float, metavar=("S", "W", "N", "E"), default=(-60, -90, 15, -30))
    parser.add_argument("--tolerance", type=float, default=0.1)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--modes", default=",".join(MODES), help=f"comma-separated subset of {','.join(MODES)}")
    parser.add_argument("--full-block", type=float, default=None, metavar="H",
                        help="also measure full-coverage blocks of an overlay level of spacing H (see full_block_probe)")
    parser.add_argument("--node-spacing", type=float, default=1 / 60, metavar="DEG",
                        help="node lattice spacing of the --full-block probe (default 1')")
    parser.add_argument("--results", type=Path, default=RESULTS, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    modes = [m for m in args.modes.split(",") if m]
    unknown = [m for m in modes if m not in MODES]
    if unknown or (modes and "serial" not in modes) or not (modes or args.full_block):
        parser.error(f"modes must include serial and be among {', '.join(MODES)} (or be empty with --full-block)")
    if args.workers < 1:
        parser.error("--workers must be at least 1")

    import numpy as np

    from geoidspline.fitting.parameters import FitParameters
    from geoidspline.sources.resolve import open_source
    from geoidspline.sphere.region import Region

    source = open_source(args.source)
    region = Region.from_bounds(*args.region)
    base = FitParameters(tolerance_m=args.tolerance)
    rows, reference = [], None
    for mode in ["serial"] + [m for m in modes if m != "serial"] if modes else []:
        print(f"running {mode} ...", file=sys.stderr, flush=True)
        row, result = run_mode(mode, source, region, base, args.workers)
        if reference is None:
            reference = result
        row["bitwise_equal_to_serial"] = all(
            np.array_equal(a.indices, b.indices) and np.array_equal(a.coefficients, b.coefficients)
            for a, b in zip(reference.spline.levels, result.spline.levels)
        ) and len(reference.spline.levels) == len(result.spline.levels)
        row["speedup_over_serial"] = round(rows[0]["wall_seconds"] / row["wall_seconds"], 3) if rows else 1.0
        rows.append(row)

    record = {
        "date": dt.datetime.now(dt.timezone.utc).replace(microsecond=0).isoformat(),
        "git_commit": git_commit(REPO),
        "machine": machine_info(),
        "source": args.source,
        "region": list(args.region),
        "tolerance_m": args.tolerance,
        "parameters": {k: v for k, v in base.as_dict().items() if k not in ("workers", "scheduler")},
        "runs": rows,
    }
    if args.full_block:
        print("probing full-coverage blocks ...", file=sys.stderr, flush=True)
        record["full_coverage_block"] = full_block_probe(args.full_block, args.node_spacing)
    args.results.parent.mkdir(parents=True, exist_ok=True)
    with open(args.results, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(record) + "\n")

    if "full_coverage_block" in record:
        print(json.dumps(record["full_coverage_block"], indent=1))
    if not rows:
        return 0
    print("| mode | workers | wall s | speed-up | bitwise = serial | block s median / max | "
          "block s total | peak worker RSS MB | coefficients |")
    print("|---|---:|---:|---:|---|---|---:|---:|---:|")
    for r in rows:
        peak = r.get("worker_peak_rss_mb") or r.get("peak_child_rss_mb")
        print(f"| {r['mode']} | {r['workers']} | {r['wall_seconds']:.1f} | {r['speedup_over_serial']:.2f} "
              f"| {'yes' if r['bitwise_equal_to_serial'] else 'NO'} "
              f"| {r['block_seconds_median']:.3f} / {r['block_seconds_max']:.3f} | {r['block_seconds_total']:.1f} "
              f"| {'n/a' if peak is None else f'{peak:.0f}'} | {r['coefficients']:,} |")
    print("\nper level (serial): h, blocks, coefficients, unknowns/block median (max), sites/block median (max), "
          "block s median (max)")
    for lv in rows[0]["levels"]:
        print(f"  {lv['h']:<9.6g} {lv['blocks']:5d} {lv['own_coefficients']:9,d} "
              f"{lv['unknowns_median']:8.0f} ({lv['unknowns_max']:,}) {lv['sites_median']:9.0f} ({lv['sites_max']:,}) "
              f"{lv['block_seconds_median']:.3f} ({lv['block_seconds_max']:.3f})")
    return 0 if all(r["bitwise_equal_to_serial"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
