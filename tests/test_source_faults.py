"""Every source is true or refused (issue 10, the sources part).

Each test reproduces a case seen against the earlier readers (a plausible wrong number,
a traceback, a crash) and checks it is now either the right value or one InputFileError
naming the file and the rule broken:

- no data is never data (GTX -88.8888, netCDF fill values, valid_range, NaN);
- values beyond the geoid's physical range are refused, with the unit mistake named;
- a model reaches its declared degree, its coefficients are physical, and its correction
  matches its degree; absurd declared sizes are refused before anything is allocated;
- a catalogue file must be one of the catalogue's known copies;
- the format is read from the content, not the name;
- faults (broken gzip, out of memory, truncation, directories, FIFOs) are messages.

The property-based tests at the end fuzz every reader with random bytes and with random
mutations of small valid files: the only exception ever raised is InputFileError.
"""

from __future__ import annotations

import gzip
import hashlib
import os
import signal
import subprocess
import sys
import textwrap
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from reference_data import need, reference_file

from geoidspline.errors import GeoidSplineError, InputFileError
from geoidspline.fitting.check_points import check_points
from geoidspline.fitting.sites import DataNodes
from geoidspline.geodesy.limits import MAX_ABS_COEFFICIENT, MAX_ABS_UNDULATION_M, MAX_MODEL_DEGREE
from geoidspline.sources.base import Provenance
from geoidspline.sources.formats import read_grid, write_netcdf
from geoidspline.sources.geotiff import write_geotiff
from geoidspline.sources.grid import GeoidGrid
from geoidspline.sources.gsi import write_gsi
from geoidspline.sources.isg import write_isg
from geoidspline.sources.harmonics.models import (
    CorrectionModel,
    HarmonicModel,
    read_icgem,
    read_model,
    read_nga,
    read_nga_correction,
)
from geoidspline.sources.harmonics.synthesis import GeoidSynthesis
from geoidspline.sources.resolve import is_model_file, load_synthesis, open_source, resolve_source
from geoidspline.sphere.region import Region

PROJ_GTX = Path("/usr/share/proj/egm96_15.gtx")
EGM96 = reference_file("egm96", "egm96_to360.ascii.gz")
CORRCOEF = reference_file("egm96", "CORRCOEF.gz")
PGM = reference_file("geographiclib", "egm84-30.pgm")

LAT = np.arange(-10.0, 10.01, 0.5)
LON = np.arange(0.0, 20.01, 0.5)


def field(lat, lon):
    """A smooth field of about 20-30 m (metres)."""
    return 25.0 + 4.0 * np.sin(np.radians(4 * lat))[..., None] * np.cos(np.radians(3 * lon))


def gtx_bytes(values, lat0=LAT[0], lon0=LON[0], step=0.5, rows=None, cols=None) -> bytes:
    """A GTX file's bytes, values written as they are (no NaN translation)."""
    values = np.asarray(values, dtype=">f4")
    rows = values.shape[0] if rows is None else rows
    cols = values.shape[1] if cols is None else cols
    header = np.array([lat0, lon0, step, step], ">f8").tobytes() + np.array([rows, cols], ">i4").tobytes()
    return header + values.tobytes()


def write(path: Path, payload) -> Path:
    path.write_bytes(payload if isinstance(payload, bytes) else payload.encode())
    return path


def refused(match, func, *args, **kwargs) -> str:
    """The message of the InputFileError ``func`` raises; it must match ``match``."""
    with pytest.raises(InputFileError, match=match) as info:
        func(*args, **kwargs)
    return str(info.value)


def small_model(nmax=6, seed=3, name="TESTMODEL"):
    """A model with physical coefficients (Kaula-like decay, EGM96's C̄20)."""
    rng = np.random.default_rng(seed)
    C = np.zeros((nmax + 1, nmax + 1))
    S = np.zeros((nmax + 1, nmax + 1))
    for n in range(2, nmax + 1):
        C[n, : n + 1] = rng.normal(size=n + 1) * 1e-6 / n**2
        S[n, 1 : n + 1] = rng.normal(size=n) * 1e-6 / n**2
    C[2, 0] = -0.484165371736e-3
    return HarmonicModel(name=name, gm=3.986004415e14, radius=6378136.3, max_degree=nmax, tide_system="tide_free",
                         C=C, S=S)


def gfc_text(model: HarmonicModel, max_degree=None, last_degree=None, header_extra="") -> str:
    declared = model.max_degree if max_degree is None else max_degree
    last = model.max_degree if last_degree is None else last_degree
    lines = [
        "begin_of_head",
        "modelname TESTMODEL",
        "earth_gravity_constant 3.986004415e14",
        "radius 6378136.3",
        f"max_degree {declared}",
        "norm fully_normalized",
        "tide_system tide_free",
        "errors no",
        header_extra,
        "end_of_head",
    ]
    for n in range(2, last + 1):
        for m in range(n + 1):
            lines.append(f"gfc {n} {m} {model.C[n, m]:.15e} {model.S[n, m]:.15e}")
    return "\n".join(lines) + "\n"


def nga_text(model: HarmonicModel, last_degree=None) -> str:
    last = model.max_degree if last_degree is None else last_degree
    return "".join(
        f"{n:4d}{m:4d} {model.C[n, m]:.12E} {model.S[n, m]:.12E} 1.0E-10 1.0E-10\n"
        for n in range(2, last + 1) for m in range(n + 1)
    )


def corr_text(nmax: int, scale=1.0) -> str:
    return "".join(f"{n} {m} {scale * 0.1 / (n + 1):.6e} {0.0 if m == 0 else -0.05 * scale:.6e}\n"
                   for n in range(nmax + 1) for m in range(n + 1))


@pytest.fixture
def hole_gtx(tmp_path):
    """A GTX whose 2°x2° block (lat 0..1.5, lon 10..11.5) holds PROJ's no-data value."""
    values = field(LAT, LON)
    values[20:24, 20:24] = -88.8888
    return write(tmp_path / "hole.gtx", gtx_bytes(values))


# ------------------------------------------------------------------ 1. no data is never data
@pytest.mark.parametrize("marker", [-88.8888, -88.888, -88.88888, -88.8888801574707])
def test_gtx_nodata_patterns_are_holes(tmp_path, marker):
    """PROJ's GTX no-data is float32 -88.8888 (GTXVerticalShiftGrid::isNodata); files
    printed with other precisions use -88.888 or -88.88888. Seen: -88.888 was read as a
    value (the old rule was |v + 88.8888| < 1e-4)."""
    values = field(LAT, LON)
    values[5:7, 8:11] = marker
    grid = read_grid(write(tmp_path / "m.gtx", gtx_bytes(values)))
    assert np.isnan(grid.values).sum() == 6 and np.isnan(grid.values[5:7, 8:11]).all()
    # a genuine value near the marker stays a value
    values[5:7, 8:11] = -88.8
    assert not np.isnan(read_grid(write(tmp_path / "m.gtx", gtx_bytes(values))).values).any()


def test_nodata_nodes_are_never_fitted_nor_checked(hole_gtx):
    """Seen: a GTX with a -88.8888 block fitted with exit 0 and the hole answered 26.996 m.
    The reader makes the block NaN; the fit's data nodes and its check points skip it
    (what a store answers inside the hole is the store's coverage, issue 10)."""
    grid = read_grid(hole_gtx)
    region = Region(-10.0, 0.0, 10.0, 20.0)
    sample = grid.nodes(region)
    assert np.isnan(sample.undulation).sum() == 16
    nodes = DataNodes.from_sample(sample, region)
    assert nodes.values.size == LAT.size * LON.size - 16 and np.isfinite(nodes.values).all()
    in_hole = (nodes.latitude >= 0.0) & (nodes.latitude <= 1.5) & (nodes.longitude >= 10.0) & (nodes.longitude <= 11.5)
    assert not in_hole.any()
    checks = check_points(grid, region)
    near = (checks.latitude > -1.0) & (checks.latitude < 2.5) & (checks.longitude > 9.0) & (checks.longitude < 12.5)
    assert not near.any() and np.isfinite(checks.truth).all()
    # a grid that must be complete (a catalogue grid) still refuses the hole
    refused(r"hole\.gtx: 16 of 1681 nodes are NaN \(no data\) in a grid that must be complete", read_grid, hole_gtx,
            complete=True)


def _nc_with(path, raw, dtype, attrs, encoding_extra=None):
    """A netCDF-4 file whose variable N stores ``raw`` as ``dtype`` with ``attrs``, unscaled."""
    import netCDF4

    with netCDF4.Dataset(path, "w") as ds:
        ds.createDimension("lat", LAT.size)
        ds.createDimension("lon", LON.size)
        lat = ds.createVariable("lat", "f8", ("lat",))
        lat[:] = LAT
        lat.units = "degrees_north"
        lon = ds.createVariable("lon", "f8", ("lon",))
        lon[:] = LON
        lon.units = "degrees_east"
        fill = attrs.pop("_FillValue", None)
        var = ds.createVariable("N", dtype, ("lat", "lon"), fill_value=fill)
        var.set_auto_maskandscale(False)
        for key, value in attrs.items():
            setattr(var, key, value)
        if raw is not None:
            var[:] = raw
    return path


@pytest.mark.parametrize("case", ["fill", "missing_value", "nan", "valid_range", "valid_min", "valid_max",
                                  "default_fill", "packed_valid_range"])
def test_netcdf_nodata_becomes_nan(tmp_path, case):
    """netCDF no-data: _FillValue, missing_value, NaN, outside valid_range/valid_min/
    valid_max (in stored, packed values), and the library's default fill where nothing
    was written. Seen: valid_range and the default fill (9.97e36) were read as values."""
    metres = field(LAT, LON)
    raw = metres.astype("f4")
    attrs = {"units": "m"}
    holes = np.zeros(raw.shape, bool)
    holes[3:5, 7:9] = True
    dtype = "f4"
    if case == "fill":
        attrs["_FillValue"] = np.float32(-9999.0)
        raw[holes] = -9999.0
    elif case == "missing_value":
        attrs["missing_value"] = np.float32(-32767.0)
        raw[holes] = -32767.0
    elif case == "nan":
        raw[holes] = np.nan
    elif case == "valid_range":
        attrs["valid_range"] = np.array([-120.0, 120.0], "f4")
        raw[holes] = 500.0
    elif case == "valid_min":
        attrs["valid_min"] = np.float32(-120.0)
        raw[holes] = -500.0
    elif case == "valid_max":
        attrs["valid_max"] = np.float32(120.0)
        raw[holes] = 9.0e20
    elif case == "default_fill":
        raw = np.ma.masked_array(raw, mask=holes)  # masked nodes are never written
    elif case == "packed_valid_range":
        dtype = "i2"
        attrs.update(scale_factor=0.01, add_offset=0.0, valid_range=np.array([-12000, 12000], "i2"))
        raw = np.round(metres * 100).astype("i2")
        raw[holes] = 20000  # 200 m once unpacked: outside the packed valid range
    if case == "default_fill":
        import netCDF4

        path = _nc_with(tmp_path / "n.nc", None, dtype, attrs)
        with netCDF4.Dataset(path, "a") as ds:
            ds["N"].set_auto_maskandscale(False)
            for i in range(LAT.size):
                row = raw[i]
                for j in np.flatnonzero(~row.mask):
                    ds["N"][i, j] = row.data[j]
    else:
        path = _nc_with(tmp_path / "n.nc", raw, dtype, attrs)
    grid = read_grid(path)
    np.testing.assert_array_equal(np.isnan(grid.values), holes)
    expected = np.round(metres * 100) / 100 if dtype == "i2" else metres.astype("f4")
    np.testing.assert_allclose(grid.values[~holes], expected[~holes], rtol=1e-6)


# ------------------------------------------------------------------ 2. plausibility
@pytest.mark.parametrize(
    "scale, hint",
    [(100.0, r"the values look like centimetres \(2\d\d\d\.?\d* cm is 2\d\.\d+ m\)"),
     (1000.0, r"the values look like millimetres \(2\d\d\d\d\.?\d* mm is 2\d\.\d+ m\)")],
)
def test_unit_mistakes_are_named(tmp_path, scale, hint):
    """Seen: centimetre values labelled metres (N ~ 2600 m) fitted with exit 0."""
    values = field(LAT, LON) * scale
    message = refused(hint, read_grid, write(tmp_path / "cm.gtx", gtx_bytes(values)))
    assert "1681 of 1681 nodes lie beyond the physical range of geoid undulations, ±150 m" in message and "cm.gtx: " in message
    # the same through netCDF, PGM and the generic writer path
    nc = tmp_path / "cm.nc"
    xr.Dataset({"N": (("lat", "lon"), values, {"units": "m"})},
               coords={"lat": ("lat", LAT, {"units": "degrees_north"}),
                       "lon": ("lon", LON, {"units": "degrees_east"})}).to_netcdf(nc)
    refused(hint, read_grid, nc)


@pytest.mark.parametrize("spike", [3.0e38, 5000.0, -160.0])
def test_isolated_spikes_name_their_node(tmp_path, spike):
    """Seen: a 3e38 spike (float32's largest number, a common fill) and +5000 m values
    were fitted, the advice printed being 'raise --max-level'."""
    values = field(LAT, LON)
    values[7, 33] = spike
    message = refused(r"1 of 1681 nodes lie beyond the physical range of geoid undulations, ±150 m", read_grid,
                      write(tmp_path / "spike.gtx", gtx_bytes(values)))
    assert f"the largest, {spike:.6g} m, is at latitude {LAT[7]:.6g}, longitude {LON[33]:.6g}" in message
    assert "no-data marker the file does not declare" in message and "max-level" not in message


def test_pgm_and_dac_values_are_checked_too(tmp_path):
    """Formats without a no-data value: a PGM whose Scale makes values absurd, a DAC whose
    int16 centimetres were damaged beyond ±150 m."""
    width, height = 8, 5
    pixels = np.full((height, width), 60000, dtype=">u2")
    header = f"P5\n# Offset -108\n# Scale 0.03\n{width} {height}\n65535\n".encode()
    refused(r"beyond the physical range.*the values look like centimetres", read_grid,
            write(tmp_path / "s.pgm", header + pixels.tobytes()))
    cm = np.full((721, 1440), 2000, dtype=">i2")
    cm[100, 200] = 30000  # 300 m
    message = refused(r"1 of 1038240 nodes lie beyond the physical range", read_grid, write(tmp_path / "flip.dac", cm.tobytes()))
    assert "the largest, 300 m, is at latitude 65, longitude 50" in message


def test_absurd_coefficients_are_refused(tmp_path):
    """Seen: a coefficient of 1e300 gave an answer of 150 digits."""
    model = small_model()
    text = nga_text(model).splitlines()
    text[7] = text[7].replace(text[7].split()[2], "1e300")  # n=4 m=0
    message = refused(r"line 8: C̄ of n=4 m=0 is 1e\+300, beyond 2\.35e-05, the physical bound", read_nga,
                      write(tmp_path / "m.ascii", "\n".join(text) + "\n"), name="X", gm=3.986004415e14, radius=6378136.3)
    assert "m.ascii: " in message
    gfc = gfc_text(model).replace(f"gfc 2 0 {model.C[2, 0]:.15e}", "gfc 2 0 -5.0e-01")
    refused(r"C̄ of n=2 m=0 is -0\.5, beyond 0\.001", read_icgem, write(tmp_path / "m.gfc", gfc))
    gfc = gfc_text(model).replace(f"{model.S[4, 4]:.15e}", "3.0e-4")
    refused(r"S̄ of n=4 m=4 is 0\.0003, beyond 2\.35e-05", read_icgem, write(tmp_path / "m.gfc", gfc))
    assert MAX_ABS_COEFFICIENT == pytest.approx(MAX_ABS_UNDULATION_M / 6378137.0)
    # a correction coefficient beyond what any part of N can be
    refused(r"line 1: the coefficient of n=0 m=0 is beyond 15000 cm", read_nga_correction,
            write(tmp_path / "CORRCOEF", corr_text(4).replace("1.000000e-01", "2.0e+06", 1)))


def test_a_synthesis_beyond_the_geoid_range_is_refused():
    """A model whose coefficients pass one by one can still sum to no geoid: every
    synthesised N (points and lattices) is checked."""
    model = small_model()
    C = np.array(model.C)
    C[3:, :] = np.where(np.tril(np.ones_like(C[3:, :]), 3) > 0, 2.0e-5, 0.0)[: C.shape[0] - 3]
    bad = HarmonicModel(name="dense", gm=model.gm, radius=model.radius, max_degree=model.max_degree,
                        tide_system=None, C=C, S=model.S, source_path="dense.gfc")
    syn = GeoidSynthesis(bad, preset="generic")
    message = refused(r"dense\.gfc: the synthesis gives N = -?\d+\.?\d* m at latitude", syn.undulation, 45.0, 10.0)
    assert "beyond ±150 m" in message
    refused(r"the synthesis gives N", syn.nodes, Region(-10, 0, 10, 20), 2.0)
    refused(r"the synthesis gives zeta", syn.height_anomaly, [45.0, 0.0], [10.0, 0.0])
    good = GeoidSynthesis(model, preset="generic")
    assert abs(good.undulation(45.0, 10.0)) < MAX_ABS_UNDULATION_M


# ------------------------------------------------------------------ 3. models: degrees and sizes
def test_a_file_named_to360_must_reach_360(tmp_path):
    """Seen: egm96_to360 that ends at degree 60 gave 25.01 m instead of 26.91 m, silently."""
    model = small_model(nmax=8, name="EGM96")
    path = write(tmp_path / "egm96_to360.ascii", nga_text(model))
    message = refused(r"egm96_to360\.ascii: the file name declares degree 360 but the model stops at degree 8: "
                      r"a truncated copy.*pass max_degree=8", read_model, path)
    assert "truncated" in message
    assert read_nga(path, max_degree=8, check_tide_system=False).max_degree == 8  # truncated on purpose
    gz = write(tmp_path / "egm96_to360.ascii.gz", gzip.compress(nga_text(model).encode()))
    refused(r"declares degree 360", read_model, gz)
    refused(r"declares degree 360", load_synthesis, gz)
    # an excerpt that says so in its name is read at its own degree
    excerpt = write(tmp_path / "EGM2008_to2190_TideFree_first30.ascii", nga_text(small_model(nmax=4, name="EGM2008")))
    assert read_nga(excerpt, check_tide_system=False).max_degree == 4
    # a correction named for its degree too
    refused(r"declares degree 2160 but the correction stops at degree 3", read_nga_correction,
            write(tmp_path / "Zeta-to-N_to2160_egm2008", corr_text(3)))


def test_icgem_header_degree_beyond_its_lines(tmp_path):
    """An ICGEM max_degree larger than the lines found: refused, saying where it stops."""
    model = small_model(nmax=8)
    message = refused(r"coefficient\(s\) missing for 2 <= n <= 8 .*the file stops at degree 5, below the declared 8",
                      read_icgem, write(tmp_path / "cut.gfc", gfc_text(model, last_degree=5)))
    assert "cut.gfc: " in message


@pytest.mark.parametrize("declared", [100_000, 2**31 + 5, 10**30])
def test_absurd_declared_degree_is_refused_before_allocating(tmp_path, declared):
    """Seen: max_degree 100000 asked numpy for 74.5 GiB (MemoryError)."""
    path = write(tmp_path / "big.gfc", gfc_text(small_model(), max_degree=declared))
    tracemalloc.start()
    try:
        refused(rf"line 5: max_degree {declared} is beyond {MAX_MODEL_DEGREE:,}", read_icgem, path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 5_000_000
    nga = write(tmp_path / "big.ascii", nga_text(small_model()) + f"{declared} 0 1.0e-9 0.0 0.0 0.0\n")
    refused(rf"line 26: degree {declared} is beyond", read_nga, nga, name="X", gm=3.986004415e14, radius=6378136.3)


def test_declared_degree_checked_against_the_lines_before_allocating(tmp_path):
    """A plausible degree (5000: 1 GB of arrays) in a file of 25 lines: refused by counting
    lines, before the arrays are allocated."""
    path = write(tmp_path / "short.gfc", gfc_text(small_model(), max_degree=5000))
    tracemalloc.start()
    try:
        message = refused(r"line 5: max_degree 5000 needs 12,507,498 coefficient lines \(n = 2\.\.5000\), but the file "
                          r"has 25 lines in [\d,]+ bytes; its last line is of degree 6", read_icgem, path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 5_000_000 and "truncated file, or a wrong degree" in message
    nga = write(tmp_path / "short.ascii", nga_text(small_model()) + "5000 0 1.0e-9 0.0 0.0 0.0\n")
    refused(r"degree 5000 needs 12,507,498 coefficient lines", read_nga, nga, name="X", gm=3.986004415e14,
            radius=6378136.3)


def test_correction_degree_must_match_the_model(tmp_path):
    """Seen: a degree-60 CORRCOEF beside a degree-360 model was summed without a word."""
    model = small_model(nmax=8)
    short = CorrectionModel("CORR60", 4, np.ones((5, 5)) * 0.1, np.zeros((5, 5)), unit_m=0.01,
                            source_path="corr60.txt")
    message = refused(r"corr60\.txt: the zeta-to-N correction stops at degree 4, but the synthesis goes to degree 8",
                      GeoidSynthesis, model, short)
    assert "max_degree=4" in message
    assert GeoidSynthesis(model, short, max_degree=4).max_degree == 4  # truncated on purpose
    refused(r"stops at degree 4, but the synthesis goes to degree 6 \(asked for\)", GeoidSynthesis, model, short,
            max_degree=6)
    # a longer correction is cut to the model's degree, as before
    long = CorrectionModel("CORR", 10, np.zeros((11, 11)), np.zeros((11, 11)), unit_m=0.01)
    assert GeoidSynthesis(model, long).correction.max_degree == 8
    # NGA's EGM2008 correction stops at 2160 beside the 2190 model: accepted
    from types import SimpleNamespace

    from geoidspline.sources.harmonics.synthesis import _check_correction_degree

    egm2008_zeta_to_n = SimpleNamespace(max_degree=2160, source_path="Zeta-to-N_to2160_egm2008", name="Z")
    _check_correction_degree(egm2008_zeta_to_n, 2190, False)
    refused(r"Zeta-to-N_to2160_egm2008: the zeta-to-N correction stops at degree 2160, but the synthesis goes to "
            r"degree 2200", _check_correction_degree, egm2008_zeta_to_n, 2200, False)
    # through files: load_synthesis refuses, and accepts an explicit max_degree
    gfc = write(tmp_path / "m.gfc", gfc_text(model))
    corr = write(tmp_path / "CORRCOEF", corr_text(4))
    refused(r"CORRCOEF: the zeta-to-N correction stops at degree 4", load_synthesis, gfc, corr)
    assert load_synthesis(gfc, corr, max_degree=4).max_degree == 4


def test_real_egm96_pair_still_reads():
    need(EGM96)
    need(CORRCOEF)
    syn = load_synthesis(EGM96, CORRCOEF)
    assert syn.max_degree == 360 and syn.correction.max_degree == 360
    assert syn.undulation(0.0, 0.0) == pytest.approx(17.16, abs=0.01)


# ------------------------------------------------------------------ 4. the catalogue's copies
def test_a_damaged_catalogue_file_is_refused(tmp_path):
    """Seen: a bit-flipped WW15MGH.DAC (values off by up to 164 m) got only a note."""
    cm = np.tile(np.linspace(-3000, 3000, 1440).astype(">i2"), (721, 1))
    path = write(tmp_path / "WW15MGH.DAC", cm.tobytes())
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    message = refused(r"WW15MGH\.DAC: sha256 [0-9a-f]{64} is none of the known copies of catalogue entry "
                      r"'egm96-15-nga'", read_grid, path)
    assert digest in message and "c738c9910ea04492c26fb14269cc8f2fe57876f41943b5c3d7f59f549cd44b77" in message
    assert "allow_unknown_copy=True" in message
    refused(r"none of the known copies", open_source, str(path))
    grid = read_grid(path, allow_unknown_copy=True)
    assert grid.shape == (721, 1440) and any("sha256 differs" in n for n in grid.provenance.notes)
    assert open_source(str(path), allow_unknown_copy=True).shape == (721, 1440)


def test_the_real_dac_is_a_known_copy(tmp_path):
    dac = need(reference_file("egm96", "WW15MGH.DAC"))
    assert read_grid(dac).undulation(0.0, 0.0) == pytest.approx(17.16, abs=1e-9)
    flipped = bytearray(dac.read_bytes())
    flipped[2 * (400 * 1440 + 700)] ^= 0x40  # +-163.84 m at one node
    refused(r"none of the known copies", read_grid, write(tmp_path / "WW15MGH.DAC", bytes(flipped)))


# ------------------------------------------------------------------ 5. formats by content
def test_projs_own_grid_by_path_is_a_grid():
    """Seen: geoid-fit /usr/share/proj/egm96_15.gtx failed with 'not a text file
    (contains NUL bytes)': a name starting with egm96_ was read as NGA coefficients."""
    if not PROJ_GTX.is_file():
        pytest.skip(f"{PROJ_GTX} not installed (apt-get install proj-data)")
    assert not is_model_file(PROJ_GTX)
    assert read_grid(PROJ_GTX).shape == (721, 1440)
    source = open_source(str(PROJ_GTX))
    assert isinstance(source, GeoidGrid) and source.undulation(0.0, 0.0, "bilinear") == pytest.approx(17.1616, abs=1e-4)


def test_names_are_only_hints(tmp_path):
    """GeographicLib's egm96-5.pgm, a GTX without extension, a model named .gtx."""
    grid_values = field(LAT, LON)
    pgm = need(PGM)
    renamed = write(tmp_path / "egm96-5.pgm", pgm.read_bytes())
    assert not is_model_file(renamed) and isinstance(open_source(str(renamed)), GeoidGrid)
    bare = write(tmp_path / "geoid_grid", gtx_bytes(grid_values))
    assert read_grid(bare).shape == (LAT.size, LON.size)
    named_like_nga = write(tmp_path / "egm96_to360_regional.gtx", gtx_bytes(grid_values))
    assert isinstance(open_source(str(named_like_nga)), GeoidGrid)
    model = write(tmp_path / "model.gtx", gfc_text(small_model()))
    assert is_model_file(model)
    assert open_source(str(model)).max_degree == 6  # read as the model it is
    refused(r"model\.gtx: is a spherical-harmonic model \(an ICGEM \.gfc\), not a grid", read_grid, model)
    corr = write(tmp_path / "corr.nc", corr_text(3))
    refused(r"corr\.nc: is a zeta-to-N correction .* not a grid", read_grid, corr)
    refused(r"corr\.nc: is a zeta-to-N correction \(n m C S\), not a model file", load_synthesis, corr)
    refused(r"model\.gtx: is a spherical-harmonic model, not a correction file", load_synthesis, model, model)
    refused(r"geoid_grid: is a geoid grid, not a model file", load_synthesis, bare)
    # an extension picks the rule quoted when the content matches nothing
    refused(r"x\.gtx: GTX file is 12 bytes, shorter than its 40-byte header", read_grid, write(tmp_path / "x.gtx", b"1" * 12))
    refused(r"x\.nc: not a netCDF file", read_grid, write(tmp_path / "x.nc", b"1" * 12))
    refused(r"x\.bin: NGS \.bin file is 12 bytes, shorter than its 44-byte header", read_grid,
            write(tmp_path / "x.bin", b"1" * 12))
    refused(r"x\.raw: unrecognised grid format: the content matches none of", read_grid, write(tmp_path / "x.raw", b"1" * 12))


# ------------------------------------------------------------------ 6. faults are messages
def _broken_deflate(text: bytes) -> bytes:
    """A gzip member whose deflate stream is invalid (zlib.error: invalid block type)."""
    good = gzip.compress(text)
    header = good[:10]
    return header + b"\xff" * 64 + good[-8:]


def test_broken_gzip_streams_are_messages(tmp_path):
    """Seen: zlib.error (a traceback) from a gzip whose deflate stream is broken."""
    with pytest.raises(zlib.error):
        gzip.decompress(_broken_deflate(b"x" * 100))  # the fault is real
    text = nga_text(small_model()).encode()
    cases = {
        "deflate.ascii.gz": _broken_deflate(text),
        "truncated.ascii.gz": gzip.compress(text)[:-30],
        "crc.ascii.gz": gzip.compress(text)[:-8] + b"\0\0\0\0" + gzip.compress(text)[-4:],
        "trailing.ascii.gz": gzip.compress(text) + b"\x1f\x8bjunk",
    }
    for name, payload in cases.items():
        path = write(tmp_path / name, payload)
        for func in (read_model, read_nga_correction, load_synthesis):
            refused(rf"{name}: .*(gzip|compressed)", func, path)
        refused(rf"{name}: .*(gzip|compressed)", read_grid, path)
    bomb = write(tmp_path / "bomb.gfc.gz", gzip.compress(b"\0" * (50 << 20)))
    refused(r"bomb\.gfc\.gz: not a text file: its gzip content contains NUL bytes", read_model, bomb)


def test_huge_gtx_header_is_refused_before_reading(tmp_path):
    """Seen: a 3.2 GB GTX under a memory limit raised MemoryError. A header declaring more
    nodes than geoidspline reads, or than the file holds, is refused from its 40 bytes."""
    rows, cols = 20000, 40000  # 800 million nodes, 3.2 GB
    sparse = tmp_path / "huge.gtx"
    with open(sparse, "wb") as fh:
        fh.write(gtx_bytes(np.zeros((0, 0)), lat0=-90, lon0=0, step=0.009, rows=rows, cols=cols))
        fh.truncate(40 + rows * cols * 4)  # sparse: no disk used
    tracemalloc.start()
    try:
        refused(r"huge\.gtx: GTX header declares 20000 x 40000 = 800,000,000 nodes, more than the 250,000,000",
                read_grid, sparse)
        liar = gtx_bytes(np.zeros((1, 100)), lat0=-90, lon0=0, step=0.009, rows=10000, cols=20000)
        refused(r"liar\.gtx: GTX file is 440 bytes, header says 10000 x 20000 float32 nodes need 800000040",
                read_grid, write(tmp_path / "liar.gtx", liar))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 5_000_000


def test_memory_error_never_escapes(tmp_path, monkeypatch):
    """Out of memory inside any reader ends as an InputFileError naming the file."""
    from geoidspline.sources import gtx

    path = write(tmp_path / "g.gtx", gtx_bytes(field(LAT, LON)))

    def no_memory(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(gtx, "finish_grid", no_memory)
    refused(r"g\.gtx: not enough memory to read this file", read_grid, path)
    model = write(tmp_path / "m.gfc", gfc_text(small_model()))
    from geoidspline.sources.harmonics import models

    monkeypatch.setattr(models, "_check_coefficients", no_memory)
    refused(r"m\.gfc: not enough memory to read this file", read_model, model)


def test_memory_limit_in_a_real_process(tmp_path):
    """Under an address-space limit, a large (sparse, 800 MB) GTX cannot be held: the
    process prints the InputFileError, no MemoryError traceback."""
    rows, cols = 10000, 20000  # 200 million nodes: within the maximum, 800 MB of float32
    path = tmp_path / "big.gtx"
    with open(path, "wb") as fh:
        fh.write(gtx_bytes(np.zeros((0, 0)), lat0=-90, lon0=0, step=0.009, rows=rows, cols=cols))
        fh.truncate(40 + rows * cols * 4)
    script = textwrap.dedent(f"""
        import resource, sys
        from geoidspline.sources.formats import read_grid
        from geoidspline.errors import InputFileError
        resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))
        try:
            read_grid({str(path)!r})
        except InputFileError as exc:
            print("ERROR:", exc)
            sys.exit(1)
    """)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 1, done.stderr[-2000:]
    assert f"ERROR: {path}: not enough memory to read this file" in done.stdout
    assert "Traceback" not in done.stderr


def test_truncated_text_and_binary_files(tmp_path):
    text = gfc_text(small_model())
    refused(r"cut\.gfc: line \d+: expected 'gfc n m C S", read_icgem, write(tmp_path / "cut.gfc", text[: text.rindex(" ")]))
    values = gtx_bytes(field(LAT, LON))
    refused(r"cut\.gtx: GTX file is \d+ bytes, header says 41 x 41 float32 nodes need 6764", read_grid,
            write(tmp_path / "cut.gtx", values[:-7]))
    nc = write_netcdf(tmp_path / "full.nc", GeoidGrid(LAT, LON, field(LAT, LON), Provenance(source="x")))
    refused(r"cut\.nc: ", read_grid, write(tmp_path / "cut.nc", nc.read_bytes()[: nc.stat().st_size // 2]))


def test_non_utf8_text(tmp_path):
    """UTF-16 text holds NUL bytes; latin-1 in a header comment is harmless; in data it
    is a bad number on its line."""
    model = small_model()
    refused(r"u16\.gfc: not a text file \(contains NUL bytes\)", read_model,
            write(tmp_path / "u16.gfc", gfc_text(model).encode("utf-16")))
    with_comment = gfc_text(model, header_extra="comment Modèle géoïde (latin-1)").encode("latin-1")
    assert read_icgem(write(tmp_path / "l1.gfc", with_comment)).max_degree == 6
    bad = gfc_text(model).replace("gfc 3 1 ", "gfc 3 1 \xe9").encode("latin-1")
    refused(r"line \d+: C '\xe9[-0-9.e]+' is not a number", read_icgem, write(tmp_path / "bad.gfc", bad))


def _no_hang(seconds=10):
    """Fail instead of hanging (a FIFO opened for reading blocks forever)."""

    def alarm(signum, frame):
        raise AssertionError("the reader blocked")

    signal.signal(signal.SIGALRM, alarm)
    signal.alarm(seconds)


def test_directories_fifos_and_devices_are_not_files(tmp_path):
    fifo = tmp_path / "pipe.gtx"
    os.mkfifo(fifo)
    _no_hang()
    try:
        for target in (tmp_path, fifo, Path("/dev/zero")):
            for func in (read_grid, read_model, read_icgem, read_nga_correction, load_synthesis):
                refused(r"(not a regular file|file not found|no such file)", func, target)
            refused(r"not a regular file|no such file", resolve_source, target)
            assert not is_model_file(target)
        from geoidspline.sources.formats import pgm_header

        refused(r"not a regular file", pgm_header, tmp_path)
    finally:
        signal.alarm(0)


def test_netcdf_library_crashers_are_refused_first(tmp_path):
    """netCDF-C trusts a classic header: mutated counts made it segfault, hang or exhaust
    memory (found by the fuzzing below). The header is walked and bounded first."""
    nc = tmp_path / "c.nc"
    xr.Dataset({"N": (("lat", "lon"), field(LAT, LON), {"units": "m"})},
               coords={"lat": ("lat", LAT, {"units": "degrees_north"}),
                       "lon": ("lon", LON, {"units": "degrees_east"})}).to_netcdf(nc, format="NETCDF3_CLASSIC")
    good = nc.read_bytes()
    assert read_grid(nc).shape == (LAT.size, LON.size)
    for offset, value, rule in [
        (12, b"\x8a\x00\x00\x02", r"2315255810 dimensions, more than the file can hold"),  # the crasher found
        (8, b"\x00\x00\x00\x07", r"expected the dimensions list tag 10 or 0, found 7"),
        (16, b"\x7f\xff\xff\xff", r"name bytes, more than the file can hold"),
    ]:
        mutated = bytearray(good)
        mutated[offset:offset + 4] = value
        refused(rule, read_grid, write(tmp_path / "m.nc", bytes(mutated)))


# ------------------------------------------------------------------ properties: fuzzing every reader
FUZZ = settings(max_examples=200, deadline=None, database=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def _seeds(tmp: Path) -> dict[str, bytes]:
    """Small valid files of every format, the starting points of the mutations."""
    values = field(LAT, LON)
    files = {"g.gtx": gtx_bytes(values)}
    nc3 = tmp / "seed3.nc"
    xr.Dataset({"N": (("lat", "lon"), values, {"units": "m"})},
               coords={"lat": ("lat", LAT, {"units": "degrees_north"}),
                       "lon": ("lon", LON, {"units": "degrees_east"})}).to_netcdf(nc3, format="NETCDF3_CLASSIC")
    files["g3.nc"] = nc3.read_bytes()
    nc4 = write_netcdf(tmp / "seed4.nc", GeoidGrid(LAT, LON, values, Provenance(source="x")))
    files["g4.nc"] = nc4.read_bytes()
    grid = GeoidGrid(LAT, LON, values, Provenance(source="x"))
    files["g.isg"] = write_isg(tmp / "seed.isg", grid).read_bytes()
    files["g.asc"] = write_gsi(tmp / "seed.asc", grid).read_bytes()
    files["g.tif"] = write_geotiff(tmp / "seed.tif", grid).read_bytes()
    width, height = 8, 5
    pixels = np.full((height, width), 40000, dtype=">u2")
    files["g.pgm"] = f"P5\n# Offset -108\n# Scale 0.003\n{width} {height}\n65535\n".encode() + pixels.tobytes()
    model = small_model()
    files["m.gfc"] = gfc_text(model).encode()
    files["egm96_to360.ascii"] = nga_text(small_model(name="EGM96")).encode()
    files["CORRCOEF"] = corr_text(4).encode()
    files["m.gfc.gz"] = gzip.compress(files["m.gfc"])
    return files


_SEEDS: dict[str, bytes] = {}


def seed(name: str, tmp: Path) -> bytes:
    """The seed file ``name`` (all made once per session; not a fixture, so that
    hypothesis does not print every seed with a failing example)."""
    if not _SEEDS:
        tmp.mkdir(exist_ok=True)
        _SEEDS.update(_seeds(tmp))
    return _SEEDS[name]


def _only_input_errors(func, path, **kwargs):
    """Call a reader on a hostile file: it returns, or raises a GeoidSplineError; a
    returned grid holds only plausible values."""
    try:
        result = func(path, **kwargs)
    except GeoidSplineError:
        return
    if isinstance(result, GeoidGrid):
        finite = result.values[np.isfinite(result.values)]
        assert finite.size and np.abs(finite).max() <= MAX_ABS_UNDULATION_M


_SUFFIXES = ["", ".gtx", ".nc", ".pgm", ".dac", ".isg", ".asc", ".tif", ".gfc", ".gz", ".ascii"]


@FUZZ
@given(payload=st.binary(max_size=4096), suffix=st.sampled_from(_SUFFIXES))
def test_random_bytes_are_refused_cleanly(tmp_path, payload, suffix):
    path = write(tmp_path / f"random{suffix}", payload)
    for func in (read_grid, read_model, read_nga_correction, is_model_file):
        _only_input_errors(func, path)


def _mutate(data: bytes, draw) -> bytes:
    """Flip bytes, overwrite a header field with an extreme integer, or cut the file."""
    data = bytearray(data)
    for _ in range(draw(st.integers(1, 6))):
        kind = draw(st.sampled_from(["byte", "int32", "cut", "digit"]))
        if not data:
            break
        at = draw(st.integers(0, len(data) - 1))
        if kind == "byte":
            data[at] = draw(st.integers(0, 255))
        elif kind == "int32":
            value = draw(st.sampled_from([0, 1, -1, 2**31 - 1, -(2**31), 2**24, 65535, 721, 1440]))
            data[at:at + 4] = value.to_bytes(4, "big", signed=True)
        elif kind == "cut":
            data = data[:at]
        else:  # a text file: a digit becomes another digit, or a sign, or an exponent
            data[at:at + 1] = draw(st.sampled_from([b"9", b"0", b"-", b"e", b"D", b"99999999", b" ", b"\n"]))
    return bytes(data)


@pytest.mark.parametrize("name", ["g.gtx", "g3.nc", "g4.nc", "g.pgm", "g.isg", "g.asc", "g.tif"])
@FUZZ
@given(data=st.data())
def test_mutated_grids_are_refused_cleanly(tmp_path, name, data):
    mutated = _mutate(seed(name, tmp_path / "seeds"), data.draw)
    _only_input_errors(read_grid, write(tmp_path / name, mutated))


@pytest.mark.parametrize("name", ["m.gfc", "egm96_to360.ascii", "CORRCOEF", "m.gfc.gz"])
@FUZZ
@given(data=st.data())
def test_mutated_models_are_refused_cleanly(tmp_path, name, data):
    mutated = _mutate(seed(name, tmp_path / "seeds"), data.draw)
    path = write(tmp_path / name, mutated)
    reader = read_nga_correction if name == "CORRCOEF" else read_model
    _only_input_errors(reader, path)
    _only_input_errors(read_grid, path)
    if name != "CORRCOEF":
        try:
            syn = load_synthesis(path)
        except GeoidSplineError:
            return
        _only_input_errors(lambda p: syn.undulation(np.array([-60.0, 0.0, 45.0]), np.array([0.0, 90.0, 200.0])), path)
