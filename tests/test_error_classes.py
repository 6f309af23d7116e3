"""render(record_classes=True): each sample's value split by where it entered
(chain estimates, the path tracer's shares of shared chain paths, traced
chain light of handed-off pixels, chain paths the path tracer kept whole at
rate 0 and elsewhere (by why), light seen through delta scattering only,
the rest), summed per pixel with
its squares (bench/error_classes.py). The classes add up to the sample, the
record changes no image, and each class holds what it names."""

from __future__ import annotations

import pathlib
import subprocess
import sys

import numpy as np
import pytest

import mpg
from mpg.render import CLASS_NAMES
from bench_util import bench_module
from stats_util import run_pass

RES = 32
ROOT = pathlib.Path(__file__).resolve().parents[1]
C = {nm: i for i, nm in enumerate(CLASS_NAMES)}


@pytest.fixture(scope="module")
def sphere(sphere32):
    return sphere32


def _render(sc, integ, **kw):
    return mpg.render(sc, integ, spp=kw.pop("spp", 16), seed=kw.pop("seed", 5), progress=False, **kw)


def _maps(seed=1):
    rng = np.random.default_rng(seed)
    q = rng.choice([0.0, 0.3, 1.0], (RES, RES)).astype(np.float32)
    k = rng.integers(1, 4, (RES, RES)).astype(np.float32)
    return q, k


@pytest.mark.parametrize("integ", ["path", "sms_star", {"type": "sms_star", "handoff_guided": 2}])
def test_the_classes_add_up_and_change_no_image(sphere, integ):
    """Per pixel the classes' sums add to the sum of the samples' values (mean
    over RGB; float rounding only), with per-pixel rate maps holding 0, a
    delta split and a pixel split; the image is bit-identical to one rendered
    without the record."""
    q, k = _maps()
    kw = {} if integ == "path" else dict(chain_rate_map=q)
    kw.update(delta_split_map=k, pixel_split_map=k[::-1].copy())
    a = _render(sphere, integ, record_classes=True, **kw)
    b = _render(sphere, integ, **kw)
    assert np.array_equal(a.rgb, b.rgb)
    assert a.stats["rejected_samples"] == 0
    total = a.rgb.astype(float).mean(axis=2) * a.spp
    got = a.class_sum.sum(axis=2)
    assert a.class_sum.shape == (RES, RES, len(CLASS_NAMES))
    # (the rest is the sample less the others, so this checks the float
    # bookkeeping and the pixel split's mean)
    assert np.allclose(got, total, rtol=1e-4, atol=1e-6)
    assert np.all(a.class_sum_sq >= 0.0)
    # every class is light added, never taken, per pixel: a class counted
    # twice by more than the rest's light pushes the rest below 0
    tol = 1e-4 * total[..., None] + 1e-6
    assert np.all(a.class_sum >= -tol) and np.all(a.class_sum <= total[..., None] + tol)
    assert b.class_sum is None and b.class_sum_sq is None


def test_each_class_holds_what_it_names(sphere):
    """path: no chain classes; sms_star at rate 1: chain estimates and the path
    tracer's shares (mis), nothing handed; at rate 0 everywhere: the chain
    light is the path tracer's whole (no estimate, no share), all of it
    handed; the path tracer's light seen in the glass is the delta class."""
    p = _render(sphere, "path", record_classes=True, spp=256)   # (the glint is rare at 32^2)
    for nm in ("chain", "shared", "traced", "handed", "unseen", "inactive", "unowned"):
        assert np.all(p.class_sum[..., C[nm]] == 0.0), nm
    assert p.class_sum[..., C["delta"]].sum() > 0 and p.class_sum[..., C["other"]].sum() > 0
    one = _render(sphere, "sms_star", record_classes=True, chain_rate_map=np.ones((RES, RES), np.float32))
    assert one.class_sum[..., C["chain"]].sum() > 0 and one.class_sum[..., C["shared"]].sum() > 0
    assert np.all(one.class_sum[..., C["handed"]] == 0.0)
    zero = _render(sphere, {"type": "sms_star", "handoff_guided": 0}, record_classes=True, spp=64,
                   chain_rate_map=np.zeros((RES, RES), np.float32))
    for nm in ("chain", "shared", "traced"):
        assert np.all(zero.class_sum[..., C[nm]] == 0.0), nm
    assert zero.class_sum[..., C["handed"]].sum() > 0
    for nm in ("unseen", "inactive", "unowned"):
        assert np.all(zero.class_sum[..., C[nm]] == 0.0), nm
    # without a guide nothing is unseen or inactive; chains longer than
    # max_chain are not the estimator's (the ball's TT is n = 2)
    short = _render(sphere, {"type": "sms_star", "max_chain": 1}, record_classes=True, spp=64,
                    chain_rate_map=np.ones((RES, RES), np.float32))
    assert short.class_sum[..., C["unowned"]].sum() > 0
    for nm in ("unseen", "inactive", "handed", "traced"):
        assert np.all(short.class_sum[..., C[nm]] == 0.0), nm


def _guide(sc, spp, **params):
    """A guide from one recording pass of mpg's estimator at rate 1."""
    from mpg import _core
    g = _core.GuidingState()
    r = run_pass(sc, "mpg", spp, 5, dict(record=True, chain_rate=1.0, light_trace_area=False, **params))
    g.build_from([r["subpaths"]], *sc.core.bbox, c=1.0, epsilon=0.1, threads=2)
    return g


def test_guided_classes(sphere):
    """With a guide: rate-0 pixels with guided traces put their first
    separator's chain light in the traced class (later separators' in
    handed); a guide whose leaves saw only one-vertex chains (max_chain 1)
    makes the ball's TT an unseen type under known_types (the path tracer's
    whole), and a shared one without. (Without area photons: they take the
    first hits' chains these classes are about.)"""
    g = _guide(sphere, 4)
    t = _render(sphere, {"type": "mpg", "guide": g, "handoff_guided": 2, "light_trace_area": False}, record_classes=True, spp=32,
                chain_rate_map=np.zeros((RES, RES), np.float32))
    assert t.class_sum[..., C["traced"]].sum() > 0
    for nm in ("chain", "shared", "unseen", "inactive", "unowned"):
        assert np.all(t.class_sum[..., C[nm]] == 0.0), nm
    g1 = _guide(sphere, 4, max_chain=1)
    rate = np.full((RES, RES), 0.5, np.float32)
    kt = _render(sphere, {"type": "mpg", "guide": g1, "known_types": True, "light_trace_area": False}, record_classes=True, spp=64,
                 chain_rate_map=rate)
    assert kt.class_sum[..., C["unseen"]].sum() > 0 and np.all(kt.class_sum[..., C["shared"]] == 0.0)
    off = _render(sphere, {"type": "mpg", "guide": g1, "known_types": False, "light_trace_area": False}, record_classes=True, spp=64,
                  chain_rate_map=rate)
    assert np.all(off.class_sum[..., C["unseen"]] == 0.0) and off.class_sum[..., C["shared"]].sum() > 0


def test_the_delta_split_mean_is_the_delta_class(sphere):
    """A delta split changes only the light seen through delta scattering only
    (its extra paths draw after the sample's own path): every other class is
    the same, pixel by pixel, as without the split."""
    plain = _render(sphere, "path", record_classes=True, spp=256, seed=9)
    split = _render(sphere, "path", record_classes=True, spp=256, seed=9,
                    delta_split_map=np.full((RES, RES), 4, np.float32))
    assert split.stats["delta_split_paths"] > 0
    for nm in CLASS_NAMES:
        if nm != "delta":
            assert np.allclose(split.class_sum[..., C[nm]], plain.class_sum[..., C[nm]], rtol=1e-4, atol=1e-3), nm
    assert split.class_sum[..., C["delta"]].sum() > 0


def test_mpg_records_its_final_render(sphere):
    """mpg.render(..., record_classes=True) with mpg: the final render's samples
    (the training's are not in the image), adding up as above; its chain
    light reaches the chain classes."""
    img = mpg.render(sphere, {"type": "mpg", "chain_rate": 0.5}, spp=48, seed=3, progress=False,
                     record_classes=True)
    assert img.class_sum.shape == (RES, RES, len(CLASS_NAMES))
    total = img.rgb.astype(float).mean(axis=2) * img.spp
    assert np.allclose(img.class_sum.sum(axis=2), total, rtol=1e-4, atol=1e-4 * max(1.0, float(total.max())))
    assert img.class_sum[..., C["chain"]].sum() > 0
    # the area light's photons (mpg's light_trace_area) are a class of their own
    assert img.class_sum[..., C["photons"]].sum() > 0 and img.stats["lt_splats"] > 0


def test_the_error_classes_script_writes_its_summary(tmp_path):
    """bench/error_classes.py on a tiny scene: a summary whose class variances
    are finite and non-negative and whose dominated shares sum to at most 1."""
    import json
    dest = tmp_path / "classes.json"
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "error_classes.py"),
                          str(ROOT / "scenes" / "sphere_glass.xml"), "--param", "res=16", "--spp", "8",
                          "--integrator", "sms_star", "--top", "400", "--seeds", "2", "--out", str(dest)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    d = json.loads(dest.read_text())
    assert set(d["class_variance"]) == set(CLASS_NAMES)
    assert all(np.isfinite(v) and v >= 0 for v in d["class_variance"].values())
    assert sum(d["dominated_share_of_image_variance"].values()) <= 1.0 + 1e-9
    assert d["spp"] == 8
    # --seeds 2: the classes' and groups' variance across the two renders
    assert d["seeds"] == 2 and set(d["class_seed_variance"]) == set(CLASS_NAMES)
    assert set(d["group_seed_variance"]) == {"chain_light", "delta", "other"}
    assert np.isfinite(d["image_seed_variance"]) and d["image_seed_variance"] > 0
    bad = subprocess.run([sys.executable, str(ROOT / "bench" / "error_classes.py"), "sphere", "--integrator", "mpg/x"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--integrator" in bad.stderr


def test_the_delta_class_is_the_light_seen_in_the_glass(sphere):
    """Sample by sample the delta class is what camera_delta=only renders with
    the same random numbers (its path is the same up to the first non-delta
    vertex, where it ends): the per-pixel sums agree to float rounding."""
    a = _render(sphere, "path", record_classes=True, spp=256, seed=9)
    only = _render(sphere, {"type": "path", "camera_delta": "only"}, spp=256, seed=9)
    want = only.rgb.astype(float).mean(axis=2) * a.spp
    assert want.sum() > 0
    assert np.allclose(a.class_sum[..., C["delta"]], want, rtol=1e-4, atol=1e-3)


def test_seed_summary_groups_anticorrelated_classes():
    """error_classes.seed_summary: where a seed's maps move one light between
    two classes (a pixel's chain light the estimator's in one seed, handed
    off in another) each class's seeds' variance is large and their group's
    is 0; a class's contribution (var(all) - var(all - class)) then counts
    its covariance, and the groups name every class once."""
    ec = bench_module("error_classes")
    GROUPS, seed_summary = ec.GROUPS, ec.seed_summary
    assert sorted(c for g in GROUPS.values() for c in g) == sorted(CLASS_NAMES)
    rng = np.random.default_rng(3)
    s, h, w = 400, 4, 4
    x = rng.normal(size=(s, h, w))
    d = 0.5 * rng.normal(size=(s, h, w))
    means = np.zeros((s, h, w, len(CLASS_NAMES)))
    means[..., C["chain"]] = 1.0 + x
    means[..., C["handed"]] = 2.0 - x
    means[..., C["delta"]] = d
    out = seed_summary(means, CLASS_NAMES)
    vx, vd = float(np.mean(x.var(axis=0, ddof=1))), float(np.mean(d.var(axis=0, ddof=1)))
    assert out["class_seed_variance"]["chain"] == pytest.approx(vx)
    assert out["group_seed_variance"]["chain_light"] == pytest.approx(0.0, abs=1e-12)
    assert out["image_seed_variance"] == pytest.approx(float(np.mean(d.var(axis=0, ddof=1))))
    assert out["group_seed_contribution"]["delta"] == pytest.approx(vd)
    assert out["group_seed_contribution"]["chain_light"] == pytest.approx(0.0, abs=1e-12)
    # all - chain = 2 - x + d: var(all) - var(all - chain) = vd - (vx + vd) + (cross terms ~ 0)
    assert out["class_seed_contribution"]["chain"] < -0.5 * vx
    with pytest.raises(ValueError):
        seed_summary(means[:1], CLASS_NAMES)


def test_split_by_mask_adds_up_to_the_groups():
    """error_classes.split_by_mask: the groups' seeds' variance in the
    masked pixels and in the rest add up to seed_summary's image means."""
    ec = bench_module("error_classes")
    GROUPS, seed_summary, split_by_mask = ec.GROUPS, ec.seed_summary, ec.split_by_mask
    rng = np.random.default_rng(4)
    means = rng.gamma(0.5, size=(5, 6, 7, len(CLASS_NAMES)))
    mask = rng.random((6, 7)) < 0.3
    whole = seed_summary(means, CLASS_NAMES)
    parts = split_by_mask(means, CLASS_NAMES, mask, 1e-3)
    assert parts["pixels_above"] == int(mask.sum())
    for g in GROUPS:
        assert parts["above"][g] + parts["below"][g] == pytest.approx(whole["group_seed_variance"][g])
        assert parts["above"][g] > 0 and parts["below"][g] > 0
    assert parts["above"]["image"] + parts["below"]["image"] == pytest.approx(whole["image_seed_variance"])
