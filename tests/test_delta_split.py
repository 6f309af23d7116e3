"""The delta split (design-notes "Splitting the light seen in the glass"): a
pixel's light seen from the camera through delta scattering only is averaged
over k camera paths per sample. Any map of k >= 1 fixed before the render keeps
the image unbiased, k = 1 is the plain render bit for bit, a split lowers the
variance of that light, and mpg learns k (Eq. 3 of mpg.chain_rates) only
where its training saw that light vary."""

from __future__ import annotations

import numpy as np
import pytest

import mpg
from mpg import _core
from mpg.chain_rates import STEP_COST, CostAccumulator, learn_delta_split
from stats_util import REGIONS_32, check_uniform_split, image_zmax, run_pass

RES = 32
REGIONS = REGIONS_32


@pytest.fixture(scope="module")
def sphere(sphere32):
    return sphere32


def _pass(sc, name, spp, seed, kmap=None, params=None):
    return run_pass(sc, name, spp, seed, params, delta_split_map=kmap)


def test_a_map_of_ones_is_the_plain_render(sphere):
    a = _pass(sphere, "path", 16, 5)
    b = _pass(sphere, "path", 16, 5, np.ones((RES, RES), np.float32))
    assert np.array_equal(a["sum"], b["sum"]) and np.array_equal(a["sum_sq"], b["sum_sq"])
    assert b["stats"]["delta_split_paths"] == 0


def test_a_split_keeps_the_image_unbiased_and_lowers_the_glints_variance(sphere):
    """A random map of k in 1..8 on the path tracer agrees with the plain path
    tracer (|z| < 5 on the image and four regions, p < 6e-7 each); in the pixels
    that see the light in the glass the per-sample variance falls (k = 8
    everywhere: below half of the plain render's; 0.18 measured)."""
    rng = np.random.default_rng(3)
    kmap = rng.integers(1, 9, (RES, RES)).astype(np.float32)
    ref = mpg.render(sphere, "path", spp=4096, seed=11, progress=False)
    img = mpg.render(sphere, "path", spp=2048, seed=13, progress=False, delta_split_map=kmap)
    assert img.stats["delta_split_paths"] > 0 and img.stats["rejected_samples"] == 0
    assert image_zmax(img, ref, REGIONS) < 5
    # the variance where the light is seen in the glass
    only = mpg.render(sphere, {"type": "path", "camera_delta": "only"}, spp=2048, seed=17, progress=False)
    lit = only.rgb.mean(axis=2) > 0
    assert lit.sum() >= 3
    n = 2048
    plain = mpg.render(sphere, "path", spp=n, seed=19, progress=False)
    split = mpg.render(sphere, "path", spp=n, seed=23, progress=False,
                       delta_split_map=np.full((RES, RES), 8, np.float32))
    v_plain = float(plain.variance[lit].sum()) * n
    v_split = float(split.variance[lit].sum()) * n
    assert v_split < 0.5 * v_plain, (v_split, v_plain)


def test_bad_split_maps_are_refused(sphere):
    core = sphere.core
    integ = _core.make_integrator(core, "path", {})
    for bad in (np.zeros((RES, RES), np.float32), np.full((RES, RES), 1.5, np.float32),
                np.full((RES, RES), 65, np.float32), np.ones((RES, RES + 1), np.float32)):
        with pytest.raises(ValueError, match="delta_split_map"):
            _core.RenderJob(core, integ, 1, 0, 0, 0, delta_split_map=bad)
    other = _core.make_integrator(core, "path", {"camera_delta": "exclude"})
    with pytest.raises(ValueError, match="camera_delta"):
        _core.RenderJob(core, other, 1, 0, 0, 0, delta_split_map=np.full((RES, RES), 2, np.float32))


def _acc(var_d, var_t, delta_rays, rays=4.0, n=64):
    """An accumulator of n samples at q = 1 whose sums give the per-sample
    variance var_t of the pixel and var_d of its light seen through delta
    scattering only (means 0.5 / 0.25), rays per sample and rays after delta
    scattering."""
    h, w = var_t.shape
    a = CostAccumulator((h, w))
    a.n = n

    def sums(mean, var):
        return (np.repeat(np.full((h, w, 1), mean * n), 3, axis=2),
                np.repeat(((var * (n - 1) / n) + mean * mean)[..., None] * n, 3, axis=2))

    a.sum, a.sum_sq = sums(0.5, var_t)
    a.delta_sum, a.delta_sum_sq = sums(0.25, var_d)
    a.rays = np.full((h, w), rays * n)
    a.rate_sum = np.full((h, w), 1.0 * n)
    a.delta_rays = delta_rays * n
    return a


def test_learned_split_is_eq3():
    """k_p = rint(sqrt(B_p mean(C) / (o_p mean(V)))) in [1, 16] (objective mse,
    no window): more paths where that light's variance is large and an extra
    path cheap against the mean sample; 1 where training saw none of it."""
    var_t = np.full((4, 4), 1.0)
    var_d = np.zeros((4, 4))
    var_d[0, :] = 0.9
    var_d[1, :] = 0.1
    var_t[0, :] = 1.0
    d_rays = np.full((4, 4), 2.0)             # o = 3
    acc = _acc(var_d, var_t, d_rays, rays=4.0)
    acc.chain_steps = np.full((4, 4), 40.0 / STEP_COST * acc.n)   # 40 ray units of chains at q = 1
    acc.walk_steps = acc.chain_steps.copy()
    q = np.full((4, 4), 0.5, np.float32)
    k, info = learn_delta_split(acc, q, radius=0, objective="mse")
    C = 4.0 + 0.5 * 40.0
    V = float(var_t.mean())
    expect = np.clip(np.rint(np.sqrt(var_d * C / (3.0 * V))), 1, 16)
    np.testing.assert_allclose(k, expect, rtol=1e-6)
    assert k[0, 0] > k[1, 0] >= 1 and np.all(k[2:] == 1)
    assert info["delta_split_fraction"] == pytest.approx(float(np.mean(expect > 1)))
    # cheaper samples (rate 0: no chain cost) -> fewer extra paths; the cap
    k0, _ = learn_delta_split(acc, np.zeros((4, 4), np.float32), radius=0, objective="mse")
    assert np.all(k0 <= k) and k0.sum() < k.sum()
    acc.chain_steps *= 1e4
    acc.walk_steps *= 1e4
    kb, _ = learn_delta_split(acc, q, radius=0, objective="mse")
    assert kb.max() == 16 and np.all(kb[2:] == 1)
    # NaN/Inf sums give finite counts
    acc.delta_sum_sq[0, 0, 0] = np.nan
    acc.sum_sq[1, 1, 1] = np.inf
    kn, _ = learn_delta_split(acc, q, radius=0, objective="mse")
    assert np.isfinite(kn).all() and kn.min() >= 1


def test_mpg_splits_where_the_camera_sees_glass_and_stays_unbiased(sphere, sphere32_path_ref):
    """mpg's learned map is > 1 only near pixels that see the light in the glass;
    with a uniform delta_split=4 mpg agrees with the path tracer
    (|z| < 5); delta_split=1 learns no map; bad settings are clear errors."""
    img = mpg.render(sphere, "mpg", spp=64, seed=2, progress=False)
    k = img.delta_split_map
    assert k is not None and img.stats["delta_split"] == "learned" and (k > 1).any()
    assert k.min() >= 1 and k.max() <= 16
    # the split pixels see the light in the glass, or are within the 7x7 window of one that does
    only = mpg.render(sphere, {"type": "path", "camera_delta": "only"}, spp=1024, seed=2, progress=False)
    lit = only.rgb.mean(axis=2) > 0
    near = np.zeros_like(lit)
    for y, x in zip(*np.nonzero(lit)):
        near[max(0, y - 3):y + 4, max(0, x - 3):x + 4] = True
    assert not (k > 1)[~near].any()
    off = mpg.render(sphere, {"type": "mpg", "delta_split": 1}, spp=16, seed=2, progress=False)
    assert off.delta_split_map is None and off.stats["delta_split"] == "off"
    check_uniform_split(sphere, sphere32_path_ref, "delta_split", 4, 512, "delta_split_paths", REGIONS)
