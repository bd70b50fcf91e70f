"""Spherical-harmonic model files: ICGEM ``.gfc``, NGA ASCII coefficients and NGA's
ζ-to-N correction coefficients (CORRCOEF).

The readers are strict: anything that does not fit the format raises
:class:`~geoidspline.errors.InputFileError` whose message names the file and, for a bad
line, its line number (1-based, counted in the decompressed text). ``.gz`` files are read
directly (recognised by their magic bytes, whatever their name).

Coefficients are returned as fully normalised (4π, no Condon-Shortley phase) 2-D arrays
``C[n, m]``, ``S[n, m]`` of shape (nmax+1, nmax+1), zero where m > n or where the file
has no entry (degrees 0 and 1 may be absent).

Before anything is allocated, a degree is checked against
:data:`~geoidspline.geodesy.limits.MAX_MODEL_DEGREE` and the number of coefficient lines
it needs against the lines the file has; afterwards every coefficient is checked
against its physical bound (:mod:`geoidspline.geodesy.limits`). A model must reach the
degree its header or its name declares (``egm96_to360`` ends at degree 360). Every
failure, including a broken gzip stream and out of memory, is an InputFileError.
"""

from __future__ import annotations

import functools
import gzip
import hashlib
import io
import math
import re
import warnings
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ...errors import InputFileError, ParameterError
from ...geodesy.ellipsoids import PERMANENT_TIDE, TIDE_SYSTEMS
from ...geodesy.limits import MAX_ABS_C20, MAX_ABS_COEFFICIENT, MAX_ABS_UNDULATION_M, MAX_MODEL_DEGREE
from ..files import reader_faults

__all__ = [
    "HarmonicModel",
    "CorrectionModel",
    "TideSystemWarning",
    "read_icgem",
    "read_nga",
    "read_nga_correction",
    "read_model",
    "NGA_CATALOGUE",
    "KNOWN_C20",
    "model_file_kind",
    "MAX_MODEL_TEXT_BYTES",
]


class TideSystemWarning(UserWarning):
    """A model's C̄20 contradicts the tide system its file or catalogue states."""


def _readonly(arr):
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class HarmonicModel:
    """A fully normalised spherical-harmonic gravity model.

    ``gm`` (m³/s²) and ``radius`` (m) are the model's own scaling constants;
    ``C``/``S`` have shape (max_degree+1, max_degree+1), indexed [n, m], read-only.
    ``tide_system`` is one of ``"tide_free"``, ``"zero_tide"``, ``"mean_tide"`` or None
    (unknown). ``notes`` records what the reader noticed (e.g. a corrected tide label).
    """

    name: str
    gm: float
    radius: float
    max_degree: int
    tide_system: str | None
    C: np.ndarray
    S: np.ndarray
    source_path: str | None = None
    sha256: str | None = None
    sigma_C: np.ndarray | None = None
    sigma_S: np.ndarray | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self):
        size = self.max_degree + 1
        for key in ("C", "S", "sigma_C", "sigma_S"):
            value = getattr(self, key)
            if value is None:
                continue
            value = _readonly(value)
            if value.shape != (size, size):
                raise ValueError(f"{key} must have shape {(size, size)}, got {value.shape}")
            object.__setattr__(self, key, value)
        if self.tide_system is not None and self.tide_system not in TIDE_SYSTEMS:
            raise ValueError(f"tide_system must be one of {TIDE_SYSTEMS} or None, got {self.tide_system!r}")
        if not (self.gm > 0 and self.radius > 0):
            raise ValueError(f"gm and radius must be positive, got {self.gm}, {self.radius}")
        object.__setattr__(self, "notes", tuple(self.notes))

    def with_tide_system(self, target: str) -> "HarmonicModel":
        """The same model with C̄20 converted to ``target`` tide system.

        Uses :data:`geoidspline.geodesy.PERMANENT_TIDE` (IERS Conventions 2010 §6.2.2,
        A0H0 = −1.39119e-8, k20 = 0.3 as NGA). Only C̄20 changes.
        """
        if target not in TIDE_SYSTEMS:
            raise ParameterError(f"unknown tide system {target!r}; expected one of {TIDE_SYSTEMS}")
        if self.tide_system is None:
            raise ParameterError(f"{self.name}: tide system unknown, cannot convert to {target}")
        if target == self.tide_system:
            return self
        C = np.array(self.C)
        C[2, 0] = PERMANENT_TIDE.convert_c20(C[2, 0], self.tide_system, target)
        note = f"C̄20 converted from {self.tide_system} to {target} (IERS 2010 §6.2.2, k20={PERMANENT_TIDE.love_k20})"
        return replace(self, C=C, tide_system=target, notes=self.notes + (note,))

    def truncated(self, max_degree: int) -> "HarmonicModel":
        """The model cut to degree ``max_degree`` (≤ its own)."""
        if not 2 <= max_degree <= self.max_degree:
            raise ParameterError(f"max_degree must be in 2..{self.max_degree}, got {max_degree}")
        if max_degree == self.max_degree:
            return self
        cut = slice(0, max_degree + 1)
        sig = {}
        for key in ("sigma_C", "sigma_S"):
            value = getattr(self, key)
            sig[key] = None if value is None else value[cut, cut]
        return replace(self, max_degree=max_degree, C=self.C[cut, cut], S=self.S[cut, cut], **sig)


@dataclass(frozen=True, eq=False)
class CorrectionModel:
    """NGA's ζ-to-N correction as spherical-harmonic coefficients (summed without (a/r)^n).

    ``C``/``S`` [n, m] are in the file's unit; ``unit_m`` converts them to metres
    (0.01 for CORRCOEF, which is in centimetres).
    """

    name: str
    max_degree: int
    C: np.ndarray
    S: np.ndarray
    unit_m: float
    source_path: str | None = None
    sha256: str | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self):
        size = self.max_degree + 1
        for key in ("C", "S"):
            value = _readonly(getattr(self, key))
            if value.shape != (size, size):
                raise ValueError(f"{key} must have shape {(size, size)}, got {value.shape}")
            object.__setattr__(self, key, value)
        object.__setattr__(self, "notes", tuple(self.notes))

    def truncated(self, max_degree: int) -> "CorrectionModel":
        if not 0 <= max_degree <= self.max_degree:
            raise ParameterError(f"max_degree must be in 0..{self.max_degree}, got {max_degree}")
        if max_degree == self.max_degree:
            return self
        cut = slice(0, max_degree + 1)
        return replace(self, max_degree=max_degree, C=self.C[cut, cut], S=self.S[cut, cut])


# --------------------------------------------------------------------------------------
# Known C̄20 values, to tell the tide system of a coefficient set from its numbers.
# EGM2008: NGA's EGM2008 web page / TideFree and ZeroTide files (the zero-tide value is
# tide free + 0.3·(−1.39119e-8), IERS 2010 §6.2.2). EGM96: the tide-free value of the NGA
# file; zero tide by the same rule (EGM96 report, Lemoine et al. 1998, §11.2).
_A0H0_K = PERMANENT_TIDE.love_k20 * PERMANENT_TIDE.a0h0
KNOWN_C20 = {
    "EGM2008": {"tide_free": -0.484165143790815e-3, "zero_tide": -0.484169317366974e-3},
    "EGM96": {"tide_free": -0.484165371736e-3, "zero_tide": -0.484165371736e-3 + _A0H0_K},
}
_C20_MATCH = 5e-16  # the files print 15 significant digits


def _check_tide_system(path, name, c20, declared, source_label, enabled):
    """Return (tide_system, notes) after comparing C̄20 with the known values."""
    if not enabled:
        return declared, ()
    key = None
    upper = (name or "").upper().replace("-", "")
    for candidate in KNOWN_C20:
        if candidate in upper:
            key = candidate
            break
    if key is None:
        return declared, ()
    found = [system for system, value in KNOWN_C20[key].items() if abs(c20 - value) <= _C20_MATCH]
    if not found:
        note = f"C̄20 = {c20!r} is none of the known {key} values; tide system kept as {declared}"
        return declared, (note,)
    actual = found[0]
    if declared == actual:
        return declared, (f"C̄20 checked: the {key} {actual} value, as {source_label} states",)
    if declared is None:
        note = f"tide system not stated; C̄20 is the {key} {actual} value: tide_system set to {actual}"
        return actual, (note,)
    note = (
        f"{source_label} says {declared} but C̄20 = {c20!r} is the {key} {actual} value "
        f"({KNOWN_C20[key][actual]!r}); tide_system set to {actual}"
    )
    warnings.warn(f"{path}: {note}", TideSystemWarning, stacklevel=3)
    return actual, (note,)


# --------------------------------------------------------------------------------------
# File access and line parsing


#: Largest decompressed text read (bytes): the reader holds the text in memory.
MAX_MODEL_TEXT_BYTES = 4 << 30

_GZIP_MAGIC = b"\x1f\x8b"


def _file_faults(reader):
    """Every fault while reading a model file ends as an InputFileError naming it."""

    @functools.wraps(reader)
    def wrapped(path, *args, **kwargs):
        with reader_faults(path):
            return reader(path, *args, **kwargs)

    return wrapped


def _read_text(path) -> tuple[str, str]:
    """(decompressed text, sha256 of the file's bytes as stored).

    A gzip file (by its magic bytes) is decompressed in blocks: a NUL byte or more than
    :data:`MAX_MODEL_TEXT_BYTES` stops it at once (a binary file or a compression bomb).
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "file not found" if not path.exists() else "not a regular file")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InputFileError(path, f"cannot read file: {exc.strerror or exc}") from None
    digest = hashlib.sha256(raw).hexdigest()
    if raw[:2] == _GZIP_MAGIC:
        raw = _gunzip(path, raw)
    elif b"\x00" in raw:
        raise InputFileError(path, "not a text file (contains NUL bytes)")
    # ASCII in practice; latin-1 decodes any byte (a stray one in a header comment),
    # and data lines are checked number by number anyway.
    return raw.decode("latin-1"), digest


def _gunzip(path, raw: bytes, limit: int = MAX_MODEL_TEXT_BYTES) -> bytes:
    """The decompressed bytes of a gzip file's content ``raw`` (all members), text only."""
    blocks, total = [], 0
    try:
        with gzip.GzipFile(fileobj=io.BytesIO(raw)) as fh:
            while block := fh.read(1 << 20):
                if b"\x00" in block:
                    raise InputFileError(path, "not a text file: its gzip content contains NUL bytes")
                total += len(block)
                if total > limit:
                    raise InputFileError(path, f"decompresses to more than {limit:,} bytes of text, "
                                         "more than this reader holds in memory")
                blocks.append(block)
    except (OSError, EOFError, zlib.error) as exc:  # BadGzipFile is an OSError
        raise InputFileError(path, f"corrupt or truncated gzip data: {exc}") from None
    return b"".join(blocks)


_NUMBER = r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eEdD][+-]?\d+)?"
_NGA_LINE = {6: re.compile(rf"^\s*\d+\s+\d+(?:\s+{_NUMBER}){{4}}\s*$"),
             4: re.compile(rf"^\s*\d+\s+\d+(?:\s+{_NUMBER}){{2}}\s*$")}
_ICGEM_HEAD = re.compile(r"^\s*(begin_of_head|end_of_head)\b", re.MULTILINE | re.IGNORECASE)
_ICGEM_KEY = re.compile(r"^\s*(earth_gravity_constant|gfc)\s", re.MULTILINE | re.IGNORECASE)


def model_file_kind(path, head_bytes: int = 1 << 16) -> str | None:
    """What a file holds, from its first ``head_bytes`` (decompressed when gzip):

    ``"icgem"`` (a ``begin_of_head``/``end_of_head`` header and ``gfc`` lines or the
    ``earth_gravity_constant`` key), ``"nga"`` (lines of ``n m C S sigmaC sigmaS``),
    ``"nga-correction"`` (lines of ``n m C S``), ``"corrupt gzip data: ..."`` when a gzip
    stream cannot be read, or None (not a model: a grid, or anything else).
    """
    path = Path(path)
    if not path.is_file():  # a FIFO would block, a device never end
        return None
    try:
        with open(path, "rb") as fh:
            head = fh.read(head_bytes)
            if head[:2] == _GZIP_MAGIC:
                fh.seek(0)
                with gzip.GzipFile(fileobj=fh) as gz:
                    head = gz.read(head_bytes)
    except (EOFError, zlib.error, gzip.BadGzipFile) as exc:
        return f"corrupt or truncated gzip data: {exc}"
    except OSError:
        return None
    if b"\x00" in head:
        return None
    text = head.decode("latin-1")
    if _ICGEM_HEAD.search(text) and _ICGEM_KEY.search(text):
        return "icgem"
    lines = text.splitlines()
    if len(head) == head_bytes and lines:
        lines = lines[:-1]  # the last line may be cut
    lines = [line for line in lines if line.strip()][:5]
    for columns, kind in ((6, "nga"), (4, "nga-correction")):
        if lines and all(_NGA_LINE[columns].match(line) for line in lines):
            return kind
    return None


def _coefficient_count(nmax: int, first_degree: int) -> int:
    """How many (n, m) with first_degree <= n <= nmax, 0 <= m <= n."""
    return (nmax + 1) * (nmax + 2) // 2 - first_degree * (first_degree + 1) // 2


def _check_degree(path, nmax: int, where: str) -> None:
    if nmax > MAX_MODEL_DEGREE:
        raise InputFileError(
            path, f"{where} {nmax} is beyond {MAX_MODEL_DEGREE:,}, the largest geoidspline reads "
            "(1 arc-minute; no published gravity model comes near): a corrupt header or line"
        )


#: Below this the coefficient arrays are allocated anyway, so that the collector names
#: each missing coefficient; above it a file too short for its degree is refused first.
_CHEAP_ALLOCATION_BYTES = 64 << 20


def _check_line_count(path, nmax: int, first_degree: int, lines: int, nbytes: int, what: str, last=None) -> None:
    """Refuse, before allocating, a file with fewer lines than degree nmax needs (when the
    arrays for nmax would be large: small ones are allocated and the missing named)."""
    needed = _coefficient_count(nmax, first_degree)
    if lines < needed and 5 * 8 * (nmax + 1) ** 2 > _CHEAP_ALLOCATION_BYTES:
        tail = f"; its last line is of degree {last}" if last is not None else ""
        raise InputFileError(
            path, f"{what} {nmax} needs {needed:,} coefficient lines (n = {first_degree}..{nmax}), but the file "
            f"has {lines:,} lines in {nbytes:,} bytes{tail}: a truncated file, or a wrong degree",
        )


def _check_coefficients(path, C, S, line_of) -> None:
    """Refuse fully normalised coefficients beyond their physical bound (degree >= 2)."""
    n = np.arange(C.shape[0])[:, None]
    bound = np.where(n >= 2, MAX_ABS_COEFFICIENT, np.inf) * np.ones_like(C)
    bound[2:3, 0] = MAX_ABS_C20
    for label, values in (("C", C), ("S", S)):
        excess = np.abs(values) / bound
        worst = np.unravel_index(int(np.argmax(excess)), excess.shape)
        if excess[worst] > 1.0:
            nn, mm = (int(v) for v in worst)
            raise InputFileError(
                path, f"line {int(line_of[nn, mm])}: {label}̄ of n={nn} m={mm} is {float(values[worst])!r}, beyond "
                f"{bound[worst]:.3g}, the physical bound of a fully normalised coefficient (one such "
                f"coefficient alone would make the geoid exceed ±{MAX_ABS_UNDULATION_M:g} m): a corrupt value, "
                "or coefficients that are not fully normalised",
            )


def _parse_float(path, lineno, token, what):
    try:
        value = float(token.replace("D", "e").replace("d", "e"))
    except ValueError:
        raise InputFileError(path, f"line {lineno}: {what} {token!r} is not a number") from None
    if not math.isfinite(value):
        raise InputFileError(path, f"line {lineno}: {what} {token!r} is not finite")
    return value


def _parse_int(path, lineno, token, what):
    try:
        return int(token)
    except ValueError:
        raise InputFileError(path, f"line {lineno}: {what} {token!r} is not an integer") from None


class _Collector:
    """Gathers (n, m, C, S[, σC, σS]) entries, rejects duplicates, checks completeness."""

    def __init__(self, path, nmax, with_sigma):
        self.path = path
        self.nmax = nmax
        size = nmax + 1
        self.C = np.zeros((size, size))
        self.S = np.zeros((size, size))
        self.sC = np.zeros((size, size)) if with_sigma else None
        self.sS = np.zeros((size, size)) if with_sigma else None
        self.line_of = np.zeros((size, size), dtype=np.int64)

    def add(self, lineno, n, m, c, s, sc=None, ss=None):
        if self.line_of[n, m]:
            raise InputFileError(
                self.path,
                f"line {lineno}: duplicate coefficient n={n} m={m} (first on line {self.line_of[n, m]})",
            )
        if m == 0 and s != 0.0:
            raise InputFileError(self.path, f"line {lineno}: S̄ of n={n} m=0 must be 0, found {s!r}")
        self.line_of[n, m] = lineno
        self.C[n, m] = c
        self.S[n, m] = s
        if self.sC is not None and sc is not None:
            self.sC[n, m] = sc
            self.sS[n, m] = ss

    def model(self, name, gm, radius, tide_system, notes, digest) -> "HarmonicModel":
        """The collected coefficients as a :class:`HarmonicModel` of this file."""
        return HarmonicModel(
            name=name, gm=float(gm), radius=float(radius), max_degree=self.nmax, tide_system=tide_system,
            C=self.C, S=self.S, source_path=str(self.path), sha256=digest,
            sigma_C=self.sC, sigma_S=self.sS, notes=notes,
        )

    def check_complete(self, first_degree, where):
        n_idx, m_idx = np.nonzero(np.tril(self.line_of == 0))
        keep = n_idx >= first_degree
        n_idx, m_idx = n_idx[keep], m_idx[keep]
        if n_idx.size:
            shown = ", ".join(f"(n={n}, m={m})" for n, m in zip(n_idx[:5], m_idx[:5]))
            more = f" and {n_idx.size - 5} more" if n_idx.size > 5 else ""
            found = np.nonzero(self.line_of.any(axis=1))[0]
            stops = ""
            if found.size and n_idx.min() > found.max():
                stops = f"; the file stops at degree {found.max()}, below the declared {self.nmax}"
            raise InputFileError(
                self.path,
                f"{n_idx.size} coefficient(s) missing for {first_degree} <= n <= {self.nmax} "
                f"({where}): {shown}{more}{stops}",
            )


# --------------------------------------------------------------------------------------
# ICGEM


_ICGEM_TIME_KEYS = {"gfct", "trnd", "acos", "asin", "dot"}
_ICGEM_TIDE = {
    "tide_free": "tide_free",
    "zero_tide": "zero_tide",
    "mean_tide": "mean_tide",
    "tide-free": "tide_free",
    "zero-tide": "zero_tide",
    "mean-tide": "mean_tide",
}


@_file_faults
def read_icgem(path, *, max_degree: int | None = None, check_tide_system: bool = True) -> HarmonicModel:
    """Read an ICGEM ``.gfc`` file (static field only).

    Header keys used: ``modelname``, ``earth_gravity_constant`` (m³/s²), ``radius`` (m),
    ``max_degree``, ``norm`` (``fully_normalized``, the ICGEM default when absent;
    ``unnormalized`` is rejected: unnormalised coefficients of high degree are not
    representable in double precision, so this reader does not convert them),
    ``tide_system``, ``errors``. The header ends at ``end_of_head`` and starts after
    ``begin_of_head`` when that marker is present (free text before the keys is allowed).

    Data lines ``gfc n m C S [sigmaC sigmaS]``; Fortran ``D`` exponents are accepted.
    Time-variable lines (``gfct``, ``trnd``, ``acos``, ``asin``) are rejected. Every
    (n, m) with 2 ≤ n ≤ max_degree must be present exactly once.

    ``max_degree`` truncates on reading (lines above it are skipped after a syntax check).
    With ``check_tide_system``, C̄20 is compared with the known EGM96/EGM2008 values
    (:data:`KNOWN_C20`); a contradiction with the header gives a :class:`TideSystemWarning`,
    the model's ``tide_system`` follows the coefficient and the fact is kept in ``notes``.
    """
    text, digest = _read_text(path)
    lines = text.splitlines()
    begin = None
    end = None
    for idx, line in enumerate(lines):
        token = line.split(None, 1)[0].lower() if line.strip() else ""
        if token == "begin_of_head" and begin is None:
            begin = idx
        elif token == "end_of_head":
            end = idx
            break
    if end is None:
        raise InputFileError(path, "no 'end_of_head' line: not an ICGEM file, or its header is truncated")
    header = {}
    header_line = {}
    start = 0 if begin is None else begin + 1
    known = {
        "product_type",
        "modelname",
        "earth_gravity_constant",
        "radius",
        "max_degree",
        "norm",
        "tide_system",
        "errors",
    }
    for idx in range(start, end):
        parts = lines[idx].split()
        if len(parts) >= 2 and parts[0].lower() in known:
            key = parts[0].lower()
            if key in header:
                raise InputFileError(path, f"line {idx + 1}: header key {key!r} repeated (first on line {header_line[key]})")
            header[key] = parts[1]
            header_line[key] = idx + 1
        elif len(parts) == 1 and parts[0].lower() in known:
            raise InputFileError(path, f"line {idx + 1}: header key {parts[0]!r} has no value")
    for key in ("earth_gravity_constant", "radius", "max_degree"):
        if key not in header:
            raise InputFileError(path, f"header lacks the mandatory key {key!r}")
    gm = _parse_float(path, header_line["earth_gravity_constant"], header["earth_gravity_constant"], "earth_gravity_constant")
    radius = _parse_float(path, header_line["radius"], header["radius"], "radius")
    if gm <= 0 or radius <= 0:
        raise InputFileError(path, "earth_gravity_constant and radius must be positive")
    file_nmax = _parse_int(path, header_line["max_degree"], header["max_degree"], "max_degree")
    if file_nmax < 2:
        raise InputFileError(path, f"line {header_line['max_degree']}: max_degree must be >= 2, got {file_nmax}")
    norm = header.get("norm", "fully_normalized").lower()
    if norm != "fully_normalized":
        where = f"line {header_line['norm']}: " if "norm" in header_line else ""
        raise InputFileError(
            path,
            f"{where}norm {header.get('norm')!r} is not supported: only fully_normalized "
            "coefficients are read (unnormalised ones are not converted)",
        )
    tide_raw = header.get("tide_system")
    if tide_raw is None:
        declared = None
    elif tide_raw.lower() in _ICGEM_TIDE:
        declared = _ICGEM_TIDE[tide_raw.lower()]
    elif tide_raw.lower() == "unknown":
        declared = None
    else:
        raise InputFileError(path, f"line {header_line['tide_system']}: unknown tide_system {tide_raw!r}")
    name = header.get("modelname", Path(path).name)
    errors_kind = header.get("errors", "no").lower()
    with_sigma = errors_kind not in ("no",)

    _check_degree(path, file_nmax, f"line {header_line['max_degree']}: max_degree")
    nmax = file_nmax if max_degree is None else int(max_degree)
    if not 2 <= nmax <= file_nmax:
        raise InputFileError(path, f"requested max_degree {max_degree} outside 2..{file_nmax} (the file's max_degree)")
    data_lines = [idx for idx in range(end + 1, len(lines)) if lines[idx].strip()]
    last = lines[data_lines[-1]].split() if data_lines else []
    _check_line_count(
        path, file_nmax, 2, len(data_lines), len(text), f"line {header_line['max_degree']}: max_degree",
        last=last[1] if len(last) > 1 and last[1].isdigit() else None,
    )
    coll = _Collector(path, nmax, with_sigma)
    for idx in range(end + 1, len(lines)):
        line = lines[idx]
        parts = line.split()
        if not parts:
            continue
        lineno = idx + 1
        key = parts[0].lower()
        if key in _ICGEM_TIME_KEYS:
            raise InputFileError(
                path,
                f"line {lineno}: time-variable coefficient line {parts[0]!r} is not supported "
                "(only static 'gfc' models are read)",
            )
        if key != "gfc":
            raise InputFileError(path, f"line {lineno}: unknown data key {parts[0]!r} (expected 'gfc')")
        if len(parts) not in (5, 7):
            raise InputFileError(
                path,
                f"line {lineno}: expected 'gfc n m C S [sigmaC sigmaS]' (5 or 7 columns), found {len(parts)}",
            )
        n = _parse_int(path, lineno, parts[1], "degree n")
        m = _parse_int(path, lineno, parts[2], "order m")
        if not 0 <= m <= n:
            raise InputFileError(path, f"line {lineno}: need 0 <= m <= n, got n={n} m={m}")
        if n > file_nmax:
            raise InputFileError(path, f"line {lineno}: degree {n} exceeds the header's max_degree {file_nmax}")
        c = _parse_float(path, lineno, parts[3], "C")
        s = _parse_float(path, lineno, parts[4], "S")
        sc = ss = None
        if len(parts) == 7:
            sc = _parse_float(path, lineno, parts[5], "sigma C")
            ss = _parse_float(path, lineno, parts[6], "sigma S")
        if n > nmax:
            continue
        coll.add(lineno, n, m, c, s, sc, ss)
    coll.check_complete(2, "truncated file or incomplete model")
    _check_coefficients(path, coll.C, coll.S, coll.line_of)
    tide, notes = _check_tide_system(path, name, coll.C[2, 0], declared, "the header's tide_system", check_tide_system)
    if declared is None and tide is None:
        notes = notes + ("tide_system not stated in the header",)
    return coll.model(name, gm, radius, tide, notes, digest)


# --------------------------------------------------------------------------------------
# NGA ASCII

# NGA's standard file names and the constants that go with them (the files have no
# header). EGM96: Lemoine et al. (1998), NASA/TP-1998-206861; NGA README. EGM2008:
# Pavlis et al. (2012), JGR 117:B04406; NGA's EGM2008 README.
NGA_CATALOGUE = {
    "egm96": ("EGM96", 3.986004415e14, 6378136.3, "tide_free"),
    "egm96_to360": ("EGM96", 3.986004415e14, 6378136.3, "tide_free"),
    "egm2008_to2190_tidefree": ("EGM2008", 3.986004415e14, 6378136.3, "tide_free"),
    "egm2008_to2190_zerotide": ("EGM2008", 3.986004415e14, 6378136.3, "zero_tide"),
}


def _nga_stem(path) -> str:
    stem = Path(path).name.lower()
    for suffix in (".gz", ".z", ".ascii", ".txt", ".dat"):
        if stem.endswith(suffix):
            stem = stem[: -len(suffix)]
    return stem


def _nga_lookup(path):
    stem = _nga_stem(path)
    if stem in NGA_CATALOGUE:
        return NGA_CATALOGUE[stem]
    # excerpts and renamed copies keep NGA's name as a prefix (..._TideFree_first30)
    for key in sorted(NGA_CATALOGUE, key=len, reverse=True):
        if stem.startswith(key + "_") or stem.startswith(key + "-") or stem.startswith(key + "."):
            return NGA_CATALOGUE[key]
    return None


#: A degree a file name declares, NGA style: "egm96_to360", "Zeta-to-N_to2160_egm2008".
_NAMED_DEGREE = re.compile(r"(?:^|[_.-])to(\d+)(?=$|[_.-])")
#: Names that say the file is a part of the model ("..._TideFree_first30").
_EXCERPT_NAME = re.compile(r"first\d*|excerpt|trunc|subset|sample")
#: Degrees of catalogued names that do not spell it ("egm96": NGA's EGM96 to 360).
_CATALOGUE_DEGREE = {"egm96": 360}


def _named_degree(path) -> int | None:
    """The degree the file's name declares, or None (no degree, or an excerpt by name)."""
    stem = _nga_stem(path)
    if _EXCERPT_NAME.search(stem):
        return None
    found = _NAMED_DEGREE.search(stem)
    return int(found.group(1)) if found else _CATALOGUE_DEGREE.get(stem)


def _check_named_degree(path, nmax: int, max_degree, what: str) -> None:
    """Refuse a file that stops below the degree its name declares (a truncated copy),
    unless the caller truncates explicitly with ``max_degree``."""
    declared = _named_degree(path)
    if declared is None or max_degree is not None or nmax >= declared:
        return
    raise InputFileError(
        path, f"the file name declares degree {declared} but the {what} stops at degree {nmax}: a truncated "
        f"copy. To use it as a degree-{nmax} {what} on purpose, pass max_degree={nmax}",
    )


def _parse_columns(path, text, ncols, max_degree, what):
    """Yield (lineno, n, m, values...) from whitespace-separated NGA lines."""
    for idx, line in enumerate(text.splitlines()):
        parts = line.split()
        if not parts:
            continue
        lineno = idx + 1
        if len(parts) != ncols:
            raise InputFileError(path, f"line {lineno}: expected {ncols} columns ({what}), found {len(parts)}")
        n = _parse_int(path, lineno, parts[0], "degree n")
        m = _parse_int(path, lineno, parts[1], "order m")
        if not 0 <= m <= n:
            raise InputFileError(path, f"line {lineno}: need 0 <= m <= n, got n={n} m={m}")
        if max_degree is not None and n > max_degree:
            continue
        values = [_parse_float(path, lineno, tok, label) for tok, label in zip(parts[2:], ("C", "S", "sigma C", "sigma S"))]
        yield lineno, n, m, values


def _rows_and_degree(path, text, ncols, what, max_degree, kind, first_degree):
    """The coefficient rows of an NGA-style text and the degree they reach, checked once
    for both readers: a degree within bounds, at least ``max_degree`` when asked, the
    degree the file's name declares, and a line count that fits the degree."""
    rows = list(_parse_columns(path, text, ncols, max_degree, what))
    if not rows:
        raise InputFileError(path, "no coefficient lines")
    last_line, nmax = max(((r[0], r[1]) for r in rows), key=lambda r: r[1])
    _check_degree(path, nmax, f"line {last_line}: degree")
    if max_degree is not None and nmax < max_degree:
        raise InputFileError(path, f"requested max_degree {max_degree} but the file stops at degree {nmax}")
    if nmax < first_degree:
        raise InputFileError(path, f"the file stops at degree {nmax}; need at least degree {first_degree}")
    _check_named_degree(path, nmax, max_degree, kind)
    _check_line_count(path, nmax, first_degree, len(rows), len(text), f"line {last_line}: degree")
    return rows, nmax


@_file_faults
def read_nga(
    path,
    *,
    name: str | None = None,
    gm: float | None = None,
    radius: float | None = None,
    tide_system: str | None = None,
    max_degree: int | None = None,
    check_tide_system: bool = True,
) -> HarmonicModel:
    """Read NGA's headerless ASCII coefficients: ``n m C S sigmaC sigmaS`` per line.

    The model constants come from :data:`NGA_CATALOGUE` by file name (NGA's standard
    names, with ``.gz``/``.ascii`` stripped; a name that starts with a catalogued one, such
    as ``EGM2008_to2190_TideFree_first30``, matches it); the keywords override them and
    are required for other names. The degree is the largest n in the file (or
    ``max_degree``, which truncates); every (n, m) with 2 ≤ n ≤ that degree must be
    present exactly once. C̄20 is checked as in :func:`read_icgem`.
    """
    entry = _nga_lookup(path)
    cat_name, cat_gm, cat_radius, cat_tide = entry if entry else (None, None, None, None)
    name = name or cat_name
    gm = gm if gm is not None else cat_gm
    radius = radius if radius is not None else cat_radius
    source_label = "the caller" if tide_system is not None else "NGA's file name"
    tide_system = tide_system if tide_system is not None else cat_tide
    missing = [k for k, v in (("name", name), ("gm", gm), ("radius", radius)) if v is None]
    if missing:
        raise InputFileError(
            path,
            f"not one of NGA's standard file names ({', '.join(sorted(NGA_CATALOGUE))}): "
            f"pass {', '.join(missing)} (and tide_system) explicitly",
        )
    if tide_system is not None and tide_system not in TIDE_SYSTEMS:
        raise ParameterError(f"tide_system must be one of {TIDE_SYSTEMS} or None, got {tide_system!r}")
    text, digest = _read_text(path)
    rows, nmax = _rows_and_degree(path, text, 6, "n m C S sigmaC sigmaS", max_degree, "model", 2)
    coll = _Collector(path, nmax, True)
    for lineno, n, m, (c, s, sc, ss) in rows:
        coll.add(lineno, n, m, c, s, sc, ss)
    coll.check_complete(2, "truncated file or incomplete model")
    _check_coefficients(path, coll.C, coll.S, coll.line_of)
    tide, notes = _check_tide_system(path, name, coll.C[2, 0], tide_system, source_label, check_tide_system)
    return coll.model(name, gm, radius, tide, notes, digest)


_UNITS = {"cm": 0.01, "m": 1.0, "mm": 0.001}


@_file_faults
def read_nga_correction(path, *, unit: str = "cm", name: str | None = None, max_degree: int | None = None) -> CorrectionModel:
    """Read NGA's ζ-to-N correction coefficients (CORRCOEF: ``n m C S`` per line, n from
    0, in centimetres; ``unit`` = "cm", "mm" or "m"). Every (n, m) with 0 ≤ n ≤ nmax must
    be present exactly once."""
    if unit not in _UNITS:
        raise ParameterError(f"unit must be one of {sorted(_UNITS)}, got {unit!r}")
    text, digest = _read_text(path)
    rows, nmax = _rows_and_degree(path, text, 4, "n m C S", max_degree, "correction", 0)
    coll = _Collector(path, nmax, False)
    for lineno, n, m, (c, s) in rows:
        coll.add(lineno, n, m, c, s)
    coll.check_complete(0, "truncated file or incomplete correction model")
    limit = MAX_ABS_UNDULATION_M / _UNITS[unit]
    worst = np.unravel_index(int(np.argmax(np.maximum(np.abs(coll.C), np.abs(coll.S)))), coll.C.shape)
    if max(abs(coll.C[worst]), abs(coll.S[worst])) > limit:
        n, m = (int(v) for v in worst)
        raise InputFileError(
            path, f"line {int(coll.line_of[n, m])}: the coefficient of n={n} m={m} is beyond {limit:g} {unit}: "
            f"no part of N exceeds ±{MAX_ABS_UNDULATION_M:g} m (a corrupt value, or a wrong unit)",
        )
    return CorrectionModel(
        name=name or Path(path).name,
        max_degree=nmax,
        C=coll.C,
        S=coll.S,
        unit_m=_UNITS[unit],
        source_path=str(path),
        sha256=digest,
    )


_GFC_HINT = re.compile(r"^\s*end_of_head\b", re.MULTILINE | re.IGNORECASE)


@_file_faults
def read_model(path, **kwargs) -> HarmonicModel:
    """Read a model file, ICGEM or NGA, telling them apart by content (:func:`model_file_kind`,
    else an ``end_of_head`` line anywhere in the text)."""
    kind = model_file_kind(path)
    if kind == "icgem":
        return read_icgem(path, **kwargs)
    if kind == "nga":
        return read_nga(path, **kwargs)
    text, _ = _read_text(path)  # the reader's own rule for anything else
    if _GFC_HINT.search(text):
        return read_icgem(path, **kwargs)
    return read_nga(path, **kwargs)
