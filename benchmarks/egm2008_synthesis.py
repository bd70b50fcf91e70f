"""EGM2008 at full degree: seconds and peak memory of reading the model and of
synthesising lattices from it (issue 22's foundations).

    python benchmarks/egm2008_synthesis.py read MODEL [MODEL ...]
    python benchmarks/egm2008_synthesis.py lattice MODEL --region global --spacing 0.0411 --engine exact
    python benchmarks/egm2008_synthesis.py lattice MODEL --region 40,0,45,5 --engine sht --threads 1
    python benchmarks/egm2008_synthesis.py compare MODEL --region 40,0,45,5 --spacing 0.05

MODEL: NGA text (``EGM2008_to2190_TideFree_synthetic.ascii.gz`` from
../shared/tools/make_synthetic_egm2008.py) or ICGEM ``.gfc``. Each measurement runs in a
fresh subprocess (its own peak RSS: ``ru_maxrss`` of that child) and prints one JSON
line: the figures, the date, the git commit, the machine and its load average at the
start. ``compare`` synthesises the lattice both ways and prints the largest difference.
With PYTHONPATH pointing at another checkout, the figures are that checkout's (how the
"before" rows of benchmarks/README.md were measured).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import git_commit, machine_info  # noqa: E402

REPO = Path(__file__).resolve().parent.parent

_CHILD = r"""
import json, resource, sys, time
args = json.loads(sys.argv[1])
import numpy as np
from geoidspline.sources.harmonics.models import read_model
t0, c0 = time.perf_counter(), time.process_time()
model = read_model(args["model"])
out = {"read_s": time.perf_counter() - t0, "read_cpu_s": time.process_time() - c0, "degree": model.max_degree}
out["read_peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
if args["task"] in ("lattice", "compare"):
    from geoidspline.sources.harmonics import GeoidSynthesis, default_preset
    from geoidspline.sphere.region import GLOBAL, Region
    region = GLOBAL if args["region"] == "global" else Region(*args["region"])
    syn = GeoidSynthesis(model, preset=default_preset(model))
    del model
    engines = [args["engine"]] if args["task"] == "lattice" else ["exact", "sht"]
    values = {}
    for engine in engines:
        syn.lattice_engine = engine
        syn.lattice_threads = args["threads"]
        t0, c0 = time.perf_counter(), time.process_time()
        sample = syn.nodes(region, args["spacing"])
        out[f"{engine}_s"] = time.perf_counter() - t0
        out[f"{engine}_cpu_s"] = time.process_time() - c0
        values[engine] = sample.undulation
        out["nodes"] = int(sample.undulation.size)
        out["rows"] = int(sample.latitude.size)
        out["spacing_deg"] = float(sample.latitude[1] - sample.latitude[0])
    out["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if len(values) == 2:
        out["max_abs_diff_m"] = float(np.max(np.abs(values["exact"] - values["sht"])))
print(json.dumps(out))
"""


def run(task: dict) -> dict:
    load = os.getloadavg()
    done = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(task)], capture_output=True, text=True,
                          env=dict(os.environ, OMP_NUM_THREADS=str(task.get("threads", 1))))
    if done.returncode:
        sys.stderr.write(done.stderr)
        raise SystemExit(done.returncode)
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    return {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "commit": git_commit(REPO), "load_1min": load[0], "machine": machine_info(), "task": task,
            **figures}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("task", choices=("read", "lattice", "compare"))
    parser.add_argument("models", nargs="+")
    parser.add_argument("--region", default="global", help="'global' or S,W,N,E in degrees")
    parser.add_argument("--spacing", type=float, default=None, help="lattice spacing (degrees); default 90/N")
    parser.add_argument("--engine", choices=("exact", "sht"), default="sht")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    region = args.region if args.region == "global" else [float(v) for v in args.region.split(",")]
    for model in args.models:
        task = {"task": args.task, "model": str(Path(model).resolve()), "region": region, "spacing": args.spacing,
                "engine": args.engine, "threads": args.threads}
        print(json.dumps(run(task)), flush=True)


if __name__ == "__main__":
    main()
