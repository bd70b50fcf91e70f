"""Spherical-harmonic gravity models and the exact geoid synthesis from them.

- :mod:`.models`: strict readers (ICGEM ``.gfc``, NGA ASCII, NGA CORRCOEF) returning
  frozen :class:`HarmonicModel` / :class:`CorrectionModel` values;
- :mod:`.legendre`: numeric kernels (fully normalised P̄nm stable to degree 2190 and
  beyond, Legendre sums per latitude), no validation;
- :mod:`.synthesis`: :class:`GeoidSynthesis`, N in metres as NGA's F477/hsynth compute it,
  a :class:`geoidspline.sources.GeoidSource`.
"""

from .models import (
    KNOWN_C20,
    NGA_CATALOGUE,
    CorrectionModel,
    HarmonicModel,
    TideSystemWarning,
    read_icgem,
    read_model,
    read_nga,
    read_nga_correction,
)
from .synthesis import PRESETS, Conventions, GeoidSynthesis

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
    "GeoidSynthesis",
    "Conventions",
    "PRESETS",
]
