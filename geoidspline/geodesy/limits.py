"""What a geoid can physically be: the limits every source is checked against.

A value beyond these is never a geoid: it is a unit mistake (centimetres labelled
metres), a corrupt file, or a no-data marker the file does not declare. The readers
refuse it with a message naming the rule, instead of fitting it.

- Undulations: the Earth's geoid spans about -107 m (Indian Ocean, south of Sri Lanka)
  to +86 m (New Guinea): EGM96 on PROJ's 15' grid ``egm96_15.gtx`` ranges from
  -106.99 m (4.75N 78.75E) to +85.39 m (8.25S 147.25E) (measured on that file).
  ±150 m leaves room for any model and its zero-degree term, and still catches a
  centimetre mistake wherever |N| exceeds 1.5 m (in centimetres that is 150).
- Coefficients: with the normal field removed, a fully normalised coefficient C̄nm of
  degree n ≥ 2 contributes about a·C̄nm to N (Bruns's formula N = T/γ with
  GM/(aγ) ≈ a: N ≈ a Σ C̄nm Ȳnm), and the mean square of N over the sphere is
  a² Σ C̄nm² (4π normalisation). One coefficient above 150 m / a = 2.35e-5 alone would
  give an RMS geoid beyond the physical range. C̄20 is the exception: it holds the
  flattening (-4.84e-4 for the Earth) and is bounded by 1e-3. EGM96's largest other
  coefficient is 2.4e-6 (C̄22), ten times below the bound.
- Degree: 10,800 resolves 1 arc-minute (180°/10,800), finer than any published global
  gravity model (EGM2008 2,190; XGM2019e 5,540 in spherical harmonics); beyond it a
  declared degree is a corrupt header, refused before anything is allocated.
- Grid size: 250 million nodes (1 GB of float32) holds a global 1' grid
  (10,801 x 21,600 = 233 million); a larger declared grid is refused before reading.
"""

from __future__ import annotations

__all__ = [
    "MAX_ABS_UNDULATION_M",
    "GEOID_RANGE_M",
    "REFERENCE_RADIUS_M",
    "MAX_ABS_C20",
    "MAX_ABS_COEFFICIENT",
    "MAX_MODEL_DEGREE",
    "MAX_GRID_NODES",
]

#: Largest |N| (metres) accepted from any source (a file or a synthesis).
MAX_ABS_UNDULATION_M = 150.0

#: The Earth's geoid, lowest and highest (metres, rounded outwards), for messages.
GEOID_RANGE_M = (-107.0, 86.0)

#: The radius a (metres) that scales coefficients to metres of N (WGS84 a).
REFERENCE_RADIUS_M = 6378137.0

#: Largest |C̄20| (fully normalised) accepted: the Earth's is -4.84e-4.
MAX_ABS_C20 = 1e-3

#: Largest |C̄nm|, |S̄nm| (fully normalised) accepted for n >= 2 other than C̄20.
MAX_ABS_COEFFICIENT = MAX_ABS_UNDULATION_M / REFERENCE_RADIUS_M

#: Largest degree of a spherical-harmonic model (1 arc-minute).
MAX_MODEL_DEGREE = 10_800

#: Largest number of nodes of a grid file (a global 1' grid has 233 million).
MAX_GRID_NODES = 250_000_000
