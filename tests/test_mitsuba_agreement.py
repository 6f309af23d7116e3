"""The same XML rendered by mpg and by Mitsuba 3 (scalar_rgb) agrees within
statistical error.

For each scene both renderers produce a per-pixel mean and an estimate of the
variance of that mean (mpg: from its per-pixel second moment; Mitsuba: from
PASSES independent passes with distinct seeds). With the box filter pixels are
independent, so the standard error of a region mean is sqrt(sum of pixel
variances) / n. We compare the whole image and a 4x4 grid of regions, per
channel: z = (a - b) / sqrt(se_a^2 + se_b^2), and require |z| < Z_MAX.

Confidence: Z_MAX = 5 is a two-sided p of 5.7e-7 per comparison under
normality; 17 regions x 3 channels x 5 scenes = 255 comparisons give a
family-wise false-alarm rate below 1.5e-4. A bias of 1% of a region's value
is detected when the relative standard error is below 0.2%.
"""

from __future__ import annotations

import numpy as np
import pytest

import mpg

mi = pytest.importorskip("mitsuba")

Z_MAX = 5.0
RES = 96
SPP_MPG = 1024
PASSES = 16
SPP_MI = 64     # per pass; Mitsuba total = PASSES * SPP_MI

SCENE_NAMES = ["sphere_glass", "slab_glass", "conductor_normalmap", "materials", "envmap_objects"]


def _mitsuba(path: str):
    mi.set_variant("scalar_rgb")
    scene = mi.load_file(path, res=str(RES), spp=str(SPP_MI))
    imgs = np.stack([np.array(mi.render(scene, spp=SPP_MI, seed=1000 + k), dtype=np.float64)[:, :, :3]
                     for k in range(PASSES)])
    mean = imgs.mean(axis=0)
    var_of_mean = imgs.var(axis=0, ddof=1) / PASSES
    return mean, var_of_mean


def _mpg(path: str):
    scene = mpg.load_file(path, res=str(RES), spp=str(SPP_MPG))
    img = mpg.render(scene, spp=SPP_MPG, seed=7, progress=False)
    assert img.stats["rejected_samples"] == 0
    return img.rgb.astype(np.float64), img.variance.astype(np.float64)


def _regions(h: int, w: int, n: int = 4):
    yield "image", (slice(0, h), slice(0, w))
    for i in range(n):
        for j in range(n):
            yield f"block{i}{j}", (slice(i * h // n, (i + 1) * h // n),
                                   slice(j * w // n, (j + 1) * w // n))


def compare(a_mean, a_var, b_mean, b_var):
    """Per-region, per-channel z-scores; returns a list of (region, channel, z, a, b)."""
    out = []
    h, w = a_mean.shape[:2]
    for name, (sy, sx) in _regions(h, w):
        n = (sy.stop - sy.start) * (sx.stop - sx.start)
        for c in range(3):
            a = a_mean[sy, sx, c].mean()
            b = b_mean[sy, sx, c].mean()
            se2 = a_var[sy, sx, c].sum() / n**2 + b_var[sy, sx, c].sum() / n**2
            if se2 == 0.0:
                z = 0.0 if a == b else np.inf
            else:
                z = (a - b) / np.sqrt(se2)
            out.append((name, "RGB"[c], float(z), float(a), float(b)))
    return out


@pytest.mark.mitsuba
@pytest.mark.parametrize("name", SCENE_NAMES)
def test_agrees_with_mitsuba(name, scenes_dir):
    path = str(scenes_dir / f"{name}.xml")
    a_mean, a_var = _mpg(path)
    b_mean, b_var = _mitsuba(path)
    assert a_mean.shape == b_mean.shape
    assert np.isfinite(a_mean).all()
    rows = compare(a_mean, a_var, b_mean, b_var)
    bad = [r for r in rows if not abs(r[2]) < Z_MAX]
    msg = "\n".join(f"{r[0]:8s} {r[1]} z={r[2]:+.2f} mpg={r[3]:.5f} mitsuba={r[4]:.5f}" for r in bad)
    assert not bad, f"{name}: {len(bad)} of {len(rows)} regions disagree:\n{msg}"
    # the image mean must also be non-trivial (a black image would agree with a black image)
    assert a_mean.mean() > 1e-3


def test_compare_detects_a_bias():
    """The comparison itself has power: a 3% bias at this noise level fails it."""
    rng = np.random.default_rng(1)
    truth = rng.uniform(0.2, 1.0, size=(64, 64, 3))
    var = np.full_like(truth, 1e-4)
    a = truth + rng.normal(0, 1e-2, truth.shape)
    b = truth + rng.normal(0, 1e-2, truth.shape)
    assert all(abs(r[2]) < Z_MAX for r in compare(a, var, b, var))
    assert any(abs(r[2]) > Z_MAX for r in compare(a * 1.03, var, b, var))
