"""Faults with a good message (issue 24): a full disk during an export names the file
and the cause (fault injection: netCDF's 'HDF error', an ENOSPC write, GDAL's silent
short write), geoidspline's warnings on the CLI's log channel, hints that fit the source
kind, the pole as one point, and commands that run every action asked for."""

from __future__ import annotations

import errno
import logging
import os

import numpy as np
import pytest
from click.testing import CliRunner

import geoidspline
from geoidspline import _files
from geoidspline.api import build_store
from geoidspline.cli import export, fit, info, query
from geoidspline.errors import ExportError
from geoidspline.fitting.driver import finer_data_hint
from geoidspline.fitting.parameters import FitParameters
from geoidspline.api.export import export_grid
from geoidspline.sphere.region import Region
from geoidspline.store.writer import write_store

from test_harmonics import C20_2008_ZERO_TIDE, GFC_HEADER, GFC_LINES, gfc_text  # noqa: I001


def no_space_left(monkeypatch, directory):
    """The file system of ``directory`` reports no free block (as a full disk does)."""
    real = os.statvfs

    class Full:
        def __init__(self, st):
            self.f_flag, self.f_frsize, self.f_files, self.f_favail = st.f_flag, st.f_frsize, st.f_files, 10
            self.f_bavail = 0

    monkeypatch.setattr(_files.os, "statvfs", lambda p: Full(real(p)) if str(p) == str(directory) else real(p))


def leftovers(directory):
    return sorted(p.name for p in directory.iterdir())


def test_netcdf_export_into_a_full_disk_names_the_file_and_the_cause(small_store, tmp_path, monkeypatch):
    import xarray as xr

    def hdf_error(self, path, *args, **kwargs):
        with open(path, "wb") as fh:
            fh.write(b"\x89HDF\r\n\x1a\n partial")  # what netCDF leaves behind
        raise RuntimeError("NetCDF: HDF error")

    monkeypatch.setattr(xr.Dataset, "to_netcdf", hdf_error)
    no_space_left(monkeypatch, tmp_path)
    store = geoidspline.open_store(small_store.path)
    with pytest.raises(ExportError) as err:
        export_grid(store, tmp_path / "n.nc", 1.0)
    assert str(err.value).startswith(f"{tmp_path / 'n.nc'}: cannot write the CF netCDF-4 export: no space left")
    assert leftovers(tmp_path) == []  # no partial file, no temporary
    # through the command: one ERROR line, exit 1
    result = CliRunner().invoke(export.main, ["--store", str(small_store.path), "--out",
                                                              str(tmp_path / "n.nc"), "--spacing", "1"])
    assert result.exit_code == 1 and result.stderr.splitlines() == [f"ERROR: {err.value}"]


def test_a_gtx_export_into_a_full_disk_names_the_file(small_store, tmp_path, monkeypatch):
    real_write = os.write

    def full(fd, data):  # the first block fits, then the disk is full
        if len(data) > 64:
            real_write(fd, bytes(data[:64]))
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(_files.Path, "write_bytes", lambda self, data: _write_with(self, data, full))
    with pytest.raises(ExportError, match=rf"^{tmp_path / 'g.gtx'}: cannot write the PROJ GTX export: no space left"):
        export_grid(geoidspline.open_store(small_store.path), tmp_path / "g.gtx", 1.0)
    assert leftovers(tmp_path) == []


def _write_with(path, data, write):
    fd = os.open(path, os.O_WRONLY | os.O_TRUNC)
    try:
        write(fd, data)
    finally:
        os.close(fd)


def test_a_geotiff_export_gdal_cut_short_is_not_written(small_store, tmp_path, monkeypatch):
    """GDAL reports a full disk at close on stderr only: the file is read back."""
    rasterio = pytest.importorskip("rasterio")
    real_open = rasterio.open

    def short(path, mode="r", **kwargs):
        ds = real_open(path, mode, **kwargs)
        if mode == "w":
            real_write = ds.write
            ds.write = lambda data, band: real_write(np.zeros_like(data), band)  # what reached the disk
        return ds

    monkeypatch.setattr(rasterio, "open", short)
    no_space_left(monkeypatch, tmp_path)
    with pytest.raises(ExportError, match=r"g\.tif: cannot write the GeoTIFF export: no space left"):
        export_grid(geoidspline.open_store(small_store.path), tmp_path / "g.tif", 1.0)
    assert leftovers(tmp_path) == []


def test_the_tide_system_warning_is_a_log_line_and_recorded(tmp_path):
    lines = list(GFC_LINES)
    lines[1] = f"gfc 2 0 {C20_2008_ZERO_TIDE!r} 0.0 1e-11 0.0"
    model = tmp_path / "egm2008_bad.gfc"
    model.write_text(gfc_text(lines, GFC_HEADER.replace("TESTMODEL", "EGM2008")))
    result = CliRunner().invoke(query.main, ["--model", str(model), "--format", "jsonl", "10", "20"])
    assert result.exit_code == 0, result.stderr
    warning = [line for line in result.stderr.splitlines() if "zero_tide" in line]
    assert len(warning) == 1 and warning[0].startswith(f"WARNING: {model}: ") and "TideSystemWarning" not in warning[0]
    assert "warnings.warn" not in result.stderr
    quiet = CliRunner().invoke(query.main, ["--model", str(model), "-q", "10", "20"])
    assert quiet.exit_code == 0 and quiet.stderr == ""
    from geoidspline.sources.resolve import load_synthesis

    with pytest.warns(UserWarning):
        synthesis = load_synthesis(model, None, None)
    assert any("zero_tide" in note for note in synthesis.provenance.notes)  # recorded in the provenance


def test_hints_fit_the_source_kind(small_store, tmp_path, caplog, make_synthesis):
    grid_hint = finer_data_hint(small_store.grid)
    assert "sample_spacing_deg" not in grid_hint and "finer nodes" in grid_hint
    assert "sample_spacing_deg" in finer_data_hint(make_synthesis(8, 1, "toy"))
    caplog.set_level(logging.WARNING)
    params = FitParameters(h0=0.1, max_level=3, tolerance_m=1e-5)  # level 3 is finer than the 2° nodes
    build_store(small_store.grid, tmp_path / "s", Region(12.0, 22.0, 18.0, 28.0), params)
    stops = [r.getMessage() for r in caplog.records if "stopping at level" in r.getMessage()]
    assert stops and all("sample_spacing" not in m and "finer nodes" in m for m in stops)


@pytest.fixture(scope="module")
def polar_store(tmp_path_factory):
    from conftest import make_synthetic_grid

    path = tmp_path_factory.mktemp("polar") / "store"
    build_store(make_synthetic_grid(), path, Region(70.0, -20.0, 90.0, 40.0),
                FitParameters(h0=0.2, max_level=0, tolerance_m=1.0))
    return geoidspline.open_store(path)


def test_the_pole_is_one_point(polar_store):
    longitudes = np.array([-180.0, -120.0, -20.0, 0.0, 40.0, 41.0, 90.0, 179.9, 359.0, 1e5])
    latitudes = np.full(longitudes.shape, 90.0)
    assert np.all(polar_store.covers(latitudes, longitudes))
    values = polar_store.undulation(latitudes, longitudes)
    assert np.all(np.isfinite(values)) and np.ptp(values) < 1e-9
    assert values[0] == pytest.approx(polar_store.undulation(90.0, 10.0), abs=1e-12)
    assert polar_store.coverage_reason(90.0, 100.0) == "inside"
    # beside the pole, longitudes outside the region stay outside
    assert not polar_store.covers(89.9, 100.0) and np.isnan(polar_store.undulation(89.9, 100.0))
    assert not polar_store.covers(90.0, float("nan"))
    result = CliRunner().invoke(query.main, ["--store", str(polar_store.path), "90", "100"])
    assert result.exit_code == 0 and float(result.stdout) == pytest.approx(values[0], abs=1e-4)


def test_a_store_short_of_the_pole_does_not_answer_it(small_store):
    store = geoidspline.open_store(small_store.path)  # 10..30 N
    assert not store.covers(90.0, 30.0) and not store.covers(-90.0, 30.0)


# -- commands never skip an asked-for action ---------------------------------------------


def test_upgrade_then_verify_runs_both(small_store, tmp_path):
    path = tmp_path / "old"
    write_store(path, small_store.result, small_store.grid.provenance, format_version=1)
    result = CliRunner().invoke(info.main, ["--store", str(path), "--upgrade", "--verify"])
    assert result.exit_code == 0, result.stderr
    out = result.stdout.splitlines()
    assert out[0].startswith(f"{path}: format 1 -> 4") and out[1] == f"{path}: every tile matches the manifest"
    assert geoidspline.open_store(path).manifest["format_version"] == 4


def test_verify_and_check_against_both_run(store_copy, tmp_path):
    model = tmp_path / "toy.gfc"
    model.write_text(gfc_text())
    result = CliRunner().invoke(info.main, ["--store", str(store_copy), "--verify", "--check-against", str(model),
                                            "--preset", "generic", "--points", "50"])
    assert result.exit_code == 0, result.stderr
    assert "every tile matches the manifest" in result.stdout and "check against" in result.stdout


@pytest.mark.parametrize("command, args, message", [
    (info.main, ["--store", "S", "--points", "10"], "--points goes with --check-against"),
    (fit.main, ["missing.gtx", "--store", "S", "--blend-width", "50"], "--blend-width goes with --update"),
    (query.main, ["--model", "m.gfc", "--key", "k.pem", "10", "20"], "--key goes with --store"),
    (info.main, ["--store", "S", "--generate-key", "k.pem"], "--generate-key writes a key pair"),
])
def test_options_that_would_be_ignored_are_refused(tmp_path, command, args, message):
    result = CliRunner().invoke(command, args)
    assert result.exit_code == 2 and len(result.stderr.splitlines()) == 1 and message in result.stderr
