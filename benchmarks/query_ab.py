#!/usr/bin/env python3
"""Two builds of the query kernel against each other, on this noisy shared machine.

    python benchmarks/query_ab.py --a main --b . --store STORE [--store STORE ...]
        [--points 1000000] [--repeat 9] [--threads 1] [--batch global --batch regional]
        [--a-cflags "-DLL_AHEAD=12"] [--b-cflags ...] [--json OUT]

``--a``/``--b``: a git revision of this repository (its ``geoidspline/_kernels/src`` and
``pyproject.toml`` through ``git archive``) or a checkout's directory (its files as they
are, edits included). Each (its ``query.c`` and ``gs_parallel.c``) is compiled into a library of its
own as ``pip install`` compiles the package's (setuptools' ``build_ext`` with the
``pyproject.toml`` of that source: Python's flags plus the extension's
``extra-compile-args``), plus the side's ``--X-cflags``.

Both libraries are loaded in this one process and called alternately (A, B, A, B, ...)
on the same 1,000,000 points with the same query tables (the index the installed
package builds from the store; its ``Spline`` record must be laid out as each library
expects: fields added at the end are fine for the older one; a library from before the
quantised tables, without ``gs_quantise_table``, is given the same spline's float64
tables, ``BrickIndex(levels, order)``, and the store's values stay bitwise the same).
Timed is
``gs_undulation_latlon`` alone: CPU time of the calling thread with ``--threads 1`` (the
kernel then runs on it; CPU time moves much less with other processes' load than wall
time), wall time otherwise. Medians and min..max of ``--repeat`` calls each, B / A, and
whether the two libraries' values are bitwise equal (they must be when B is meant to
change speed only).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import datetime as dt
import io
import json
import os
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
import tomllib
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import numpy as np  # noqa: E402
from _common import git_commit, machine_info  # noqa: E402
from query_benchmark import EUROPE, random_points  # noqa: E402
from query_speed import SEED  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
MAX_LONGITUDE = 1e6  # degrees: geoidspline.sphere.region.MAX_ABS_POINT_LONGITUDE_DEG
SOURCE_DIR = "geoidspline/_kernels/src"


def fetch_sources(spec: str, into: Path) -> str:
    """Copy pyproject.toml and the kernel sources of spec (a directory or a git revision)
    into ``into``; returns a label for the report."""
    path = Path(spec)
    if path.is_dir():
        shutil.copytree(path / SOURCE_DIR, into / SOURCE_DIR)
        shutil.copy(path / "pyproject.toml", into / "pyproject.toml")
        return f"{path.resolve()} (working tree, {git_commit(path.resolve())})"
    sha = subprocess.run(["git", "rev-parse", spec], cwd=REPO, capture_output=True, text=True,
                         check=True).stdout.strip()
    archive = subprocess.run(["git", "archive", sha, SOURCE_DIR, "pyproject.toml"], cwd=REPO, capture_output=True,
                             check=True).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(into, filter="data")
    return f"{spec} ({sha[:10]})"


def build_library(root: Path, extra_cflags: list[str]) -> Path:
    """The kernel library of the sources under root, built as pip builds it."""
    from setuptools import Distribution, Extension
    from setuptools.command.build_ext import build_ext

    config = tomllib.loads((root / "pyproject.toml").read_text())
    (ext,) = config["tool"]["setuptools"]["ext-modules"]
    # the query kernel and the thread fan-out it calls: the other kernels are not timed
    sources = [s for s in ext["sources"] if Path(s).name in ("gs_parallel.c", "query.c")]
    extension = Extension(ext["name"], sources=sources, depends=ext.get("depends", []),
                          extra_compile_args=ext.get("extra-compile-args", []) + extra_cflags,
                          extra_link_args=ext.get("extra-link-args", []))
    dist = Distribution({"name": "ab", "ext_modules": [extension]})
    cmd = build_ext(dist)
    cmd.build_lib = str(root / "lib")
    cmd.build_temp = str(root / "tmp")
    cmd.ensure_finalized()
    here = os.getcwd()
    os.chdir(root)  # the sources are relative to the tree's root
    try:
        with open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet):  # setuptools' command lines
            cmd.run()
    finally:
        os.chdir(here)
    (built,) = (root / "lib").rglob("_libkernels*.so")
    return built


def kernel(library: Path):
    """(gs_undulation_latlon, whether the library reads quantised tables, the bytes of the
    column offsets it reads with them: 2, int16, from 2026-12-06 on; 4 before)"""
    lib = ctypes.CDLL(str(library))
    f = lib.gs_undulation_latlon
    # the last arguments, max_abs_longitude (degrees, branch q23c) and in_order (branch
    # q23q), are new in 2026-12; an older library ignores them (extra register arguments)
    f.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64,
                  ctypes.c_void_p, ctypes.c_int64, ctypes.c_double, ctypes.c_int64]
    f.restype = ctypes.c_int64
    offs_width = lib.gs_quantised_offs_width() if hasattr(lib, "gs_quantised_offs_width") else 4
    return f, hasattr(lib, "gs_quantise_table"), offs_width


def int32_offsets(index):
    """The quantised index's record with its column offsets as int32 (the libraries before
    2026-12-06 read them so); an index with int32 bricks in int16 slots (which they do not
    read) is built again as they had it (``MIXED_WIDTHS`` off) from its levels."""
    from geoidspline._kernels.query import QBASE_WIDE
    from geoidspline.bspline import index as index_module

    if (index.qbase == QBASE_WIDE).any():
        mixed, index_module.MIXED_WIDTHS = index_module.MIXED_WIDTHS, False
        try:
            index = index_module.BrickIndex(index.levels, index.order, value_step=index.value_step, quantise=True)
        finally:
            index_module.MIXED_WIDTHS = mixed
    record = type(index.spline).from_buffer_copy(index.spline)
    own = index.own_offs.astype(np.int32)
    fold = own if index.fold_offs is index.own_offs else index.fold_offs.astype(np.int32)
    record._offs = (own, fold)  # alive with the record
    record.own_offs, record.fold_offs = own.ctypes.data, fold.ctypes.data
    record._index = index
    return record


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--a", required=True, help="git revision or checkout directory (the reference)")
    parser.add_argument("--b", required=True, help="git revision or checkout directory (the change)")
    parser.add_argument("--a-cflags", default="", help="extra compiler flags for A (e.g. -DLL_AHEAD=12)")
    parser.add_argument("--b-cflags", default="", help="extra compiler flags for B")
    parser.add_argument("--store", action="append", required=True, type=Path)
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--batch", action="append", choices=("global", "regional"))
    parser.add_argument("--repeat", type=int, default=9)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)

    import geoidspline

    work = Path(tempfile.mkdtemp(prefix="query_ab_"))
    from geoidspline.bspline.index import BrickIndex

    try:
        from geoidspline.bspline.index import IN_ORDER_MAX_BYTES
    except ImportError:  # an installed package from before branch q23q: always sorted
        IN_ORDER_MAX_BYTES = -1

    libs, labels, quantised, offs_width = {}, {}, {}, {}
    try:
        for side, spec, flags in (("A", args.a, args.a_cflags), ("B", args.b, args.b_cflags)):
            root = work / side
            labels[side] = fetch_sources(spec, root) + (f" {flags}" if flags else "")
            t0 = time.perf_counter()
            libs[side], quantised[side], offs_width[side] = kernel(build_library(root, flags.split()))
            print(f"{side}: {labels[side]}, built in {time.perf_counter() - t0:.1f} s")
        batches = {"global": random_points(args.points),
                   "regional": random_points(args.points, SEED + 1, EUROPE)}  # query_benchmark.py's batches
        report = {"date": dt.datetime.now(dt.timezone.utc).replace(microsecond=0).isoformat(),
                  "machine": machine_info(), "a": labels["A"], "b": labels["B"], "threads": args.threads,
                  "points": args.points, "repeat": args.repeat, "stores": []}
        print(f"{report['date']}, {args.points:,} points, {args.threads} thread(s), "
              f"{'CPU' if args.threads == 1 else 'wall'} time of gs_undulation_latlon, medians of {args.repeat}")
        print("| store | batch | A ns/pt (min..max) | B ns/pt (min..max) | B / A | bitwise equal | load |")
        print("|---|---|---:|---:|---:|---|---|")
        clock = time.thread_time if args.threads == 1 else time.perf_counter
        for store in args.store:
            full = geoidspline.open_store(store).spline.full
            index = full.index
            float_index = BrickIndex(full.levels, full.order) if index.values.size == 0 else index
            records = {side: (index if quantised[side] else float_index).spline for side in libs}
            for side in libs:
                if index.qvalues is not None and quantised[side] and offs_width[side] == 4:
                    records[side] = int32_offsets(index)  # a library from before the int16 offsets
            splines = {side: ctypes.addressof(record) for side, record in records.items()}
            in_order = int(IN_ORDER_MAX_BYTES >= 0 and index.hot_bytes <= IN_ORDER_MAX_BYTES)  # as BrickIndex does
            for name in args.batch or ["global"]:
                lat, lon = (np.ascontiguousarray(a) for a in batches[name])
                m = lat.size
                nblocks = max(1, min(4 * args.threads, m >> 15))  # as BrickIndex.undulation_latlon
                outs = {side: np.empty(m) for side in libs}
                samples = {side: [] for side in libs}
                for side, f in libs.items():  # untimed first calls: page faults, caches
                    f(splines[side], lat.ctypes.data, lon.ctypes.data, m, nblocks, outs[side].ctypes.data,
                      args.threads, MAX_LONGITUDE, in_order)
                load = os.getloadavg()[0]
                for _ in range(args.repeat):
                    for side, f in libs.items():
                        t0 = clock()
                        f(splines[side], lat.ctypes.data, lon.ctypes.data, m, nblocks, outs[side].ctypes.data,
                          args.threads, MAX_LONGITUDE, in_order)
                        samples[side].append((clock() - t0) / m * 1e9)
                load = (load, os.getloadavg()[0])
                med = {side: statistics.median(s) for side, s in samples.items()}
                equal = bool(np.array_equal(outs["A"], outs["B"], equal_nan=True))
                row = {"store": str(store), "batch": name, "ns_per_point": samples, "median": med,
                       "b_over_a": med["B"] / med["A"], "bitwise_equal": equal, "load": load,
                       "max_abs_diff": float(np.nanmax(np.abs(outs["A"] - outs["B"])))}
                report["stores"].append(row)
                same = "yes" if equal else f"NO, max {row['max_abs_diff']:.3g}"
                print(f"| {store.name} | {name} | {med['A']:.1f} ({min(samples['A']):.1f}..{max(samples['A']):.1f}) "
                      f"| {med['B']:.1f} ({min(samples['B']):.1f}..{max(samples['B']):.1f}) | "
                      f"{med['B'] / med['A']:.3f} | {same} | {load[0]:.1f}..{load[1]:.1f} |")
        if args.json:
            args.json.write_text(json.dumps(report, indent=1))
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
