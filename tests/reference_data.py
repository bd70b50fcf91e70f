"""Where the shared reference data (real EGM96/EGM2008/GeographicLib files) are found.

One place for every test: ``$GEOIDSPLINE_TEST_DATA`` when set, else ``../shared/data``
relative to the repository root (not the working directory, so running pytest from
another folder finds the same files). Tests that need a file skip, naming it, when it
is absent; nothing from there is copied into the repository.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
REFERENCE_DATA = Path(os.environ.get("GEOIDSPLINE_TEST_DATA") or REPO.parent / "shared" / "data")


def reference_file(*parts: str) -> Path:
    """The path of a reference file (it may be absent)."""
    return REFERENCE_DATA.joinpath(*parts)


def need(path: Path) -> Path:
    """``path``, or skip the test saying which reference file is missing and why."""
    if not path.is_file():
        pytest.skip(f"{path} not found: reference data absent (set GEOIDSPLINE_TEST_DATA or put the shared "
                    f"data at {REPO.parent / 'shared' / 'data'})")
    return path
