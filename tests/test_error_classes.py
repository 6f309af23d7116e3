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
    assert np.allclose(got, total, rtol=1e-4, atol=1e-4 * max(1.0, float(total.max())))
    assert np.all(a.class_sum_sq >= 0.0)
    # every class is light added, never taken: a class counted twice would
    # push the rest below 0
    assert np.all(a.class_sum >= -1e-4 * max(1.0, float(total.max())))
    assert not hasattr(b, "class_sum") or b.class_sum is None


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


def test_the_error_classes_script_writes_its_summary(tmp_path):
    """bench/error_classes.py on a tiny scene: a summary whose class variances
    are finite and non-negative and whose dominated shares sum to at most 1."""
    import json
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "error_classes.py"),
                          str(ROOT / "scenes" / "sphere_glass.xml"), "--param", "res=16", "--time", "1.5",
                          "--integrator", "sms_star"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    written = [ln.split("wrote ", 1)[1] for ln in out.stdout.splitlines() if ln.startswith("wrote ")]
    assert written, out.stdout
    d = json.loads(pathlib.Path(written[0]).read_text())
    pathlib.Path(written[0]).unlink()
    assert set(d["class_variance"]) == set(CLASS_NAMES)
    assert all(np.isfinite(v) and v >= 0 for v in d["class_variance"].values())
    assert sum(d["dominated_share_of_image_variance"].values()) <= 1.0 + 1e-9
    assert d["spp"] >= 2



def test_the_delta_class_is_the_light_seen_in_the_glass(sphere):
    """Sample by sample the delta class is what camera_delta=only renders with
    the same random numbers (its path is the same up to the first non-delta
    vertex, where it ends): the per-pixel sums agree to float rounding."""
    a = _render(sphere, "path", record_classes=True, spp=256, seed=9)
    only = _render(sphere, {"type": "path", "camera_delta": "only"}, spp=256, seed=9)
    want = only.rgb.astype(float).mean(axis=2) * a.spp
    assert want.sum() > 0
    assert np.allclose(a.class_sum[..., C["delta"]], want, rtol=1e-4, atol=1e-3)
