"""The synthesis conventions (presets) a model can be evaluated with, and which one a
model or a store gets when none is named. Light: importing it imports no kernel, so the
command line reads its choices from here."""

from __future__ import annotations

import re

__all__ = ["PRESETS", "DEFAULT_PRESET", "default_preset", "store_preset"]

#: The synthesis conventions :class:`~geoidspline.sources.harmonics.GeoidSynthesis`
#: knows (see its documentation): NGA's F477 (EGM96), NGA's hsynth_WGS84 (EGM2008),
#: and a plain synthesis with the model's own constants.
PRESETS = ("nga-f477", "nga-hsynth", "generic")

#: The preset of a model given without one (unless :func:`default_preset` says otherwise).
DEFAULT_PRESET = "nga-f477"


def default_preset(model, correction=None) -> str:
    """The preset used when none is given.

    NGA's EGM2008 (model name starting with "EGM2008") gets ``nga-hsynth`` (NGA's
    hsynth_WGS84, N0 = −0.41 m), alone or with EGM2008's own ζ-to-N correction (in
    metres, Zeta-to-N_to2160_egm2008); everything else, in particular EGM96 and any model
    given with a correction in centimetres (EGM96's CORRCOEF), gets
    geoidspline.sources.harmonics' default, ``nga-f477`` (NGA's F477, N0 = −0.53 m). A
    non-NGA model is better run with an explicit ``preset="generic"``.
    """
    name = (getattr(model, "name", "") or "").upper()
    if name.startswith("EGM2008") and (correction is None or getattr(correction, "unit_m", None) == 1.0):
        return "nga-hsynth"
    return DEFAULT_PRESET


def store_preset(store, model=None):
    """The synthesis preset a store was fitted with, from its provenance notes, or None.

    With ``model`` given, only when the store was fitted from that very model file
    (same sha256); a store fitted from a grid has none.
    """
    prov = store.manifest.get("provenance", {}) or {}
    if prov.get("kind") != "harmonic":
        return None
    if model is not None and (not prov.get("sha256") or prov.get("sha256") != getattr(model, "sha256", None)):
        return None
    for note in prov.get("notes", ()) or ():
        match = re.match(r"preset ([\w-]+):", str(note))
        if match and match.group(1) in PRESETS:
            return match.group(1)
    return None
