"""Signed stores: a detached Ed25519 signature over the manifest's bytes.

The manifest lists every tile's size and sha256, so a signature over its exact bytes
covers every coefficient: a tile altered and its sha256 and the manifest recomputed (a
forgery, which ``--verify`` alone cannot tell from an honest write) no longer matches
the signature. Keys are PEM files as OpenSSL writes them (``openssl genpkey -algorithm
ed25519``: PKCS#8 private key; ``openssl pkey -pubout``: SubjectPublicKeyInfo public
key); :func:`generate_key` writes such a pair. The signature is the 64 raw bytes of
Ed25519 (RFC 8032), so OpenSSL checks it too::

    openssl pkeyutl -verify -pubin -inkey agency.pub.pem -rawin \\
        -in STORE/manifest.json -sigfile STORE/manifest.json.v3.sig

The signature of store version N is ``STORE/manifest.json.vN.sig``. It is written and
flushed to disk *before* the manifest naming version N replaces the old one
(:func:`geoidspline.store.writer.commit`), and the previous version's signature is
removed only after that: a crash at any point leaves either the old manifest with its
own signature or the new one with its own (a signature of a version never committed is
a leftover the next write removes). Ed25519 through the ``cryptography`` package
(OpenSSL underneath), imported only when a key is used.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from ..errors import InputFileError, StoreCorruptError
from .format import MANIFEST, SIGNATURE_NAME, parse_manifest, read_manifest_bytes, validate_manifest

__all__ = ["SIGNATURE_NAME", "SignatureError", "check_signature", "generate_key", "key_fingerprint",
           "load_private_key", "load_public_key", "load_signed_manifest", "signature_name", "write_signature"]

#: Bytes of an Ed25519 signature.
SIGNATURE_BYTES = 64


class SignatureError(StoreCorruptError):
    """A store that should be signed by a key is not, or its signature does not match."""


def signature_name(version: int) -> str:
    """The file name of the signature of store version ``version``."""
    return f"{MANIFEST}.v{int(version)}.sig"


def _crypto():
    try:
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric import ed25519
    except ImportError:  # pragma: no cover - a dependency; only a broken install lacks it
        from ..errors import GeoidSplineError

        raise GeoidSplineError("signing needs the cryptography package: pip install cryptography") from None
    return serialization, ed25519


def _read_pem(path, what: str) -> bytes:
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise InputFileError(path, f"no such {what} file") from None
    except OSError as exc:
        raise InputFileError(path, f"cannot read the {what}: {exc.strerror or exc}") from None
    return data


def load_private_key(key):
    """An Ed25519 private key: a key object as it is, or a PEM file (PKCS#8, unencrypted)."""
    serialization, ed25519 = _crypto()
    if isinstance(key, ed25519.Ed25519PrivateKey):
        return key
    data = _read_pem(key, "private key")
    try:
        loaded = serialization.load_pem_private_key(data, password=None)
    except TypeError:
        raise InputFileError(key, "the private key is encrypted: give an unencrypted PEM key "
                                  "(openssl genpkey -algorithm ed25519 -out KEY.pem)") from None
    except ValueError:
        hint = " (this is a public key: signing needs the private one)" if b"PUBLIC KEY" in data else ""
        raise InputFileError(key, f"not a PEM private key{hint}") from None
    if not isinstance(loaded, ed25519.Ed25519PrivateKey):
        raise InputFileError(key, f"is a {type(loaded).__name__.replace('_', '')}, not an Ed25519 key "
                                  "(openssl genpkey -algorithm ed25519)")
    return loaded


def load_public_key(key):
    """An Ed25519 public key: a key object as it is, a PEM public key file, or a PEM
    private key file (its public half)."""
    serialization, ed25519 = _crypto()
    if isinstance(key, ed25519.Ed25519PublicKey):
        return key
    if isinstance(key, ed25519.Ed25519PrivateKey):
        return key.public_key()
    data = _read_pem(key, "public key")
    if b"PRIVATE KEY" in data:
        return load_private_key(key).public_key()
    try:
        loaded = serialization.load_pem_public_key(data)
    except ValueError:
        raise InputFileError(key, "not a PEM public key (openssl pkey -in KEY.pem -pubout -out KEY.pub.pem)") \
            from None
    if not isinstance(loaded, ed25519.Ed25519PublicKey):
        raise InputFileError(key, f"is a {type(loaded).__name__.replace('_', '')}, not an Ed25519 public key")
    return loaded


def key_fingerprint(key) -> str:
    """sha256 of the raw public key, first 16 hex digits: how messages name a key."""
    serialization, _ = _crypto()
    raw = load_public_key(key).public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return hashlib.sha256(raw).hexdigest()[:16]


def generate_key(path, overwrite: bool = False) -> tuple[Path, Path]:
    """Write a new Ed25519 key pair: ``path`` (private, PKCS#8 PEM, mode 0600) and
    ``path`` with ``.pub.pem`` for ``.pem`` (public, SubjectPublicKeyInfo PEM).
    Returns both paths. An existing file is kept unless ``overwrite``."""
    serialization, ed25519 = _crypto()
    private_path = Path(path)
    stem = private_path.name[:-4] if private_path.name.endswith(".pem") else private_path.name
    public_path = private_path.with_name(f"{stem}.pub.pem")
    for target in (private_path, public_path):
        if target.exists() and not overwrite:
            raise InputFileError(target, "exists already; a key is never overwritten (remove it, or choose "
                                         "another name)")
    if not private_path.parent.is_dir():
        raise InputFileError(private_path, "the directory does not exist")
    key = ed25519.Ed25519PrivateKey.generate()
    private_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                    serialization.NoEncryption())
    public_pem = key.public_key().public_bytes(serialization.Encoding.PEM,
                                               serialization.PublicFormat.SubjectPublicKeyInfo)
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW | os.O_CLOEXEC
    for target, data, mode in ((private_path, private_pem, 0o600), (public_path, public_pem, 0o644)):
        fd = os.open(target, flags, mode)
        try:
            os.fchmod(fd, mode)
            os.write(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
    return private_path, public_path


def sign(key, data: bytes) -> bytes:
    """The Ed25519 signature (64 bytes) of ``data`` with a private key (object or PEM file)."""
    return load_private_key(key).sign(data)


def check_signature(root, manifest_bytes: bytes, version: int, key) -> None:
    """Raise :class:`SignatureError` unless ``STORE/manifest.json.v{version}.sig`` is a
    signature of ``manifest_bytes`` by ``key`` (a public key object or PEM file)."""
    public = load_public_key(key)
    root = Path(root)
    path = root / signature_name(version)
    who = f"key {key_fingerprint(public)}"
    try:
        with open(path, "rb") as fh:
            signature = fh.read(SIGNATURE_BYTES + 1)
    except FileNotFoundError:
        raise SignatureError(f"{root / MANIFEST}: store version {version} is not signed (no {path.name}); "
                             f"refused, as asked, for want of a signature by {who}") from None
    except OSError as exc:
        raise SignatureError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    from cryptography.exceptions import InvalidSignature

    try:
        if len(signature) != SIGNATURE_BYTES:
            raise InvalidSignature
        public.verify(signature, manifest_bytes)
    except InvalidSignature:
        raise SignatureError(f"{path}: does not sign {root / MANIFEST} with {who}: the manifest (or a tile it "
                             f"lists) was altered after signing, or another key signed it; do not use this "
                             f"store") from None


def load_signed_manifest(root, key) -> dict:
    """The store's manifest, read and checked as :func:`~geoidspline.store.format.load_manifest`
    does, and refused (:class:`SignatureError`) unless ``key`` signed its exact bytes."""
    root = Path(root)
    key = load_public_key(key)  # a bad key file is named before the store is read
    for attempt in range(3):
        data = read_manifest_bytes(root)
        manifest = parse_manifest(root / MANIFEST, data)
        validate_manifest(root / MANIFEST, manifest)
        try:
            check_signature(root, data, manifest["store_version"], key)
            return manifest
        except SignatureError:
            # a writer may have committed a new version (and removed this one's
            # signature) between the two reads: read again while the manifest moves
            if attempt == 2 or read_manifest_bytes(root) == data:
                raise
    raise AssertionError("unreachable")  # pragma: no cover


def write_signature(root, manifest_bytes: bytes, version: int, key) -> Path:
    """Write the signature of ``manifest_bytes`` as store version ``version``'s, flushed
    to disk (the caller commits the manifest afterwards); returns its path."""
    path = Path(root) / signature_name(version)
    signature = sign(key, manifest_bytes)
    path.unlink(missing_ok=True)  # an attempt at this version that never committed
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    try:
        os.write(fd, signature)
        os.fsync(fd)
    finally:
        os.close(fd)
    return path
