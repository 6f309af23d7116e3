"""The line search's limits as counterfactuals of the full search
(WalkResult::limited_tries, ChainEstimator::tally_limits) and mpg's choice
among them (mpg.guiding.choose_step_halvings; design-notes "Step control")."""

import numpy as np
import pytest

import mpg
from mpg import _core
from mpg.errors import RenderError
from mpg.guiding import choose_step_halvings
from test_chains import mirror_scene
from test_manifold import MIRROR, core

FULL = 11   # the slot of the walk as configured (kFullSearch)


def test_a_walk_under_each_limit_is_read_off_the_full_search():
    """Limit H stops a walk at the first iteration after the first whose line
    search rejects more than H tries, after H + 1 of them; until then the walk
    is the full search's. So one full walk tells what every limit would do:
    checked against walks actually run under each limit, from 200 seeds towards
    a light 0.05 above a mirror (the case that needs long searches)."""
    mirror = core(MIRROR)
    rng = np.random.default_rng(3)
    dirs = [[rng.uniform(-1, 1), -1, rng.uniform(-1, 1)] for _ in range(200)]
    walks = long_searches = 0
    for d in dirs:
        full = _core.manifold_walk(mirror, [0, 1, 0], [0, -1, 0], [1, 0.05, 0], [0, 1, 0], d, "R", {})
        if "reprojections" not in full:   # the seed itself missed the mirror
            continue
        walks += 1
        long_searches += full["later_rejections"] > 2
        assert full["limited_tries"][FULL] == full["reprojections"]
        for h in range(11):
            r = _core.manifold_walk(mirror, [0, 1, 0], [0, -1, 0], [1, 0.05, 0], [0, 1, 0], d, "R",
                                    {"step_halvings": h})
            assert r["reprojections"] == full["limited_tries"][h], (d, h)
            assert bool(r["converged"]) == (bool(full["converged"]) and full["later_rejections"] <= h), (d, h)
    # the limits must actually bind on some of these walks
    assert walks > 150 and long_searches > 20, (walks, long_searches)


@pytest.mark.parametrize("h0", [-1, 0, 2])
def test_the_limit_in_force_reads_off_as_it_ran(h0, scenes_dir):
    """Under an active limit h0 its own slot of the counterfactual must be the
    estimator as it ran: the same second moment and the same walk steps as the
    'full' slot (the walk as configured), and that moment the estimates' own
    sum of X^2 / q. This exercises the whole bookkeeping (first trial, the
    MIS-aware rounds with their free successes, the rounds past K) on the
    slab, whose walks fail often."""
    sc = mpg.load_file(scenes_dir / "slab_glass.xml", res="24")
    integ = _core.make_integrator(sc.core, "sms_star", {"count_limits": True, "step_halvings": h0})
    job = _core.RenderJob(sc.core, integ, 64, 1, 0, 0)
    job.wait(1e9)
    s = job.result()["stats"]
    assert s["chain_contributions"] > 1000 and s["bernoulli_trials"] > 2000 and s["owned_shared"] > 100
    # the estimates' and the path tracer's shares' own second moments
    assert s["limit_m2_full"] == pytest.approx(s["chain_m2"], rel=1e-9)
    assert s["limit_pt_m2_full"] == pytest.approx(s["pt_shared_m2"], rel=1e-9)
    if h0 >= 0:
        for key in ("limit_m2", "limit_pt_m2", "limit_steps", "limit_pt_steps"):
            assert s[f"{key}_{h0}"] == pytest.approx(s[f"{key}_full"], rel=1e-9), key
    else:
        # the strictest limit walks less on the slab
        assert s["limit_steps_0"] < s["limit_steps_full"]
    for key in ("limit_m2_full", "limit_steps_full", "limit_pt_m2_full", "limit_pt_steps_full"):
        assert np.isfinite(s[key]) and s[key] > 0, key
    # off (the default): nothing counted
    integ = _core.make_integrator(sc.core, "sms_star", {"step_halvings": h0})
    job = _core.RenderJob(sc.core, integ, 2, 1, 0, 0)
    job.wait(1e9)
    assert job.result()["stats"]["limit_steps_full"] == 0


def test_the_predicted_work_of_a_limit_is_what_it_costs(scenes_dir):
    """The counterfactual is an expectation of the limited estimator: the walk
    steps predicted for limit H by full-search renders match renders run under
    H (other seeds). 12 renders each side, 24^2 x 64 spp of the slab; the
    steps of one render spread ~1-2 %, and the means must agree within 5
    standard errors."""
    sc = mpg.load_file(scenes_dir / "slab_glass.xml", res="24")

    def steps(h, seed, slot):
        integ = _core.make_integrator(sc.core, "sms_star", {"count_limits": True, "step_halvings": h})
        job = _core.RenderJob(sc.core, integ, 64, seed, 0, 0)
        job.wait(1e9)
        s = job.result()["stats"]
        return s[f"limit_steps_{slot}"] + s[f"limit_pt_steps_{slot}"]

    for h in (0, 2):
        pred = np.array([steps(-1, 100 + i, h) for i in range(12)])
        real = np.array([steps(h, 200 + i, "full") for i in range(12)])
        se = np.sqrt(pred.var(ddof=1) / len(pred) + real.var(ddof=1) / len(real))
        assert abs(pred.mean() - real.mean()) < 5 * se, (h, pred.mean(), real.mean(), se)
        # and the limit saves work there (the test means something)
        assert real.mean() < 0.95 * np.mean([steps(-1, 300 + i, "full") for i in range(4)])


def test_choose_step_halvings_on_constructed_counts():
    """r_H = (1 + m dM_H / (n V)) (1 + s TRY_COST dS_H / (n W)): the smallest
    below 1 - margin wins, else the full search."""
    from mpg.guiding import TRY_COST
    base = {"limit_m2_full": 10.0, "limit_steps_full": 100.0}
    st = dict(base, **{f"limit_m2_{h}": 10.0 for h in range(11)},
              **{f"limit_steps_{h}": 100.0 for h in range(11)})
    # H = 3: second moment +2 (V = 4 per sample -> x1.5), steps -60 (W = 100 TRY_COST -> x0.4): r = 0.6
    st["limit_m2_3"], st["limit_steps_3"] = 12.0, 40.0
    h, info = choose_step_halvings(st, n=1, variance=4.0, work=100.0 * TRY_COST, m_scale=1.0, s_scale=1.0)
    assert h == 3 and info["step_halvings_predicted"] == pytest.approx(0.6)
    # the same with a render rate of 1/4: the moment's change counts 4x -> r = 3 * 0.4 = 1.2: full search
    h, info = choose_step_halvings(st, n=1, variance=4.0, work=100.0 * TRY_COST, m_scale=4.0, s_scale=1.0)
    assert h == -1 and info["step_halvings_ratios"][3] == pytest.approx(1.2)
    # within the margin: no limit
    st["limit_m2_3"], st["limit_steps_3"] = 10.0, 97.0
    assert choose_step_halvings(st, 1, 4.0, 100.0 * TRY_COST, 1.0, 1.0)[0] == -1
    # no chain work or no variance: the full search
    assert choose_step_halvings(base, 1, 0.0, 1.0, 1.0, 1.0)[0] == -1
    assert choose_step_halvings({}, 1, 1.0, 1.0, 1.0, 1.0)[0] == -1


def test_mpg_keeps_the_full_search_near_a_mirror_and_limits_it_on_the_slab(scenes_dir):
    """step_halvings=auto (mpg's default): a point light 0.05 above a mirror
    needs long line searches (every limit predicted worse; measured 15x worse
    MSE x time at H = 0, bench/line_search.py), the bumpy slab's walks mostly
    fail and a limit pays. The choice is re-made after each training iteration
    and, by default, the next iterations walk under it (limit_in_training),
    so it can only tighten. A fixed value is used as given. (The mirror's
    light on the floor seen directly would be light traced by default: the
    estimator's walks are what is judged here, so light_trace is 0.)"""
    sc = mpg.load_string(mirror_scene(32, 0.95))
    st = mpg.render(sc, integrator={"type": "mpg", "light_trace": 0}, spp=64, seed=1, progress=False).stats
    assert st["step_halvings_mode"] == "auto" and st["step_halvings"] == -1
    r0 = st["step_halvings_ratios"][0]   # None: censored, left out of the choice
    assert (r0 is None or r0 > 1.5) and set(st["step_halvings_history"]) == {-1}
    sc = mpg.load_file(scenes_dir / "slab_glass.xml", res="32")
    for lit in (True, False):
        st = mpg.render(sc, integrator={"type": "mpg", "limit_in_training": lit}, spp=64, seed=1,
                        progress=False).stats
        hist = st["step_halvings_history"]
        assert st["step_halvings"] >= 0 and len(hist) >= 2 and hist[-1] == st["step_halvings"], hist
        if lit:   # under a limit only tighter ones can be judged
            assert all(b <= a for a, b in zip(hist, hist[1:]) if a >= 0), hist
    st = mpg.render(sc, integrator={"type": "mpg", "step_halvings": 3}, spp=8, seed=1, progress=False).stats
    assert st["step_halvings_mode"] == "fixed" and st["step_halvings"] == 3
    with pytest.raises(RenderError, match="step_halvings"):
        mpg.render(sc, integrator={"type": "sms_star", "step_halvings": "auto"}, spp=1, progress=False)
