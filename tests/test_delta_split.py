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
from mpg.chain_rates import STEP_COST, TREE_COST, CostAccumulator, learn_delta_split
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


def _sums(var, n, mean):
    """Sums and squares (height x width x 3) of n samples of the given mean
    whose sample variance per pixel is var."""
    h, w = var.shape
    return (np.repeat(np.full((h, w, 1), mean * n), 3, axis=2),
            np.repeat(((var * (n - 1) / n) + mean * mean)[..., None] * n, 3, axis=2))


def _acc(var_d, var_t, delta_rays, rays=4.0, n=64):
    """An accumulator of n samples at q = 1 whose sums give the per-sample
    variance var_t of the pixel and var_d of its light seen through delta
    scattering only (means 0.5 / 0.25), rays per sample and rays after delta
    scattering."""
    h, w = var_t.shape
    a = CostAccumulator((h, w))
    a.n = n
    a.sum, a.sum_sq = _sums(var_t, n, 0.5)
    a.delta_sum, a.delta_sum_sq = _sums(var_d, n, 0.25)
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
    # branched extra paths: one (k = 2) where B / V > TREE_COST o / C, to first order
    # (row 0: 0.9 > 2 * 3 / 24 = 0.25; row 1: 0.1 < 0.25), 1 elsewhere
    kt, _ = learn_delta_split(acc, q, radius=0, objective="mse", branched=True)
    np.testing.assert_array_equal(kt, np.where(var_d * C > TREE_COST * 3.0 * V, 2.0, 1.0))
    assert np.all(kt[0] == 2) and np.all(kt[1:] == 1)
    # the threshold is TREE_COST: B C / (o V) = 1.5 gets none (a rule without the
    # cost factor would split), 2.1 gets one (Eq. 3 would round sqrt(2.1) to 1)
    vb = np.zeros((4, 4))
    vb[0, :] = 1.5 * 3.0 * V / C
    vb[1, :] = 2.1 * 3.0 * V / C
    accb = _acc(vb, var_t, d_rays, rays=4.0)
    accb.chain_steps, accb.walk_steps = acc.chain_steps.copy(), acc.walk_steps.copy()
    kb2, _ = learn_delta_split(accb, q, radius=0, objective="mse", branched=True)
    assert TREE_COST == 2.0 and np.all(kb2[0] == 1) and np.all(kb2[1] == 2) and np.all(kb2[2:] == 1)
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


def test_where_the_window_saw_none_of_that_light_a_wider_one_counts(monkeypatch):
    """A short training sees a light's images in glass in a few pixels: where
    the 7x7 window (radius 3) saw none of it, B is its mean over the window
    DELTA_FILL_SCALE (2) times as wide, 13x13; farther away, and with radius
    0 (no window), none. Where the narrow window saw it, B is unchanged. From
    DELTA_FILL_MAX_TRAINING (8) training spp on, the narrow window's none
    stands."""
    import mpg.chain_rates as cr
    var_t = np.full((32, 32), 1.0)
    var_d = np.zeros((32, 32))
    var_d[16, 16] = 49.0 * 169.0   # one pixel saw it
    acc = _acc(var_d, var_t, np.full((32, 32), 2.0), rays=4.0, n=7)
    q = np.zeros((32, 32), np.float32)
    dist = np.maximum(*np.abs(np.mgrid[:32, :32] - 16))   # Chebyshev distance to (16, 16)
    # against means that split wherever B > 0 (B C > TREE_COST o V for B >= 1/9)
    k, _ = learn_delta_split(acc, q, objective="mse", branched=True, means=(1e-3, 1.0))
    np.testing.assert_array_equal(k, np.where(dist <= 6, 2.0, 1.0))
    b, _ = cr._delta_parts(acc, "mse", 3)
    np.testing.assert_allclose(b[dist <= 3], var_d[16, 16] / 49.0, rtol=1e-9)
    np.testing.assert_allclose(b[(dist > 3) & (dist <= 6)], var_d[16, 16] / 169.0, rtol=1e-9)
    assert np.all(b[dist > 6] == 0.0)
    monkeypatch.setattr(cr, "DELTA_FILL_SCALE", 1)
    k1, _ = learn_delta_split(acc, q, objective="mse", branched=True, means=(1e-3, 1.0))
    np.testing.assert_array_equal(k1, np.where(dist <= 3, 2.0, 1.0))
    monkeypatch.setattr(cr, "DELTA_FILL_SCALE", 2)
    k0, _ = learn_delta_split(acc, q, radius=0, objective="mse", branched=True, means=(1e-3, 1.0))
    np.testing.assert_array_equal(k0, np.where(dist == 0, 2.0, 1.0))
    # "saw none" is a count of the window's lit pixels, not the blurred value:
    # a summed-area table can leave ~1e-17 in a window that holds nothing
    rng = np.random.default_rng(3)
    vr = np.zeros((32, 32))
    vr[:12, :12] = np.where(rng.random((12, 12)) < 0.3, rng.random((12, 12)) * 1e3, 0.0)
    accr = _acc(vr, var_t, np.full((32, 32), 2.0), rays=4.0, n=7)
    br, _ = cr._delta_parts(accr, "mse", 3)

    def window_mean(y, x, r):
        w = vr[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1]
        return w.mean(), (w > 0).any()

    for y in range(32):
        for x in range(32):
            narrow, seen = window_mean(y, x, 3)
            expect = narrow if seen else window_mean(y, x, 6)[0]
            assert br[y, x] == pytest.approx(expect, rel=1e-9, abs=1e-9), (y, x)
    assert cr.DELTA_FILL_MAX_TRAINING == 8
    long = _acc(var_d, var_t, np.full((32, 32), 2.0), rays=4.0, n=8)
    k8, _ = learn_delta_split(long, q, objective="mse", branched=True, means=(1e-3, 1.0))
    np.testing.assert_array_equal(k8, np.where(dist <= 3, 2.0, 1.0))


def test_the_split_weighs_against_the_means_given_and_its_effect_is_its_model():
    """learn_delta_split with means=(mean(wV), mean(C)) (learn_jointly's: the
    render's as the rates predict it) splits by the same rule against those;
    delta_split_effect gives what a map takes from mean(wV) and adds to
    mean(C) in that model: branched, (1 - BRANCH_RESIDUAL / (k - 1)) B at
    TREE_COST o (k - 1); unbranched, (1 - 1/k) B at o (k - 1)."""
    from mpg.chain_rates import BRANCH_RESIDUAL, delta_split_effect
    var_t = np.full((4, 4), 1.0)
    var_d = np.zeros((4, 4))
    var_d[0, :] = 0.9
    var_d[1, :] = 0.1
    acc = _acc(var_d, var_t, np.full((4, 4), 2.0), rays=4.0)   # o = 3
    q = np.zeros((4, 4), np.float32)
    k_own, _ = learn_delta_split(acc, q, radius=0, objective="mse", branched=True)
    # against the training's means (V 1, C 4): 0.9 x 4 < 2 x 3 x 1, none
    assert np.all(k_own == 1)
    for v, c in ((1.0, 4.0), (0.2, 24.0), (0.01, 24.0)):
        k, _ = learn_delta_split(acc, q, radius=0, objective="mse", branched=True, means=(v, c))
        np.testing.assert_array_equal(k, np.where(var_d * c > TREE_COST * 3.0 * v, 2.0, 1.0))
    assert np.all(k[:2] == 2) and np.all(k[2:] == 1)
    dv, dc = delta_split_effect(acc, k, radius=0, objective="mse", branched=True)
    assert dv == pytest.approx(np.mean(np.where(k > 1, var_d, 0.0)) * (1 - BRANCH_RESIDUAL), rel=1e-6)
    assert dc == pytest.approx(0.5 * TREE_COST * 3.0, rel=1e-6)
    k4 = np.where(var_d > 0, 4.0, 1.0)
    dv, dc = delta_split_effect(acc, k4, radius=0, objective="mse")
    assert dv == pytest.approx(np.mean(var_d) * 0.75, rel=1e-6)
    assert dc == pytest.approx(0.5 * 3.0 * 3.0, rel=1e-6)
    assert delta_split_effect(acc, np.ones((4, 4)), radius=0, objective="mse") == (0.0, 0.0)


def test_mpg_splits_where_the_camera_sees_glass_and_stays_unbiased(sphere, sphere32_path_ref):
    """mpg's learned map is > 1 only near pixels that see the light in the glass;
    with a uniform delta_split=4 mpg agrees with the path tracer
    (|z| < 5); delta_split=1 learns no map; bad settings are clear errors."""
    img = mpg.render(sphere, "mpg", spp=64, seed=2, progress=False)
    k = img.delta_split_map
    assert k is not None and img.stats["delta_split"] == "learned" and (k > 1).any()
    from mpg.chain_rates import SPLIT_PATHS_MAX   # (the learned map's 16, the measured counts' 64)
    assert k.min() >= 1 and k.max() <= SPLIT_PATHS_MAX
    # the split pixels see the light in the glass, or are within the 7x7 window
    # of one that does (DELTA_FILL_SCALE times as wide after a training of
    # under DELTA_FILL_MAX_TRAINING spp; this one trains 15)
    from mpg.chain_rates import DELTA_FILL_MAX_TRAINING, DELTA_FILL_SCALE
    only = mpg.render(sphere, {"type": "path", "camera_delta": "only"}, spp=1024, seed=2, progress=False)
    lit = only.rgb.mean(axis=2) > 0
    near = np.zeros_like(lit)
    r = 3 * (DELTA_FILL_SCALE if img.stats["spp_training"] < DELTA_FILL_MAX_TRAINING else 1)
    for y, x in zip(*np.nonzero(lit)):
        near[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1] = True
    assert not (k > 1)[~near].any()
    # mpg's default branches those pixels' extra paths (delta_branch = 8)
    assert img.stats["integrator_params"]["delta_branch"] == 8 and img.stats["delta_branches"] > 0
    off = mpg.render(sphere, {"type": "mpg", "delta_split": 1}, spp=16, seed=2, progress=False)
    assert off.delta_split_map is None and off.stats["delta_split"] == "off"
    check_uniform_split(sphere, sphere32_path_ref, "delta_split", 4, 512, "delta_split_paths", REGIONS)


def _lit_z(img, ref, lit):
    """|z| of the mean over the pixels `lit` between two independent renders."""
    n = int(lit.sum())
    d = img.rgb[lit].astype(np.float64).mean(axis=0) - ref.rgb[lit].astype(np.float64).mean(axis=0)
    se = np.sqrt(img.variance[lit].sum(axis=0) + ref.variance[lit].sum(axis=0)) / n
    return float(np.max(np.abs(d) / np.maximum(se, 1e-12)))


def test_branched_paths_stay_unbiased_and_cut_the_glints_variance(sphere, sphere32_path_ref, scenes_dir):
    """delta_branch: a split pixel's extra paths follow both lobes of the first
    delta_branch two-lobe delta vertices (each with weight x probability) and
    replace the sample's own delta part. The image agrees with the path tracer
    (|z| < 5 on the image, its quarters and the pixels that see the light in
    the glass, p < 6e-7 each), on the sphere and on double_slabs (two bumpy
    slabs: many delta vertices, every level of the tree used); in the pixels
    that see the light in the glass one branched path per sample (k = 2) has
    below 1/10 of the plain render's per-sample variance and below half of
    that of eight unbranched paths (k = 8) (measured over seeds 41-47: 1/23-1/26
    and 1/2.9-1/3.1 in one run, 1/2.35 against k = 8 from a second seed).
    delta_branch = 0 is the
    unbranched split bit for bit; out of [0, 8] it is refused."""
    ref = sphere32_path_ref
    only = mpg.render(sphere, {"type": "path", "camera_delta": "only"}, spp=1024, seed=2, progress=False)
    lit = only.rgb.mean(axis=2) > 0
    assert lit.sum() >= 3
    n = 2048
    two = np.full((RES, RES), 2, np.float32)
    br = mpg.render(sphere, {"type": "path", "delta_branch": 3}, spp=n, seed=41, progress=False,
                    delta_split_map=two)
    assert br.stats["delta_branches"] > 0 and br.stats["rejected_samples"] == 0
    assert image_zmax(br, ref, REGIONS) < 5 and _lit_z(br, ref, lit) < 5
    k8 = mpg.render(sphere, "path", spp=n, seed=43, progress=False,
                    delta_split_map=np.full((RES, RES), 8, np.float32))
    plain = mpg.render(sphere, "path", spp=n, seed=45, progress=False)
    v_br = float(br.variance[lit].sum())
    assert v_br < float(plain.variance[lit].sum()) / 10 and v_br < float(k8.variance[lit].sum()) / 2
    # 0: the unbranched split, bit for bit
    a = _pass(sphere, "path", 16, 5, two)
    b = _pass(sphere, "path", 16, 5, two, {"delta_branch": 0})
    assert np.array_equal(a["sum"], b["sum"]) and b["stats"]["delta_branches"] == 0
    for bad in (-1, 9):
        with pytest.raises(mpg.RenderError, match="delta_branch"):
            mpg.render(sphere, {"type": "path", "delta_branch": bad}, spp=1, progress=False)
    # double_slabs: paths through two bumpy slabs, a deep tree
    ds = mpg.load_file(scenes_dir / "eval" / "double_slabs.xml", res=32)
    dref = mpg.render(ds, "path", spp=4096, seed=51, progress=False)
    donly = mpg.render(ds, {"type": "path", "camera_delta": "only"}, spp=256, seed=2, progress=False)
    dlit = donly.rgb.mean(axis=2) > 0
    assert dlit.sum() >= 3
    dbr = mpg.render(ds, {"type": "path", "delta_branch": 8}, spp=1024, seed=53, progress=False,
                     delta_split_map=two)
    assert dbr.stats["delta_branches"] > 8 * dbr.stats["delta_split_paths"] / 100
    assert image_zmax(dbr, dref, REGIONS) < 5 and _lit_z(dbr, dref, dlit) < 5


# tests/test_sampler.py's EDGE: a camera looking straight down at an emitting
# half-plane whose edge crosses the image at 20 degrees. The light seen
# through delta scattering only (here directly) is the covered fraction of a
# pixel's footprint, decided by the film position alone.
def _edge_scene(res: int):
    from test_sampler import EDGE
    return mpg.load_string(EDGE.format(sampler="independent").replace('value="8"/>', f'value="{res}"/>'))


def _edge_renders(sobol: bool, spp: int, seeds: range) -> np.ndarray:
    """The split's extra path alone per sample (delta_branch 1: a split sample
    leaves its own delta part out; no vertex here has two lobes)."""
    sc = _edge_scene(8)
    two = np.full((8, 8), 2, np.float32)
    integ = {"type": "path", "delta_branch": 1, "delta_split_sobol": sobol}
    return np.stack([mpg.render(sc, integ, spp=spp, seed=s, progress=False, delta_split_map=two).rgb[..., 0]
                     for s in seeds]).astype(np.float64)


def test_sobol_extra_paths_stay_unbiased_and_stratify_an_edge():
    """delta_split_sobol: the split's extra paths at the points of a per-pixel
    randomly shifted Sobol sequence. 96 seeds of each: per pixel the mean over
    seeds agrees with independent positions' within |z| < 4.5 in every pixel
    the edge crosses (at most 64, p < 5e-4 for them) at 12 spp (the passes 1, 1, 2, 4, 4 end
    mid-block); at 16 spp the summed variance over seeds of the edge pixels is
    below half the independent positions' (expected near 16^-1/2, ~0.25; the
    96-seed ratio has a relative error near 0.2). Off is the plain split bit
    for bit (tests above)."""
    seeds = range(96)
    for spp in (12, 16):
        ind = _edge_renders(False, spp, seeds)
        sob = _edge_renders(True, spp, seeds)
        se = np.sqrt(ind.var(axis=0, ddof=1) / len(seeds) + sob.var(axis=0, ddof=1) / len(seeds))
        diff = np.abs(sob.mean(axis=0) - ind.mean(axis=0))
        edge = (ind.mean(axis=0) > 0.05) & (ind.mean(axis=0) < 0.95)
        assert edge.sum() >= 6, "the edge should cross several pixels"
        assert np.all(diff[edge] < 4.5 * se[edge]), (spp, (diff / np.maximum(se, 1e-12))[edge])
        if spp == 16:
            ratio = sob[:, edge].var(axis=0, ddof=1).sum() / ind[:, edge].var(axis=0, ddof=1).sum()
            assert ratio < 0.5, ratio


def test_sobol_extra_paths_continue_one_sequence_over_passes_and_pixel_splits():
    """The extra paths' points continue one sequence per pixel: over the
    passes (a render of 9 spp in passes 1, 1, 2, 4, 1 gives the image of one
    9-spp pass; a pass starting at sample 1 does not) and over a pixel split
    (8 spp of 2 camera samples each are the same 16 points as 16 spp), since
    each value here is decided by its position alone. Two threads give the
    image of one."""
    sc = _edge_scene(48)   # 9 tiles: the threads share the image
    two = np.full((48, 48), 2, np.float32)
    p = {"type": "path", "delta_branch": 1, "delta_split_sobol": True}
    a = mpg.render(sc, p, spp=9, seed=3, threads=1, progress=False, delta_split_map=two)
    b = mpg.render(sc, p, spp=9, seed=3, threads=2, progress=False, delta_split_map=two)
    assert np.array_equal(a.rgb, b.rgb) and a.stats["passes"] == 5
    assert a.stats["delta_split_paths"] == 9 * 48 * 48

    def one_pass(spp, offset, smap=None):
        integ = _core.make_integrator(sc.core, "path", {"delta_branch": 1, "delta_split_sobol": True})
        job = _core.RenderJob(sc.core, integ, spp, 3, 0, 1, sample_offset=offset, delta_split_map=two,
                              pixel_split_map=smap)
        while not job.wait(1.0):
            pass
        return np.asarray(job.result()["sum"]).reshape(a.rgb.shape) / spp

    assert np.allclose(one_pass(9, 0), a.rgb, rtol=0, atol=1e-6)
    assert not np.allclose(one_pass(9, 1), a.rgb, rtol=0, atol=1e-6)
    assert np.allclose(one_pass(8, 0, two), one_pass(16, 0), rtol=0, atol=1e-6)
    # another seed shifts the sequences
    c = mpg.render(sc, p, spp=9, seed=4, threads=1, progress=False, delta_split_map=two)
    assert not np.array_equal(a.rgb, c.rgb)


def test_mpg_takes_the_sobol_extra_paths_by_default(sphere):
    img = mpg.render(sphere, "mpg", spp=64, seed=1, progress=False)
    assert img.stats["integrator_params"]["delta_split_sobol"] is True
    off = mpg.render(sphere, {"type": "mpg", "delta_split_sobol": False}, spp=64, seed=1, progress=False)
    assert off.stats["integrator_params"]["delta_split_sobol"] is False
    with pytest.raises(mpg.RenderError, match="delta_split_sobol"):
        mpg.render(sphere, {"type": "path", "delta_split_sobol": "maybe"}, spp=1, progress=False)


def test_record_delta_leaves_the_image_and_returns_each_samples_own_delta_light(sphere):
    """RenderJob(record_delta=True): the pass's sums bit for bit as without
    it, plus per pixel the sums and squares of each sample's own path's light
    seen through delta scattering only -- non-negative, finite, some of it
    where the camera sees the light in the sphere, and its mean that light's
    (camera_delta=only's image, |z| < 5 on the lit pixels' total)."""
    a = run_pass(sphere, "path", 64, 7)
    b = run_pass(sphere, "path", 64, 7, None, record_delta=True)
    assert np.array_equal(a["sum"], b["sum"]) and np.array_equal(a["sum_sq"], b["sum_sq"])
    assert "delta_sum" not in a
    ds, ds2 = np.asarray(b["delta_sum"]), np.asarray(b["delta_sum_sq"])
    assert ds.shape == (RES, RES, 3) and np.isfinite(ds).all() and ds.min() >= 0 and np.all(ds2 >= 0)
    assert ds.sum() > 0
    # with a split map too (the sample's own path, not the split's mean)
    c = run_pass(sphere, "path", 64, 7, None, record_delta=True,
                 delta_split_map=np.full((RES, RES), 3.0, np.float32))
    assert np.isfinite(np.asarray(c["delta_sum"])).all()
    n = 1024
    only = mpg.render(sphere, {"type": "path", "camera_delta": "only"}, spp=4 * n, seed=17, progress=False)
    lit = only.rgb.mean(axis=2) > 0
    d = run_pass(sphere, "path", n, 29, None, record_delta=True)
    m = np.asarray(d["delta_sum"])[lit] / n
    v = (np.asarray(d["delta_sum_sq"])[lit] / n - m * m) / (n - 1)
    z = (m.sum() - only.rgb[lit].sum()) / np.sqrt(v.sum() + only.variance[lit].sum())
    assert abs(z) < 5, z


def test_record_delta_returns_the_split_paths_values_and_rays(sphere):
    """RenderJob(record_delta=True) with a delta split: per pixel the sums
    and squares of the split's extra paths' values (PassResult::split_path_*),
    their count -- exactly (k - 1) per sample, whatever the path met, and in
    all the pass's Stats::delta_split_paths -- and their rays (at least one
    camera ray each); their mean is the light seen through delta scattering
    only (camera_delta=only's image, |z| < 5 on the lit pixels' total, p <
    6e-7). Without a split no path is recorded; without record_delta nothing."""
    k3 = np.full((RES, RES), 3.0, np.float32)
    a = run_pass(sphere, "path", 16, 7, None, delta_split_map=k3)
    assert "split_path_n" not in a
    b = run_pass(sphere, "path", 16, 7, None, record_delta=True)
    assert np.all(np.asarray(b["split_path_n"]) == 0) and np.all(np.asarray(b["split_path_sum"]) == 0)
    n = 1024
    c = run_pass(sphere, "path", n, 29, None, record_delta=True, delta_split_map=k3)
    pn, rays = np.asarray(c["split_path_n"]), np.asarray(c["split_path_rays"])
    assert np.all(pn == 2 * n) and pn.sum() == c["stats"]["delta_split_paths"]
    assert np.all(rays >= pn)
    ps, ps2 = np.asarray(c["split_path_sum"]), np.asarray(c["split_path_sum_sq"])
    assert np.isfinite(ps).all() and ps.min() >= 0 and np.all(ps2 >= 0)
    # squares of the same values: sum x^2 >= (sum x)^2 / n per pixel and
    # channel, and positive exactly where a path saw the light
    assert np.all(ps2 * (2 * n) >= ps * ps * (1 - 1e-9))
    np.testing.assert_array_equal(ps2 > 0, ps > 0)
    # a pixel split: every sub-sample traces its k - 1 paths
    p2 = run_pass(sphere, "path", 8, 31, None, record_delta=True, delta_split_map=k3,
                  pixel_split_map=np.full((RES, RES), 2.0, np.float32))
    assert np.all(np.asarray(p2["split_path_n"]) == 2 * 2 * 8)
    only = mpg.render(sphere, {"type": "path", "camera_delta": "only"}, spp=4 * n, seed=17, progress=False)
    lit = only.rgb.mean(axis=2) > 0
    m = ps[lit] / (2 * n)
    v = (ps2[lit] / (2 * n) - m * m) / (2 * n - 1)
    z = (m.sum() - only.rgb[lit].sum()) / np.sqrt(v.sum() + only.variance[lit].sum())
    assert abs(z) < 5, z


def _path_sums(var, n, mean=2.0):
    """The split paths' sums (height x width x 3) and squares of n paths per
    pixel with per-path variance var, and their count."""
    s, s2 = _sums(var, n, mean)
    return s, s2, np.full(var.shape, float(n))


def test_measured_counts_follow_eq3_from_the_render_paths(monkeypatch):
    """DeltaSplitRefiner.measured_counts (design-notes "The split's counts
    from its own paths"): a split pixel's count from its extra paths' own variance V
    and rays r over the 3x3 window, Eq. 3: four times the variance -> about
    twice the paths, four times the rays -> about half; a branched pixel
    keeps at least one extra path, a plain one whose paths never vary falls
    to 1; the window pools each pixel's deviations about its own mean (a
    pixel's variance counts in its neighbours', pixels' different means do
    not); fewer than SPLIT_PATHS_MIN paths in the window, or an unsplit
    pixel, keep their count; a pixel split of 2 halves the extra paths the
    variance asks for; counts are integers in [1, SPLIT_PATHS_MAX];
    NaN/Inf in the sums give a defined map."""
    from mpg.chain_rates import SPLIT_PATHS_MAX, SPLIT_PATHS_MIN, DeltaSplitRefiner
    acc = _refiner_acc(n=16)
    means = (1.0, 40.0)   # (a sample's cost far above a path's: counts of several)
    ref = DeltaSplitRefiner(acc, means, objective="mse", branched=True)
    h = w = 32
    k = np.full((h, w), 2.0, np.float32)
    k[:, 28:] = 1.0   # not split
    var = np.zeros((h, w))
    var[0:8, 0:8] = 40.0       # A
    var[0:8, 12:20] = 160.0    # B: 4 V
    var[16:24, 0:8] = 40.0     # D: V at 4 r
    var[16:24, 12:20] = 1000.0   # E: 25 V
    var[:, 28:] = 500.0        # unsplit
    var[13, 4] = 9 * 40.0      # H: one pixel holds its window's variance
    ps, ps2, pn = _path_sums(var, 64)
    # A's pixels at two means far apart: each pixel's deviations about its own mean count
    ps22, ps222, _ = _path_sums(var, 64, mean=22.0)
    cb = np.zeros((h, w), bool)
    cb[0:8, 0:8] = (np.add.outer(np.arange(8), np.arange(8)) % 2) == 1
    ps, ps2 = np.where(cb[..., None], ps22, ps), np.where(cb[..., None], ps222, ps2)
    pn[24:28, 0:8] = SPLIT_PATHS_MIN / 9.0 - 1.0 / 9.0   # F: too few paths even pooled
    prays = np.full((h, w), 6.0) * pn
    prays[16:24, 0:8] *= 4.0
    plain_at = np.zeros((h, w), bool)
    plain_at[8:12, 20:28] = True   # G: plain paths whose values never vary
    ref.plain = plain_at
    wb = np.zeros((h, w))
    k1, info = ref.measured_counts(k, wb, ps, ps2, pn, prays)
    m = k1 - 1.0
    a, b_, d, e = m[2:6, 2:6], m[2:6, 14:18], k1[18:22, 2:6] - 1.0, k1[18:22, 14:18]
    assert np.all(a == a[0, 0]) and a[0, 0] >= 2
    # H: pooled over the window, its neighbours as A (one pixel's variance / 9 each)
    assert np.all(m[12:15, 3:6] == a[0, 0])
    assert abs(b_[0, 0] / a[0, 0] - 2.0) <= 1.0 / a[0, 0] + 1e-9
    assert abs(d[0, 0] / a[0, 0] - 0.5) <= 1.0 / a[0, 0] + 1e-9
    assert np.all(e == e[0, 0]) and e[0, 0] - 1.0 >= 4.0 * a[0, 0]
    assert np.all(k1[:, 28:] == 1.0)   # (not split: not the refiner's to split)
    np.testing.assert_array_equal(k1[25:27, 2:6], 2.0)   # F
    assert np.all(k1[9:11, 22:26] == 1.0)   # G: plain, nothing to average
    zero_branched = (var == 0) & (k == 2) & ~plain_at
    zero_branched[24:28, 0:8] = False
    assert np.all(k1[zero_branched] >= 2.0)   # (branched: at least one extra path)
    assert np.all(k1 == np.floor(k1)) and k1.min() >= 1 and k1.max() <= SPLIT_PATHS_MAX
    assert 0 < info["delta_split_online_measured"] <= 1
    bad_s, bad_s2 = ps.copy(), ps2.copy()
    bad_s[3, 3, 0] = np.nan
    bad_s2[4, 4, 1] = np.inf
    k2, _ = ref.measured_counts(k, wb, bad_s, bad_s2, pn, prays)
    assert np.isfinite(k2).all() and k2.min() >= 1 and k2.max() <= SPLIT_PATHS_MAX
    # a pixel split: kpix sub-samples each trace the count -> about 1/kpix of the extra paths
    kpix = np.ones((h, w), np.float32)
    kpix[0:8, 12:20] = 2.0   # B at 4 V, each sample averaging twice the paths: as A
    k5, _ = ref.measured_counts(k, wb, ps, ps2, pn, prays, kpix)
    assert abs((k5[2:6, 14:18] - 1.0)[0, 0] / (k5[2:6, 2:6] - 1.0)[0, 0] - 1.0) <= 1.0 / a[0, 0] + 1e-9
    # the cap
    import mpg.chain_rates as cr
    monkeypatch.setattr(cr, "SPLIT_PATHS_MAX", 3)
    k4, _ = ref.measured_counts(k, wb, ps, ps2, pn, prays)
    assert k4.max() == 3 and np.all(k4[18:22, 14:18] == 3)
    monkeypatch.undo()
    # nothing measured: the counts as given
    k3, info3 = ref.measured_counts(k, wb, ps, ps2, np.zeros((h, w)), prays)
    np.testing.assert_array_equal(k3, k)
    assert info3["delta_split_online_measured"] == 0.0


def _refiner_acc(n=7):
    """A training of n spp on 32 x 32 pixels: glass (delta rays) in columns
    8..23, its light seen there in one pixel (16, 16), none elsewhere."""
    var_t = np.full((32, 32), 1.0)
    var_d = np.zeros((32, 32))
    var_d[16, 16] = 50.0
    d_rays = np.zeros((32, 32))
    d_rays[:, 8:24] = 2.0
    return _acc(var_d, var_t, d_rays, rays=4.0, n=n)


def _render_sums(var_d, n):
    """The render's own delta sums and squares of n samples with per-sample variance var_d."""
    return _sums(var_d, n, 0.25)


def test_the_delta_split_check_keeps_the_training_split_where_the_render_sees_nothing_new():
    """DeltaSplitRefiner: learn_delta_split hands it the means it solved
    against; render samples that see no light keep the training's map and
    its branch choice; fewer than 2 render samples or training spp are
    refused."""
    from mpg.chain_rates import DeltaSplitRefiner
    acc = _refiner_acc(n=16)
    q = np.zeros((32, 32), np.float32)
    means = (1e-3, 1.0)
    k0, info0 = learn_delta_split(acc, q, objective="mse", branched=True, means=means)
    assert "means" not in info0 and np.any(k0 > 1)   # (given means: learn_jointly's, no check)
    k_own, info_own = learn_delta_split(acc, q, objective="mse", branched=True)
    assert len(info_own["means"]) == 2 and info_own["means"][0] > 0
    ref = DeltaSplitRefiner(acc, means, objective="mse", branched=True, base=k0)
    k, b, info = ref.update(*_render_sums(np.zeros((32, 32)), 16), 16)
    np.testing.assert_array_equal(k, k0)
    assert b is None and info["delta_split_online_updates"] == 1 and info["delta_split_online_glass"] == 0
    assert info["delta_split_online_fraction"] == pytest.approx(float(np.mean(k0 > 1)))
    with pytest.raises(ValueError):
        ref.update(*_render_sums(np.zeros((32, 32)), 4), 1)
    with pytest.raises(ValueError):
        DeltaSplitRefiner(_refiner_acc(n=1), means)


def test_the_held_out_choice_splits_the_glass_only_where_the_render_sees_light_the_training_missed():
    """The refiner's held-out choice: the render's own samples find the light
    in many glass pixels the training's split left alone (a bumpy slab's thin
    images) -> every glass pixel split twice, branched; they find it only
    where the training split (one image the training saw, the smooth sphere)
    -> the training's map. Outside the glass nothing is split by it."""
    from mpg.chain_rates import DeltaSplitRefiner
    acc = _refiner_acc(n=7)
    q = np.zeros((32, 32), np.float32)
    means = (1.0, 8.0)
    k0, _ = learn_delta_split(acc, q, objective="mse", branched=True, means=means)
    assert 0 < np.sum(k0 > 1) < 32 * 16
    ref = DeltaSplitRefiner(acc, means, objective="mse", branched=True, base=k0)
    rng = np.random.default_rng(5)
    spread = np.zeros((32, 32))
    spread[:, 8:24] = np.where(rng.random((32, 16)) < 0.3, 20.0, 0.0)   # across the glass
    k, b, info = ref.update(*_render_sums(spread, 8), 8)
    assert info["delta_split_online_glass"] == 1 and info["delta_split_online_glass_gain"] > 1
    assert np.all(k[:, 8:24] >= 2) and np.all(k[:, :8] == 1) and np.all(k[:, 24:] == 1) and b is None
    where_split = np.where(k0 > 1, 50.0, 0.0)   # only where the training split
    k1, _, info1 = ref.update(*_render_sums(where_split, 8), 8)
    assert info1["delta_split_online_glass"] == 0 and info1["delta_split_online_glass_gain"] < 1
    np.testing.assert_array_equal(k1, k0)
    # NaN/Inf in the render's sums: a defined choice
    bad = list(_render_sums(spread, 8))
    bad[1][0, 8, 0] = np.nan
    bad[0][1, 9, 1] = np.inf
    k2, _, info2 = ref.update(bad[0], bad[1], 8)
    assert np.isfinite(info2["delta_split_online_glass_gain"]) and np.isfinite(k2).all()


def test_mpg_checks_its_delta_split_and_stays_unbiased(sphere, sphere32_path_ref):
    """mpg's delta split checked between its passes (delta_split_online, the
    default): checked at least twice, the image agrees with the path tracer
    (|z| < 5 on the image and its quarters, p < 6e-7 each) and reports the
    map it ran last; off, no check; without the measured counts
    (delta_split_measured false) it agrees too. With the glass split forced
    (the check's other choice), whose counts the measured paths then set,
    the image agrees too."""
    img = mpg.render(sphere, "mpg", spp=384, seed=43, progress=False)
    st = img.stats
    assert st["delta_split_online_updates"] >= 2 and st["rejected_samples"] == 0
    k = img.delta_split_map
    assert float(0.0 if k is None else np.mean(k > 1)) == pytest.approx(st["delta_split_online_fraction"])
    assert image_zmax(img, sphere32_path_ref, REGIONS) < 5
    off = mpg.render(sphere, {"type": "mpg", "delta_split_online": False}, spp=64, seed=2, progress=False)
    assert "delta_split_online_updates" not in off.stats
    unmeasured = mpg.render(sphere, {"type": "mpg", "delta_split_measured": False}, spp=384, seed=41,
                            progress=False)
    assert "delta_split_online_measured" not in unmeasured.stats
    assert image_zmax(unmeasured, sphere32_path_ref, REGIONS) < 5
    import mpg.chain_rates as cr
    real = cr.DeltaSplitRefiner.model_f
    try:   # (the glass split always: its F the lower)
        cr.DeltaSplitRefiner.model_f = lambda self, k, wb: float(np.sum(k == 1))
        glass = mpg.render(sphere, "mpg", spp=384, seed=47, progress=False)
    finally:
        cr.DeltaSplitRefiner.model_f = real
    assert glass.stats["delta_split_online_glass"] == 1 and glass.stats["rejected_samples"] == 0
    # (the split ran from the first check on: its counts from its measured paths, delta_split_measured)
    assert glass.stats["delta_split_online_measured"] > 0
    assert np.mean(glass.delta_split_map > 1) > np.mean(img.delta_split_map > 1 if img.delta_split_map is not None else 0)
    assert image_zmax(glass, sphere32_path_ref, REGIONS) < 5
    with pytest.raises(mpg.RenderError, match="delta_split_online"):
        mpg.render(sphere, {"type": "mpg", "delta_split_online": "maybe"}, spp=4, progress=False)


def test_render_checks_the_delta_split_from_2_spp_and_the_pixel_split_from_4(sphere, monkeypatch):
    """render(delta_split_refine=g, pixel_split_refine=f) on a 16-spp render
    (passes of 1, 1, 2, 4, 8 spp): g before the passes at 2, 4 and 8 spp
    (DELTA_REFINE_FIRST, then doubling) with the sums of each sample's own
    delta light so far, f at 4 and 8 (REFINE_FIRST), g before f where both
    are due; each point a new epoch of the Sobol shifts; the passes run with
    the maps g returns. Where the two schedules part, g also runs wherever f
    does and not apart from it."""
    import sys
    render_mod = sys.modules["mpg.render"]   # (the module; mpg.render is its function)
    assert render_mod.DELTA_REFINE_FIRST == 2 and render_mod.REFINE_FIRST == 4
    order, jobs = [], []
    real = _core.RenderJob

    def job(*a, **kw):
        jobs.append((kw.get("sequence_epoch", 0), kw.get("sample_offset", 0),
                     None if kw.get("delta_split_map") is None else float(kw["delta_split_map"][0, 0])))
        return real(*a, **kw)

    def grefine(ds, ds2, n, paths):
        order.append(("delta", n))
        assert ds.shape == (RES, RES, 3) and np.all(ds2 >= 0)
        # (the split's extra paths so far: sums, squares, count, rays; the pixel split map)
        assert paths[0].shape == (RES, RES, 3) and paths[2].shape == (RES, RES) and np.all(paths[3] >= paths[2])
        assert paths[4] is None
        return np.full((RES, RES), 1.0 + len(order), np.float32), None, {"delta_split_online_updates": n}

    def frefine(ks, ks2, kn, n):
        order.append(("pixel", n))
        return None, {}

    monkeypatch.setattr(_core, "RenderJob", job)
    img = mpg.render(sphere, "path", spp=16, seed=3, progress=False,
                     delta_split_refine=grefine, pixel_split_refine=frefine)
    monkeypatch.setattr(_core, "RenderJob", real)
    assert order == [("delta", 2), ("delta", 4), ("pixel", 4), ("delta", 8), ("pixel", 8)]
    # epochs: a new one at 2, 4 and 8 spp; the maps g returned (2, then 3, then 5)
    assert jobs == [(0, 0, None), (0, 1, None), (1, 0, 2.0), (2, 0, 3.0), (3, 0, 5.0)]
    assert img.stats["spp"] == 16
    # passes of 1, 2, 2, 2, 2, 2 spp: g at 3 spp (its next at 6), f at 5 and g
    # with it (its next then at 10, not at 7 apart from f): one epoch more
    # than f alone
    order.clear()
    jobs.clear()
    monkeypatch.setattr(render_mod, "pass_schedule", lambda first=1, cap=32: iter([1] + [2] * 8))
    monkeypatch.setattr(_core, "RenderJob", job)
    mpg.render(sphere, "path", spp=11, seed=3, progress=False, delta_split_refine=grefine, pixel_split_refine=frefine)
    monkeypatch.setattr(_core, "RenderJob", real)
    assert order == [("delta", 3), ("delta", 5), ("pixel", 5)]
    assert [j[0] for j in jobs] == [0, 0, 1, 2, 2, 2]
