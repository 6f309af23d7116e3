"""Statistical and analytic tests of the BSDFs (cpp/scene/bsdf.cpp,
microfacet.h, fresnel.h) through the _core test entry points.

Conventions (Mitsuba 3's): local frame = identity, normal +z; wi points to the
viewer; eval returns f(wi, wo) |cos wo|; radiance transport, so a refraction
from the side of wi (IOR eta_i) into the side of wo (eta_o) carries
(eta_i / eta_o)^2.

Every goodness-of-fit test rejects at significance ALPHA = 1e-4; seeds are
fixed.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate

from mpg import _core
from stats_util import ALPHA, binomial_z, sphere_gof, uniform_u

N = 500_000
ETA = 1.5

# --- helpers ------------------------------------------------------------------


def direction(cos_theta, phi=0.0):
    s = math.sqrt(max(0.0, 1.0 - cos_theta * cos_theta))
    return (s * math.cos(phi), s * math.sin(phi), cos_theta)


def normalized(v):
    v = np.asarray(v, dtype=np.float64)
    return tuple(v / np.linalg.norm(v))


def make(kind, **p):
    """A fresh scene with one BSDF (plus its children). Returns (scene, id)."""
    s = _core.Scene()
    if kind in ("diffuse", "plastic"):
        p.setdefault("reflectance", s.add_texture_constant(p.pop("albedo", [0.7, 0.5, 0.3])))
    if kind in ("conductor", "roughconductor"):
        p.setdefault("eta", [0.2, 0.92, 1.1])  # gold-ish
        p.setdefault("k", [3.9, 2.45, 2.2])
    if kind in ("dielectric", "roughdielectric", "thindielectric", "plastic"):
        p.setdefault("int_ior", ETA)
        p.setdefault("ext_ior", 1.0)
    return s, s.add_bsdf(kind, p)


def make_normalmap(child_kind, normal, **p):
    s = _core.Scene()
    if child_kind == "diffuse":
        p.setdefault("reflectance", s.add_texture_constant([0.8, 0.8, 0.8]))
    else:
        p.setdefault("eta", [0.2, 0.92, 1.1])
        p.setdefault("k", [3.9, 2.45, 2.2])
    child = s.add_bsdf(child_kind, p)
    n = np.asarray(normalized(normal))
    tex = s.add_texture_constant(list(0.5 * (n + 1.0)))  # value v -> normal 2v - 1
    return s, s.add_bsdf("normalmap", {"nested": child, "normalmap": tex})


def make_twosided_diffuse():
    s = _core.Scene()
    f = s.add_bsdf("diffuse", {"reflectance": s.add_texture_constant([0.8, 0.6, 0.4])})
    bk = s.add_bsdf("diffuse", {"reflectance": s.add_texture_constant([0.3, 0.5, 0.9])})
    return s, s.add_bsdf("twosided", {"front": f, "back": bk})


def sample(sb, wi, n=N, seed=5):
    s, b = sb
    u = uniform_u(n, 3, seed)
    return _core.bsdf_sample(s, b, wi, u)


def energy_factor(wi, wo, eta):
    """Radiance weights of refraction carry (eta_i/eta_o)^2; multiplying by
    (eta_o/eta_i)^2 turns the weight into the fraction of energy carried."""
    trans = (wo[:, 2] * wi[2]) < 0
    eta_it = eta if wi[2] > 0 else 1.0 / eta  # eta_o / eta_i for a refraction
    return np.where(trans, eta_it ** 2, 1.0)


# --- 3. sampling matches the pdf ------------------------------------------------

CHI2_CASES = []


def _case(name, factory, wi, sub=32):
    CHI2_CASES.append(pytest.param(factory, wi, sub, id=name))


_case("diffuse", lambda: make("diffuse"), direction(0.8))
_case("diffuse-grazing", lambda: make("diffuse"), direction(0.05))
for dist in ("ggx", "beckmann"):
    for a in (0.05, 0.3, 0.8):
        sub = 64 if a <= 0.05 else 32
        _case(f"roughconductor-{dist}-a{a}", lambda d=dist, a=a: make("roughconductor", alpha=a, distribution=d),
              direction(0.7, 0.3), sub)
    _case(f"roughconductor-{dist}-aniso", lambda d=dist: make("roughconductor", alpha_u=0.1, alpha_v=0.5, distribution=d),
          direction(0.6, 0.7), 48)
    _case(f"roughconductor-{dist}-grazing", lambda d=dist: make("roughconductor", alpha=0.3, distribution=d),
          direction(0.05, 1.0))
for a in (0.3, 0.8):
    _case(f"roughconductor-ggx-nonvisible-a{a}",
          lambda a=a: make("roughconductor", alpha=a, distribution="ggx", sample_visible=False), direction(0.5))
for dist in ("ggx", "beckmann"):
    for a in (0.05, 0.3, 0.8):
        for c in (0.7, -0.7, 0.05, -0.05):
            sub = 64 if a <= 0.05 else 32
            _case(f"roughdielectric-{dist}-a{a}-cos{c}",
                  lambda d=dist, a=a: make("roughdielectric", alpha=a, distribution=d), direction(c, 0.4), sub)
_case("roughdielectric-ggx-nonvisible-a0.5-cos0.3",
      lambda: make("roughdielectric", alpha=0.5, distribution="ggx", sample_visible=False), direction(0.3))
_case("roughdielectric-ggx-nonvisible-a0.5-cos-0.3",
      lambda: make("roughdielectric", alpha=0.5, distribution="ggx", sample_visible=False), direction(-0.3))
_case("roughdielectric-beckmann-aniso", lambda: make("roughdielectric", alpha_u=0.1, alpha_v=0.4), direction(-0.6, 0.9), 48)
_case("plastic", lambda: make("plastic"), direction(0.6))
_case("plastic-grazing-nonlinear", lambda: make("plastic", nonlinear=True), direction(0.1))
_case("normalmap-diffuse", lambda: make_normalmap("diffuse", (0.5, 0.2, 0.8)), direction(0.7, 2.0))
_case("normalmap-roughconductor", lambda: make_normalmap("roughconductor", (0.5, 0.2, 0.8), alpha=0.3,
                                                          distribution="ggx"), direction(0.7, 0.3))
_case("twosided-diffuse-back", make_twosided_diffuse, direction(-0.6, 1.0))


@pytest.mark.parametrize("factory,wi,sub", CHI2_CASES)
def test_sampling_matches_pdf(factory, wi, sub):
    # Chi-square of the N = 5e5 sampled non-delta directions against
    # bsdf_pdf over 20 x 40 (cos theta, phi) cells of the full sphere, pdf
    # integrated with sub x sub midpoint nodes per cell (64 for alpha = 0.05
    # lobes); reject at p < 1e-4.
    sb = factory()
    s, b = sb
    wo, w, pdf, delta = sample(sb, wi)
    assert np.isfinite(wo).all() and np.isfinite(w).all() and np.isfinite(pdf).all()
    assert (w >= 0).all() and (pdf >= 0).all()
    ok = (~delta) & (pdf > 0)
    # Failed (absorbed) samples carry zero weight.
    assert (w[(~delta) & (pdf == 0)] == 0).all()
    wo_ok = wo[ok]
    np.testing.assert_allclose(np.linalg.norm(wo_ok.astype(np.float64), axis=1), 1.0, atol=1e-5)

    # pdf from sample() == bsdf_pdf(wo); weight == eval / pdf (float32 round-off,
    # amplified by the wo -> world -> local round trip of a normal map).
    rtol = 2e-3 if "normalmap" in str(factory) else 1e-4
    p_re = _core.bsdf_pdf(s, b, wi, wo_ok)
    np.testing.assert_allclose(pdf[ok], p_re, rtol=rtol)
    f = _core.bsdf_eval(s, b, wi, wo_ok)
    np.testing.assert_allclose(w[ok], f / p_re[:, None], rtol=rtol, atol=1e-6)

    p, msg, integral, n_out = sphere_gof(wo_ok, lambda v: _core.bsdf_pdf(s, b, wi, v), N, sub=sub)
    assert p > ALPHA, msg
    # The pdf integrates to the probability that sample() returns a non-delta
    # direction (binomial; |z| < 5, plus 2e-3 for the quadrature).
    frac = ok.mean()
    sd = math.sqrt(max(integral * (1 - integral), 1e-12) / N)
    assert abs(frac - integral) < 5 * sd + 2e-3, f"valid fraction {frac} vs pdf integral {integral}"
    assert integral <= 1 + 2e-3


# --- 4. energy -------------------------------------------------------------------

ENERGY_BSDFS = {
    "diffuse-white": lambda: make("diffuse", albedo=[1, 1, 1]),
    "roughconductor-ggx-a0.05": lambda: make("roughconductor", alpha=0.05, distribution="ggx"),
    "roughconductor-ggx-a0.8-mirror": lambda: make("roughconductor", alpha=0.8, distribution="ggx", eta=[0, 0, 0],
                                                   k=[1e4, 1e4, 1e4]),
    "roughconductor-beckmann-a0.8-mirror": lambda: make("roughconductor", alpha=0.8, eta=[0, 0, 0], k=[1e4, 1e4, 1e4]),
    "roughconductor-ggx-nonvisible-a0.5-mirror": lambda: make("roughconductor", alpha=0.5, distribution="ggx",
                                                              sample_visible=False, eta=[0, 0, 0], k=[1e4, 1e4, 1e4]),
    "roughconductor-aniso-mirror": lambda: make("roughconductor", alpha_u=0.05, alpha_v=0.6, distribution="ggx",
                                                eta=[0, 0, 0], k=[1e4, 1e4, 1e4]),
    "roughdielectric-ggx-a0.1": lambda: make("roughdielectric", alpha=0.1, distribution="ggx"),
    "roughdielectric-ggx-a0.8": lambda: make("roughdielectric", alpha=0.8, distribution="ggx"),
    "roughdielectric-beckmann-a0.5": lambda: make("roughdielectric", alpha=0.5),
    "roughdielectric-ggx-nonvisible-a0.8": lambda: make("roughdielectric", alpha=0.8, distribution="ggx",
                                                         sample_visible=False),
    "dielectric": lambda: make("dielectric"),
    "thindielectric": lambda: make("thindielectric"),
    "conductor-mirror": lambda: make("conductor", eta=[0, 0, 0], k=[1e4, 1e4, 1e4]),
    "plastic-white": lambda: make("plastic", albedo=[1, 1, 1]),
    "plastic-white-nonlinear": lambda: make("plastic", albedo=[1, 1, 1], nonlinear=True),
    "twosided-diffuse": make_twosided_diffuse,
    "normalmap-diffuse": lambda: make_normalmap("diffuse", (0.5, 0.2, 0.8)),
    "null": lambda: make("null"),
}
ENERGY_COS = (1.0, 0.7, 0.3, 0.05, -0.05, -0.3, -0.7, -1.0)


@pytest.mark.parametrize("name", list(ENERGY_BSDFS))
def test_albedo_at_most_one(name):
    # Energy albedo E[weight * (eta_o/eta_i)^2 on refraction] over 2e5 samples
    # per wi must not exceed 1 by more than 5 standard errors + 1e-3 (a
    # one-sided z-test at about 3e-7 per wi).
    sb = ENERGY_BSDFS[name]()
    for c in ENERGY_COS:
        wi = direction(c, 0.3)
        wo, w, pdf, delta = sample(sb, wi, n=200_000, seed=21)
        assert np.isfinite(w).all() and (w >= 0).all(), (name, c)
        # (a thin sheet transmits back into the same medium: no eta factor)
        crosses = name.startswith("dielectric") or name.startswith("roughdielectric")
        e = w.max(axis=1) * (energy_factor(wi, wo, ETA) if crosses else 1.0)
        m, se = e.mean(), e.std() / math.sqrt(len(e))
        assert m <= 1 + 5 * se + 1e-3, f"{name} cos_i={c}: albedo {m:.5f} +- {se:.1e}"


def test_white_diffuse_albedo_is_one():
    sb = make("diffuse", albedo=[1, 1, 1])
    for c in (1.0, 0.5, 1e-3):
        wo, w, pdf, delta = sample(sb, direction(c), n=100_000)
        ok = pdf > 0
        assert ok.all() and not delta.any()
        np.testing.assert_allclose(w, 1.0, rtol=1e-6)
        assert (wo[:, 2] >= 0).all()


def test_white_plastic_diffuse_albedo():
    # With a white base the diffuse layer of plastic returns all light that
    # enters it: the energy is E[weight] = F(cos_i) + (1 - F(cos_i)) * A,
    # A = 2 int (1 - F_o(mu)) mu dmu / (eta^2 (1 - fdr_int)) (Mitsuba's model).
    # A = (1 - fdr_ext) / (eta^2 (1 - fdr_int)) = 1 by the reciprocity
    # relation 1 - fdr_ext = eta^2 (1 - fdr_int); tolerance 5 se + 2e-3.
    sb = make("plastic", albedo=[1, 1, 1])
    for c in (0.9, 0.4):
        wo, w, pdf, delta = sample(sb, direction(c), n=400_000)
        e = w[:, 0]
        m, se = e.mean(), e.std() / math.sqrt(len(e))
        assert abs(m - 1.0) < 5 * se + 2e-3, (c, m, se)


@pytest.mark.parametrize("cos_i", [1.0, 0.8, 0.3, 0.02, -0.02, -0.5, -0.7, -0.74, -0.9, -1.0])
def test_smooth_dielectric(cos_i):
    # Reflection fraction ~ F (binomial, |z| < 5); reflection weight 1,
    # refraction weight eta_ti^2 exactly; E[weight] = F + (1-F) eta_ti^2
    # (radiance) within 5 se; directions obey the mirror law and Snell's law.
    sb = make("dielectric")
    wi = direction(cos_i, 0.9)
    n = 200_000
    wo, w, pdf, delta = sample(sb, wi, n=n, seed=31)
    assert delta.all() and np.isfinite(w).all()
    F, cos_t, eta_it, eta_ti = ref_fresnel(abs(cos_i), ETA if cos_i > 0 else 1 / ETA)
    refl = wo[:, 2] * cos_i > 0
    k = int(refl.sum())
    assert abs(binomial_z(k, n, F)) < 5 or (F in (0.0, 1.0) and k == n * F), (k / n, F)
    np.testing.assert_allclose(w[refl], 1.0, rtol=1e-6)
    np.testing.assert_allclose(w[~refl], eta_ti ** 2, rtol=1e-5)
    expect = F + (1 - F) * eta_ti ** 2
    se = w[:, 0].std() / math.sqrt(n)
    assert abs(w[:, 0].mean() - expect) < 5 * se + 1e-6
    wi_a = np.array(wi)
    np.testing.assert_allclose(wo[refl], np.broadcast_to(wi_a * [-1, -1, 1], wo[refl].shape), atol=1e-6)
    if (~refl).any():
        t = wo[~refl].astype(np.float64)
        np.testing.assert_allclose(np.hypot(t[:, 0], t[:, 1]), eta_ti * math.sqrt(1 - cos_i ** 2), atol=1e-5)
        np.testing.assert_allclose(t[:, 2], -math.copysign(cos_t, cos_i), atol=1e-5)
        np.testing.assert_allclose(t[:, :2], np.broadcast_to(-eta_ti * wi_a[:2], t[:, :2].shape), atol=1e-5)


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
@pytest.mark.parametrize("alpha", [0.1, 0.5])
def test_index_matched_rough_dielectric(dist, alpha):
    # int_ior == ext_ior: the interface is invisible. Everything must pass
    # straight through (wo = -wi, weight 1, albedo exactly 1); eval/pdf have
    # no non-delta part.
    sb = make("roughdielectric", alpha=alpha, distribution=dist, int_ior=1.33, ext_ior=1.33)
    s, b = sb
    for c in (0.9, 0.2, -0.6):
        wi = direction(c, 0.5)
        wo, w, pdf, delta = sample(sb, wi, n=20_000)
        np.testing.assert_allclose(w, 1.0, rtol=1e-6)
        np.testing.assert_allclose(wo, np.broadcast_to(-np.array(wi), wo.shape), atol=1e-6)
        dirs = _core.warp_sample("uniform_sphere", uniform_u(10_000, 2, 3), 0.0)
        assert (_core.bsdf_eval(s, b, wi, dirs) == 0).all()
        assert (_core.bsdf_pdf(s, b, wi, dirs) == 0).all()


def test_rough_dielectric_approaches_smooth():
    # alpha -> 0: the rough dielectric's energy split tends to the smooth one,
    # F + (1 - F) eta_ti^2 in radiance units (5 se + 1e-2 for the residual
    # masking at alpha = 1e-3).
    for c in (0.8, 0.3, -0.5):
        wi = direction(c)
        F, _, _, eta_ti = ref_fresnel(abs(c), ETA if c > 0 else 1 / ETA)
        wo, w, pdf, delta = sample(make("roughdielectric", alpha=1e-3, distribution="ggx"), wi, n=200_000)
        refl = wo[:, 2] * c > 0
        m, se = w[:, 0].mean(), w[:, 0].std() / math.sqrt(len(w))
        assert abs(m - (F + (1 - F) * eta_ti ** 2)) < 5 * se + 1e-2, (c, m)
        assert abs(refl.mean() - F) < 5 * math.sqrt(F * (1 - F) / len(w)) + 1e-2


# --- 5. reciprocity ------------------------------------------------------------------


def random_dirs(n, seed, lower=False):
    v = _core.warp_sample("cosine_hemisphere", uniform_u(n, 2, seed), 0.0).astype(np.float64)
    v = v[v[:, 2] > 0.02]
    if lower:
        v[:, 2] = -v[:, 2]
    return v


def f_over_cos(s, b, wi, wo):
    """f(wi, wo) for one wi and many wo."""
    return _core.bsdf_eval(s, b, tuple(wi), wo.astype(np.float32)).astype(np.float64) / np.abs(wo[:, 2:3])


def swapped(s, b, wis, wo):
    """f(wo, wi_j) for many wi_j (one call per pair)."""
    out = np.array([_core.bsdf_eval(s, b, tuple(wo), np.float32([w_]))[0] for w_ in wis], dtype=np.float64)
    return out / np.abs(np.asarray(wis, dtype=np.float64)[:, 2:3])


RECIPROCAL = {
    "diffuse": lambda: make("diffuse"),
    "roughconductor-ggx": lambda: make("roughconductor", alpha=0.3, distribution="ggx"),
    "roughconductor-beckmann": lambda: make("roughconductor", alpha=0.3),
    "roughconductor-aniso": lambda: make("roughconductor", alpha_u=0.2, alpha_v=0.6, distribution="ggx"),
    "plastic": lambda: make("plastic"),
    "roughdielectric-reflection": lambda: make("roughdielectric", alpha=0.4, distribution="ggx"),
}


@pytest.mark.parametrize("name", list(RECIPROCAL))
def test_reciprocity_reflection(name):
    # f(wi, wo) == f(wo, wi) for reflection, to float32 round-off (rtol 1e-4)
    # at 300 random pairs.
    s, b = RECIPROCAL[name]()
    wis = random_dirs(300, 41)
    wos = random_dirs(300, 42)
    n = min(len(wis), len(wos))
    for flip in ((False,) if "dielectric" not in name else (False, True)):
        a_s, a_o = (wis[:n], wos[:n]) if not flip else (wis[:n] * [1, 1, -1], wos[:n] * [1, 1, -1])
        fw = np.array([f_over_cos(s, b, a_s[i], a_o[i:i + 1])[0] for i in range(n)])
        bw = np.array([swapped(s, b, [a_s[i]], a_o[i])[0] for i in range(n)])
        assert (fw > 0).any()
        np.testing.assert_allclose(fw, bw, rtol=1e-4, atol=1e-7 * fw.max())


@pytest.mark.parametrize("dist", ["ggx", "beckmann"])
@pytest.mark.parametrize("alpha", [0.1, 0.5])
def test_reciprocity_rough_transmission(dist, alpha):
    # Radiance-mode BTDF of the code: f(wi, wo) = (1-F) D G |wi.m||wo.m| /
    # (|cos_i||cos_o| (wi.m + eta_p wo.m)^2), eta_p = eta_o / eta_i (Walter 2007
    # Eq. 21 times 1/eta_p^2). Swapping the arguments keeps m, F, D, G and
    # divides the denominator by eta_p^2, so
    #     f(wo, wi) = eta_p^2 f(wi, wo),  i.e.  f(wi, wo) / eta_i^2 = f(wo, wi) / eta_o^2,
    # with eta_i the IOR on the side of wi. This is Veach 1997 Eq. 5.14,
    # f(w_light -> w_out) / eta_out^2 = f(w_out -> w_light) / eta_light^2, since
    # here light arrives along wo and leaves along wi. Asserted to rtol 1e-3
    # (float32 round-off of the half vector is amplified in the far tail of D,
    # e.g. a Beckmann exponent tan^2/alpha^2 ~ 100) or 1e-7 absolute.
    s, b = make("roughdielectric", alpha=alpha, distribution=dist)
    checked = 0
    for side in (1.0, -1.0):  # wi outside / inside
        eta_i, eta_o = (1.0, ETA) if side > 0 else (ETA, 1.0)
        # Pairs (wi, wo) drawn from the BSDF itself, so that they lie in the
        # transmission lobe: 40 wi, 5 refracted wo each.
        for j, wi in enumerate(random_dirs(40, 51 + int(side))):
            wi = wi * [1, 1, side]
            wo, _, pdf, delta = sample((s, b), tuple(wi), n=64, seed=100 + j)
            wo = wo[(pdf > 0) & (wo[:, 2] * side < 0)][:5].astype(np.float64)
            for o in wo:
                f_io = f_over_cos(s, b, wi, o[None])[0, 0]
                f_oi = swapped(s, b, [wi], o)[0, 0]
                if f_io == 0 and f_oi == 0:
                    continue
                checked += 1
                assert f_io / eta_i ** 2 == pytest.approx(f_oi / eta_o ** 2, rel=1e-3, abs=1e-6), (wi, o, f_io, f_oi)
    assert checked > 150


# --- 6. Fresnel -------------------------------------------------------------------------


def ref_fresnel(cos_i, eta):
    """Independent float64 unpolarised Fresnel reflectance (Hecht, Optics
    Eqs. 4.42-4.43) for light arriving at |cos_i| on the side whose relative
    IOR to the other side is eta = eta_t / eta_i. Returns (F, |cos_t|, eta, 1/eta)."""
    ci = abs(cos_i)
    if eta == 1:
        return 0.0, ci, 1.0, 1.0
    st2 = (1 - ci * ci) / (eta * eta)
    if st2 >= 1:
        return 1.0, 0.0, eta, 1 / eta
    ct = math.sqrt(1 - st2)
    rs = (ci - eta * ct) / (ci + eta * ct)
    rp = (eta * ci - ct) / (eta * ci + ct)
    return 0.5 * (rs * rs + rp * rp), ct, eta, 1 / eta


def fresnel_sensitivity(cos_i, eta):
    """|dF/d(sin_t^2)| of the reference, by a central difference in cos_t^2."""
    ci = abs(cos_i)
    ct2 = 1 - (1 - ci * ci) / (eta * eta)
    if eta == 1 or ct2 <= 0:
        return 0.0

    def F_of(ct2_):
        ct = math.sqrt(max(ct2_, 0.0))
        rs = (ci - eta * ct) / (ci + eta * ct)
        rp = (eta * ci - ct) / (eta * ci + ct)
        return 0.5 * (rs * rs + rp * rp)

    h = min(1e-9, ct2 / 2)
    return abs(F_of(ct2 + h) - F_of(ct2 - h)) / (2 * h)


@pytest.mark.parametrize("eta", [1.0, 1.0001, 1.33, 1.5046, 2.4, 1 / 1.5])
def test_fresnel_dielectric_vs_reference(eta):
    cosines = np.concatenate([np.linspace(-1, 1, 2001), [0.0, 1e-6, -1e-6, 1e-3, -1e-3]])
    for c in cosines:
        c = float(np.float32(c))
        F, cos_t, eta_it, eta_ti = _core.fresnel_dielectric(c, eta)
        rel = eta if c >= 0 else 1 / eta
        Fr, ctr, _, _ = ref_fresnel(c, rel)
        # Tolerance 2e-5 plus the float32 conditioning: near the critical angle
        # cos_t = sqrt(1 - sin_t^2) cancels, an error of 4 ulp of 1 in sin_t^2
        # moves F by |dF/d(sin_t^2)| * 2.4e-7 (finite difference in float64).
        tol = 2e-5 + fresnel_sensitivity(c, rel) * 2.4e-7
        assert F == pytest.approx(Fr, abs=tol), (c, eta)
        assert abs(cos_t) == pytest.approx(ctr, abs=2e-5 + 1.2e-7 / max(ctr, 1e-3)), (c, eta)
        assert eta_it == pytest.approx(rel, rel=1e-6) and eta_ti == pytest.approx(1 / rel, rel=1e-6)
        if ctr > 0:
            assert math.copysign(1, cos_t) == -math.copysign(1, c if c != 0 else 1.0)
        if Fr == 1.0 and c != 0:  # total internal reflection
            assert F == 1.0 and cos_t == 0.0, (c, eta, F, cos_t)


def test_fresnel_tir_and_grazing():
    eta = 1.5
    crit = math.sqrt(1 - 1 / eta ** 2)  # cos of the critical angle, inside
    for c in np.linspace(0, crit * (1 - 1e-4), 200)[1:]:
        F, cos_t, _, _ = _core.fresnel_dielectric(-float(c), eta)
        assert F == 1.0 and cos_t == 0.0
    # Just past the critical angle refraction resumes with F < 1.
    F, cos_t, _, _ = _core.fresnel_dielectric(-crit * 1.01, eta)
    assert F < 1.0 and cos_t > 0
    # Grazing from outside: F -> 1.
    assert _core.fresnel_dielectric(1e-6, eta)[0] > 0.999
    # Normal incidence ((eta - 1) / (eta + 1))^2 from both sides.
    r0 = ((eta - 1) / (eta + 1)) ** 2
    assert _core.fresnel_dielectric(1.0, eta)[0] == pytest.approx(r0, rel=1e-5)
    assert _core.fresnel_dielectric(-1.0, eta)[0] == pytest.approx(r0, rel=1e-5)


@pytest.mark.parametrize("eta", [0.2, 1.33, 1.5, 3.0])
def test_fresnel_conductor_k0_is_dielectric(eta):
    for c in np.linspace(0.001, 1, 300):
        c = float(np.float32(c))
        fc = _core.fresnel_conductor(c, eta, 0.0)
        fd = ref_fresnel(c, eta)[0]
        assert fc == pytest.approx(fd, abs=2e-5), (c, eta)
        # and k -> 0 continuously (k = 1e-6: near the critical angle of eta < 1
        # a small absorption already lowers the total reflection noticeably)
        assert _core.fresnel_conductor(c, eta, 1e-6) == pytest.approx(fd, abs=1e-3), (c, eta)


@pytest.mark.parametrize("eta,k", [(0.2, 3.9), (1.1, 2.2), (2.9, 3.0), (0.05, 0.0), (1.5, 0.0), (1e-3, 1e4)])
def test_fresnel_conductor_limits(eta, k):
    r0 = ((eta - 1) ** 2 + k ** 2) / ((eta + 1) ** 2 + k ** 2)
    assert _core.fresnel_conductor(1.0, eta, k) == pytest.approx(r0, rel=1e-5, abs=1e-6)
    # Grazing incidence reflects everything; everything stays in [0, 1].
    assert _core.fresnel_conductor(0.0, eta, k) == pytest.approx(1.0, abs=1e-5)
    vals = [_core.fresnel_conductor(float(c), eta, k) for c in np.linspace(0, 1, 101)]
    assert all(0 <= v <= 1 and math.isfinite(v) for v in vals)


def test_fresnel_conductor_vs_reference():
    # Complex-IOR Fresnel (Born & Wolf 14.2), float64 numpy, vs the float32 C++.
    def ref(c, eta, k):
        e = complex(eta, k)
        st2 = (1 - c * c) / (e * e)
        ct = np.sqrt(1 - st2)
        rs = (c - e * ct) / (c + e * ct)
        rp = (e * c - ct) / (e * c + ct)
        return 0.5 * (abs(rs) ** 2 + abs(rp) ** 2)

    for eta, k in [(0.2, 3.9), (1.1, 2.2), (2.9, 3.0), (0.5, 0.5)]:
        for c in np.linspace(0.01, 1, 100):
            c = float(np.float32(c))
            assert _core.fresnel_conductor(c, eta, k) == pytest.approx(ref(c, eta, k), abs=5e-5), (eta, k, c)


@settings(max_examples=400, deadline=None)
@given(c=st.floats(0.0, 1.0), eta=st.floats(1e-3, 20.0), k=st.one_of(st.just(0.0), st.floats(1e-6, 1e4)))
def test_fresnel_conductor_real_form_matches_the_complex_one(c, eta, k):
    """The core's real-arithmetic conductor Fresnel (a^2 + b^2 form, in double)
    against the complex form in float64 numpy, over indices from 1e-3 to 20
    and absorption from 0 to 1e4 (where the complex form's a^2 cancels), at
    every angle: within 1e-6 (the float result's rounding)."""
    c = float(np.float32(c))
    eta, k = float(np.float32(eta)), float(np.float32(k))
    e = complex(eta, k)
    ct = np.sqrt(1 - (1 - c * c) / (e * e))
    rs = (c - e * ct) / (c + e * ct)
    rp = (e * c - ct) / (e * c + ct)
    want = 0.5 * (abs(rs) ** 2 + abs(rp) ** 2) if c > 0 else 1.0
    got = _core.fresnel_conductor(c, eta, k)
    assert math.isfinite(got) and 0.0 <= got <= 1.0
    assert got == pytest.approx(min(max(want, 0.0), 1.0), abs=1e-6), (c, eta, k, want)


@pytest.mark.parametrize("eta", [1 / 1.7, 1 / 1.5, 1 / 1.33, 1 / 1.1, 1.1, 1.33, 1.5, 2.0])
def test_fresnel_diffuse_reflectance(eta):
    # 2 int_0^1 F(mu) mu dmu by adaptive quadrature of the float64 reference,
    # split at the critical angle; C++ within 1e-4 absolute.
    pts = [math.sqrt(1 - eta * eta)] if eta < 1 else None
    ref, _ = integrate.quad(lambda mu: 2 * mu * ref_fresnel(mu, eta)[0], 0, 1, points=pts, limit=200,
                            epsabs=1e-10)
    got = _core.fresnel_diffuse_reflectance(eta)
    assert got == pytest.approx(ref, abs=1e-4)
    if eta < 1:
        # Egan & Hilgeman 1973 fit for the internal case (as used by Mitsuba):
        # within 1% for 1/eta in [1.1, 1.7].
        eh = -1.4399 * eta ** 2 + 0.7099 * eta + 0.6681 + 0.0636 / eta
        assert got == pytest.approx(eh, rel=1e-2)


def test_fresnel_diffuse_reciprocity():
    # 1 - fdr(eta) = eta^2 (1 - fdr(1/eta)): the hemispherical transmittance
    # from outside equals eta^2 times the one from inside (Snell's law and
    # etendue; used by plastic's albedo). Within 2e-4.
    for eta in (1.1, 1.33, 1.5, 2.0):
        a = 1 - _core.fresnel_diffuse_reflectance(eta)
        bb = 1 - _core.fresnel_diffuse_reflectance(1 / eta)
        assert a == pytest.approx(eta ** 2 * bb, abs=2e-4)


# --- 7. numerically hard cases -------------------------------------------------------------

HARD_BSDFS = {
    "diffuse": lambda: make("diffuse"),
    "conductor": lambda: make("conductor"),
    "roughconductor-ggx": lambda: make("roughconductor", alpha=0.3, distribution="ggx"),
    "roughconductor-ggx-a1e-4": lambda: make("roughconductor", alpha=1e-4, distribution="ggx"),
    "roughconductor-beckmann-a1e-4": lambda: make("roughconductor", alpha=1e-4),
    "roughconductor-ggx-nonvisible-a1e-4": lambda: make("roughconductor", alpha=1e-4, distribution="ggx",
                                                        sample_visible=False),
    "roughconductor-aniso-a1e-4": lambda: make("roughconductor", alpha_u=1e-4, alpha_v=0.5, distribution="ggx"),
    "dielectric": lambda: make("dielectric"),
    "roughdielectric-ggx": lambda: make("roughdielectric", alpha=0.3, distribution="ggx"),
    "roughdielectric-ggx-a1e-4": lambda: make("roughdielectric", alpha=1e-4, distribution="ggx"),
    "roughdielectric-beckmann-a1e-4": lambda: make("roughdielectric", alpha=1e-4),
    "roughdielectric-beckmann-a1": lambda: make("roughdielectric", alpha=1.0),
    "thindielectric": lambda: make("thindielectric"),
    "plastic": lambda: make("plastic"),
    "twosided": make_twosided_diffuse,
    "normalmap-diffuse": lambda: make_normalmap("diffuse", (0.5, 0.2, 0.8)),
    "normalmap-degenerate": lambda: make_normalmap("diffuse", (0.0, 0.0, -1.0)),
    "null": lambda: make("null"),
}
ONE_SIDED = {"diffuse", "conductor", "roughconductor-ggx", "roughconductor-ggx-a1e-4",
             "roughconductor-beckmann-a1e-4", "roughconductor-ggx-nonvisible-a1e-4",
             "roughconductor-aniso-a1e-4", "plastic"}
HARD_WI = [(0, 0, 1), (0, 0, -1), direction(1e-6), direction(-1e-6), direction(1e-6, 1.3),
           (1, 0, 0), (0, 1, 0), direction(0.999999), direction(-0.999999, 2.0)]


@pytest.mark.parametrize("name", list(HARD_BSDFS))
def test_no_nan_in_hard_cases(name):
    s, b = HARD_BSDFS[name]()
    u = uniform_u(20_000, 3, 61)
    # corners of the sample domain too
    one_m = np.float32(1) - np.float32(2.0 ** -24)
    corners = np.array([[a, c, d] for a in (0, one_m) for c in (0, 0.5, one_m) for d in (0, 0.5, one_m)],
                       dtype=np.float32)
    u = np.concatenate([u, corners])
    probe = np.concatenate([_core.warp_sample("uniform_sphere", uniform_u(2000, 2, 62), 0.0),
                            np.float32([[0, 0, 1], [0, 0, -1], [1, 0, 0], direction(1e-6)])])
    for wi in HARD_WI:
        wo, w, pdf, delta = _core.bsdf_sample(s, b, wi, u)
        assert np.isfinite(wo).all() and np.isfinite(w).all() and np.isfinite(pdf).all(), (name, wi)
        assert (w >= 0).all() and (pdf >= 0).all(), (name, wi)
        ev = _core.bsdf_eval(s, b, wi, probe)
        pp = _core.bsdf_pdf(s, b, wi, probe)
        assert np.isfinite(ev).all() and np.isfinite(pp).all() and (ev >= 0).all() and (pp >= 0).all(), (name, wi)
        if name in ONE_SIDED and wi[2] < 0:
            # wi from below a one-sided BSDF: no light, not NaN.
            assert (w == 0).all() and (ev == 0).all() and (pp == 0).all(), (name, wi)
        # Non-delta samples: sample pdf matches bsdf_pdf (skip huge densities of
        # alpha = 1e-4 lobes where a float32 wo cannot hold the direction).
        ok = (~delta) & (pdf > 0) & (pdf < 1e4)
        if ok.any():
            p_re = _core.bsdf_pdf(s, b, wi, wo[ok])
            assert np.isfinite(p_re).all()
