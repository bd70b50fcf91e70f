"""Exact geoid undulations at points by a synthesis independent of geoidspline's code.

The truth the EGM2008 benchmark measures stores against (issue 22): nothing of
geoidspline is imported. The coefficients are read here (NGA text or ICGEM ``.gfc``),
the fully normalised Legendre functions come from SHTOOLS (``pyshtools.legendre.PlmBar``,
4π normalisation without the Condon-Shortley phase, scaled internally so that degree
2190 does not underflow at the poles), and the conventions are NGA's hsynth_WGS84 as
../reference/METHOD.md §6 states them (geoidspline's preset ``nga-hsynth``):

    r, ψ   geocentric radius and latitude of the point on the WGS84 ellipsoid (h = 0);
    T    = (GM/r) Σ_{n≥2} (a/r)^n Σ_m (ΔC̄nm cos mλ + S̄nm sin mλ) P̄nm(sin ψ),
           GM, a the model's, ΔC̄n0 = C̄n0 + (GM84/GM)(a84/a)^n J_n/√(2n+1), n = 2..10;
    N    = T/γ(φ) + C(φ, λ) + N0,  γ Somigliana (WGS84), C the ζ-to-N correction series
           (no (a/r)^n; optional), N0 = -0.41 m.

Points are drawn in rings: ``count / per_ring`` latitudes uniform in area, each with
``per_ring`` longitudes uniform at random (the Legendre functions of one latitude,
O(N²), serve every point of its ring; the longitude sum is O(N) a point). Values are
cached in a ``.npz`` named by the sha256 of the model (and correction) file and the
sample's parameters, so a rerun reads them.

    python benchmarks/independent_synthesis.py validate MODEL [COUNT]   # largest difference to geoidspline
"""

from __future__ import annotations

import gzip
import hashlib
import json
import math
import re
import sys
import time
from pathlib import Path

import numpy as np

# WGS84 as NGA's hsynth_WGS84 uses it (METHOD.md §6)
GM84, A84 = 3.986004418e14, 6378137.0
E2 = 0.00669437999013
GAMMA_E, GAMMA_K = 9.7803253359, 0.00193185265246
J_WGS84 = {2: 0.108262982131e-2, 4: -0.237091120053e-05, 6: 0.608346498882e-8, 8: -0.142681087920e-10,
           10: 0.121439275882e-13}
N0_EGM2008 = -0.41
#: EGM2008's GM and a: NGA's text files carry none (hsynth_WGS84 has them built in).
EGM2008_GM, EGM2008_A = 3.986004415e14, 6378136.3


def _text(path) -> str:
    raw = Path(path).read_bytes()
    if raw[:2] == b"\x1f\x8b":
        raw = gzip.decompress(raw)
    return raw.decode("ascii")


def sha256_of(path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 22), b""):
            digest.update(block)
    return digest.hexdigest()


def read_coefficients(path, *, correction: bool = False):
    """(GM, a, nmax, C, S): C, S packed by SHTOOLS' index n(n+1)/2 + m. NGA text (``n m C
    S ...``, E or D exponents) or ICGEM ``.gfc`` (``gfc n m C S ...`` after end_of_head)."""
    text = _text(path)
    gm, radius = EGM2008_GM, EGM2008_A
    if "end_of_head" in text:
        head, body = text.split("end_of_head", 1)
        body = body.split("\n", 1)[1]
        gm = float(re.search(r"earth_gravity_constant\s+(\S+)", head).group(1).replace("D", "E"))
        radius = float(re.search(r"\nradius\s+(\S+)", head).group(1).replace("D", "E"))
        rows = [line.replace("D", "E").replace("d", "e").split()[1:5] for line in body.splitlines()
                if line.startswith("gfc")]
        values = np.array(rows, dtype=float).reshape(-1, 4)
    else:
        values = np.array(text.replace("D", "E").replace("d", "e").split(), dtype=float)
        ncols = 4 if correction else 6
        values = values.reshape(-1, ncols)[:, :4]
    n = values[:, 0].astype(np.int64)
    m = values[:, 1].astype(np.int64)
    nmax = int(n.max())
    size = (nmax + 1) * (nmax + 2) // 2
    C = np.zeros(size)
    S = np.zeros(size)
    C[n * (n + 1) // 2 + m] = values[:, 2]
    S[n * (n + 1) // 2 + m] = values[:, 3]
    return gm, radius, nmax, C, S


class IndependentSynthesis:
    """N (metres) at points: EGM2008 in NGA hsynth's conventions (module docstring).
    ``correction_unit_m``: the correction file's unit (1.0 for EGM2008's Zeta-to-N)."""

    def __init__(self, model_path, correction_path=None, correction_unit_m: float = 1.0, n0_m: float = N0_EGM2008):
        import pyshtools  # noqa: F401  (fail early: the benchmark's sht extra)

        self.gm, self.a, self.nmax, C, self.S = read_coefficients(model_path)
        n_of = np.concatenate([np.full(k + 1, k) for k in range(self.nmax + 1)])
        self.m_of = np.concatenate([np.arange(k + 1) for k in range(self.nmax + 1)])
        self.degree_of = n_of
        for n, j in J_WGS84.items():
            if n <= self.nmax:
                C[n * (n + 1) // 2] += (GM84 / self.gm) * (A84 / self.a) ** n * j / math.sqrt(2 * n + 1)
        C[n_of < 2] = 0.0
        self.S = np.where(n_of < 2, 0.0, self.S)
        self.C = C
        self.n0_m = n0_m
        self.correction = None
        if correction_path is not None:
            _, _, ncmax, cc, cs = read_coefficients(correction_path, correction=True)
            self.correction = (ncmax, cc * correction_unit_m, cs * correction_unit_m)

    def ring(self, latitude_deg: float, longitude_deg) -> np.ndarray:
        """N (m) at geodetic ``latitude_deg`` and each of ``longitude_deg``."""
        from pyshtools.legendre import PlmBar

        phi = math.radians(latitude_deg)
        nu = A84 / math.sqrt(1.0 - E2 * math.sin(phi) ** 2)
        p, z = nu * math.cos(phi), nu * (1.0 - E2) * math.sin(phi)
        r = math.hypot(p, z)
        sin_psi = z / r
        plm = PlmBar(self.nmax, sin_psi)
        q_n = np.exp(np.arange(self.nmax + 1) * math.log(self.a / r))
        weighted = plm * q_n[self.degree_of]
        size = self.nmax + 1
        A = np.bincount(self.m_of, self.C * weighted, minlength=size)
        B = np.bincount(self.m_of, self.S * weighted, minlength=size)
        gamma = GAMMA_E * (1.0 + GAMMA_K * math.sin(phi) ** 2) / math.sqrt(1.0 - E2 * math.sin(phi) ** 2)
        scale = self.gm / (r * gamma)
        A *= scale
        B *= scale
        if self.correction is not None:
            ncmax, cc, cs = self.correction
            pc = plm[: cc.size] if ncmax <= self.nmax else PlmBar(ncmax, sin_psi)
            A[: ncmax + 1] += np.bincount(self.m_of[: cc.size], cc * pc, minlength=ncmax + 1)
            B[: ncmax + 1] += np.bincount(self.m_of[: cc.size], cs * pc, minlength=ncmax + 1)
        lam = np.radians(np.atleast_1d(np.asarray(longitude_deg, dtype=float)))
        out = np.empty(lam.size)
        m = np.arange(size)
        for start in range(0, lam.size, 64):  # (points, orders) blocks
            angle = lam[start:start + 64, None] * m[None, :]
            out[start:start + 64] = np.cos(angle) @ A + np.sin(angle) @ B
        return out + self.n0_m


def ring_points(count: int, per_ring: int, region, seed: int):
    """Latitudes (one per ring, uniform in area) and longitudes (per_ring each) in
    ``region`` (south, west, north, east degrees)."""
    south, west, north, east = region
    rng = np.random.default_rng(seed)
    rings = max(1, math.ceil(count / per_ring))
    lat = np.degrees(np.arcsin(rng.uniform(math.sin(math.radians(south)), math.sin(math.radians(north)), rings)))
    lon = west + rng.uniform(0.0, east - west, (rings, per_ring))
    return lat, lon


def reference_values(model_path, region, count: int, cache_dir, *, seed: int = 22, per_ring: int = 10,
                     correction_path=None, correction_unit_m: float = 1.0, log=sys.stderr):
    """(latitude, longitude, N) at ``count`` points in ``region``: read from the cache or
    computed (and cached). Also returns the seconds spent computing (0 when cached)."""
    key = sha256_of(model_path)
    if correction_path is not None:
        key = hashlib.sha256((key + sha256_of(correction_path) + repr(correction_unit_m)).encode()).hexdigest()
    tag = "_".join(f"{v:g}" for v in region)
    cache = Path(cache_dir) / f"ref_{key[:16]}_{tag}_{count}_{per_ring}_{seed}.npz"
    if cache.exists():
        data = np.load(cache)
        return data["latitude"], data["longitude"], data["undulation"], 0.0
    start = time.perf_counter()
    synthesis = IndependentSynthesis(model_path, correction_path, correction_unit_m)
    lat, lon = ring_points(count, per_ring, region, seed)
    values = np.empty(lon.shape)
    for i in range(lat.size):
        values[i] = synthesis.ring(lat[i], lon[i])
        if log and (i + 1) % 200 == 0:
            print(f"reference: {i + 1}/{lat.size} rings, {time.perf_counter() - start:.0f} s", file=log, flush=True)
    latitude = np.repeat(lat, per_ring)
    longitude, undulation = lon.ravel(), values.ravel()
    seconds = time.perf_counter() - start
    Path(cache_dir).mkdir(parents=True, exist_ok=True)
    tmp = cache.with_suffix(".tmp.npz")
    np.savez(tmp, latitude=latitude, longitude=longitude, undulation=undulation,
             meta=json.dumps({"model": str(model_path), "sha256": key, "region": list(region), "count": count,
                              "per_ring": per_ring, "seed": seed, "seconds": seconds}))
    tmp.replace(cache)
    return latitude, longitude, undulation, seconds


def validate(model_path, count: int = 400, seed: int = 5):
    """Largest |independent - geoidspline| (m) at ``count`` points, poles and equator
    included (geoidspline imported here only, as the thing checked)."""
    from geoidspline.api import load_synthesis

    synthesis = IndependentSynthesis(model_path)
    ours = load_synthesis(model_path)
    lat, lon = ring_points(count, 4, (-90.0, -180.0, 90.0, 180.0), seed)
    lat = np.concatenate([lat, [90.0, -90.0, 0.0, 89.99, -89.99]])
    lon = np.vstack([lon, np.tile([0.0, 120.0, -45.0, 179.9], (5, 1))])
    worst = 0.0
    for i in range(lat.size):
        mine = synthesis.ring(lat[i], lon[i])
        theirs = ours.undulation(np.full(lon.shape[1], lat[i]), lon[i])
        worst = max(worst, float(np.abs(mine - theirs).max()))
    return worst, int(lon.size), ours.preset


if __name__ == "__main__":
    if len(sys.argv) in (3, 4) and sys.argv[1] == "validate":
        start = time.perf_counter()
        worst, points, preset = validate(sys.argv[2], *[int(v) for v in sys.argv[3:]])
        print(json.dumps({"model": sys.argv[2], "points": points, "preset": preset, "max_abs_diff_m": worst,
                          "seconds": round(time.perf_counter() - start, 1)}))
    else:
        print(__doc__)
        sys.exit(2)
