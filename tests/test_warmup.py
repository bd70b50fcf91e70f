"""The install-time warm-up (``geoid-warmup``): it compiles every numba kernel for
exactly the argument types real fits and queries pass, so that they load from numba's
cache instead of compiling."""

from __future__ import annotations

import json
import subprocess
import sys

from geoidspline import warmup

# In a fresh process (so that only the warm-up's signatures are loaded): the warm-up,
# then a CLI fit with an overlay level and large CLI and API queries; prints the kernel
# signatures the fit and queries added, and what the warm-up reported.
SCRIPT = r"""
import json, sys
import numpy as np
from click.testing import CliRunner
import geoidspline
from geoidspline import warmup
from geoidspline.cli.fit import main as fit_main
from geoidspline.cli.query import main as query_main

gtx, store = sys.argv[1], sys.argv[2]
report = warmup.warm_up()
def signatures():
    return {name: set(map(str, d.signatures)) for name, d in warmup.kernel_dispatchers().items()}
before = signatures()
fit = CliRunner().invoke(fit_main, [gtx, "--store", store, "--region", "10", "20", "30", "40", "--h0", "0.2",
                                    "--max-level", "1", "--tolerance", "0.05", "-q"])
assert fit.exit_code in (0, 3), fit.output
rng = np.random.default_rng(5)
lat = rng.uniform(10, 30, 5000)
lon = rng.uniform(20, 40, 5000)
rows = "lat,lon\n" + "".join(f"{a:.5f},{b:.5f}\n" for a, b in zip(lat, lon))
query = CliRunner().invoke(query_main, ["--store", store, "--input", "-", "--deflection"], input=rows)
assert query.exit_code == 0, query.output
assert len(query.stdout.splitlines()) == 5001
assert np.all(np.isfinite(geoidspline.open_store(store).undulation(lat, lon)))
# a store whose source has a no-data hole: its coverage carries a mask
from geoidspline.sources.formats import read_grid, write_gtx
from geoidspline.sources.grid import GeoidGrid
grid = read_grid(gtx)
values = grid.values.copy()
values[(grid.latitude[:, None] >= 18) & (grid.latitude[:, None] <= 22) & (grid.longitude[None, :] >= 28)
       & (grid.longitude[None, :] <= 32)] = np.nan
holed = write_gtx(store + "-holed.gtx", GeoidGrid(grid.latitude, grid.longitude, values, grid.provenance))
fit = CliRunner().invoke(fit_main, [str(holed), "--store", store + "-holed", "--region", "10", "20", "30", "40",
                                    "--h0", "0.2", "--max-level", "1", "--tolerance", "0.05", "-q"])
assert fit.exit_code in (0, 3), fit.output
query = CliRunner().invoke(query_main, ["--store", store + "-holed", "--input", "-", "--outside", "nan"], input=rows)
assert query.exit_code == 0, query.output
answers = geoidspline.open_store(store + "-holed").undulation(lat, lon)
assert np.isnan(answers).any() and np.isfinite(answers).any()
after = signatures()
added = {name: sorted(after[name] - before.get(name, set())) for name in after if after[name] - before.get(name, set())}
print(json.dumps({"added": added, "kernels": sorted(report["kernels"])}))
"""


def test_warmup_covers_the_kernel_signatures_of_a_cli_fit_and_large_queries(synthetic_gtx, tmp_path):
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(synthetic_gtx), str(tmp_path / "store")],
                          capture_output=True, text=True, timeout=1200, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    result = json.loads(proc.stdout.splitlines()[-1])
    assert {"geoidspline._kernels.fitting.normal_equations", "geoidspline._kernels.interpolation.filter_axis",
            "geoidspline._kernels.legendre.row_sums", "geoidspline._kernels.coverage.cells_have_data"} \
        <= set(result["kernels"])
    # a kernel compiled for an argument type the warm-up did not use gains a signature
    assert result["added"] == {}


def test_check_fails_when_a_kernel_had_to_be_compiled(monkeypatch, capsys):
    def report(compiled):
        return {"seconds": 1.0, "cache": "/cache", "kernels": {
            "geoidspline._kernels.query.undulation_latlon": {"signatures": 1, "loaded": 1 - compiled, "compiled": compiled}}}

    monkeypatch.setattr(warmup, "warm_up", lambda: report(1))
    assert warmup.main(["--check", "-q"]) == 1
    assert "ERROR: kernels had to be compiled" in capsys.readouterr().err
    assert warmup.main(["-q"]) == 0  # without --check, compiling is what the warm-up is for
    monkeypatch.setattr(warmup, "warm_up", lambda: report(0))
    assert warmup.main(["--check", "-q"]) == 0
    assert "0 compiled, 1 loaded from the cache" in capsys.readouterr().out
