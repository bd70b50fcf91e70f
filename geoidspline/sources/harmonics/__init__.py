"""Spherical-harmonic gravity models and the exact geoid synthesis from them.

- :mod:`.models`: strict readers (ICGEM ``.gfc``, NGA ASCII, NGA CORRCOEF) returning
  frozen :class:`HarmonicModel` / :class:`CorrectionModel` values;
- :mod:`geoidspline._kernels.legendre`: numeric kernels (fully normalised P̄nm stable to degree 2190 and
  beyond, Legendre sums per latitude), no validation;
- :mod:`.synthesis`: :class:`GeoidSynthesis`, N in metres as NGA's F477/hsynth compute it,
  a :class:`geoidspline.sources.base.GeoidSource`.
"""

from __future__ import annotations

import importlib

#: Public names and the submodule holding each: imported on first access (PEP 562),
#: so that reading the presets (the command line's choices) does not import the kernels.
_EXPORTS = {
    "HarmonicModel": "models", "CorrectionModel": "models", "TideSystemWarning": "models",
    "read_icgem": "models", "read_nga": "models", "read_nga_correction": "models", "read_model": "models",
    "NGA_CATALOGUE": "models", "KNOWN_C20": "models", "correction_unit": "models",
    "GeoidSynthesis": "synthesis", "Conventions": "synthesis",
    "PRESETS": "presets", "DEFAULT_PRESET": "presets", "default_preset": "presets", "store_preset": "presets",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)


def __dir__():
    return __all__
