"""mpg.metrics on constructed images whose errors are known by hand."""

from __future__ import annotations

import numpy as np
import pytest

import mpg
from mpg import metrics
from mpg.metrics import MetricError, mape, mse, relmse


def const(h, w, v):
    return np.full((h, w, 3), v, dtype=np.float32)


def test_hand_computed_two_pixels():
    # one row of two pixels, grey: ref (1, 0), image (1.5, 0.1)
    ref = np.array([[[1.0] * 3, [0.0] * 3]])
    img = np.array([[[1.5] * 3, [0.1] * 3]])
    assert mse(img, ref) == pytest.approx((0.25 + 0.01) / 2)
    assert relmse(img, ref) == pytest.approx((0.25 / 1.01 + 0.01 / 0.01) / 2)
    # 2 pixels: floor(0.001 * 2) = 0 discarded
    assert mape(img, ref) == pytest.approx((0.5 / 1.01 + 0.1 / 0.01) / 2)


def test_per_channel_average():
    ref = np.array([[[1.0, 2.0, 4.0]]])
    img = np.array([[[2.0, 2.0, 2.0]]])
    assert mse(img, ref) == pytest.approx((1 + 0 + 4) / 3)
    assert relmse(img, ref) == pytest.approx((1 / 1.01 + 0 + 4 / 16.01) / 3)
    assert mape(img, ref) == pytest.approx((1 / 1.01 + 0 + 2 / 4.01) / 3)


def test_constant_offset():
    ref = const(16, 16, 0.5)
    img = ref + 0.1
    assert mse(img, ref) == pytest.approx(0.01, rel=1e-5)
    assert relmse(img, ref) == pytest.approx(0.01 / 0.26, rel=1e-5)
    assert mape(img, ref) == pytest.approx(0.1 / 0.51, rel=1e-5)
    # identical images: zero error
    assert mse(ref, ref) == relmse(ref, ref) == mape(ref, ref) == 0.0


def test_mape_discards_the_worst_tenth_of_a_percent():
    # 100 x 100 = 10000 pixels -> 10 pixels discarded
    ref = const(100, 100, 1.0)
    img = ref.copy()
    img += 0.01                       # every pixel: APE 0.01/1.01
    base = 0.01 / 1.01
    img[0, :10] = 1000.0              # 10 outliers: discarded exactly
    assert mape(img, ref) == pytest.approx(base, rel=1e-5)
    img[1, 0] = 2.0                   # an 11th outlier stays in the mean
    expect = (9989 * base + 1.0 / 1.01) / 9990
    assert mape(img, ref) == pytest.approx(expect, rel=1e-5)
    # without the discard rule the outliers dominate
    assert mape(img, ref, discard=0.0) > 0.9
    # 999 pixels: floor(0.999) = 0 discarded
    small_ref = const(1, 999, 1.0)
    small = small_ref.copy()
    small[0, 0] = 2.0
    assert mape(small, small_ref) == pytest.approx((1 / 1.01) / 999, rel=1e-5)


def test_discard_is_per_pixel_not_per_channel():
    ref = const(100, 100, 1.0)
    img = ref.copy()
    img[0, :10, 0] = 11.0             # 10 pixels with one bad channel: those pixels go
    assert mape(img, ref) == pytest.approx(0.0, abs=1e-12)


def test_box_region():
    ref = const(10, 20, 1.0)
    img = ref.copy()
    img[2:5, 4:10] = 3.0              # error only inside rows 2..4, cols 4..9
    box = (0.2, 0.2, 0.5, 0.5)        # cols 4..9, rows 2..4
    assert mse(img, ref, box) == pytest.approx(4.0)
    assert relmse(img, ref, box) == pytest.approx(4.0 / 1.01)
    assert mse(img, ref) == pytest.approx(4.0 * 18 / 200)
    # a box that only partly overlaps a pixel includes it
    rows, cols = metrics.box_to_slices((10, 20), (0.21, 0.21, 0.49, 0.49))
    assert (rows, cols) == (slice(2, 5), slice(4, 10))
    m = metrics.region_mask((10, 20), box)
    assert m.sum() == 18


def test_mask_region():
    ref = const(8, 8, 1.0)
    img = ref.copy()
    img[::2] = 2.0
    mask = np.zeros((8, 8), bool)
    mask[::2] = True
    assert mse(img, ref, mask) == pytest.approx(1.0)
    assert mse(img, ref, ~mask) == 0.0
    assert mape(img, ref, mask) == pytest.approx(1 / 1.01)


def test_all_metrics_and_image_objects():
    ref = const(4, 4, 1.0)
    img = mpg.Image(rgb=ref * 2, variance=np.zeros_like(ref), spp=1)
    out = metrics.all_metrics(img, ref, box=(0, 0, 0.5, 0.5))
    assert set(out) == {"image", "caustic"}
    assert set(out["image"]) == {"mse", "relmse", "mape"}
    assert out["caustic"]["mse"] == pytest.approx(1.0)
    assert metrics.all_metrics(img, ref)["caustic"] is None


def test_grayscale_2d_inputs():
    assert mse(np.ones((3, 3)), np.zeros((3, 3))) == 1.0


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_input_raises(bad):
    ref = const(4, 4, 1.0)
    img = ref.copy()
    img[1, 2, 0] = bad
    for f in (mse, relmse, mape):
        with pytest.raises(MetricError, match=r"image has .* \(first at pixel x=2, y=1\)"):
            f(img, ref)
        with pytest.raises(MetricError, match="reference has"):
            f(ref, img)


def test_shape_and_region_errors():
    with pytest.raises(MetricError, match="differs"):
        mse(const(4, 4, 1), const(4, 5, 1))
    with pytest.raises(MetricError, match="0 <= x0 < x1"):
        mse(const(4, 4, 1), const(4, 4, 1), (0.5, 0, 0.2, 1))
    with pytest.raises(MetricError, match="no pixel"):
        mse(const(4, 4, 1), const(4, 4, 1), np.zeros((4, 4), bool))
    with pytest.raises(MetricError, match="mask has shape"):
        mse(const(4, 4, 1), const(4, 4, 1), np.ones((3, 4), bool))
    assert issubclass(MetricError, ValueError)


def test_seed_variance_is_the_mse_of_unbiased_renders():
    """Renders = truth + independent noise of known variance: the seeds'
    variance estimates the noise's variance, and so each render's mean MSE
    against the truth, with no reference in it. 3 renders of 3 x 96^2
    values, half at sigma 0.1 and half at 0.3: a value's variance estimate
    (ddof 1, 3 renders) has variance sigma^4, so the mean's relative
    standard deviation is sqrt(mean(sigma^4) / 27648) / mean(sigma^2) =
    0.77 % and 5 % is 6.5 sigma (the MSE's: 0.63 %); the left half alone,
    0.1^2 over 13 824 values: 0.85 %, so 10 % is 11 sigma."""
    rng = np.random.default_rng(7)
    truth = rng.uniform(0.0, 2.0, (96, 96, 3))
    sigma = np.where(np.arange(96)[None, :, None] < 48, 0.1, 0.3) * np.ones_like(truth)
    renders = [truth + sigma * rng.standard_normal(truth.shape) for _ in range(3)]
    expect = float(np.mean(sigma ** 2))
    assert metrics.seed_variance(renders) == pytest.approx(expect, rel=0.05)
    assert np.mean([mse(r, truth) for r in renders]) == pytest.approx(expect, rel=0.05)
    # a region: the left half's noise alone
    assert metrics.seed_variance(renders, (0.0, 0.0, 0.5, 1.0)) == pytest.approx(0.01, rel=0.1)
    # two renders: half their squared difference, by hand on one pixel
    a, b = const(1, 1, 1.0), const(1, 1, 3.0)
    assert metrics.seed_variance([a, b]) == pytest.approx(2.0)
    # a bias leaves it unchanged (it is the spread, not the error)
    assert metrics.seed_variance([r + 0.5 for r in renders]) == pytest.approx(
        metrics.seed_variance(renders), rel=1e-12)


def test_seed_variance_errors():
    with pytest.raises(MetricError, match="at least 2 renders"):
        metrics.seed_variance([const(2, 2, 1)])
    with pytest.raises(MetricError, match="shapes differ"):
        metrics.seed_variance([const(2, 2, 1), const(2, 3, 1)])
    bad = const(2, 2, 1)
    bad[1, 0, 2] = np.nan
    with pytest.raises(MetricError, match="render 1 has 1 NaN"):
        metrics.seed_variance([const(2, 2, 1), bad])
