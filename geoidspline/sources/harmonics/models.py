"""Spherical-harmonic model files: ICGEM ``.gfc``, NGA ASCII coefficients and NGA's
ζ-to-N correction coefficients (EGM96's CORRCOEF, EGM2008's Zeta-to-N_to2160_egm2008).

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
import itertools
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
    "correction_unit",
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
# File access: the decompressed text in blocks of whole lines, parsed block by block


#: Largest decompressed text a model file may have (bytes): more is a compression bomb
#: or not a model (EGM2008 to degree 2190 has 243 MB).
MAX_MODEL_TEXT_BYTES = 4 << 30

#: The text is parsed in blocks of about this many bytes, each cut at a line end: memory
#: follows the coefficients (40 bytes a line), never the text (100 bytes a line).
_BLOCK_BYTES = 8 << 20

_GZIP_MAGIC = b"\x1f\x8b"


def _file_faults(reader):
    """Every fault while reading a model file ends as an InputFileError naming it."""

    @functools.wraps(reader)
    def wrapped(path, *args, **kwargs):
        with reader_faults(path):
            return reader(path, *args, **kwargs)

    return wrapped


class _Hashed:
    """A binary file whose bytes feed a sha256 as they are read."""

    def __init__(self, fh):
        self._fh = fh
        self._digest = hashlib.sha256()
        self._read = self._told = 0

    def read(self, size=-1):
        data = self._fh.read(size)
        self._digest.update(data)
        self._read += len(data)
        return data

    def advance(self) -> int:
        """Bytes read since the last call."""
        done, self._told = self._read - self._told, self._read
        return done

    def hexdigest(self) -> str:
        """The digest of the whole file (what was not read yet is read now)."""
        while self.read(1 << 20):
            pass
        return self._digest.hexdigest()


class _Text:
    """The text of a model file, plain or gzip (by its magic bytes, whatever its name),
    read in blocks that end at a line end. After :meth:`blocks` is exhausted, ``nbytes``
    is the decompressed size and ``sha256`` the digest of the file's bytes as stored.

    A NUL byte or more than :data:`MAX_MODEL_TEXT_BYTES` stops it at once (a binary
    file or a compression bomb)."""

    def __init__(self, path, block_bytes: int | None = None, limit: int = MAX_MODEL_TEXT_BYTES):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputFileError(self.path, "file not found" if not self.path.exists() else "not a regular file")
        self.block_bytes = _BLOCK_BYTES if block_bytes is None else block_bytes
        self.limit = limit
        self.nbytes = 0
        self.sha256 = None

    def blocks(self, advance=None):
        """The text's blocks; ``advance(n)`` is told of each ``n`` bytes of the file read."""
        path = self.path
        try:
            fh = open(path, "rb")
        except OSError as exc:
            raise InputFileError(path, f"cannot read file: {exc.strerror or exc}") from None
        with fh:
            gz = fh.read(2) == _GZIP_MAGIC
            fh.seek(0)
            hashed = _Hashed(fh)
            stream = gzip.GzipFile(fileobj=hashed, mode="rb") if gz else hashed
            pending = []
            size = min(1 << 16, self.block_bytes)  # growing: a header-only file stays small
            while True:
                try:
                    block = stream.read(size)
                    size = min(2 * size, self.block_bytes)
                except (OSError, EOFError, zlib.error) as exc:  # BadGzipFile is an OSError
                    if gz:
                        raise InputFileError(path, f"corrupt or truncated gzip data: {exc}") from None
                    raise InputFileError(path, f"cannot read file: {exc.strerror or exc}") from None
                if not block:
                    break
                if b"\x00" in block:
                    raise InputFileError(path, "not a text file: its gzip content contains NUL bytes" if gz
                                         else "not a text file (contains NUL bytes)")
                self.nbytes += len(block)
                if self.nbytes > self.limit:
                    raise InputFileError(path, f"has more than {self.limit:,} bytes of text, more than any model "
                                         "file (a compression bomb, or not a model)")
                cut = block.rfind(b"\n") + 1
                if cut == 0:  # no line end yet: a long line continues
                    pending.append(block)
                    continue
                pending.append(block[:cut])
                if advance is not None:
                    advance(hashed.advance())
                yield b"".join(pending)
                pending = [block[cut:]] if cut < len(block) else []
            if pending:
                yield b"".join(pending)
            self.sha256 = hashed.hexdigest()
            if advance is not None:
                advance(hashed.advance())


# Separators that str.splitlines() or str.split() honour and bytes do not (VT, FF,
# FS..US, NEL, NBSP, a CR not followed by LF): a block holding one is parsed line by line
# in Python, so that line numbers and tokens stay those of the text.
_ODD = np.zeros(256, dtype=bool)
_ODD[[0x0B, 0x0C, 0x1C, 0x1D, 0x1E, 0x1F, 0x85, 0xA0]] = True
_SPACE = np.zeros(256, dtype=bool)
_SPACE[[9, 10, 13, 32]] = True
_DIGIT = np.zeros(256, dtype=bool)
_DIGIT[48:58] = True
_FORTRAN_EXPONENT = bytes.maketrans(b"Dd", b"Ee")


def _has_odd_separators(buf: np.ndarray) -> bool:
    if _ODD[buf].any():
        return True
    cr = np.flatnonzero(buf[:-1] == 13)
    return bool((buf[cr + 1] != 10).any() or (buf.size and buf[-1] == 13))


def _line_count(block: bytes, odd: bool) -> int:
    """Lines in a block that ends at a line end, counted as str.splitlines() counts them."""
    if odd:
        return len(block.decode("latin-1").splitlines())
    return block.count(b"\n")


@dataclass(frozen=True)
class _Layout:
    """How the data lines of one format read.

    ``widths``: the token counts a line may have; ``key``: the first token (ICGEM's
    ``gfc``) or None; ``values``: how many numbers a row keeps after n and m (missing
    ones are 0); ``max_n``: the largest degree a line may have; ``keep_n``: rows above
    it are checked and dropped (truncation on reading); ``line_rule(lineno, parts)``:
    the row of one line, by the strict per-line rules (raising the file's message for a
    bad line), or None for a line that is skipped.
    """

    widths: tuple
    key: bytes | None
    values: int
    max_n: int
    keep_n: int
    line_rule: object


class _Rows:
    """Rows (line, n, m, values) gathered block by block into compact arrays."""

    def __init__(self, layout: _Layout):
        self.layout = layout
        self.parts = []
        self.parsed = 0  # rows read, kept or not (the line count checked against a degree)
        self.last_n = None

    def add(self, line, n, m, values):
        if n.size:
            self.parsed += n.size
            self.last_n = int(n[-1])
            keep = n <= self.layout.keep_n
            if not keep.all():
                line, n, m, values = line[keep], n[keep], m[keep], values[keep]
            self.parts.append((line, n, m, values))

    def arrays(self):
        """(line, n, m, values[rows, k]) of the kept rows, in file order."""
        if not self.parts:
            empty = np.zeros(0, dtype=np.int64)
            return empty, empty, empty, np.zeros((0, self.layout.values))
        columns = [np.concatenate(col) for col in zip(*self.parts)]
        self.parts = []
        return tuple(columns)


def _fast_block(layout: _Layout, block: bytes, first_line: int, buf: np.ndarray):
    """The rows of a regular block, parsed by numpy at once; None when anything in it is
    irregular (the block is then read line by line, which names the first bad line).

    Regular: every non-blank line has the same number of whitespace-separated tokens,
    one of ``layout.widths``; the key column (if any) is the key; n and m are digit
    strings; every number is finite and numpy's text parser (correctly rounded, as
    Python's float()) reads exactly one number per token (it refuses what float()
    refuses but for the non-finite spellings, which end in the per-line reader)."""
    if layout.key is not None:
        block = block.lower()  # keys are case-insensitive; the exponent letter either way
    if b"d" in block or b"D" in block:
        block = block.translate(_FORTRAN_EXPONENT)
    if layout.key is not None or buf is None:
        buf = np.frombuffer(block, dtype=np.uint8)  # (letters changed, spaces did not)
    space = _SPACE[buf]
    starts = ~space
    starts[1:] &= space[:-1]
    starts = np.flatnonzero(starts)
    ends = space[1:] & ~space[:-1]
    ends = np.flatnonzero(ends) + 1
    if buf.size and not space[-1]:
        ends = np.append(ends, buf.size)
    if ends.size != starts.size:
        return None
    token_line = np.searchsorted(np.flatnonzero(buf == 10), starts)
    for width in layout.widths:
        if starts.size % width:
            continue
        grid = token_line.reshape(-1, width)
        if (grid[:, 0] == grid[:, -1]).all() and (grid[1:, 0] > grid[:-1, -1]).all():
            break
    else:
        return None
    first = 0
    if layout.key is not None:
        first = 1
        key = starts[0::width]
        if not ((ends[0::width] - key == len(layout.key)).all()
                and all((buf[key + i] == c).all() for i, c in enumerate(layout.key))):
            return None
        block = block.replace(layout.key, b" " * len(layout.key))
    # n and m: digits only (int() takes a sign too, and underscores: the per-line reader)
    for column in (first, first + 1):
        begin, stop = starts[column::width], ends[column::width]
        for offset in range(int((stop - begin).max(initial=0))):
            at = begin + offset
            inside = at < stop
            if not _DIGIT[buf[at[inside]]].all():
                return None
    try:
        with warnings.catch_warnings():  # numpy < 2.3 warns where later ones raise
            warnings.simplefilter("error", DeprecationWarning)
            numbers = np.fromstring(block, sep=" ")
    except (ValueError, DeprecationWarning):
        return None
    if numbers.size != starts.size - (starts.size // width) * first:
        return None
    table = numbers.reshape(-1, width - first)
    n, m = table[:, 0], table[:, 1]
    if table.size and not (((m <= n) & (n <= layout.max_n)).all() and np.isfinite(table).all()):
        return None
    values = np.zeros((table.shape[0], layout.values))
    k = min(layout.values, width - first - 2)
    values[:, :k] = table[:, 2:2 + k]
    return first_line + 1 + grid[:, 0], n.astype(np.int64), m.astype(np.int64), values


def _slow_block(layout: _Layout, block: bytes, first_line: int):
    """The rows of a block by the per-line rules (the first bad line raises)."""
    rows = []
    for idx, line in enumerate(block.decode("latin-1").splitlines()):
        parts = line.split()
        if parts:
            row = layout.line_rule(first_line + idx + 1, parts)
            if row is not None:
                rows.append(row)
    k = layout.values
    if not rows:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty, empty, np.zeros((0, k))
    line = np.array([r[0] for r in rows], dtype=np.int64)
    n = np.array([r[1] for r in rows], dtype=np.int64)
    m = np.array([r[2] for r in rows], dtype=np.int64)
    values = np.array([r[3:3 + k] for r in rows], dtype=np.float64).reshape(len(rows), k)
    return line, n, m, values


def _read_rows(layout: _Layout, blocks, first_line: int = 0) -> _Rows:
    """Every data row of ``blocks`` (text after ``first_line`` lines), checked."""
    rows = _Rows(layout)
    for block in blocks:
        buf = np.frombuffer(block, dtype=np.uint8)
        odd = _has_odd_separators(buf)
        part = None if odd else _fast_block(layout, block, first_line, buf)
        rows.add(*(part if part is not None else _slow_block(layout, block, first_line)))
        first_line += _line_count(block, odd)
    return rows


# --------------------------------------------------------------------------------------
# Recognising a model file and checking what it declares

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

    def add_rows(self, line, n, m, values):
        """Place rows (file line, n, m, values C, S[, σC, σS]) read in file order. The first
        fault in file order is refused: a repeated (n, m) or a non-zero S̄ of order 0."""
        size = self.nmax + 1
        flat = n * size + m
        faults = []
        if np.bincount(flat, minlength=size * size).max(initial=0) > 1:
            order = np.argsort(flat, kind="stable")
            ordered = flat[order]
            repeats = order[1:][ordered[1:] == ordered[:-1]]
            k = repeats[np.argmin(line[repeats])]
            first = line[order[np.searchsorted(ordered, flat[k])]]
            faults.append((int(line[k]), 0, f"line {line[k]}: duplicate coefficient n={n[k]} m={m[k]} "
                           f"(first on line {first})"))
        sine = np.flatnonzero((m == 0) & (values[:, 1] != 0.0))
        if sine.size:
            k = sine[np.argmin(line[sine])]
            faults.append((int(line[k]), 1, f"line {line[k]}: S̄ of n={n[k]} m=0 must be 0, found {float(values[k, 1])!r}"))
        if faults:
            raise InputFileError(self.path, min(faults)[2])
        self.line_of.reshape(-1)[flat] = line
        self.C.reshape(-1)[flat] = values[:, 0]
        self.S.reshape(-1)[flat] = values[:, 1]
        if self.sC is not None:
            self.sC.reshape(-1)[flat] = values[:, 2]
            self.sS.reshape(-1)[flat] = values[:, 3]

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


#: An ICGEM header longer than this many lines is no header (the file is not ICGEM).
_MAX_HEADER_LINES = 100_000


def _icgem_header(text: _Text, progress=None):
    """(header lines, index of the ``end_of_head`` line, the blocks of the data after it).

    The data blocks are the rest of the block the header ends in, then the file's next
    blocks."""
    blocks = text.blocks(progress)
    lines = []
    for block in blocks:
        chunk = block.decode("latin-1").splitlines(keepends=True)
        for idx, line in enumerate(chunk):
            lines.append(line)
            token = line.split(None, 1)[0].lower() if line.strip() else ""
            if token == "end_of_head":
                rest = "".join(chunk[idx + 1:]).encode("latin-1")
                return lines, len(lines) - 1, itertools.chain([rest], blocks)
            if len(lines) > _MAX_HEADER_LINES:
                raise InputFileError(text.path, f"no 'end_of_head' line in its first {_MAX_HEADER_LINES:,} lines: "
                                     "not an ICGEM file, or its header is truncated")
    raise InputFileError(text.path, "no 'end_of_head' line: not an ICGEM file, or its header is truncated")


def _icgem_line(path, file_nmax, lineno, parts):
    """(line, n, m, C, S, σC, σS) of one ICGEM data line, by the format's rules."""
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
    sc = ss = 0.0
    if len(parts) == 7:
        sc = _parse_float(path, lineno, parts[5], "sigma C")
        ss = _parse_float(path, lineno, parts[6], "sigma S")
    return lineno, n, m, c, s, sc, ss


@_file_faults
def read_icgem(path, *, max_degree: int | None = None, check_tide_system: bool = True,
               progress=None) -> HarmonicModel:
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
    ``progress``: called with each number of bytes of the file read (a progress bar's
    advance).
    """
    text = _Text(path)
    lines, end, blocks = _icgem_header(text, progress)
    begin = None
    for idx, line in enumerate(lines[:end]):
        token = line.split(None, 1)[0].lower() if line.strip() else ""
        if token == "begin_of_head":
            begin = idx
            break
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
    layout = _Layout((5, 7), b"gfc", 4, file_nmax, nmax, functools.partial(_icgem_line, path, file_nmax))
    rows = _read_rows(layout, blocks, end + 1)
    _check_line_count(
        path, file_nmax, 2, rows.parsed, text.nbytes, f"line {header_line['max_degree']}: max_degree", last=rows.last_n,
    )
    coll = _Collector(path, nmax, with_sigma)
    coll.add_rows(*rows.arrays())
    coll.check_complete(2, "truncated file or incomplete model")
    _check_coefficients(path, coll.C, coll.S, coll.line_of)
    tide, notes = _check_tide_system(path, name, coll.C[2, 0], declared, "the header's tide_system", check_tide_system)
    if declared is None and tide is None:
        notes = notes + ("tide_system not stated in the header",)
    return coll.model(name, gm, radius, tide, notes, text.sha256)


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


def _nga_line(path, ncols, what, keep_n, lineno, parts):
    """(line, n, m, values...) of one NGA line of ``ncols`` columns, by the format's rules;
    None for a line above ``keep_n`` (dropped)."""
    if len(parts) != ncols:
        raise InputFileError(path, f"line {lineno}: expected {ncols} columns ({what}), found {len(parts)}")
    n = _parse_int(path, lineno, parts[0], "degree n")
    m = _parse_int(path, lineno, parts[1], "order m")
    if not 0 <= m <= n:
        raise InputFileError(path, f"line {lineno}: need 0 <= m <= n, got n={n} m={m}")
    if n > keep_n:
        return None
    _check_degree(path, n, f"line {lineno}: degree")
    values = [_parse_float(path, lineno, tok, label) for tok, label in zip(parts[2:], ("C", "S", "sigma C", "sigma S"))]
    return (lineno, n, m, *values)


def _nga_rows(path, text, ncols, what, max_degree, kind, first_degree, progress=None):
    """The coefficient rows of an NGA-style text and the degree they reach, checked once
    for both readers: a degree within bounds, at least ``max_degree`` when asked, the
    degree the file's name declares, and a line count that fits the degree."""
    keep_n = math.inf if max_degree is None else int(max_degree)
    layout = _Layout((ncols,), None, ncols - 2, MAX_MODEL_DEGREE, keep_n,
                     functools.partial(_nga_line, path, ncols, what, keep_n))
    rows = _read_rows(layout, text.blocks(progress))
    line, n, m, values = rows.arrays()
    if not n.size:
        raise InputFileError(path, "no coefficient lines")
    top = int(np.argmax(n))
    nmax, last_line = int(n[top]), int(line[top])
    _check_degree(path, nmax, f"line {last_line}: degree")
    if max_degree is not None and nmax < max_degree:
        raise InputFileError(path, f"requested max_degree {max_degree} but the file stops at degree {nmax}")
    if nmax < first_degree:
        raise InputFileError(path, f"the file stops at degree {nmax}; need at least degree {first_degree}")
    _check_named_degree(path, nmax, max_degree, kind)
    _check_line_count(path, nmax, first_degree, rows.parsed, text.nbytes, f"line {last_line}: degree")
    return (line, n, m, values), nmax


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
    progress=None,
) -> HarmonicModel:
    """Read NGA's headerless ASCII coefficients: ``n m C S sigmaC sigmaS`` per line.

    The model constants come from :data:`NGA_CATALOGUE` by file name (NGA's standard
    names, with ``.gz``/``.ascii`` stripped; a name that starts with a catalogued one, such
    as ``EGM2008_to2190_TideFree_first30``, matches it); the keywords override them and
    are required for other names. The degree is the largest n in the file (or
    ``max_degree``, which truncates); every (n, m) with 2 ≤ n ≤ that degree must be
    present exactly once. C̄20 is checked as in :func:`read_icgem`. ``progress``: as
    :func:`read_icgem`'s.
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
    text = _Text(path)
    rows, nmax = _nga_rows(path, text, 6, "n m C S sigmaC sigmaS", max_degree, "model", 2, progress)
    coll = _Collector(path, nmax, True)
    coll.add_rows(*rows)
    del rows
    coll.check_complete(2, "truncated file or incomplete model")
    _check_coefficients(path, coll.C, coll.S, coll.line_of)
    tide, notes = _check_tide_system(path, name, coll.C[2, 0], tide_system, source_label, check_tide_system)
    return coll.model(name, gm, radius, tide, notes, text.sha256)


_UNITS = {"cm": 0.01, "m": 1.0, "mm": 0.001}


def correction_unit(path, model_name: str | None = None) -> str:
    """The unit of NGA's ζ-to-N correction coefficients in file ``path``.

    NGA publishes two, both ``n m C S`` per line from degree 0: EGM96's CORRCOEF in
    centimetres (F477 divides its sum by 100) and EGM2008's ``Zeta-to-N_to2160_egm2008``
    in metres (hsynth_WGS84 reads it with the same routine as its elevation models and
    adds its sum, unscaled, to ζ and N0). The file's name tells which; a renamed copy
    takes the unit of the model it goes with (EGM2008: metres), else centimetres."""
    stem = _nga_stem(path)
    if stem.startswith("zeta-to-n"):
        return "m"
    if stem.startswith(("corrcoef", "corcoef")):
        return "cm"
    return "m" if (model_name or "").upper().replace("-", "").startswith("EGM2008") else "cm"


@_file_faults
def read_nga_correction(path, *, unit: str | None = None, name: str | None = None, max_degree: int | None = None,
                        progress=None) -> CorrectionModel:
    """Read NGA's ζ-to-N correction coefficients: ``n m C S`` per line from degree 0
    (free format; Fortran ``D`` exponents read as ``E``). ``unit`` = "cm", "mm" or "m";
    None: by the file's name (:func:`correction_unit`: CORRCOEF centimetres,
    Zeta-to-N_to2160_egm2008 metres). Every (n, m) with 0 ≤ n ≤ nmax must be present
    exactly once."""
    if unit is None:
        unit = correction_unit(path)
    if unit not in _UNITS:
        raise ParameterError(f"unit must be one of {sorted(_UNITS)}, got {unit!r}")
    text = _Text(path)
    rows, nmax = _nga_rows(path, text, 4, "n m C S", max_degree, "correction", 0, progress)
    coll = _Collector(path, nmax, False)
    coll.add_rows(*rows)
    del rows
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
        sha256=text.sha256,
        notes=(f"coefficients in {unit}",),
    )


_GFC_HINT = re.compile(rb"^\s*end_of_head\b", re.MULTILINE | re.IGNORECASE)


@_file_faults
def read_model(path, **kwargs) -> HarmonicModel:
    """Read a model file, ICGEM or NGA, telling them apart by content (:func:`model_file_kind`,
    else an ``end_of_head`` line anywhere in the text)."""
    kind = model_file_kind(path)
    if kind == "icgem":
        return read_icgem(path, **kwargs)
    if kind == "nga":
        return read_nga(path, **kwargs)
    # the reader's own rule for anything else: an end_of_head line anywhere
    if any(_GFC_HINT.search(block) for block in _Text(path).blocks()):
        return read_icgem(path, **kwargs)
    return read_nga(path, **kwargs)
