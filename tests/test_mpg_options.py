"""mpg's options beside the default: photon initialisation (supplemental
Sec. 2), the photon guide, product-sampling weights (MPG Eq. 14), and how integrator parameters
are checked. Unbiasedness by the same z-tests as tests/test_guiding.py
(|z| < 5, p < 6e-7 per comparison) and by closed forms."""

from __future__ import annotations

import collections

import numpy as np
import pytest

import mpg
from mpg import _core
from mpg.errors import RenderError

from test_chains import mirror_expected, mirror_scene
from stats_util import image_zmax


def _photons(scene, count, seed, **params):
    integ = _core.make_integrator(scene.core, "mpg", dict(params, record=True))
    return integ.trace_photons(count, seed).arrays()


def test_photons_land_on_the_separator_behind_the_sphere(scenes_dir):
    """Photons from the area light through the glass sphere (sphere_glass.xml:
    unit sphere at (0, 1, 0), floor y = 0, light 0.8 x 0.8 at y = 4.5): every
    sample starts on the floor, ends on the light, has n >= 1, and its first
    direction omega_D points at the sphere; T-T dominates, R (n = 1) next."""
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="24")
    a = _photons(sc, 50_000, 1)
    N = len(a["n"])
    assert N > 1000
    assert np.abs(a["xD"][:, 1]).max() < 1e-4
    assert np.all(np.abs(a["xD"][:, [0, 2]]) <= 5 + 1e-4)
    assert np.abs(a["xL"][:, 1] - 4.5).max() < 1e-4
    assert a["xL"][:, 0].min() >= -1.2 - 1e-4 and a["xL"][:, 0].max() <= -0.4 + 1e-4
    assert a["xL"][:, 2].min() >= -0.8 - 1e-4 and a["xL"][:, 2].max() <= 0.0 + 1e-4
    assert a["n"].min() >= 1
    # omega_D from x_D toward the sphere: the ray hits the unit sphere at (0, 1, 0)
    p = a["xD"].astype(np.float64)
    d = a["dir"].astype(np.float64)
    oc = p - np.array([0.0, 1.0, 0.0])
    b = (oc * d).sum(1)
    disc = b * b - ((oc * oc).sum(1) - 1)
    assert np.all(disc > -1e-3) and np.all(b < 0)
    kinds = collections.Counter(zip(a["n"].tolist(), a["tau"].tolist()))
    assert kinds.most_common(1)[0][0] == (2, 0)      # T-T (tau bits 0)
    assert kinds[(1, 1)] > 0                         # R (one reflection)
    assert np.all(np.isfinite(a["weight"])) and a["weight"].min() > 0


def test_photons_are_deterministic_per_seed(scenes_dir):
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="24")
    a, b, c = (_photons(sc, 20_000, s) for s in (3, 3, 4))
    for k in a:
        assert np.array_equal(a[k], b[k])
    assert len(a["n"]) != len(c["n"]) or not np.array_equal(a["xD"], c["xD"])


def test_photons_from_a_point_light_reflect_once_in_the_mirror():
    """Point light at (0, 1, 0), mirror x = 1, floor y = 0: every photon sample
    is n = 1, tau = R, ends at the light, and omega_D points to the mirror at
    the point where the reflected ray from the light's image (2, 1, 0) crosses
    x = 1."""
    sc = mpg.load_string(mirror_scene())
    a = _photons(sc, 20_000, 2)
    assert len(a["n"]) > 500
    assert np.all(a["n"] == 1) and np.all(a["tau"] == 1)
    assert np.allclose(a["xL"], [0.0, 1.0, 0.0], atol=1e-5)
    img = np.array([2.0, 1.0, 0.0])
    to_img = img - a["xD"]
    to_img /= np.linalg.norm(to_img, axis=1, keepdims=True)
    # (floor points within 5 cm of the mirror excluded: there the float
    # offset of the mirror hit point, ~1e-5, turns a few mrad of direction)
    far = a["xD"][:, 0] < 0.95
    assert far.mean() > 0.9
    assert np.allclose(a["dir"][far], to_img[far], atol=2e-3)


def test_the_photons_do_not_depend_on_the_thread_count(scenes_dir):
    """trace_photons runs its photons in blocks on several threads: every
    photon has its own random stream and the blocks are appended in index
    order, so 1, 2 and 3 threads (and a count that does not divide evenly)
    give the same buffer, sample for sample."""
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="24")
    integ = _core.make_integrator(sc.core, "mpg", dict(record=True))
    one = integ.trace_photons(30_001, 5, threads=1).arrays()
    assert len(one["n"]) > 500
    for t in (2, 3):
        other = integ.trace_photons(30_001, 5, threads=t).arrays()
        for k in one:
            assert np.array_equal(one[k], other[k]), (t, k)
    with pytest.raises(ValueError, match="threads"):
        integ.trace_photons(10, 5, threads=-1)


def test_photon_ranges_appended_are_the_whole_trace(scenes_dir):
    """trace_photons(count, seed, begin=, end=): photons [begin, end) of the
    count-photon trace, weighted as in it (flux / count). The photon guide
    grows over the training's builds from such ranges, so consecutive
    ranges appended in order must be the whole trace's buffer, sample for
    sample, whatever the threads; a range outside [0, count] is refused."""
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="24")
    integ = _core.make_integrator(sc.core, "mpg", dict(record=True))
    whole = integ.trace_photons(30_001, 9, threads=2).arrays()
    # (one empty range; a thread takes 4096 photons or more, and no more
    # threads than cores: the third range runs on up to 3 threads, the
    # fourth on 2, the first on 1)
    cuts = [0, 5_000, 5_000, 17_500, 30_001]
    parts = [integ.trace_photons(30_001, 9, threads=t, begin=a, end=b).arrays()
             for t, (a, b) in zip((1, 2, 3, 2), zip(cuts[:-1], cuts[1:]))]
    assert len(parts[1]["n"]) == 0 and len(parts[0]["n"]) > 100
    for k in whole:
        assert np.array_equal(whole[k], np.concatenate([q[k] for q in parts])), k
    for a, b in ((5, 4), (0, 30_002), (-1, 10), (0, -3)):
        with pytest.raises(ValueError, match="begin <= end <= count"):
            integ.trace_photons(30_001, 9, begin=a, end=b)


def test_a_scaled_buffer_scales_the_weights_alone(scenes_dir):
    """SubpathBuffer.scaled (the photon guide's samples put on the training
    samples' scale): every weight times f, every other field as it was."""
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="24")
    integ = _core.make_integrator(sc.core, "mpg", dict(record=True))
    buf = integ.trace_photons(5_000, 2)
    a, b = buf.arrays(), buf.scaled(37.5).arrays()
    assert len(a["n"]) > 100
    assert np.allclose(b["weight"], 37.5 * a["weight"], rtol=1e-6)
    for k in ("xD", "xL", "dir", "n", "tau"):
        assert np.array_equal(a[k], b[k])


def test_the_photon_guide_joins_every_training_guide(scenes_dir):
    """photon_guide (on by default): its photons' sub-path samples join the
    guide each training iteration builds, grown over the builds (a quarter,
    half, then all); 0 traces none. With them the leaves hold more samples,
    so the STree splits more."""
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="16")
    on = mpg.render(sc, "mpg", spp=24, seed=4, progress=False).stats
    off = mpg.render(sc, {"type": "mpg", "photon_guide": 0}, spp=24, seed=4, progress=False).stats
    assert on["photon_guide"] == 200_000 and on["photon_guide_samples"] > 1000
    # (grown over the builds: 1/4, 1/2, then all of them from the third)
    assert on["training_iterations"] >= 3 and on["photon_guide_traced"] == 200_000
    short = mpg.render(sc, "mpg", spp=4, seed=4, progress=False).stats   # (1 training spp: one build)
    assert short["training_iterations"] == 1 and short["photon_guide_traced"] == 50_000
    assert 0 < short["photon_guide_samples"] < on["photon_guide_samples"] / 2
    assert off["photon_guide"] == 0 and off["photon_guide_samples"] == 0 and off["seconds_photon_guide"] == 0
    assert on["guide_leaves"] > off["guide_leaves"]
    assert on["seconds_photon_guide"] > 0
    assert on["guide_bytes"] == (on["subpath_samples"] + on["photon_guide_samples"]) * _core.SUBPATH_SAMPLE_BYTES
    # the whole guide: its samples and more (the tree, copies, the leaves' lobes)
    assert on["guide_memory_bytes"] > on["guide_bytes"] and on["guide_bytes_per_sample"] > 40
    assert off["guide_memory_bytes"] > 0
    # no training (training_fraction 0): no photons either
    none = mpg.render(sc, {"type": "mpg", "training_fraction": 0.0}, spp=4, seed=4, progress=False).stats
    assert none["photon_guide_samples"] == 0 and none["seconds_photon_guide"] == 0
    assert none["guide_memory_bytes"] == 0 and none["guide_bytes_per_sample"] == 0
    # init=photon: its first guide is its own photons' alone; the photon
    # guide's join the training's guides
    ini = mpg.render(sc, {"type": "mpg", "init": "photon", "photons": 5000}, spp=24, seed=4, progress=False).stats
    # (its first guide holds no photon guide, and on this 16x16 image its
    # first iteration found no sub-path sample, so built none: two builds
    # held the photon guide, half of it)
    assert ini["photon_samples"] > 0 and ini["photon_guide_traced"] == 100_000
    assert 0 < ini["photon_guide_samples"] < on["photon_guide_samples"]
    # a scene without chains: the stats are there, and nothing was traced
    diffuse = mpg.load_file(scenes_dir / "eval" / "diffuse_room.xml", res="8")
    d = mpg.render(diffuse, "mpg", spp=2, seed=1, progress=False).stats
    assert d["photon_guide_samples"] == 0 and d["seconds_photon_guide"] == 0 and d["photon_guide"] == 200_000


def test_the_photon_guide_scale_does_not_depend_on_order():
    """guiding._order_free_mean: the same bits for any order of the weights
    (float32 summed in a shuffled order would not be)."""
    from mpg.guiding import _order_free_mean
    rng = np.random.default_rng(8)
    w = (rng.lognormal(0.0, 4.0, 20_000)).astype(np.float32)
    ref = _order_free_mean(w)
    naive = {float(np.mean(rng.permutation(w))) for _ in range(20)}
    assert len(naive) > 1   # (the order does move a plain mean's last bits)
    for _ in range(20):
        assert _order_free_mean(rng.permutation(w)) == ref


def test_the_photon_guide_leaves_the_image_deterministic():
    """The photon guide's scale is the mean weight of a training buffer whose
    order depends on which thread ran which tile; taken in that order, its
    last bits moved the guide and the image from run to run on 2 threads
    (the mirror's line-search limit then came out 4 instead of the full
    search in one run of three). The same seed and spp give one image on 1
    and 2 threads, twice."""
    sc = mpg.load_string(mirror_scene(32, 0.95))
    imgs = [mpg.render(sc, integrator={"type": "mpg", "light_trace": 0}, spp=64, seed=1, threads=t,
                       progress=False) for t in (1, 2, 2)]
    assert imgs[0].stats["photon_guide_samples"] > 0
    for b in imgs[1:]:
        assert np.array_equal(imgs[0].rgb, b.rgb)
        assert b.stats["subpath_samples"] == imgs[0].stats["subpath_samples"]


def test_photons_need_chains(scenes_dir):
    """No chain emitter or caster: no photons are traced."""
    sc = mpg.load_string("""<scene version="3.0.0">
      <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>
      <integer name="height" value="8"/></film></sensor>
      <shape type="sphere"><bsdf type="diffuse"/></shape>
      <emitter type="point"><point name="position" x="0" y="3" z="0"/></emitter></scene>""")
    assert len(_photons(sc, 1000, 0)["n"]) == 0


@pytest.mark.parametrize("params", [{"init": "photon"}, {"product": True},
                                    {"init": "photon", "product": "true"}, {"photon_guide": 0},
                                    {"lobe_anchor": "auto"}, {"lobe_anchor": 0.3}])
def test_mpg_options_are_unbiased_against_path_tracing(params, scenes_dir):
    """As test_guiding's unbiasedness test, with photon initialisation and
    product-sampling weights: |z| < 5 on the image and nine regions. 1024 spp:
    the chain estimates are heavy-tailed, and at 384 spp the photon + product
    case sat at |z| = 4.25 with the full line search and 5.4 with the limit
    mpg chose (the same block, low in both: a short run of a heavy-tailed
    estimator mostly falls short). Checked with scratch scripts, not kept:
    over 24 seeds x 384 spp both agreed with a 65 536 spp path reference
    (|z| < 2.2 in every region); at 1024 spp six seeds gave |z| <= 3.3."""
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="24")
    ref = mpg.render(sc, integrator="path", spp=16384, seed=11, progress=False)
    img = mpg.render(sc, integrator=dict(params, type="mpg"), spp=1024, seed=12, progress=False)
    st = img.stats
    if params.get("init") == "photon":
        assert st["init"] == "photon" and st["photon_samples"] > 0
    if "lobe_anchor" in params:   # (the lobes the render drew from are anchored)
        assert st["lobe_anchor"] == params["lobe_anchor"] and st["lobe_anchored_fraction"] > 0
    assert st["guided_trials"] > 0 and st["chain_contributions"] > 0
    assert st["rejected_samples"] == 0
    assert not any("ignores" in w for w in st["warnings"])
    regions = [np.s_[:, :]] + [np.s_[i:i + 8, j:j + 8] for i in (0, 8, 16) for j in (0, 8, 16)]
    assert image_zmax(img, ref, regions) < 5


def _assert_mirror_closed_form(img):
    """The image's mean matches test_chains' closed form of the mirror scene
    (|z| < 5, or within 0.2 %)."""
    exp = mirror_expected()
    a = img.rgb[..., 0].astype(np.float64)
    se = np.sqrt(img.variance[..., 0].sum()) / a.size
    assert abs(a.mean() - exp.mean()) < max(5 * se, 2e-3 * exp.mean()), (a.mean(), exp.mean(), se)


@pytest.mark.parametrize("params", [{"init": "photon"}, {"init": "photon", "training_fraction": 0.0},
                                    {"init": "photon", "known_types": True}, {"lobe_anchor": "auto"}])
def test_mpg_photon_init_matches_the_mirror_closed_form(params):
    """Point light seen through a mirror (a path tracer cannot render it):
    with the photon-built guide (and with it alone, no training) the image
    matches the closed form of test_chains. (light_trace 0: the floor is seen
    directly, so mpg would light trace the mirror's light, test_light_trace.)"""
    sc = mpg.load_string(mirror_scene())
    img = mpg.render(sc, integrator=dict(params, type="mpg", light_trace=0), spp=64, seed=3, progress=False)
    _assert_mirror_closed_form(img)
    assert img.stats["chain_contributions"] > 0


def test_mpg_shows_its_training_progress(scenes_dir, capsys):
    """With progress on, each training iteration reports its number, spp (and
    all so far), sub-path samples, leaves, time and what is left of the
    training budget; then the render's bar. Off: nothing on stderr."""
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="16")
    mpg.render(sc, "mpg", spp=16, seed=1, progress=True)
    err = capsys.readouterr().err
    for i in (1, 2):
        assert f"mpg: training iteration {i}: " in err
    assert "sub-path samples" in err and "leaves" in err and "spp of training left" in err
    import re
    assert re.search(r"\] +[0-9.]+%  \d+/\d+ spp .*ETA", err)   # the render's bar
    mpg.render(sc, "mpg", time=0.5, seed=1, progress=True)
    assert "s of training left" in capsys.readouterr().err
    mpg.render(sc, "mpg", spp=16, seed=1, progress=False)
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("params", [{}, {"guide_n": False}, {"guide_tau": False}, {"guide_dir": False},
                                    {"stree_filter": "none"}, {"stree_filter": "stochastic"},
                                    {"guide_structure": "knn", "knn_k": 64}])
def test_mpg_ablations_match_the_mirror_closed_form(params):
    """A point light seen through a mirror, which the path tracer cannot
    render: with the surface-uniform initialisation and each ablation of MPG
    Fig. 14 / supplemental Fig. 3 the image matches test_chains' closed form
    (|z| < 5 or within 0.2 %; light_trace 0, as in the photon test above)."""
    sc = mpg.load_string(mirror_scene())
    img = mpg.render(sc, integrator=dict(params, type="mpg", light_trace=0), spp=64, seed=7, progress=False)
    _assert_mirror_closed_form(img)
    st = img.stats
    assert st["chain_contributions"] > 0 and st["subpath_samples"] > 0
    assert st["guided_trials"] > 0


@pytest.mark.parametrize("key,value", [("product", "maybe"), ("selective", "2x"), ("known_types", "2x"),
                                       ("photons", "many"), ("photon_guide", -1), ("photon_guide", "many"),
                                       ("photon_guide", True), ("photon_guide", 2.5),
                                       ("init", "camera"), ("photons", 0),
                                       ("training_guide_fraction", 1.0),
                                       ("training_guide_fraction", "half"), ("lobe_anchor", -1),
                                       ("lobe_anchor", "far"), ("lobe_anchor", True), ("lobe_anchor", "inf"),
                                       ("lobe_anchor", 1e7)])
def test_bad_mpg_parameters_are_named(key, value, scenes_dir):
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="8")
    with pytest.raises(RenderError, match=key):
        mpg.render(sc, integrator={"type": "mpg", key: value}, spp=4, progress=False)


@pytest.mark.parametrize("text,expect", [("true", True), ("False", False), ("1", True), ("no", False),
                                         (True, True), (0, False)])
def test_boolean_parameters(text, expect):
    from mpg.render import _as_bool
    assert _as_bool("x", text) is expect


@pytest.mark.parametrize("integ,key,hint", [("mpg", "chain_rat", "chain_rate"), ("path", "max_dept", "max_depth"),
                                             ("sms_star", "bogus", None)])
def test_an_unknown_parameter_is_an_error(integ, key, hint, scenes_dir):
    """A name none of mpg's integrators has is an error, with the near names: a
    typo in a dict would otherwise render the defaults with only a warning."""
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="8")
    with pytest.raises(RenderError, match=f"unknown parameter '{key}'") as e:
        mpg.render(sc, integrator={"type": integ, key: 1}, spp=2, progress=False)
    if hint:
        assert f"did you mean {hint}" in str(e.value)


def test_cli_rejects_an_unknown_parameter_and_keeps_the_scene_files(tmp_path, scenes_dir, capsys):
    """-P with a typo stops before rendering; a scene file's integrator parameter
    mpg does not know (another renderer's) still only warns."""
    from mpg.cli import main
    out = tmp_path / "a.exr"
    rc = main([str(scenes_dir / "sphere_glass.xml"), "-D", "res=8", "--spp", "2", "-q", "-o", str(out),
               "--integrator", "mpg", "-P", "chain_rat=1"])
    assert rc != 0 and not out.exists()
    assert "unknown parameter 'chain_rat'" in capsys.readouterr().err
    text = (scenes_dir / "sphere_glass.xml").read_text()
    i = text.index("<integrator")
    j = text.index(">", i) + 1
    scene = tmp_path / "s.xml"
    scene.write_text(text[:j] + '<integer name="samples_per_pass" value="1"/>' + text[j:])
    rc = main([str(scene), "-D", "res=8", "--spp", "2", "-q", "-o", str(out), "-P", "max_depth=6"])
    assert rc == 0 and out.exists()
    assert "ignores parameter(s) samples_per_pass" in capsys.readouterr().err


def test_an_ignored_parameter_is_reported(scenes_dir):
    sc = mpg.load_file(scenes_dir / "sphere_glass.xml", res="8")
    img = mpg.render(sc, integrator={"type": "path", "tau": "TT"}, spp=2, progress=False)
    assert any("ignores parameter(s) tau" in w for w in img.stats["warnings"])


def test_bench_entries_take_parameters():
    from mpg.bench.runners import BenchError, parse_integrator
    s = parse_integrator("mpg/init=photon/product=true")
    assert s.name == "mpg" and s.params == (("init", "photon"), ("product", "true"))
    assert s.label == "mpg/init=photon/product=true"
    assert parse_integrator("path").params == ()
    with pytest.raises(BenchError, match="did you mean chain_rate"):
        parse_integrator("mpg/chain_rat=1")
    # `sampler` is the render's setting, not an integrator parameter (run_mpg)
    assert parse_integrator("path/sampler=stratified").params == (("sampler", "stratified"),)
    with pytest.raises(BenchError, match="key=value"):
        parse_integrator("mpg/init")


def test_largest_chain_estimate_is_reported():
    """The stats name the largest single chain estimate and its factors. A
    planar mirror has one solution (n = 1, P(n) = 1, K a whole number >= 1),
    and the largest estimate is at least the brightest pixel's chain part (a
    pixel's value is a mean over its samples)."""
    sc = mpg.load_string(mirror_scene())
    img = mpg.render(sc, integrator={"type": "sms", "tau": "R"}, spp=8, seed=1, progress=False)
    st = img.stats
    assert st["max_chain_K"] >= 1 and st["max_chain_K"] == int(st["max_chain_K"])
    assert st["max_chain_n"] == 1 and st["max_chain_guided"] == 0
    assert st["max_chain_G"] > 0 and st["max_chain_pn"] == 1
    direct = mpg.render(sc, integrator="path", spp=8, seed=1, progress=False)
    chain_part = (img.rgb - direct.rgb).mean(-1)     # the mirror term (path tracing misses it)
    assert st["max_chain_value"] >= 0.9 * chain_part.max() > 0
    # ... as it enters the sample: after the roulette's 1/q (per unit K, an
    # estimate here varies by ~25 % over the mirror; 1/q = 4)
    assert st["max_chain_rate"] == 1.0
    sq = mpg.render(sc, integrator={"type": "sms", "tau": "R", "chain_rate": 0.25}, spp=8, seed=1,
                    progress=False).stats
    assert sq["max_chain_rate"] == 0.25
    assert sq["max_chain_value"] / sq["max_chain_K"] >= 2.0 * st["max_chain_value"] / st["max_chain_K"]
