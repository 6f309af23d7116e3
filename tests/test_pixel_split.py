"""The pixel split (design-notes "Splitting the pixels"): each sample of a
pixel is the mean of k camera samples, k from a map fixed before the render.
Any map of k >= 1 keeps the image unbiased, k = 1 is the plain render bit for
bit, k divides a sample's variance by k, and mpg learns k (Eq. 4 of
mpg.chain_rates) where its training saw a pixel's variance large for its
cost."""

from __future__ import annotations

import numpy as np
import pytest

import mpg
from mpg import _core
from mpg.chain_rates import CostAccumulator, PixelSplitRefiner, learn_pixel_split, split_sample_variance
from stats_util import REGIONS_32, check_uniform_split, image_zmax, run_pass

RES = 32
REGIONS = REGIONS_32


@pytest.fixture(scope="module")
def sphere(sphere32):
    return sphere32


def _pass(sc, name, spp, seed, smap=None):
    return run_pass(sc, name, spp, seed, pixel_split_map=smap)


def test_a_map_of_ones_is_the_plain_render(sphere):
    for name in ("path", "sms_star"):
        a = _pass(sphere, name, 8, 5)
        b = _pass(sphere, name, 8, 5, np.ones((RES, RES), np.float32))
        assert np.array_equal(a["sum"], b["sum"]) and np.array_equal(a["sum_sq"], b["sum_sq"])
        assert b["stats"]["pixel_split_samples"] == 0


def test_a_split_keeps_the_image_unbiased_and_divides_the_variance(sphere):
    """A random map of k in 1..8 agrees with the plain path tracer (|z| < 5 on
    the image and four regions, p < 6e-7 each); k = 4 everywhere divides the
    per-sample variance summed over the image by about 4 (asserted: below 0.5
    of the plain render's and above 0.1)."""
    rng = np.random.default_rng(3)
    smap = rng.integers(1, 9, (RES, RES)).astype(np.float32)
    ref = mpg.render(sphere, "path", spp=4096, seed=11, progress=False)
    img = mpg.render(sphere, "path", spp=1024, seed=13, progress=False, pixel_split_map=smap)
    assert img.stats["pixel_split_samples"] == pytest.approx(1024 * (smap - 1).sum())
    assert img.stats["rejected_samples"] == 0
    assert image_zmax(img, ref, REGIONS) < 5
    n = 1024
    plain = mpg.render(sphere, "path", spp=n, seed=19, progress=False)
    split = mpg.render(sphere, "path", spp=n, seed=23, progress=False,
                       pixel_split_map=np.full((RES, RES), 4, np.float32))
    ratio = float(split.variance.sum()) / float(plain.variance.sum())
    assert 0.1 < ratio < 0.5, ratio


def test_bad_split_maps_are_refused(sphere):
    core = sphere.core
    integ = _core.make_integrator(core, "path", {})
    for bad in (np.zeros((RES, RES), np.float32), np.full((RES, RES), 1.5, np.float32),
                np.full((RES, RES), 65, np.float32), np.ones((RES, RES + 1), np.float32),
                np.full((RES, RES), np.nan, np.float32)):
        with pytest.raises(ValueError, match="pixel_split_map"):
            _core.RenderJob(core, integ, 1, 0, 0, 0, pixel_split_map=bad)
    with pytest.raises(ValueError, match="record_costs"):
        _core.RenderJob(core, integ, 1, 0, 0, 0, pixel_split_map=np.full((RES, RES), 2, np.float32),
                        record_costs=True)


def _acc(var_t, rays, n=64):
    """n training samples at q = 1 with per-sample variance var_t (mean 0.5),
    rays per sample, no chain work and no light seen through delta scattering."""
    h, w = var_t.shape
    a = CostAccumulator((h, w))
    a.n = n
    a.sum = np.full((h, w, 3), 0.5 * n)
    a.sum_sq = np.repeat(((var_t * (n - 1) / n) + 0.25)[..., None] * n, 3, axis=2)
    a.rays = rays * n
    a.rate_sum = np.full((h, w), 1.0 * n)
    return a


def test_learned_split_is_eq4():
    """The map is Eq. 4's fixed point: each k_p = rint(sqrt(V_p mean(kC) /
    (C_p mean(V/k)))) in [1, 16] with the means of the map returned
    (objective mse, no window); more samples where the variance is larger or
    a sample cheaper, 1 where training saw no variance."""
    rng = np.random.default_rng(0)
    var_t = rng.uniform(0.0, 1.0, (8, 8))
    var_t[0, 0] = 400.0
    var_t[7, :] = 0.0
    rays = rng.uniform(2.0, 8.0, (8, 8))
    acc = _acc(var_t, rays)
    q = np.ones((8, 8), np.float32)
    k, info = learn_pixel_split(acc, q, np.ones((8, 8)), radius=0, objective="mse")
    v, c = var_t, rays
    c_mean, v_mean = float(np.mean(k * c)), float(np.mean(v / k))
    np.testing.assert_array_equal(k, np.clip(np.rint(np.sqrt(v * c_mean / (c * v_mean))), 1, 16))
    assert k[0, 0] == 16 and np.all(k[7] == 1) and k.max() <= 16 and k.min() >= 1
    assert info["pixel_split_fraction"] == pytest.approx(float(np.mean(k > 1)))
    assert info["pixel_split_cost"] == pytest.approx(c_mean / float(np.mean(c)))
    # where: the split only in the masked pixels (pixel_split=handoff: rate 0), the
    # same fixed point over them with k = 1 elsewhere
    where = np.zeros((8, 8), bool)
    where[:4] = True
    kw, _ = learn_pixel_split(acc, q, np.ones((8, 8)), radius=0, objective="mse", where=where)
    assert np.all(kw[~where] == 1) and kw[0, 0] == 16
    c_mean, v_mean = float(np.mean(kw * c)), float(np.mean(v / kw))
    np.testing.assert_array_equal(kw[where], np.clip(np.rint(np.sqrt(
        v * c_mean / (c * v_mean))), 1, 16)[where])
    # relmse weighs a pixel's variance by 1 / (I^2 + 0.01): a brighter pixel gets fewer
    acc.sum[0, 1] = 10.0 * acc.n                  # mean 10, variance 100
    acc.sum_sq[0, 1] = (100.0 * (acc.n - 1) / acc.n + 100.0) * acc.n
    kr, _ = learn_pixel_split(acc, q, np.ones((8, 8)), radius=0, objective="relmse")
    km, _ = learn_pixel_split(acc, q, np.ones((8, 8)), radius=0, objective="mse")
    assert kr[0, 1] < km[0, 1]
    # NaN/Inf sums give finite counts
    acc.sum_sq[1, 1, 1] = np.nan
    acc.sum_sq[2, 2, 0] = np.inf
    kn, _ = learn_pixel_split(acc, q, np.ones((8, 8)), radius=0, objective="mse")
    assert np.isfinite(kn).all() and kn.min() >= 1


def test_learned_split_under_a_cost_cap():
    """pixel_split_max_cost: above the cap the map is clamp(rint(s sqrt(V
    mean(kC) / (C mean(V/k)))), 1, 16) with the uncapped fixed point's means
    and the largest s that keeps mean(kC) / mean(C) at or below the cap
    (checked: within the cap, and s a little larger breaks it); the pixels
    keep their order (more variance per cost, k no smaller); a cap above the
    uncapped cost changes nothing."""
    rng = np.random.default_rng(2)
    var_t = rng.uniform(0.0, 1.0, (16, 16))
    var_t[:3, :3] = rng.uniform(50.0, 400.0, (3, 3))
    rays = rng.uniform(2.0, 8.0, (16, 16))
    acc = _acc(var_t, rays)
    q = np.ones((16, 16), np.float32)
    k0, info0 = learn_pixel_split(acc, q, np.ones((16, 16)), radius=0, objective="mse")
    cost0 = info0["pixel_split_cost"]
    assert cost0 > 1.1
    same, _ = learn_pixel_split(acc, q, np.ones((16, 16)), radius=0, objective="mse", max_cost=cost0 + 0.01)
    np.testing.assert_array_equal(same, k0)
    cap = 1.0 + 0.5 * (cost0 - 1.0)
    k, info = learn_pixel_split(acc, q, np.ones((16, 16)), radius=0, objective="mse", max_cost=cap)
    c = rays
    assert info["pixel_split_cost"] <= cap + 1e-12 and info["pixel_split_capped"] == pytest.approx(cost0)
    assert (k > 1).any() and np.all(k <= k0)
    base = np.sqrt(var_t * float(np.mean(k0 * c)) / (c * float(np.mean(var_t / k0))))
    s = info["pixel_split_scale"]
    assert 0.0 < s < 1.0
    np.testing.assert_array_equal(k, np.clip(np.rint(s * base), 1, 16))
    bigger = np.clip(np.rint(1.02 * s * base), 1, 16)
    assert float(np.mean(bigger * c) / np.mean(c)) > cap or np.array_equal(bigger, k)
    order = np.argsort((var_t / c).ravel())
    assert np.all(np.diff(k.ravel()[order]) >= 0)


def test_learned_split_models_branched_delta_paths():
    """With branched delta paths (mpg's delta_branch > 0) a pixel whose
    variance is the light seen in the glass and whose delta split is 2 keeps
    BRANCH_RESIDUAL of that light's variance, not half, at TREE_COST o per
    extra path: the map is Eq. 4's fixed point under that model and splits
    such a pixel less than the unbranched model does."""
    from mpg.chain_rates import BRANCH_RESIDUAL, TREE_COST
    rng = np.random.default_rng(1)
    var_t = rng.uniform(0.0, 1.0, (8, 8))
    var_t[0, 0] = 400.0
    rays = rng.uniform(2.0, 8.0, (8, 8))
    acc = _acc(var_t, rays)
    n = acc.n
    var_d = np.zeros((8, 8))
    var_d[0, 0] = 390.0                          # nearly all of the pixel's variance
    acc.delta_sum = np.zeros((8, 8, 3))
    acc.delta_sum_sq = np.repeat((var_d * (n - 1) / n)[..., None] * n, 3, axis=2)
    acc.delta_rays = np.full((8, 8), 3.0 * n)    # o = 4
    kd = np.ones((8, 8))
    kd[0, 0] = 2.0
    q = np.ones((8, 8), np.float32)
    kb, _ = learn_pixel_split(acc, q, kd, radius=0, objective="mse", branched=True)
    ku, _ = learn_pixel_split(acc, q, kd, radius=0, objective="mse", branched=False)
    o = 4.0
    v = var_t.copy()
    v[0, 0] -= (1.0 - BRANCH_RESIDUAL) * 390.0
    c = rays + (kd - 1.0) * o * TREE_COST
    c_mean, v_mean = float(np.mean(kb * c)), float(np.mean(v / kb))
    np.testing.assert_array_equal(kb, np.clip(np.rint(np.sqrt(v * c_mean / (c * v_mean))), 1, 16))
    assert kb[0, 0] < ku[0, 0]


def test_mpg_pixel_split_options(sphere, sphere32_path_ref):
    """mpg learns a map with pixel_split=mse (the default, capped); a uniform
    pixel_split=3 stays unbiased against the path tracer (|z| < 5); bad
    settings are clear errors."""
    off = mpg.render(sphere, {"type": "mpg", "pixel_split": "off"}, spp=32, seed=2, progress=False)
    assert off.pixel_split_map is None and off.stats["pixel_split"] == "off"
    # the default: learned for MSE, its predicted cost capped at 1.1
    img = mpg.render(sphere, "mpg", spp=64, seed=2, progress=False)
    assert img.stats["pixel_split"] == "mse" and img.stats["pixel_split_cost"] <= 1.1 + 1e-9
    uncapped = mpg.render(sphere, {"type": "mpg", "pixel_split_max_cost": "none"}, spp=64, seed=2, progress=False)
    assert "pixel_split_capped" not in uncapped.stats
    k = img.pixel_split_map
    assert k is not None and (k > 1).any() and k.min() >= 1 and k.max() <= 16
    assert img.stats["pixel_split_samples"] > 0
    # handoff: only pixels handed to the path tracer (rate 0) are split
    # (64 spp train 15, too few for the default hand-off: asked for here)
    ho = mpg.render(sphere, {"type": "mpg", "pixel_split": "handoff", "chain_handoff": True}, spp=64, seed=2,
                    progress=False)
    assert ho.stats["pixel_split"] == "handoff" and ho.chain_rate_map is not None
    kh = ho.pixel_split_map
    assert kh is not None and (kh > 1).any() and np.all(ho.chain_rate_map[kh > 1] == 0)
    check_uniform_split(sphere, sphere32_path_ref, "pixel_split", 3, 256, "pixel_split_samples", REGIONS)
    capped = mpg.render(sphere, {"type": "mpg", "pixel_split": "mse", "pixel_split_max_cost": 1.05},
                        spp=64, seed=2, progress=False)
    assert capped.stats["pixel_split_cost"] <= 1.05 + 1e-9
    for bad in (0.5, "x", float("nan")):
        with pytest.raises(mpg.RenderError, match="pixel_split_max_cost"):
            mpg.render(sphere, {"type": "mpg", "pixel_split": "mse", "pixel_split_max_cost": bad},
                       spp=4, seed=2, progress=False)


def test_split_sample_variance_of_mixed_counts():
    """Samples each the mean of k camera samples (k = 1, 4 and 16 in one
    pixel): the precision-weighted estimate of one camera sample's variance
    V = 3 is unbiased. Over 40 000 pixels of 32 samples its mean is within
    1 % of 3 (its standard error is under 0.1 %); the plain spread times the
    mean k, the estimate without the weights, is ~6 % high."""
    rng = np.random.default_rng(1)
    P, V = 40_000, 3.0
    ks, ks2, kn, n = np.zeros((P, 1, 3)), np.zeros((P, 1, 3)), np.zeros((P, 1)), 0
    for k, c in ((1, 6), (4, 10), (16, 16)):
        s = rng.normal(2.0, np.sqrt(V / k), (P, 1, 3, c))
        ks += k * s.sum(-1)
        ks2 += k * (s * s).sum(-1)
        kn += k * c
        n += c
    est = split_sample_variance(ks, ks2, kn, n)
    assert est.shape == (P, 1)
    assert float(est.mean()) == pytest.approx(V, rel=0.01)
    # one count for all: the plain sample variance times k
    s = rng.normal(1.0, 1.0, (5, 4, 3, 9))
    k = 3.0
    got = split_sample_variance(k * s.sum(-1), k * (s * s).sum(-1), np.full((5, 4), k * 9), 9)
    np.testing.assert_allclose(got, k * s.var(axis=-1, ddof=1).mean(axis=-1), rtol=1e-12)


def test_refiner_pools_the_renders_variance_into_eq4():
    """PixelSplitRefiner.update: Eq. 4's fixed point (no window, objective mse)
    for V = (n_t V_train + n V_render) / (n_t + n). A pixel the training saw
    flat but the render saw noisy is split; when the render sees less, the
    counts fall again; under a cap the map keeps within it."""
    rng = np.random.default_rng(4)
    var_t = rng.uniform(0.5, 1.0, (8, 8))
    var_t[3, 3] = 0.0                        # training saw nothing here
    rays = rng.uniform(2.0, 8.0, (8, 8))
    acc = _acc(var_t, rays, n=8)
    q, ones = np.ones((8, 8), np.float32), np.ones((8, 8))
    n = 24
    v_r = var_t.copy()
    v_r[3, 3] = 900.0                        # ... the render did (one camera sample's variance)
    # sums of n samples at k = 1 whose spread is exactly v_r (mean 0.5)
    kn = np.full((8, 8), float(n))
    ks = np.full((8, 8, 3), 0.5 * n)
    ks2 = np.repeat((v_r * (n - 1) / n + 0.25)[..., None] * n, 3, axis=2)
    np.testing.assert_allclose(split_sample_variance(ks, ks2, kn, n), v_r, rtol=1e-9, atol=1e-12)
    ref = PixelSplitRefiner(acc, q, ones, radius=0, objective="mse")
    k, info = ref.update(ks, ks2, kn, n)
    v = (8 * var_t + n * v_r) / (8 + n)
    c_mean, v_mean = float(np.mean(k * rays)), float(np.mean(v / k))
    np.testing.assert_array_equal(k, np.clip(np.rint(np.sqrt(v * c_mean / (rays * v_mean))), 1, 16))
    assert k[3, 3] == 16 and k.min() >= 1 and k.dtype == np.float32
    # no pixel worth splitting: None (no split), as learn's maps are
    assert PixelSplitRefiner(_acc(np.zeros((8, 8)), rays, n=8), q, ones, radius=0, objective="mse").update(
        ks, np.repeat(np.full((8, 8), 0.25)[..., None] * n, 3, axis=2), kn, n)[0] is None
    assert info["pixel_split_online_updates"] == 1
    assert info["pixel_split_online_fraction"] == pytest.approx(float(np.mean(k > 1)))
    # the render sees every pixel flat later: the training's model alone, diluted
    flat = np.repeat(np.full((8, 8), 0.25)[..., None] * n, 3, axis=2)
    k2, info2 = ref.update(ks, flat, kn, n)
    assert (k2 is None or k2[3, 3] < k[3, 3]) and info2["pixel_split_online_updates"] == 2
    # under a cost cap: within it, below the uncapped map
    capped = PixelSplitRefiner(acc, q, ones, radius=0, objective="mse", max_cost=1.05)
    kc, infoc = capped.update(ks, ks2, kn, n)
    assert infoc["pixel_split_online_cost"] <= 1.05 + 1e-9 and np.all(kc <= k)
    assert 0.0 < infoc["pixel_split_online_scale"] < 1.0
    with pytest.raises(ValueError, match="at least 2 samples"):
        ref.update(ks, ks2, kn, 1)


def test_refiner_after_one_training_spp_learns_from_the_render_alone():
    """A training of 1 spp has the costs but no variance: the refiner's own
    map (solve) splits nothing, and its updates solve Eq. 4 for the render's
    own variance alone, n_t = 0 (a short render's training: the sphere at
    1 s trains 1 spp in most fresh processes). A training of 0 spp has no
    costs: an error."""
    rng = np.random.default_rng(5)
    rays = rng.uniform(2.0, 8.0, (8, 8))
    q, ones = np.ones((8, 8), np.float32), np.ones((8, 8))
    acc = _acc(np.zeros((8, 8)), rays, n=1)
    acc.sum_sq = rng.uniform(0.0, 5.0, (8, 8, 3))   # (one sample: its square says nothing of a variance)
    ref = PixelSplitRefiner(acc, q, ones, radius=0, objective="mse")
    k0, info0 = ref.solve()
    assert np.all(k0 == 1) and info0["pixel_split_fraction"] == 0.0
    n = 12
    v_r = rng.uniform(0.5, 1.0, (8, 8))
    v_r[2, 5] = 400.0
    kn = np.full((8, 8), float(n))
    ks = np.full((8, 8, 3), 0.5 * n)
    ks2 = np.repeat((v_r * (n - 1) / n + 0.25)[..., None] * n, 3, axis=2)
    k, info = ref.update(ks, ks2, kn, n)
    c_mean, v_mean = float(np.mean(k * rays)), float(np.mean(v_r / k))
    np.testing.assert_array_equal(k, np.clip(np.rint(np.sqrt(v_r * c_mean / (rays * v_mean))), 1, 16))
    assert k[2, 5] == 16 and np.all(np.isfinite(k))
    empty = _acc(np.zeros((8, 8)), rays, n=1)
    empty.n = 0
    with pytest.raises(ValueError, match="at least 1 spp"):
        PixelSplitRefiner(empty, q, ones)


def test_sequence_epoch_salts_the_sobol_shifts_only(sphere):
    """RenderJob's sequence_epoch: 0 is the default pass bit for bit; another
    epoch moves the Sobol positions (a stratified pass's, and the delta
    split's extra paths' with delta_split_sobol) and nothing else (an
    independent pass without a delta split is the same)."""
    smap = np.where(np.arange(RES)[None, :] % 3 == 0, 3.0, 1.0).repeat(RES, axis=0).astype(np.float32)

    def same(x, y):
        return np.array_equal(x["sum"], y["sum"]) and np.array_equal(x["sum_sq"], y["sum_sq"])
    kw = dict(pixel_split_map=smap, stratify=True, sample_offset=8)
    assert same(run_pass(sphere, "path", 4, 9, **kw), run_pass(sphere, "path", 4, 9, sequence_epoch=0, **kw))
    assert not same(run_pass(sphere, "path", 4, 9, **kw), run_pass(sphere, "path", 4, 9, sequence_epoch=1, **kw))
    plain = dict(pixel_split_map=smap)
    assert same(run_pass(sphere, "path", 4, 9, **plain), run_pass(sphere, "path", 4, 9, sequence_epoch=3, **plain))
    dkw = dict(params={"delta_split_sobol": True, "delta_branch": 8},   # (as mpg: branched extra paths)
               delta_split_map=np.full((RES, RES), 3, np.float32))
    assert same(run_pass(sphere, "path", 4, 9, **dkw), run_pass(sphere, "path", 4, 9, sequence_epoch=0, **dkw))
    assert not same(run_pass(sphere, "path", 4, 9, **dkw), run_pass(sphere, "path", 4, 9, sequence_epoch=2, **dkw))


def test_render_hands_the_refiner_its_k_weighted_sums(sphere, monkeypatch):
    """render(pixel_split_refine=f) calls f before the passes at 4 and 8 spp
    of a 16-spp render (REFINE_FIRST, then doubling), with the sums of k s,
    k s^2 and k over the samples so far; the passes run with the map f
    returns (counted extra samples), each refinement starting a new epoch of
    the Sobol shifts with its offsets counted from 0, and the image reports
    the map."""
    calls, jobs = [], []
    real = _core.RenderJob

    def job(*a, **kw):   # (records each pass's sequence epoch and offset in it)
        jobs.append((kw.get("sequence_epoch", 0), kw.get("sample_offset", 0)))
        return real(*a, **kw)

    def refine(ks, ks2, kn, n):
        calls.append((ks.copy(), ks2.copy(), kn.copy(), n))
        return np.full((RES, RES), 2.0 + len(calls), np.float32), {"pixel_split_online_updates": len(calls)}

    monkeypatch.setattr(_core, "RenderJob", job)
    img = mpg.render(sphere, "path", spp=16, seed=3, progress=False, pixel_split_refine=refine)
    monkeypatch.setattr(_core, "RenderJob", real)
    assert [c[3] for c in calls] == [4, 8]
    # passes of 1, 1, 2, 4, 8 spp: each refinement a new epoch, its offsets from 0
    assert jobs == [(0, 0), (0, 1), (0, 2), (1, 0), (2, 0)]
    ks, ks2, kn, _ = calls[0]
    np.testing.assert_array_equal(kn, np.full((RES, RES), 4.0))     # 4 samples at k = 1
    assert np.all(ks2 >= 0)
    np.testing.assert_array_equal(calls[1][2], np.full((RES, RES), 4.0 + 3.0 * 4))   # then 4 at k = 3
    # 4 spp at k = 3 and 8 at k = 4: (2 + 3) extra camera samples per sample and pixel
    assert img.stats["pixel_split_samples"] == RES * RES * (4 * 2 + 8 * 3)
    assert img.stats["pixel_split_online_updates"] == 2
    np.testing.assert_array_equal(img.pixel_split_map, np.full((RES, RES), 4.0))
    # the same render without the hook is the plain one, bit for bit
    a = mpg.render(sphere, "path", spp=16, seed=3, progress=False)
    b = mpg.render(sphere, "path", spp=16, seed=3, progress=False, pixel_split_refine=None)
    assert np.array_equal(a.rgb, b.rgb) and b.pixel_split_map is None


def test_mpg_online_split_stays_unbiased(sphere, sphere32_path_ref):
    """mpg's pixel split refined between its passes (pixel_split_online, the
    default) agrees with the path tracer (|z| < 5 on the image and its
    quarters, p < 6e-7 each) after refining at least twice into a map other
    than the training's, within the cost cap; off, the map is the
    training's."""
    img = mpg.render(sphere, "mpg", spp=384, seed=41, progress=False)
    st = img.stats
    assert st["pixel_split_online_updates"] >= 2
    assert (st["pixel_split_online_fraction"], st["pixel_split_online_mean"]) != (
        st["pixel_split_fraction"], st["pixel_split_mean"])
    assert st["pixel_split_online_cost"] <= 1.1 + 1e-9
    k = img.pixel_split_map
    assert float(0.0 if k is None else np.mean(k > 1)) == pytest.approx(st["pixel_split_online_fraction"])
    assert st["rejected_samples"] == 0
    assert image_zmax(img, sphere32_path_ref, REGIONS) < 5
    off = mpg.render(sphere, {"type": "mpg", "pixel_split_online": False}, spp=64, seed=2, progress=False)
    assert "pixel_split_online_updates" not in off.stats
    assert float(np.mean(off.pixel_split_map > 1)) == pytest.approx(off.stats["pixel_split_fraction"])
    with pytest.raises(mpg.RenderError, match="pixel_split_online"):
        mpg.render(sphere, {"type": "mpg", "pixel_split_online": "maybe"}, spp=4, progress=False)


def test_mpg_online_split_after_one_training_spp_stays_unbiased(sphere, sphere32_path_ref):
    """A training of 1 spp (training_fraction 0.003 of 384 spp) learns no maps,
    yet the render refines a pixel split from its own samples (before, it
    rendered unsplit); the image agrees with the path tracer (|z| < 5 on the
    image and its quarters, p < 6e-7 each)."""
    img = mpg.render(sphere, {"type": "mpg", "training_fraction": 0.003}, spp=384, seed=43, progress=False)
    st = img.stats
    assert st["spp_training"] == 1 and st["pixel_split_fraction"] == 0.0   # (no map from the training)
    assert st["pixel_split_online_updates"] >= 2 and st["pixel_split_online_fraction"] > 0.0
    assert st["pixel_split_samples"] > 0 and st["rejected_samples"] == 0
    assert image_zmax(img, sphere32_path_ref, REGIONS) < 5
