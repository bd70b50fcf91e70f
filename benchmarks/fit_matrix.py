#!/usr/bin/env python3
"""The fit matrix of issue 21: does every fit keep its promise?

    python benchmarks/fit_matrix.py ROW [ROW...] [--out-dir DIR] [--max-memory GB] [--list]

Each row runs ``geoid-fit SOURCE --tolerance T [--region ...] --store DIR --json -q``
with nothing else (the parameters chosen for the user) under ``/usr/bin/time`` (peak
RSS, wall time), then checks the store it wrote **independently of the fit**: a grid's
nodes are read with numpy straight from the file (GTX, NGA .DAC, GeographicLib .pgm:
the readers below, not geoidspline's) and compared with the store read back from disk;
a model's store is compared with the exact synthesis at 20,000 random points (seed 1;
the fit's own check points use seed 0). Recorded per row: exit status, wall time, peak
RSS, coefficients, levels chosen/used, store bytes, node max/RMS, the cell-centre
figure (grids: the store's largest distance from the interval of the grid's bilinear and
bicubic interpolants at its cell centres, from the fit's summary), and the refusal
message of a fit refused up front. One JSON line per row goes to
benchmarks/results/fit_matrix.jsonl (date, commit, load average); a markdown row is
printed. The machine is shared: run one row at a time.
"""

from __future__ import annotations

import argparse
import datetime as dt
import gzip
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import git_commit, machine_info  # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / "results" / "fit_matrix.jsonl"
DATA = Path(os.environ.get("GEOIDSPLINE_TEST_DATA", "/work/shared/data"))
PROJ_EGM96 = Path("/usr/share/proj/egm96_15.gtx")
ANDES = ("-60", "-90", "15", "-30")
EGM96 = [str(DATA / "egm96" / "egm96_to360.ascii.gz"), "--correction", str(DATA / "egm96" / "CORRCOEF.gz")]

#: name -> (source arguments, region or None, tolerance, how the truth is read)
ROWS = {
    "egm96-15 global 1.0": (["egm96-15"], None, 1.0, ("gtx", PROJ_EGM96)),
    "egm96-15 global 0.5": (["egm96-15"], None, 0.5, ("gtx", PROJ_EGM96)),
    "egm96-15 global 0.1": (["egm96-15"], None, 0.1, ("gtx", PROJ_EGM96)),
    "egm96-15 Andes 0.5": (["egm96-15"], ANDES, 0.5, ("gtx", PROJ_EGM96)),
    "egm96-15 Andes 0.1": (["egm96-15"], ANDES, 0.1, ("gtx", PROJ_EGM96)),
    "egm96-15 Andes 0.05": (["egm96-15"], ANDES, 0.05, ("gtx", PROJ_EGM96)),
    "egm96-15 Andes 0.01": (["egm96-15"], ANDES, 0.01, ("gtx", PROJ_EGM96)),
    "WW15MGH.DAC global 0.5": ([str(DATA / "egm96" / "WW15MGH.DAC")], None, 0.5,
                               ("dac", DATA / "egm96" / "WW15MGH.DAC")),
    "egm84-30.pgm global 0.5": ([str(DATA / "geographiclib" / "egm84-30.pgm")], None, 0.5,
                                ("pgm", DATA / "geographiclib" / "egm84-30.pgm")),
    "EGM96+CORRCOEF global 0.01": (EGM96, None, 0.01, ("model", EGM96)),
    "EGM96+CORRCOEF global 0.002": (EGM96, None, 0.002, ("model", EGM96)),
    "EGM96+CORRCOEF global 0.001": (EGM96, None, 0.001, ("model", EGM96)),
    "EGM2008_120 global 0.01": ([str(DATA / "egm2008" / "EGM2008_120.gfc")], None, 0.01,
                                ("model", [str(DATA / "egm2008" / "EGM2008_120.gfc")])),
    "EGM2008_120 global 0.002": ([str(DATA / "egm2008" / "EGM2008_120.gfc")], None, 0.002,
                                 ("model", [str(DATA / "egm2008" / "EGM2008_120.gfc")])),
}


# -- independent readers of the grid files (numpy only) -------------------------------


def read_gtx(path):
    """PROJ GTX: 40-byte big-endian header (lat0, lon0, dlat, dlon, rows, cols), then
    float32 rows from the south; -88.8888 is no data."""
    raw = Path(path).read_bytes()
    lat0, lon0, dlat, dlon = np.frombuffer(raw[:32], ">f8")
    rows, cols = np.frombuffer(raw[32:40], ">i4")
    values = np.frombuffer(raw[40:], ">f4", count=rows * cols).reshape(rows, cols).astype(np.float64)
    values[np.abs(values + 88.8888) < 1e-3] = np.nan
    return lat0 + dlat * np.arange(rows), lon0 + dlon * np.arange(cols), values


def read_dac(path):
    """NGA WW15MGH.DAC: 721 x 1440 int16 big-endian centimetres, 90N -> 90S, 0E eastwards."""
    values = np.fromfile(path, ">i2").reshape(721, 1440).astype(np.float64) / 100.0
    return np.linspace(90.0, -90.0, 721), np.arange(1440) * 0.25, values


def read_pgm(path):
    """GeographicLib PGM: text header with '# Offset' and '# Scale', then big-endian
    uint16 rows from 90N, columns from 0E; height = offset + scale * pixel."""
    raw = Path(path).read_bytes()
    offset = scale = None
    pos, fields = 0, []
    while len(fields) < 4:  # P5, width, height, maxval, with comment lines between
        end = raw.index(b"\n", pos)
        line = raw[pos:end].decode("ascii")
        pos = end + 1
        if line.startswith("#"):
            key, _, value = line[1:].strip().partition(" ")
            if key == "Offset":
                offset = float(value)
            elif key == "Scale":
                scale = float(value)
            continue
        fields += line.split()
    width, height = int(fields[1]), int(fields[2])
    pixels = np.frombuffer(raw[pos:], ">u2", count=width * height).reshape(height, width)
    return np.linspace(90.0, -90.0, height), np.arange(width) * 360.0 / width, offset + scale * pixels


READERS = {"gtx": read_gtx, "dac": read_dac, "pgm": read_pgm}


def node_errors(store, truth, region):
    """Store minus the file's own values at every node inside ``region`` (degrees)."""
    lat, lon, values = READERS[truth[0]](truth[1])
    south, west, north, east = region
    lat_in = (lat >= south - 1e-9) & (lat <= north + 1e-9)
    lon_w = np.mod(lon - west, 360.0)
    lon_in = lon_w <= (east - west) + 1e-9 if east - west < 360 else np.ones(lon.size, bool)
    la, lo = np.meshgrid(lat[lat_in], lon[lon_in], indexing="ij")
    v = values[np.ix_(lat_in, lon_in)]
    ok = np.isfinite(v)
    out = np.empty(ok.sum())
    la, lo, v = la[ok], lo[ok], v[ok]
    for start in range(0, v.size, 500_000):
        stop = start + 500_000
        out[start:stop] = store.undulation(la[start:stop], lo[start:stop]) - v[start:stop]
    return out


def model_errors(store, model_args, region, count=20_000, seed=1):
    from geoidspline.api import load_synthesis

    correction = model_args[2] if len(model_args) > 2 else None
    synthesis = load_synthesis(model_args[0], correction)
    rng = np.random.default_rng(seed)
    south, west, north, east = region
    lat = np.degrees(np.arcsin(rng.uniform(np.sin(np.radians(south)), np.sin(np.radians(north)), count)))
    lon = west + rng.uniform(0.0, east - west, count)
    return store.undulation(lat, lon) - synthesis.undulation(lat, lon)


def run_row(name, out_dir: Path, python_bin: Path, max_memory_gb=None) -> dict:
    source, region, tolerance, truth = ROWS[name]
    store = out_dir / name.replace(" ", "_")
    cmd = [str(python_bin.parent / "geoid-fit"), *source, "--tolerance", str(tolerance), "--store", str(store),
           "--overwrite", "--json", "-q"]
    if max_memory_gb is not None:  # a ceiling for the shared machine, not a parameter of the fit
        cmd += ["--max-memory", str(max_memory_gb)]
    if region:
        cmd[1 + len(source):1 + len(source)] = ["--region", *region]
    timer = shutil.which("time") or "/usr/bin/time"
    started = time.perf_counter()
    proc = subprocess.run([timer, "-f", "TIME %M %e %U %S", *cmd], capture_output=True, text=True)
    wall = time.perf_counter() - started
    timed = next((line.split() for line in proc.stderr.splitlines() if line.startswith("TIME ")), None)
    peak_kb = int(timed[1]) if timed else None
    row = {"row": name, "command": cmd[1:], "exit": proc.returncode, "wall_s": round(wall, 1),
           "peak_rss_gb": round(peak_kb / 1e6, 3) if peak_kb else None,
           "cpu_s": round(float(timed[3]) + float(timed[4]), 1) if timed and len(timed) > 4 else None}
    if proc.returncode not in (0, 3):
        row["refusal"] = next((line for line in proc.stderr.splitlines() if line.startswith("ERROR")),
                              proc.stderr.strip()[-300:])
        return row
    info = json.loads(proc.stdout)
    import geoidspline

    opened = geoidspline.open_store(store, lazy=False)
    bounds = tuple(info["region"])
    errors = model_errors(opened, truth[1], bounds) if truth[0] == "model" else node_errors(opened, truth, bounds)
    row.update({
        "coefficients": info["coefficients"], "levels_used": info["levels_used"],
        "levels_chosen": info["levels_chosen"], "store_bytes": info["bytes"],
        "check": "20,000 random points vs the exact synthesis" if truth[0] == "model"
        else "every node of the file in the region (numpy reader)",
        "max_m": float(np.abs(errors).max()), "rms_m": float(np.sqrt(np.mean(errors ** 2))),
        "points": int(errors.size), "fit_node_max_m": info["node_max_error_m"],
        "cell_centre_max_m": info.get("cell_centre_max_m"),
        "kept": bool(info.get("promise", {}).get("kept")) and float(np.abs(errors).max()) <= tolerance,
    })
    return row


def markdown(row) -> str:
    def g(key, fmt="{}"):
        value = row.get(key)
        return "" if value is None else fmt.format(value)

    return (f"| {row['row']} | {row['exit']} | {row['wall_s']:.0f} s | {g('peak_rss_gb', '{:.2f} GB')} | "
            f"{g('coefficients', '{:,}')} | {g('levels_used')}/{g('levels_chosen')} | {g('store_bytes', '{:,}')} | "
            f"{g('max_m', '{:.4g}')} / {g('rms_m', '{:.3g}')} m | {g('cell_centre_max_m', '{:.3g}')} | "
            f"{row.get('refusal', '')} |")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("rows", nargs="*", help="row names (see --list)")
    parser.add_argument("--list", action="store_true", help="list the rows and exit")
    parser.add_argument("--out-dir", type=Path, default=None, help="where stores go (default: a temporary dir)")
    parser.add_argument("--no-record", action="store_true", help="do not append to results/fit_matrix.jsonl")
    parser.add_argument("--max-memory", type=float, default=None, metavar="GB",
                        help="passed to geoid-fit (on a shared machine; recorded in the row's command)")
    args = parser.parse_args(argv)
    if args.list or not args.rows:
        print("\n".join(ROWS))
        return 0
    unknown = [r for r in args.rows if r not in ROWS]
    if unknown:
        parser.error(f"unknown rows {unknown}; --list shows them")
    out_dir = args.out_dir or Path(tempfile.mkdtemp(prefix="fit_matrix_"))
    out_dir.mkdir(parents=True, exist_ok=True)
    print("| source, region, T | exit | wall | peak RSS | coefficients | levels used/chosen | store bytes | "
          "max / RMS (independent) | cell centres | refusal |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in args.rows:
        load = os.getloadavg()[0]
        row = run_row(name, out_dir, Path(sys.executable), args.max_memory)
        row.update({"date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                    "commit": git_commit(REPO), "load_before": round(load, 2),
                    "load_after": round(os.getloadavg()[0], 2), "machine": machine_info()})
        if not args.no_record:
            RESULTS.parent.mkdir(parents=True, exist_ok=True)
            with RESULTS.open("a", encoding="utf-8") as fh:
                fh.write(json.dumps(row) + "\n")
        print(markdown(row), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
