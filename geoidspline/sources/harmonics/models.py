"""Spherical-harmonic model files: ICGEM ``.gfc``, NGA ASCII coefficients and NGA's
ζ-to-N correction coefficients (CORRCOEF).

The readers are strict: anything that does not fit the format raises
:class:`~geoidspline.errors.InputFileError` whose message names the file and, for a bad
line, its line number (1-based, counted in the decompressed text). ``.gz`` files are read
directly (recognised by their magic bytes, whatever their name).

Coefficients are returned as fully normalised (4π, no Condon-Shortley phase) 2-D arrays
``C[n, m]``, ``S[n, m]`` of shape (nmax+1, nmax+1), zero where m > n or where the file
has no entry (degrees 0 and 1 may be absent).
"""

from __future__ import annotations

import gzip
import hashlib
import math
import re
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ...errors import InputFileError
from ...geodesy.ellipsoids import PERMANENT_TIDE, TIDE_SYSTEMS

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
            raise ValueError(f"unknown tide system {target!r}; expected one of {TIDE_SYSTEMS}")
        if self.tide_system is None:
            raise ValueError(f"{self.name}: tide system unknown, cannot convert to {target}")
        if target == self.tide_system:
            return self
        C = np.array(self.C)
        C[2, 0] = PERMANENT_TIDE.convert_c20(C[2, 0], self.tide_system, target)
        note = f"C̄20 converted from {self.tide_system} to {target} (IERS 2010 §6.2.2, k20={PERMANENT_TIDE.love_k20})"
        return replace(self, C=C, tide_system=target, notes=self.notes + (note,))

    def truncated(self, max_degree: int) -> "HarmonicModel":
        """The model cut to degree ``max_degree`` (≤ its own)."""
        if not 2 <= max_degree <= self.max_degree:
            raise ValueError(f"max_degree must be in 2..{self.max_degree}, got {max_degree}")
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
            raise ValueError(f"max_degree must be in 0..{self.max_degree}, got {max_degree}")
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


def _read_text(path) -> tuple[str, str]:
    """(decompressed text, sha256 of the file's bytes as stored)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputFileError(path, "file not found") from None
    except OSError as exc:
        raise InputFileError(path, f"cannot read file: {exc.strerror or exc}") from None
    digest = hashlib.sha256(raw).hexdigest()
    if raw[:2] == b"\x1f\x8b":
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError) as exc:
            raise InputFileError(path, f"corrupt or truncated gzip data: {exc}") from None
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError as exc:
        # latin-1 only in header comments is tolerated; data lines are checked anyway
        try:
            text = raw.decode("latin-1")
        except UnicodeDecodeError:  # pragma: no cover - latin-1 decodes everything
            raise InputFileError(path, f"not a text file ({exc})") from None
    if "\x00" in text:
        raise InputFileError(path, "not a text file (contains NUL bytes)")
    return text, digest


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
            raise InputFileError(
                self.path,
                f"{n_idx.size} coefficient(s) missing for {first_degree} <= n <= {self.nmax} "
                f"({where}): {shown}{more}",
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

    nmax = file_nmax if max_degree is None else int(max_degree)
    if not 2 <= nmax <= file_nmax:
        raise InputFileError(path, f"requested max_degree {max_degree} outside 2..{file_nmax} (the file's max_degree)")
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
        raise ValueError(f"tide_system must be one of {TIDE_SYSTEMS} or None, got {tide_system!r}")
    text, digest = _read_text(path)
    rows = list(_parse_columns(path, text, 6, max_degree, "n m C S sigmaC sigmaS"))
    if not rows:
        raise InputFileError(path, "no coefficient lines")
    nmax = max(r[1] for r in rows)
    if max_degree is not None and nmax < max_degree:
        raise InputFileError(path, f"requested max_degree {max_degree} but the file stops at degree {nmax}")
    if nmax < 2:
        raise InputFileError(path, f"the file stops at degree {nmax}; need at least degree 2")
    coll = _Collector(path, nmax, True)
    for lineno, n, m, (c, s, sc, ss) in rows:
        coll.add(lineno, n, m, c, s, sc, ss)
    coll.check_complete(2, "truncated file or incomplete model")
    tide, notes = _check_tide_system(path, name, coll.C[2, 0], tide_system, source_label, check_tide_system)
    return coll.model(name, gm, radius, tide, notes, digest)


_UNITS = {"cm": 0.01, "m": 1.0, "mm": 0.001}


def read_nga_correction(path, *, unit: str = "cm", name: str | None = None, max_degree: int | None = None) -> CorrectionModel:
    """Read NGA's ζ-to-N correction coefficients (CORRCOEF: ``n m C S`` per line, n from
    0, in centimetres; ``unit`` = "cm", "mm" or "m"). Every (n, m) with 0 ≤ n ≤ nmax must
    be present exactly once."""
    if unit not in _UNITS:
        raise ValueError(f"unit must be one of {sorted(_UNITS)}, got {unit!r}")
    text, digest = _read_text(path)
    rows = list(_parse_columns(path, text, 4, max_degree, "n m C S"))
    if not rows:
        raise InputFileError(path, "no coefficient lines")
    nmax = max(r[1] for r in rows)
    if max_degree is not None and nmax < max_degree:
        raise InputFileError(path, f"requested max_degree {max_degree} but the file stops at degree {nmax}")
    coll = _Collector(path, nmax, False)
    for lineno, n, m, (c, s) in rows:
        coll.add(lineno, n, m, c, s)
    coll.check_complete(0, "truncated file or incomplete correction model")
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


def read_model(path, **kwargs) -> HarmonicModel:
    """Read a model file, ICGEM or NGA, telling them apart by the ``end_of_head`` line."""
    text, _ = _read_text(path)
    if _GFC_HINT.search(text):
        return read_icgem(path, **kwargs)
    return read_nga(path, **kwargs)
