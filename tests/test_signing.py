"""Signed stores (issue 24 item 6): a forgery that recomputes the checksums passes
``--verify`` but not ``--verify --key``; unsigned and other-key stores are refused by
name; a signed update keeps the store signed; a crash at any commit point leaves each
manifest with its own signature (fault injection at the writer's crash points)."""

from __future__ import annotations

import hashlib
import json
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("cryptography")

import geoidspline  # noqa: E402
from geoidspline.cli import info, query, update  # noqa: E402
from geoidspline.errors import InputFileError  # noqa: E402
from geoidspline.store import writer  # noqa: E402
from geoidspline.store.format import load_manifest, manifest_text, read_tile_file, write_tile_file  # noqa: E402
from geoidspline.store.signing import SignatureError, generate_key, key_fingerprint  # noqa: E402

UPDATE_REGION = (15.0, 25.0, 25.0, 35.0)


@pytest.fixture(scope="module")
def keys(tmp_path_factory):
    base = tmp_path_factory.mktemp("keys")
    agency = generate_key(base / "agency.pem")
    other = generate_key(base / "other.pem")
    return {"agency": agency, "other": other}


@pytest.fixture
def signed_store(small_store, keys, tmp_path):
    path = tmp_path / "signed"
    writer.write_store(path, small_store.result, small_store.grid.provenance, sign=keys["agency"][0])
    return path


def forge(store):
    """The forgery of the issue: halve the values of the tile with the most coefficients,
    recompute its sha256 and size, and the manifest (with its integrity digest)."""
    manifest = load_manifest(store)
    entry = max(manifest["tiles"], key=lambda e: e["coefficients"])
    path = store / entry["file"]
    indices, levels, values = read_tile_file(path, entry, path.read_bytes(), manifest)
    spline = manifest["spline"]
    attrs = {"order": spline["order"], "h0": spline["h0"], "tile_size": spline["tile_size"],
             "store_id": manifest["store_id"], "store_version": manifest["store_version"],
             "value_step_m": spline.get("value_step_m")}
    path.unlink()
    write_tile_file(path, tuple(entry["tile"]), levels, indices, values / 2, attrs, manifest["format_version"])
    entry["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    entry["bytes"] = path.stat().st_size
    (store / "manifest.json").write_bytes(manifest_text(manifest))
    return path


def cli(command, args):
    result = CliRunner().invoke(command, [str(a) for a in args], prog_name=command.name)
    assert "Traceback" not in result.stderr + result.stdout
    return result


def test_a_signed_store_verifies_and_openssl_layout(signed_store, keys):
    assert sorted(p.name for p in signed_store.iterdir() if p.is_file()) == [
        ".geoidspline-store", ".lock", "manifest.json", "manifest.json.v1.sig"]
    assert len((signed_store / "manifest.json.v1.sig").read_bytes()) == 64  # raw Ed25519, as openssl writes
    result = cli(info.main, ["--store", signed_store, "--verify", "--key", keys["agency"][1]])
    assert result.exit_code == 0 and "signed by that key" in result.stdout
    store = geoidspline.open_store(signed_store, key=keys["agency"][1])
    assert store.info()["signature"] == "manifest.json.v1.sig"


def test_a_forged_tile_passes_checksums_but_not_the_key(signed_store, keys):
    before = geoidspline.open_store(signed_store)
    lat, lon = np.meshgrid(np.arange(10.5, 30, 1.0), np.arange(20.5, 40, 1.0))
    truth = before.undulation(lat, lon)
    tile = forge(signed_store)
    forged = geoidspline.open_store(signed_store)
    assert np.nanmax(np.abs(forged.undulation(lat, lon) - truth)) > 1.0  # metres: the forgery matters
    plain = cli(info.main, ["--store", signed_store, "--verify"])
    assert plain.exit_code == 0  # checksums find damage, not forgery
    keyed = cli(info.main, ["--store", signed_store, "--verify", "--key", keys["agency"][1]])
    assert keyed.exit_code == 1
    assert "manifest.json.v1.sig: does not sign" in keyed.stdout and key_fingerprint(keys["agency"][1]) in keyed.stdout
    with pytest.raises(SignatureError, match="does not sign"):
        geoidspline.open_store(signed_store, key=keys["agency"][1])
    assert tile.exists()


def test_an_unsigned_store_and_another_key_are_refused_by_name(store_copy, signed_store, keys):
    with pytest.raises(SignatureError, match=r"store version 1 is not signed \(no manifest.json.v1.sig\)"):
        geoidspline.open_store(store_copy, key=keys["agency"][1])
    result = cli(info.main, ["--store", store_copy, "--verify", "--key", keys["agency"][1]])
    assert result.exit_code == 1 and "is not signed" in result.stdout
    with pytest.raises(SignatureError, match=key_fingerprint(keys["other"][1])):
        geoidspline.open_store(signed_store, key=keys["other"][1])
    answer = cli(query.main, ["--store", store_copy, "--key", keys["agency"][1], "20", "30"])
    assert answer.exit_code == 1 and answer.stderr.startswith("ERROR: ") and answer.stdout == ""


def test_keys_are_pem_files_and_mistakes_are_named(tmp_path, keys):
    private, public = keys["agency"]
    assert private.read_bytes().startswith(b"-----BEGIN PRIVATE KEY-----")
    assert public.read_bytes().startswith(b"-----BEGIN PUBLIC KEY-----")
    assert private.stat().st_mode & 0o777 == 0o600
    with pytest.raises(InputFileError, match="exists already"):
        generate_key(private)
    with pytest.raises(InputFileError, match="this is a public key"):
        writer.load_private_key(public)
    junk = tmp_path / "junk.pem"
    junk.write_text("not a key")
    with pytest.raises(InputFileError, match="not a PEM public key"):
        geoidspline.open_store(tmp_path, key=junk)
    result = cli(info.main, ["--generate-key", tmp_path / "new.pem"])
    assert result.exit_code == 0 and (tmp_path / "new.pub.pem").exists()


def test_the_signature_survives_an_update_signed_with_the_same_key(signed_store, small_store, keys):
    result = cli(update.main, [small_store.gtx, "--store", signed_store, "--region", *UPDATE_REGION,
                               "--sign", keys["agency"][0], "--json"])
    assert result.exit_code in (0, 3), result.stderr
    assert json.loads(result.stdout)["signed_by"] == key_fingerprint(keys["agency"][0])
    names = sorted(p.name for p in signed_store.iterdir() if p.name.endswith(".sig"))
    assert names == ["manifest.json.v2.sig"]  # the old version's signature is gone with it
    store = geoidspline.open_store(signed_store, key=keys["agency"][1])
    assert store.manifest["store_version"] == 2
    # another key cannot sign over this one's store, and nothing changes
    before = (signed_store / "manifest.json").read_bytes()
    with pytest.raises(SignatureError):
        geoidspline.update(signed_store, small_store.grid, UPDATE_REGION, sign=keys["other"][0])
    assert (signed_store / "manifest.json").read_bytes() == before


def test_an_unsigned_update_leaves_no_stale_signature(signed_store, small_store, keys, caplog):
    geoidspline.update(signed_store, small_store.grid, UPDATE_REGION)
    assert "this update is not" in caplog.text
    assert not list(signed_store.glob("*.sig"))
    with pytest.raises(SignatureError, match="store version 2 is not signed"):
        geoidspline.open_store(signed_store, key=keys["agency"][1])


class Killed(BaseException):
    """A crash at a commit point: nothing below it runs, no clean-up (like SIGKILL)."""


@pytest.mark.parametrize("point", ["before-manifest", "signature-written", "manifest-written", "after-manifest"])
def test_a_crash_at_any_commit_point_leaves_a_signed_state(signed_store, small_store, keys, monkeypatch, point):
    def crash(name):
        if name == point:
            raise Killed(name)

    monkeypatch.setattr(writer, "crash_point", crash)
    monkeypatch.setattr("geoidspline.store.update.crash_point", crash)
    with pytest.raises(Killed):
        geoidspline.update(signed_store, small_store.grid, UPDATE_REGION, sign=keys["agency"][0])
    monkeypatch.undo()
    store = geoidspline.open_store(signed_store, key=keys["agency"][1], lazy=False)  # verifies, every tile
    committed = point == "after-manifest"
    assert store.manifest["store_version"] == (2 if committed else 1)
    # the next signed write clears what the crash left and signs its own version
    geoidspline.update(signed_store, small_store.grid, UPDATE_REGION, sign=keys["agency"][0])
    after = geoidspline.open_store(signed_store, key=keys["agency"][1])
    assert [p.name for p in signed_store.glob("*.sig")] == [f"manifest.json.v{after.manifest['store_version']}.sig"]


def test_a_fault_writing_the_signature_keeps_the_previous_version(signed_store, small_store, keys, monkeypatch):
    import errno

    import geoidspline.store.signing as signing

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(signing, "sign", full)
    with pytest.raises(geoidspline.StoreError, match=r"manifest.json.v2.sig: cannot write the store .*no space left"):
        geoidspline.update(signed_store, small_store.grid, UPDATE_REGION, sign=keys["agency"][0])
    monkeypatch.undo()
    assert geoidspline.open_store(signed_store, key=keys["agency"][1]).manifest["store_version"] == 1
    assert not (signed_store / "manifest.json.v2.sig").exists()


def test_a_copied_store_keeps_its_signature(signed_store, keys, tmp_path):
    """What travels (a directory copy, a Docker layer) verifies where it arrives."""
    copy = shutil.copytree(signed_store, tmp_path / "arrived")
    assert geoidspline.open_store(copy, key=keys["agency"][1]).manifest["store_version"] == 1


def test_an_upgrade_says_the_signature_is_gone(small_store, keys, tmp_path, caplog):
    from geoidspline.store.upgrade import upgrade_store

    path = tmp_path / "old"
    writer.write_store(path, small_store.result, small_store.grid.provenance, format_version=1, sign=keys["agency"][0])
    geoidspline.open_store(path, key=keys["agency"][1])
    upgrade_store(path)
    assert "was signed; the upgraded store is not" in caplog.text
    assert not list(path.glob("*.sig"))
