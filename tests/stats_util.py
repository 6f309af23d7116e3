"""Shared helpers for the statistical warp and BSDF tests.

Chi-square goodness of fit of sampled directions against a density, in the
style of Mitsuba's ChiSquareTest: directions are binned over a (cos theta, phi)
grid (equal-area cells for a uniform cos grid), the density is integrated over
each cell with a sub-sampled midpoint rule, cells with a small expected count
are pooled, and the statistic is compared with the chi2 distribution.

Everything is float64 numpy on the Python side; the C++ entry points take
float32 directions, so the midpoint nodes are rounded to float32 before they
are handed to a density function.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

# Significance level of every goodness-of-fit test: a correct sampler fails a
# single test with probability 1e-4 (and with fixed seeds, deterministically
# never once it has passed).
ALPHA = 1e-4


def uniform_u(n: int, dim: int, seed: int) -> np.ndarray:
    """n x dim float32 uniforms in [0, 1) from a fixed seed."""
    return np.random.default_rng(seed).random((n, dim), dtype=np.float32)


def spherical(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(v, dtype=np.float64)
    z = np.clip(v[:, 2], -1.0, 1.0)
    phi = np.mod(np.arctan2(v[:, 1], v[:, 0]), 2.0 * np.pi)
    return z, phi


def histogram_sphere(v: np.ndarray, n_cos: int, n_phi: int,
                     z_range: tuple[float, float] = (-1.0, 1.0)) -> tuple[np.ndarray, int]:
    """Counts over an n_cos x n_phi grid of (cos theta in z_range, phi).

    Returns (counts, n_outside) where n_outside counts samples with cos theta
    outside z_range."""
    z, phi = spherical(v)
    z0, z1 = z_range
    inside = (z >= z0) & (z <= z1)
    iz = np.minimum(((z[inside] - z0) / (z1 - z0) * n_cos).astype(np.int64), n_cos - 1)
    ip = np.minimum((phi[inside] / (2.0 * np.pi) * n_phi).astype(np.int64), n_phi - 1)
    counts = np.bincount(iz * n_phi + ip, minlength=n_cos * n_phi).reshape(n_cos, n_phi)
    return counts.astype(np.float64), int((~inside).sum())


def _row_nodes(a: float, b: float, sub: int, toward: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Midpoints and widths of sub intervals of [a, b]; geometrically graded
    toward the end `toward` (a pole) if given."""
    e = np.linspace(a, b, sub + 1)
    if toward is not None:
        # plus geometrically graded edges inside the sub-interval at the pole,
        # down to 1e-6 of the row: a feature at 1 - |cos| ~ 1e-6 .. 1e-3
        # (a fraction of a degree to a few degrees from the pole) is resolved.
        g = np.geomspace(1e-6, 1.0 / sub, sub) * (b - a)
        e = np.unique(np.concatenate([e, a + g if toward == a else b - g]))
    return 0.5 * (e[1:] + e[:-1]), np.diff(e)


def integrate_sphere_grid(pdf_fn, n_cos: int, n_phi: int, sub: int = 16,
                          z_range: tuple[float, float] = (-1.0, 1.0),
                          chunk: int = 1 << 20) -> np.ndarray:
    """Integral of pdf_fn (solid-angle density of (M,3) float32 directions) over
    every cell of the grid, dOmega = d(cos theta) d(phi), by the midpoint rule
    on sub x sub nodes per cell. The rows touching a pole get sub more nodes in
    cos theta, graded geometrically toward the pole: near a pole the cells are thin wedges
    and a uniform cos grid cannot see a support edge a degree from the pole."""
    z0, z1 = z_range
    zb = np.linspace(z0, z1, n_cos + 1)
    zc, zw, zrow = [], [], []
    for i in range(n_cos):
        pole = -1.0 if (i == 0 and z0 == -1.0) else (1.0 if (i == n_cos - 1 and z1 == 1.0) else None)
        c, w = _row_nodes(zb[i], zb[i + 1], sub, pole)
        zc.append(c), zw.append(w), zrow.append(np.full(len(c), i))
    zc, zw, zrow = map(np.concatenate, (zc, zw, zrow))
    nphi = n_phi * sub
    dphi = 2.0 * np.pi / nphi
    pc = (np.arange(nphi) + 0.5) * dphi
    Z, P = np.meshgrid(zc, pc, indexing="ij")
    R = np.sqrt(np.maximum(0.0, 1.0 - Z * Z))
    dirs = np.stack([R * np.cos(P), R * np.sin(P), Z], axis=-1).reshape(-1, 3).astype(np.float32)
    vals = np.concatenate([np.asarray(pdf_fn(dirs[i:i + chunk]), dtype=np.float64)
                           for i in range(0, len(dirs), chunk)])
    vals = vals.reshape(len(zc), n_phi, sub).sum(axis=2) * dphi * zw[:, None]
    out = np.zeros((n_cos, n_phi))
    np.add.at(out, zrow, vals)
    return out


def chi2_test(observed: np.ndarray, expected: np.ndarray, n_total: int,
              min_expected: float = 5.0) -> tuple[float, int, float, str]:
    """Pearson chi-square of observed vs expected counts (Mitsuba's pooling:
    cells sorted by expected count, the small ones merged until the pool
    reaches min_expected).

    Returns (statistic, dof, p_value, message). A cell with zero expected
    count but more than 1e-5 * n_total observed samples (sampling outside the
    support) gives p = 0."""
    obs = np.asarray(observed, dtype=np.float64).ravel()
    exp = np.asarray(expected, dtype=np.float64).ravel()
    bad = (exp <= 0.0) & (obs > 0)
    if obs[bad].sum() > max(1e-5 * n_total, 0.0):
        return np.inf, 0, 0.0, f"{int(obs[bad].sum())} samples in cells of zero expected count"
    order = np.argsort(exp, kind="stable")
    obs, exp = obs[order], exp[order]
    # Pool the prefix of small cells until the pool itself holds >= min_expected.
    csum = np.cumsum(exp)
    n_pool = int(np.searchsorted(exp, min_expected))
    if n_pool > 0 and csum[n_pool - 1] < min_expected:
        n_pool = min(len(exp), int(np.searchsorted(csum, min_expected)) + 1)
    chsq, dof = 0.0, 0
    if n_pool > 0:
        pe, po = exp[:n_pool].sum(), obs[:n_pool].sum()
        if pe > 0:
            chsq += (po - pe) ** 2 / pe
            dof += 1
    e, o = exp[n_pool:], obs[n_pool:]
    chsq += float(((o - e) ** 2 / e).sum())
    dof += len(e)
    dof -= 1
    if dof < 1:
        return chsq, dof, 1.0, "too few cells for a test"
    p = float(stats.chi2.sf(chsq, dof))
    # Worst cell, to make a failure message actionable.
    k = int(np.argmax((o - e) ** 2 / e)) if len(e) else 0
    msg = (f"chi2={chsq:.1f} dof={dof} p={p:.3g}; worst cell expected={e[k]:.1f} "
           f"observed={o[k]:.0f}" if len(e) else "")
    return chsq, dof, p, msg


def sphere_gof(samples: np.ndarray, pdf_fn, n_total: int, n_cos: int = 20, n_phi: int = 40,
               sub: int = 16, z_range: tuple[float, float] = (-1.0, 1.0)):
    """Chi-square of sampled directions (the valid ones; n_total draws in all,
    which may include failed or delta samples) against the solid-angle density
    pdf_fn. Returns (p_value, message, integral of pdf over the grid)."""
    obs, n_out = histogram_sphere(samples, n_cos, n_phi, z_range)
    integ = integrate_sphere_grid(pdf_fn, n_cos, n_phi, sub, z_range)
    exp = integ * n_total
    _, _, p, msg = chi2_test(obs, exp, n_total)
    return p, msg + f"; outside={n_out}; integral={integ.sum():.6f}", integ.sum(), n_out


def binomial_z(k: int, n: int, p: float) -> float:
    """z-score of k successes out of n with success probability p."""
    sd = np.sqrt(max(n * p * (1.0 - p), 1e-300))
    return (k - n * p) / sd


def image_zmax(a, b, regions) -> float:
    """Largest |z| over regions (numpy slices) and channels between the means of
    two independent renders, from their per-pixel variances of the mean."""
    out = []
    for sy, sx in regions:
        A, B = a.rgb[sy, sx].astype(np.float64), b.rgb[sy, sx].astype(np.float64)
        n = A[..., 0].size
        se = np.sqrt(a.variance[sy, sx].sum(axis=(0, 1)) + b.variance[sy, sx].sum(axis=(0, 1))) / n
        out.append(np.abs(A.mean(axis=(0, 1)) - B.mean(axis=(0, 1))) / np.maximum(se, 1e-12))
    return float(np.max(out))


# the image and its nine 8x8 blocks, for the 24x24 agreement tests
REGIONS_24 = [np.s_[:, :]] + [np.s_[i:i + 8, j:j + 8] for i in (0, 8, 16) for j in (0, 8, 16)]
# a 32x32 image and its four quarters
REGIONS_32 = [np.s_[:, :]] + [np.s_[i:i + 16, j:j + 16] for i in (0, 16) for j in (0, 16)]


def run_pass(sc, name, spp, seed, params=None, **kw):
    """One render pass of integrator `name` through the core (RenderJob
    keywords: the per-pixel maps, record_costs) and its result dict."""
    from mpg import _core
    core = sc.core
    job = _core.RenderJob(core, _core.make_integrator(core, name, params or {}), spp, seed, 0, 0, **kw)
    while not job.wait(0.05):
        pass
    return job.result()


def check_uniform_split(sc, ref, param, k, spp, counter, regions):
    """mpg with the split `param` = k everywhere agrees with the path-traced
    `ref` (|z| < 5 on each region), counts its extra work in stats[counter],
    reports the setting; 0, 'x' and 65 are clear errors naming the parameter."""
    import mpg
    import pytest
    img = mpg.render(sc, {"type": "mpg", param: k}, spp=spp, seed=37, progress=False)
    assert img.stats[param] == str(k) and img.stats[counter] > 0
    assert image_zmax(img, ref, regions) < 5
    for bad in (0, "x", 65):
        with pytest.raises(mpg.RenderError, match=param):
            mpg.render(sc, {"type": "mpg", param: bad}, spp=2, progress=False)
