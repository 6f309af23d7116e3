"""Statistical tests of the sample warps in cpp/core/warp.h.

Every goodness-of-fit test below rejects at significance ALPHA = 1e-4 (a
correct warp fails one test with probability 1e-4; seeds are fixed, so a
passing test stays passing). Sample counts are chosen so that the tests detect
density errors of about 1% of the mass of a cell.
"""

import math

import numpy as np
import pytest
from scipy import stats

from mpg import _core
from stats_util import ALPHA, chi2_test, sphere_gof, uniform_u

N = 1_000_000

# (name, param, grid rows over cos theta)
SPHERE_WARPS = [
    ("uniform_sphere", 0.0),
    ("uniform_hemisphere", 0.0),
    ("cosine_hemisphere", 0.0),
    ("uniform_cone", -0.3),
    ("uniform_cone", 0.5),
    ("vmf", 1e-8),
    ("vmf", 1e-3),
    ("vmf", 1.0),
    ("vmf", 10.0),
]
KAPPAS = [1e-8, 1e-3, 1.0, 10.0, 1e3, 1e5, 1e8]


def sample(name, param, n=N, seed=1):
    u = uniform_u(n, 2, seed)
    v = _core.warp_sample(name, u, param)
    assert v.shape == (n, 3) and v.dtype == np.float32
    return u, v


def pdf_fn(name, param):
    return lambda d: _core.warp_pdf(name, d, param)


def vmf_pdf_ref(cos_theta, kappa):
    """Supplemental Eq. 1 of the MPG paper, kappa / (4 pi sinh kappa) e^{kappa cos},
    evaluated in float64 in a form that neither overflows nor cancels."""
    cos_theta = np.asarray(cos_theta, dtype=np.float64)
    if kappa == 0:
        return np.full_like(cos_theta, 1.0 / (4.0 * math.pi))
    return kappa / (2.0 * math.pi * -math.expm1(-2.0 * kappa)) * np.exp(kappa * (cos_theta - 1.0))


def one_minus_cos(v):
    """1 - cos theta in float64 without cancellation near the pole:
    1 - z = (x^2 + y^2) / (1 + z) for z > 0."""
    v = v.astype(np.float64)
    z = v[:, 2]
    r2 = v[:, 0] ** 2 + v[:, 1] ** 2
    return np.where(z > 0, r2 / (1.0 + np.abs(z)), 1.0 - z)


# --- 1. histograms against the pdf --------------------------------------------


@pytest.mark.parametrize("name,param", SPHERE_WARPS)
def test_warp_matches_pdf_chi2(name, param):
    # Chi-square over 20 x 40 equal-area (cos theta, phi) cells, density
    # integrated with 16 x 16 midpoint nodes per cell; reject at p < 1e-4.
    u, v = sample(name, param)
    assert np.isfinite(v).all()
    norms = np.linalg.norm(v.astype(np.float64), axis=1)
    np.testing.assert_allclose(norms, 1.0, atol=1e-5)
    p, msg, integral, n_out = sphere_gof(v, pdf_fn(name, param), N)
    assert p > ALPHA, f"{name}({param}): {msg}"
    # The pdf integrates to one over the sphere (grid midpoint rule; the only
    # discontinuities of these densities are at cell edges or the cone edge).
    assert abs(integral - 1.0) < 2e-3, f"{name}({param}): integral {integral}"


def test_uniform_cone_narrow():
    # A narrow cone (cos_max = 0.99) on a grid that covers only cos in
    # [0.98, 1]; nothing may fall outside the cone. Confidence as above.
    cos_max = 0.99
    _, v = sample("uniform_cone", cos_max, seed=2)
    assert (v[:, 2] >= np.float32(cos_max) - 1e-6).all()
    p, msg, integral, n_out = sphere_gof(v, pdf_fn("uniform_cone", cos_max), N,
                                         n_cos=20, n_phi=40, z_range=(0.98, 1.0))
    assert n_out == 0
    assert p > ALPHA, msg
    assert abs(integral - 1.0) < 2e-3


@pytest.mark.parametrize("kappa", KAPPAS)
def test_vmf_rescaled(kappa):
    # For every kappa, t = kappa (1 - cos theta) has the exact law
    # P(t <= s) = (1 - e^{-s}) / (1 - e^{-2 kappa}) on [0, 2 kappa] (integrate
    # supplemental Eq. 1 over the cap), and phi is uniform and independent.
    # This works where the (cos theta, phi) grid cannot resolve the lobe
    # (kappa >= 1e3: all mass within 1 - cos < 1e-2).
    # Tests (each at significance 1e-4): KS of t; chi-square of the joint
    # (F(t), phi) histogram on 20 x 40 equiprobable cells.
    k = float(np.float32(kappa))  # the binding takes a float32 kappa
    _, v = sample("vmf", kappa, seed=3)
    assert np.isfinite(v).all()
    t = k * one_minus_cos(v)
    assert (t >= 0).all() and (t <= 2 * k * (1 + 1e-6) + 1e-12).all()
    denom = -math.expm1(-2.0 * k)
    cdf = lambda s: -np.expm1(-np.asarray(s)) / denom
    ks = stats.kstest(t, cdf)
    assert ks.pvalue > ALPHA, f"kappa={kappa}: KS D={ks.statistic:.3g} p={ks.pvalue:.3g}"
    phi = np.mod(np.arctan2(v[:, 1].astype(np.float64), v[:, 0]), 2 * np.pi)
    it = np.minimum((np.clip(cdf(t), 0, 1) * 20).astype(int), 19)
    ip = np.minimum((phi / (2 * np.pi) * 40).astype(int), 39)
    obs = np.bincount(it * 40 + ip, minlength=800)
    _, _, p, msg = chi2_test(obs, np.full(800, N / 800.0), N)
    assert p > ALPHA, f"kappa={kappa}: {msg}"


@pytest.mark.parametrize("kappa", KAPPAS)
def test_vmf_pdf_values_and_normalisation(kappa):
    k = float(np.float32(kappa))
    # Pointwise against supplemental Eq. 1 at float32-representable cosines
    # (dense near the pole, where the lobe of large kappa lives).
    s = np.concatenate([np.geomspace(1e-12, 2.0, 4000), np.linspace(0, 2, 2001)])
    z = np.unique((1.0 - s).astype(np.float32))
    v = np.stack([np.sqrt(np.maximum(0, 1 - z.astype(np.float64) ** 2)), np.zeros_like(z, dtype=np.float64),
                  z], axis=1).astype(np.float32)
    p = _core.warp_pdf("vmf", v, kappa)
    assert np.isfinite(p).all() and (p >= 0).all()
    ref = vmf_pdf_ref(z.astype(np.float64), k)
    np.testing.assert_allclose(p, ref, rtol=1e-9, atol=1e-300)

    # Normalisation: 2 pi integral_{-1}^{1} pdf(z) dz over float32 nodes
    # z_j (in float64 quadrature), nodes as dense as float32 allows near the
    # pole. Between nodes the density is interpolated log-linearly, which is
    # exact for an exponential in z, so the rule stays exact even when the
    # float32 spacing (6e-8) exceeds the lobe width 1/kappa (kappa = 1e8).
    z = np.unique(np.concatenate([np.float32(1.0) - np.arange(0, 4096, dtype=np.float32) * np.float32(2.0 ** -24),
                                  (1.0 - np.geomspace(1e-9, 2.0, 200000)).astype(np.float32),
                                  np.float32([-1.0, 1.0])]))
    v = np.stack([np.sqrt(np.maximum(0, 1 - z.astype(np.float64) ** 2)), np.zeros(len(z)), z],
                 axis=1).astype(np.float32)
    p = _core.warp_pdf("vmf", v, kappa)
    zd, h = z.astype(np.float64), np.diff(z.astype(np.float64))
    pa, pb = p[:-1], p[1:]
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.log(pb / pa)
        seg = np.where(np.abs(lr) > 1e-8, (pb - pa) * h / lr, 0.5 * (pa + pb) * h)
    seg = np.where((pa == 0) | (pb == 0), 0.5 * (pa + pb) * h, seg)
    total = 2 * math.pi * seg.sum()
    # Tolerance: float32 nodes are exact, so the rule is exact up to float64
    # round-off summed over ~2e5 segments.
    assert abs(total - 1.0) < 1e-6, f"kappa={kappa}: integral {total}"


@pytest.mark.parametrize("kappa", KAPPAS + [0.0, 1e-30, 1e30, 88.0, 89.0, 710.0])
def test_vmf_extremes_finite(kappa):
    # Including the corners of [0,1)^2 and the largest float32 below one.
    one_m = np.float32(1) - np.float32(2.0 ** -24)
    u = np.array([[0, 0], [0, one_m], [one_m, 0], [one_m, one_m], [0.5, 0.5], [0.25, 1e-30]],
                 dtype=np.float32)
    v = _core.warp_sample("vmf", u, kappa)
    assert np.isfinite(v).all(), (kappa, v)
    np.testing.assert_allclose(np.linalg.norm(v.astype(np.float64), axis=1), 1.0, atol=1e-6)
    p = _core.warp_pdf("vmf", v, kappa)
    assert np.isfinite(p).all() and (p >= 0).all(), (kappa, p)
    # The pole and the antipode.
    p = _core.warp_pdf("vmf", np.float32([[0, 0, 1], [0, 0, -1]]), kappa)
    assert np.isfinite(p).all() and (p >= 0).all(), (kappa, p)
    assert p[0] >= p[1]


# --- 2. every pdf integrates to one (independent quadrature) ------------------


@pytest.mark.parametrize("name,param", SPHERE_WARPS)
def test_pdf_integrates_to_one_mc(name, param):
    # Monte Carlo with 2e6 stratified uniform-sphere directions (a 1000 x 2000
    # grid in (cos theta, phi), one jittered node per cell): for these
    # densities (peak / mean <= 20) the estimate 4 pi mean(pdf) has relative
    # standard deviation < 1e-4; tolerance 5e-3 (the cone edge and the
    # hemisphere edge at cos = 0 are resolved to one cell row, 2e-3).
    # Narrow lobes (vMF kappa >= 1e3) are checked by the exact quadrature of
    # test_vmf_pdf_values_and_normalisation instead.
    rng = np.random.default_rng(7)
    nz, nphi = 1000, 2000
    z = -1 + (np.arange(nz)[:, None] + rng.random((nz, nphi))) * (2.0 / nz)
    phi = (np.arange(nphi)[None, :] + rng.random((nz, nphi))) * (2 * np.pi / nphi)
    r = np.sqrt(np.maximum(0, 1 - z * z))
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1).reshape(-1, 3).astype(np.float32)
    est = 4 * np.pi * _core.warp_pdf(name, d, param).mean()
    assert abs(est - 1.0) < 5e-3, f"{name}({param}): {est}"


# --- planar warps --------------------------------------------------------------


def test_uniform_disk():
    # Points inside the unit disk; chi-square over 20 x 40 equal-area polar
    # cells (r^2, phi), expected N / 800 each; significance 1e-4.
    u, v = sample("uniform_disk", 0.0, seed=11)
    assert np.isfinite(v).all() and (v[:, 2] == 0).all()
    x, y = v[:, 0].astype(np.float64), v[:, 1].astype(np.float64)
    r2 = x * x + y * y
    assert (r2 <= 1 + 1e-6).all()
    phi = np.mod(np.arctan2(y, x), 2 * np.pi)
    ir = np.minimum((r2 * 20).astype(int), 19)
    ip = np.minimum((phi / (2 * np.pi) * 40).astype(int), 39)
    obs = np.bincount(ir * 40 + ip, minlength=800)
    _, _, p, msg = chi2_test(obs, np.full(800, N / 800), N)
    assert p > ALPHA, msg
    # The centre of the square maps to the centre of the disk; corners to the rim.
    c = _core.warp_sample("uniform_disk", np.float32([[0.5, 0.5], [0, 0], [0, 0.5]]), 0.0)
    np.testing.assert_allclose(c[0], 0, atol=1e-7)
    np.testing.assert_allclose(np.hypot(c[1:, 0], c[1:, 1]), 1, atol=1e-6)


def test_uniform_triangle():
    # Barycentrics (b1, b2) uniform on {b1, b2 >= 0, b1 + b2 <= 1}: chi-square
    # over a 20 x 20 grid of the unit square clipped to the triangle (interior
    # cells area h^2, diagonal cells h^2 / 2); significance 1e-4.
    u, v = sample("uniform_triangle", 0.0, seed=12)
    b1, b2 = v[:, 0].astype(np.float64), v[:, 1].astype(np.float64)
    assert np.isfinite(v).all()
    assert (b1 >= 0).all() and (b2 >= 0).all() and (b1 + b2 <= 1 + 1e-6).all()
    n = 20
    i = np.minimum((b1 * n).astype(int), n - 1)
    j = np.minimum((b2 * n).astype(int), n - 1)
    obs = np.bincount(i * n + j, minlength=n * n)
    I, J = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    area = np.where(I + J < n - 1, 1.0, np.where(I + J == n - 1, 0.5, 0.0)) / n ** 2
    _, _, p, msg = chi2_test(obs, (area / 0.5).ravel() * N, N)
    assert p > ALPHA, msg


# --- DiscreteDistribution (cpp/core/distribution.h) --------------------------
# Tables of 16 bins and more search only the bins a guide table allows; the
# index and the rescaled u must be those of the inverse CDF over the whole table.

def _discrete_reference(weights: np.ndarray, u: np.ndarray):
    """The inverse CDF as distribution.h defines it, in numpy (double CDF)."""
    w = np.where(np.isfinite(weights) & (weights > 0), weights.astype(np.float64), 0.0)
    cdf = np.concatenate([[0.0], np.cumsum(w)])
    cdf = cdf / cdf[-1]
    cdf[-1] = 1.0
    pmf = (cdf[1:] - cdf[:-1]).astype(np.float32)
    x = u.astype(np.float64)
    idx = np.minimum(np.searchsorted(cdf[1:], x, side="right"), len(w) - 1)
    for k in range(len(idx)):   # skip zero-probability bins, as the C++ does
        while pmf[idx[k]] == 0.0 and idx[k] + 1 < len(w):
            idx[k] += 1
    lo, width = cdf[idx], cdf[idx + 1] - cdf[idx]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(width > 0, np.clip((x - lo) / width, 0.0, np.float32(1 - 2**-24)), 0.0)
    return idx, r.astype(np.float32)


@pytest.mark.parametrize("size", [1, 5, 15, 16, 17, 256, 1000, 4096])
@pytest.mark.parametrize("kind", ["equal", "random", "zeros", "spiky"])
def test_discrete_sample_is_the_inverse_cdf(size, kind):
    rng = np.random.default_rng(size * 31 + len(kind))
    if kind == "equal":
        w = np.ones(size, np.float32)
    elif kind == "random":
        w = rng.random(size).astype(np.float32)
    elif kind == "zeros":   # runs of empty bins, a NaN and an Inf among them
        w = (rng.random(size) * (rng.random(size) < 0.3)).astype(np.float32)
        w[0] = 0.0
        if size > 3:
            w[1], w[2] = np.nan, np.inf
        if not np.any(w[np.isfinite(w)] > 0):
            w[-1] = 1.0
    else:                   # a few bins carry almost all the mass
        w = (10.0 ** rng.uniform(-8, 8, size)).astype(np.float32)
    # random u, the bucket edges j/m as floats and their neighbours, 0 and 1-
    edges = (np.arange(size + 1) / size).astype(np.float32)
    u = np.concatenate([rng.random(20000).astype(np.float32), edges,
                        np.nextafter(edges, np.float32(0)), np.nextafter(edges, np.float32(1)),
                        [0.0, np.float32(1 - 2**-24)]]).astype(np.float32)
    u = u[(u >= 0) & (u < 1)]
    idx, r = _core.discrete_sample(w, u)
    ref_idx, ref_r = _discrete_reference(w, u)
    np.testing.assert_array_equal(idx, ref_idx)
    np.testing.assert_array_equal(r, ref_r)


def test_discrete_sample_errors():
    with pytest.raises(ValueError, match="positive finite sum"):
        _core.discrete_sample(np.zeros(20, np.float32), np.array([0.5], np.float32))
    with pytest.raises(ValueError, match="u must lie"):
        _core.discrete_sample(np.ones(20, np.float32), np.array([1.0], np.float32))
