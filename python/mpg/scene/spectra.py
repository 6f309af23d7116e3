"""Spectral data the loader needs: named indices of refraction, conductor
constants, and conversion of sampled spectra to linear sRGB.

Spectrum -> RGB method
----------------------
The CIE 1931 2-degree colour matching functions are evaluated with the
multi-lobe piecewise-Gaussian fit of Wyman, Sloan and Shirley, "Simple Analytic
Approximations to the CIE XYZ Color Matching Functions" (JCGT 2013), whose
error against the tabulated CIE data is below the precision scene files carry.
A spectrum given as ``wavelength:value`` pairs is interpolated linearly between
its samples and is zero outside them (Mitsuba's irregular spectrum), integrated
against the fit on a 1 nm grid over 360-830 nm, converted from XYZ to linear
sRGB (Rec. 709 primaries), and finally divided channel-wise by the RGB of the
unit equal-energy spectrum. The last step makes a flat spectrum of value c map
to the grey (c, c, c): reflectances keep their albedo and white lights stay
white, which is what a scene author writing a flat spectrum means.
"""

from __future__ import annotations

import numpy as np

# --------------------------------------------------------------------------
# Named indices of refraction (Mitsuba's table of the same names).
IOR_TABLE: dict[str, float] = {
    "vacuum": 1.0,
    "helium": 1.00004,
    "hydrogen": 1.00013,
    "air": 1.000277,
    "carbon dioxide": 1.00045,
    "water": 1.3330,
    "acetone": 1.36,
    "ethanol": 1.361,
    "carbon tetrachloride": 1.461,
    "glycerol": 1.4729,
    "benzene": 1.501,
    "silicone oil": 1.52045,
    "bromine": 1.661,
    "water ice": 1.31,
    "fused quartz": 1.458,
    "pyrex": 1.470,
    "acrylic glass": 1.49,
    "polypropylene": 1.49,
    "bk7": 1.5046,
    "sodium chloride": 1.544,
    "amber": 1.55,
    "pet": 1.5750,
    "diamond": 2.419,
}


def lookup_ior(name: str) -> float | None:
    """IOR of a named material, or None if unknown."""
    return IOR_TABLE.get(name.strip().lower())


# --------------------------------------------------------------------------
# Conductors: complex IOR (eta, k) in linear RGB, obtained by reducing measured
# spectral data to the sRGB primaries. 'none' is the perfect mirror: with
# eta = 0 and k = 1 the conductor Fresnel term is exactly 1 at every angle.
CONDUCTORS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "none": ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
    "Au": ((0.143119, 0.374957, 1.44248), (3.98316, 2.38572, 1.60322)),
    "Ag": ((0.155265, 0.116723, 0.138342), (4.82835, 3.12225, 2.14696)),
    "Cu": ((0.200438, 0.924033, 1.10221), (3.91295, 2.45285, 2.14219)),
    "Al": ((1.65746, 0.880369, 0.521229), (9.22387, 6.26952, 4.837)),
    "Cr": ((4.36968, 2.9167, 1.6547), (5.20637, 4.23131, 3.75469)),
}


def lookup_conductor(name: str) -> tuple[np.ndarray, np.ndarray] | None:
    v = CONDUCTORS.get(name)
    if v is None:
        return None
    return np.array(v[0], dtype=np.float64), np.array(v[1], dtype=np.float64)


# --------------------------------------------------------------------------
# CIE 1931 colour matching functions, multi-lobe fit (see module docstring).

def _lobe(lam: np.ndarray, mu: float, s1: float, s2: float) -> np.ndarray:
    t = (lam - mu) / np.where(lam < mu, s1, s2)
    return np.exp(-0.5 * t * t)


def cie_xyz(lam: np.ndarray) -> np.ndarray:
    """(len(lam), 3) values of x-bar, y-bar, z-bar at wavelengths in nm."""
    lam = np.asarray(lam, dtype=np.float64)
    x = 1.056 * _lobe(lam, 599.8, 37.9, 31.0) + 0.362 * _lobe(lam, 442.0, 16.0, 26.7) \
        - 0.065 * _lobe(lam, 501.1, 20.4, 26.2)
    y = 0.821 * _lobe(lam, 568.8, 46.9, 40.5) + 0.286 * _lobe(lam, 530.9, 16.3, 31.1)
    z = 1.217 * _lobe(lam, 437.0, 11.8, 36.0) + 0.681 * _lobe(lam, 459.0, 26.0, 13.8)
    return np.stack([x, y, z], axis=-1)


XYZ_TO_SRGB = np.array([
    [3.2404542, -1.5371385, -0.4985314],
    [-0.9692660, 1.8760108, 0.0415560],
    [0.0556434, -0.2040259, 1.0572252],
])

LAMBDA_MIN, LAMBDA_MAX = 360.0, 830.0
_GRID = np.arange(LAMBDA_MIN, LAMBDA_MAX + 0.5, 1.0)
_CMF = cie_xyz(_GRID)
_WHITE_RGB = XYZ_TO_SRGB @ _CMF.sum(axis=0)   # RGB of the unit equal-energy spectrum


def spectrum_to_rgb(wavelengths, values) -> np.ndarray:
    """Linear sRGB of a sampled spectrum (piecewise linear, zero outside)."""
    wl = np.asarray(wavelengths, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    order = np.argsort(wl, kind="stable")
    wl, v = wl[order], v[order]
    if len(wl) == 1:
        return np.full(3, float(v[0]))
    s = np.interp(_GRID, wl, v, left=0.0, right=0.0)
    xyz = (_CMF * s[:, None]).sum(axis=0)
    return (XYZ_TO_SRGB @ xyz) / _WHITE_RGB


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
