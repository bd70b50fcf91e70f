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
    "FitError",
    "ExportError",
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


class FitError(GeoidSplineError):
    """A fit cannot be set up with the given data and parameters."""


class ExportError(GeoidSplineError):
    """A grid export cannot be written (a full disk, a read-only file system, ...); the
    message names the file and the cause, and no partial file is left."""
