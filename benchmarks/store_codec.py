"""Store codec: tile formats 2 and 3 on the same coefficients (benchmarks/README.md, "Store codec").

``bytes STORE...``: every tile of each store is decoded and encoded again in format 2
and in format 3 (the values checked to decode bitwise alike), and the bytes per
coefficient, the zero-order entropy of each format's value residuals and the decode
time per tile (median of ``--repeat``) are printed, one JSON line a store.
``--step S`` quantises again with a coarser step first (what a store of that step
would cost; its values are then those of step S, not the store's).

``recode SRC DST --format N``: a copy of store SRC whose tiles are encoded again in
format N (the same coefficients; manifest sizes, digests and format updated; a
signature is not copied): the same store in both formats for ``cold``.

``cold STORE...``: in a fresh process each time (median of ``--repeat``): opening the
store, its first batch of ``--points`` random points, and a one-point ``geoid-query``;
stores of either format side by side in one run, so that their ratio is what counts
on a loaded machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from geoidspline.bspline.keys import unpack_keys
from geoidspline.store import codec

RECORD = ("store_id", "store_version", "order", "h0", "tile_size")


def _entropy_bytes(values):
    """Zero-order entropy (bytes) of an integer array: what an ideal coder of independent
    symbols would need."""
    if values.size == 0:
        return 0.0
    _, counts = np.unique(values, return_counts=True)
    p = counts / counts.sum()
    return float(-(counts * np.log2(p)).sum() / 8)


def _median_ms(fn, repeat):
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def measure_bytes(store, repeat, step=None):
    tiles = sorted((Path(store) / "tiles").glob("*.gst"))
    total = {"stored": 0, 2: 0, 3: 0}
    entropy = {2: 0.0, 3: 0.0}
    decode_ms = {2: [], 3: []}
    coefficients = 0
    for path in tiles:
        data = path.read_bytes()
        header, levels = codec.decode_tile(data)
        tile_step = float(step or header["value_step_m"])
        lv = np.concatenate([np.full(k.size, level) for level, (k, _) in levels.items()])
        idx = np.concatenate([unpack_keys(k) for k, _ in levels.values()])
        values = np.concatenate([v for _, v in levels.values()])
        record = {key: header[key] for key in RECORD if key in header}
        decoded = {}
        for fmt in (2, 3):
            blob = codec.encode_tile(header["tile"], lv, idx, values, tile_step, record, tile_format=fmt)
            total[fmt] += len(blob)
            decoded[fmt] = codec.decode_tile(blob)[1]
            decode_ms[fmt].append(_median_ms(lambda b=blob: codec.decode_tile(b), repeat))
        for level, (keys, got) in decoded[3].items():
            assert np.array_equal(got.view(np.int64), decoded[2][level][1].view(np.int64)), (path, level)
            q = codec.quantise(got, tile_step)
            entropy[2] += _entropy_bytes(np.diff(q, prepend=0))
            entropy[3] += min(_entropy_bytes(codec.radial_residuals(keys, int(header.get("order", 0)), q, column))
                              for column in (False, True))  # the encoder's choice
        if step is None:
            for level, (keys, got) in levels.items():
                assert np.array_equal(got.view(np.int64), decoded[3][level][1].view(np.int64)), (path, level)
        total["stored"] += len(data)
        coefficients += values.size
    n = max(coefficients, 1)
    return {
        "store": str(store), "tiles": len(tiles), "coefficients": coefficients,
        "value_step_m": step or header["value_step_m"], "requantised": step is not None,
        "stored_bytes": total["stored"],
        "format2_bytes": total[2], "format3_bytes": total[3], "ratio_3_to_2": round(total[3] / max(total[2], 1), 4),
        "format2_bytes_per_coefficient": round(total[2] / n, 4), "format3_bytes_per_coefficient": round(total[3] / n, 4),
        "values_entropy_bytes_per_coefficient": {"format2_delta": round(entropy[2] / n, 4),
                                                 "format3_radial": round(entropy[3] / n, 4)},
        "decode_ms_per_tile_median": {"format2": round(float(np.median(decode_ms[2])), 3),
                                      "format3": round(float(np.median(decode_ms[3])), 3)},
        "decode_ms_all_tiles": {"format2": round(sum(decode_ms[2]), 1), "format3": round(sum(decode_ms[3]), 1)},
    }


COLD = """
import sys, time
start = time.perf_counter()
import numpy as np
import geoidspline
store = geoidspline.open_store(sys.argv[1])
opened = time.perf_counter()
rng = np.random.default_rng(7)
n = int(sys.argv[2])
lat, lon = np.degrees(np.arcsin(rng.uniform(-1, 1, n))), rng.uniform(-180, 180, n)
ready = time.perf_counter()
store.undulation(lat, lon)
done = time.perf_counter()
print(opened - start, done - ready + opened - start)
"""


def measure_cold(stores, points, repeat):
    rows = {str(s): {"open_s": [], "first_batch_s": [], "one_point_query_s": []} for s in stores}
    query = str(Path(sys.executable).with_name("geoid-query"))
    for _ in range(repeat):
        for store in stores:  # interleaved: the machine's load falls on both alike
            out = subprocess.run([sys.executable, "-c", COLD, str(store), str(points)], capture_output=True,
                                 text=True, check=True).stdout.split()
            rows[str(store)]["open_s"].append(float(out[0]))
            rows[str(store)]["first_batch_s"].append(float(out[1]))
            start = time.perf_counter()
            subprocess.run([query, "--store", str(store), "45.5", "7.25"], capture_output=True, check=True)
            rows[str(store)]["one_point_query_s"].append(time.perf_counter() - start)
    return [{"store": s, "points": points, **{k: round(float(np.median(v)), 3) for k, v in r.items()}}
            for s, r in rows.items()]


def recode(source, target, tile_format):
    import hashlib
    import shutil

    from geoidspline.store.format import manifest_text

    source, target = Path(source), Path(target)
    shutil.copytree(source, target, ignore=shutil.ignore_patterns("*.sig"))
    manifest = json.loads((target / "manifest.json").read_text())
    for entry in manifest["tiles"]:
        path = target / entry["file"]
        header, levels = codec.decode_tile(path.read_bytes())
        lv = np.concatenate([np.full(k.size, level) for level, (k, _) in levels.items()])
        idx = np.concatenate([unpack_keys(k) for k, _ in levels.values()])
        values = np.concatenate([v for _, v in levels.values()])
        record = {key: header[key] for key in RECORD if key in header}
        data = codec.encode_tile(header["tile"], lv, idx, values, header["value_step_m"], record,
                                 tile_format=tile_format)
        path.write_bytes(data)
        entry.update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    manifest["format_version"] = tile_format
    (target / "manifest.json").write_bytes(manifest_text(manifest))
    return [{"store": str(target), "from": str(source), "format": tile_format,
             "tile_bytes": sum(e["bytes"] for e in manifest["tiles"])}]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    b = sub.add_parser("bytes", help="bytes per coefficient and decode time per tile, formats 2 and 3")
    b.add_argument("stores", nargs="+", type=Path)
    b.add_argument("--repeat", type=int, default=5)
    b.add_argument("--step", type=float, help="quantise again with this coarser step (metres) first")
    c = sub.add_parser("cold", help="open time, first batch and one-point query in fresh processes")
    c.add_argument("stores", nargs="+", type=Path)
    c.add_argument("--points", type=int, default=1_000_000)
    c.add_argument("--repeat", type=int, default=3)
    r = sub.add_parser("recode", help="copy a store with its tiles encoded again in another format")
    r.add_argument("source", type=Path)
    r.add_argument("target", type=Path)
    r.add_argument("--format", type=int, choices=(2, 3, 4), default=4)
    args = parser.parse_args(argv)
    context = {"time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "load": os.getloadavg(),
               "cpus": os.cpu_count(), "machine": platform.processor() or platform.machine()}
    try:
        context["commit"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False,
                                           cwd=Path(__file__).parent).stdout.strip()
    except OSError:
        pass
    if args.what == "bytes":
        rows = [measure_bytes(s, args.repeat, args.step) for s in args.stores]
    elif args.what == "recode":
        rows = recode(args.source, args.target, args.format)
    else:
        rows = measure_cold(args.stores, args.points, args.repeat)
    context["load_after"] = os.getloadavg()
    for row in rows:
        print(json.dumps({**context, **row}))


if __name__ == "__main__":
    main()
