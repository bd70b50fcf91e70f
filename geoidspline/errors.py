"""The exception tree of geoidspline.

Every error a user can cause derives from :class:`GeoidSplineError`, so the command-line
tools catch that one class and print its message instead of a traceback.
"""

from __future__ import annotations

__all__ = [
    "GeoidSplineError",
    "InputFileError",
    "CoordinateError",
    "StoreError",
    "StoreCorruptError",
    "StoreFileMissingError",
    "FitError",
    "ExportError",
    "ParameterError",
]


class GeoidSplineError(Exception):
    """Base class of every error geoidspline raises on purpose."""


class InputFileError(GeoidSplineError, ValueError):
    """A grid or model file is missing, malformed or not what it claims to be.

    The message names the file and the rule it breaks (GeographicLib style).
    """

    def __init__(self, path, rule: str):
        self.path = str(path)
        self.rule = rule
        super().__init__(f"{self.path}: {rule}")


class CoordinateError(GeoidSplineError, ValueError):
    """Coordinates out of range or of the wrong kind (latitude beyond ±90°, say)."""


class StoreError(GeoidSplineError):
    """A tile store cannot be opened, written or updated."""


class StoreCorruptError(StoreError):
    """A tile store's files disagree with its manifest (missing, truncated or altered)."""


class StoreFileMissingError(StoreCorruptError):
    """A file or directory of a tile store is not there (the reader tells a store
    rewritten since it was opened from a damaged one by this type)."""


class ParameterError(GeoidSplineError, ValueError):
    """An argument of a call is outside what it accepts (an unknown tide system, a
    degree beyond the model's); the message names the argument and what it takes."""


class FitError(GeoidSplineError):
    """A fit cannot be set up with the given data and parameters."""


class ExportError(GeoidSplineError):
    """A grid export cannot be written (a full disk, a read-only file system, ...); the
    message names the file and the cause, and no partial file is left."""
