"""Plain paths where the trees keep the choice's variance (design-notes, same
name): the training of a branching integrator records, per pixel, the variance
of a branched and of a plain delta path at a fixed film position; the learned
delta split takes plain extra paths where the trees keep more than
BRANCH_KEEP_MAX of it, and the render takes that choice per pixel
(delta_branch_map). Any fixed map keeps the image unbiased."""

from __future__ import annotations

import numpy as np
import pytest

import mpg
from mpg import _core
from mpg.chain_rates import (BRANCH_KEEP_MAX, BRANCH_MIN_RECORDS, BRANCH_RESIDUAL, STEP_COST, TREE_COST,
                             delta_split_effect, learn_delta_split, learn_pixel_split)
from mpg.render import RenderError
from stats_util import REGIONS_32, image_zmax, run_pass
from test_delta_split import _acc, _edge_scene
from test_sampler import EDGE

RES = 32

# test_sampler's EDGE seen in a mirror: its camera looks straight down at a
# perfect conductor; above it the emitting half-plane faces down, its edge
# crossing the image at 20 degrees.
MIRROR_EDGE = EDGE.format(sampler="independent").split("  <shape")[0] + """  <shape type="rectangle">
    <transform name="to_world"><scale value="20"/><rotate x="1" angle="-90"/></transform>
    <bsdf type="conductor"/>
  </shape>
  <shape type="rectangle">
    <transform name="to_world">
      <scale value="10"/><rotate x="1" angle="90"/><translate x="10" y="8"/><rotate y="1" angle="20"/>
    </transform>
    <emitter type="area"><rgb name="radiance" value="1"/></emitter>
  </shape>
</scene>"""


@pytest.fixture(scope="module")
def slabs(scenes_dir):
    return mpg.load_file(scenes_dir / "eval" / "double_slabs.xml", res=RES)


def test_a_plain_branch_map_is_the_unbranched_split_bit_for_bit(slabs):
    """delta_branch_map 0 makes a branching integrator's split paths the plain
    ones (the sample's own delta part back in the mean): bit for bit the
    integrator without branching; a map of ones is no map; bad maps are
    refused with the map's name."""
    two = np.full((RES, RES), 2, np.float32)
    zeros, ones = np.zeros((RES, RES), np.float32), np.ones((RES, RES), np.float32)
    plain = run_pass(slabs, "path", 8, 3, {"delta_branch": 0}, delta_split_map=two)
    mapped = run_pass(slabs, "path", 8, 3, {"delta_branch": 8}, delta_split_map=two, delta_branch_map=zeros)
    assert np.array_equal(plain["sum"], mapped["sum"]) and np.array_equal(plain["sum_sq"], mapped["sum_sq"])
    assert mapped["stats"]["delta_branches"] == 0 and mapped["stats"]["delta_split_paths"] > 0
    tree = run_pass(slabs, "path", 8, 3, {"delta_branch": 8}, delta_split_map=two)
    tree1 = run_pass(slabs, "path", 8, 3, {"delta_branch": 8}, delta_split_map=two, delta_branch_map=ones)
    assert np.array_equal(tree["sum"], tree1["sum"]) and tree["stats"]["delta_branches"] > 0
    integ = _core.make_integrator(slabs.core, "path", {"delta_branch": 8})
    for bad in (np.full((RES, RES), 0.5, np.float32), np.full((RES, RES), 2, np.float32),
                np.ones((RES, RES + 1), np.float32)):
        with pytest.raises(ValueError, match="delta_branch_map"):
            _core.RenderJob(slabs.core, integ, 1, 0, 0, 0, delta_split_map=two, delta_branch_map=bad)
    with pytest.raises(RenderError, match="delta_branch_map"):
        mpg.render(slabs, {"type": "path", "delta_branch": 8}, spp=1, progress=False, delta_split_map=two,
                   delta_branch_map=np.full((RES, RES), 3, np.float32))


def test_a_mixed_branch_map_stays_unbiased(slabs):
    """A random branch map and a random split of 1..4 on double_slabs (two bumpy
    slabs: deep trees and plain paths side by side) agree with the plain path
    tracer: |z| < 5 on the image and its quarters (p < 6e-7 each)."""
    rng = np.random.default_rng(7)
    kmap = rng.integers(1, 5, (RES, RES)).astype(np.float32)
    bmap = rng.integers(0, 2, (RES, RES)).astype(np.float32)
    ref = mpg.render(slabs, "path", spp=4096, seed=61, progress=False)
    img = mpg.render(slabs, {"type": "path", "delta_branch": 8}, spp=1024, seed=63, progress=False,
                     delta_split_map=kmap, delta_branch_map=bmap)
    assert img.stats["delta_branches"] > 0 and img.stats["rejected_samples"] == 0
    assert image_zmax(img, ref, REGIONS_32) < 5


def test_training_records_the_paths_variance_at_a_fixed_position(slabs):
    """A branching integrator's record_costs pass also records, in one sample of
    eight whose own path met a delta vertex, two branched and two plain delta
    paths of one camera ray: the samples' own sums, squares and rays are bit
    for bit those of the pass without branching (the records are off them);
    on double_slabs the trees keep below 0.3 of the plain paths' variance
    at a fixed position where the light is seen in the glass. A directly
    seen emitter's edge (no delta vertex) records nothing; seen in a perfect
    mirror, both kinds' records are exactly 0 (two paths from two positions
    would differ at the edge)."""
    spp = 512
    a = run_pass(slabs, "path", spp, 9, {"delta_branch": 0}, record_costs=True, record_branch=True)
    b = run_pass(slabs, "path", spp, 9, {"delta_branch": 8}, record_costs=True, record_branch=True)
    for key in ("sum", "sum_sq", "rays", "delta_rays", "delta_sum", "delta_sum_sq"):
        assert np.array_equal(a[key], b[key]), key
    # ... and a chain integrator's records (the path tracer alone's values, the traces')
    keys = ("sum", "sum_sq", "rays", "chain_m2", "walk_steps", "alt_sum", "alt_sum_sq", "alt_hits",
            "delta_rays", "delta_sum", "delta_sum_sq", "trace_n", "trace1_sum", "trace1_var")
    sa = run_pass(slabs, "sms_star", 32, 9, {"delta_branch": 0}, record_costs=True, record_branch=True)
    sb = run_pass(slabs, "sms_star", 32, 9, {"delta_branch": 8}, record_costs=True, record_branch=True)
    for key in keys:
        assert np.array_equal(sa[key], sb[key]), key
    assert sb["bdelta_n"].sum() > 0 and sa["alt_hits"].sum() > 0
    # (record_branch is off unless asked: other record_costs callers pay nothing)
    assert not run_pass(slabs, "path", 8, 9, {"delta_branch": 8}, record_costs=True)["bdelta_n"].any()
    assert not a["bdelta_n"].any() and not a["udelta_within"].any()
    assert (b["bdelta_n"] <= spp // 8).all() and b["bdelta_n"].max() == spp // 8
    glass = b["delta_rays"] > 0
    assert not b["bdelta_n"][~glass].any() and b["bdelta_n"][glass].sum() > 0
    assert (b["bdelta_within"] >= 0).all() and (b["udelta_within"] >= 0).all()
    assert (b["bdelta_rays"] >= b["bdelta_n"]).all()   # (at least the camera ray each)
    lit = b["udelta_within"] > 0
    assert lit.sum() >= 10
    # (0.04-0.10 over seeds 0-5; from two positions it would be about 1 or more)
    assert b["bdelta_within"][lit].sum() < 0.3 * b["udelta_within"][lit].sum()
    edge = _edge_scene(8)
    e = run_pass(edge, "path", 64, 1, {"delta_branch": 8}, record_costs=True, record_branch=True)
    assert not e["bdelta_n"].any() and not e["bdelta_rays"].any()
    # the same edge seen in a perfect mirror: a path's value is its film
    # position's alone, so both records are exactly 0 though the edge pixels vary
    m = run_pass(mpg.load_string(MIRROR_EDGE), "path", 256, 1, {"delta_branch": 8}, record_costs=True,
                 record_branch=True)
    assert m["bdelta_n"].sum() == 256 // 8 * 64
    assert not m["bdelta_within"].any() and not m["udelta_within"].any()
    mean = m["sum"][..., 0] / 256
    assert (m["sum_sq"][..., 0] / 256 - mean * mean).max() > 0.01   # (the edge pixels vary)


def _records(acc, keep_rows, n_rec):
    """Records of n_rec samples per pixel whose trees keep keep_rows[i] of the
    plain paths' variance (1 per record) in row i."""
    h, w = acc.chain_m2.shape
    acc.bdelta_n = np.full((h, w), float(n_rec))
    acc.udelta_within = np.full((h, w), float(n_rec))
    acc.bdelta_within = np.repeat(np.asarray(keep_rows, float)[:, None] * n_rec, w, axis=1)
    return acc


def test_the_split_takes_plain_paths_where_the_trees_keep_the_choice():
    """learn_delta_split, branched: where the records (at least
    BRANCH_MIN_RECORDS in the window) show the trees keeping more than
    BRANCH_KEEP_MAX of the plain paths' variance at a fixed position, Eq. 3's
    k of plain paths (branch map 0); elsewhere one branched path where B / V >
    TREE_COST o / C, as without records. delta_split_effect and
    learn_pixel_split count each pixel as its map says."""
    var_t = np.full((4, 4), 1.0)
    var_d = np.full((4, 4), 0.9)
    var_d[3, :] = 0.0
    d_rays = np.full((4, 4), 2.0)   # o = 3
    acc = _acc(var_d, var_t, d_rays, rays=4.0)
    acc.chain_steps = np.full((4, 4), 40.0 / STEP_COST * acc.n)
    acc.walk_steps = acc.chain_steps.copy()
    q = np.full((4, 4), 0.5, np.float32)
    C, V = 4.0 + 0.5 * 40.0, 1.0
    eq3 = np.clip(np.rint(np.sqrt(0.9 * C / (3.0 * V))), 1, 16)
    assert eq3 > 2
    keep = [0.5, 2 * BRANCH_KEEP_MAX, 0.5 * BRANCH_KEEP_MAX, 0.5]
    _records(acc, keep, BRANCH_MIN_RECORDS)
    k, info = learn_delta_split(acc, q, radius=0, objective="mse", branched=True)
    bmap = info["branch_map"]
    np.testing.assert_array_equal(k[0], eq3)
    np.testing.assert_array_equal(k[1], eq3)
    np.testing.assert_array_equal(k[2], 2.0)
    np.testing.assert_array_equal(k[3], 1.0)       # (nothing to split)
    np.testing.assert_array_equal(bmap[:2], 0.0)
    np.testing.assert_array_equal(bmap[2:], 1.0)
    assert info["delta_split_plain_fraction"] == pytest.approx(8 / 12)
    # too few records: the rule without them (one branched path)
    _records(acc, keep, BRANCH_MIN_RECORDS - 1)
    k_few, info_few = learn_delta_split(acc, q, radius=0, objective="mse", branched=True)
    np.testing.assert_array_equal(k_few[:3], 2.0)
    assert np.all(info_few["branch_map"] == 1.0) and info_few["delta_split_plain_fraction"] == 0.0
    # not branching: Eq. 3 everywhere, whatever the records
    k_u, info_u = learn_delta_split(acc, q, radius=0, objective="mse", branched=False)
    np.testing.assert_array_equal(k_u[:3], eq3)
    assert np.all(info_u["branch_map"] == 1.0)
    # the effect: plain pixels keep 1 / k at o (k - 1), branched ones BRANCH_RESIDUAL at TREE_COST o
    dv, dc = delta_split_effect(acc, k, radius=0, objective="mse", branched=bmap)
    n_pix = 16.0
    exp_dv = (8 * 0.9 * (1 - 1 / eq3) + 4 * 0.9 * (1 - BRANCH_RESIDUAL)) / n_pix
    exp_dc = (8 * 3.0 * (eq3 - 1) + 4 * TREE_COST * 3.0) / n_pix
    assert dv == pytest.approx(exp_dv, rel=1e-6) and dc == pytest.approx(exp_dc, rel=1e-6)
    dv_all, dc_all = delta_split_effect(acc, k, radius=0, objective="mse", branched=True)
    assert dc_all > dc and dv_all != pytest.approx(dv)
    # the pixel split: a plain pixel's delta part keeps 1 / kd (here 1/3), a
    # branched one's BRANCH_RESIDUAL (1/24): with the map the image's mean
    # leftover variance is larger, so the pixels without that light (row 3)
    # get fewer samples (2 against 3)
    ks_map, _ = learn_pixel_split(acc, q, k, radius=0, objective="mse", branched=bmap)
    ks_all, _ = learn_pixel_split(acc, q, k, radius=0, objective="mse", branched=True)
    assert np.all(ks_map[3] < ks_all[3]), (ks_map, ks_all)


def test_mpg_learns_a_branch_map_and_renders_with_it(scenes_dir):
    """mpg on chain_length_4 (four bumpy slabs): the training's records make
    some split pixels plain, the map reaches the image (0 only where the split
    is on) and the stats; delta_plain false records nothing and branches
    wherever it splits; a bad value is a clear error."""
    sc = mpg.load_file(scenes_dir / "eval" / "chain_length_4.xml", res=RES)
    img = mpg.render(sc, "mpg", spp=512, seed=3, progress=False)
    st = img.stats
    assert st["delta_split"] == "learned" and "delta_split_plain_fraction" in st
    assert st["rejected_samples"] == 0 and np.isfinite(img.rgb).all()
    assert st["delta_split_plain_fraction"] > 0 and img.delta_branch_map is not None
    assert set(np.unique(img.delta_branch_map)) <= {0.0, 1.0}
    assert np.all(img.delta_split_map[img.delta_branch_map == 0] > 1)
    off = mpg.render(sc, {"type": "mpg", "delta_plain": False}, spp=512, seed=3, progress=False)
    assert off.stats["delta_split_plain_fraction"] == 0.0 and off.delta_branch_map is None
    assert off.stats["delta_split_fraction"] > 0
    with pytest.raises(RenderError, match="delta_plain"):
        mpg.render(sc, {"type": "mpg", "delta_plain": "maybe"}, spp=1, progress=False)
