"""Image error metrics against a reference: MSE, relMSE and MAPE, over a region.

All metrics take an image and a reference of the same shape, (H, W, 3) or (H, W)
(numpy arrays or `mpg.Image`), and an optional region:

- None: the whole image;
- a box (x0, y0, x1, y1) in normalised image coordinates, x to the right and y
  down, 0..1 (the `caustic_box` of a scene sidecar); it covers the pixels whose
  area overlaps the box (columns floor(x0*W) .. ceil(x1*W)-1, rows likewise);
- a boolean (H, W) mask.

Every metric is computed per channel and averaged over the channels and the
pixels of the region (every channel of every pixel counts once). Inputs with NaN
or infinite values raise `MetricError`: a metric of a broken image is not a number
to report, and a reference with NaN is a broken reference.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Union

import numpy as np

from mpg.errors import MPGError

EPS = 0.01          # the epsilon of relMSE and MAPE (as the NASG paper's MAPE)
MAPE_DISCARD = 0.001  # MAPE drops this fraction of the pixels with the highest error

Region = Union[None, Sequence[float], np.ndarray]


class MetricError(MPGError, ValueError):
    """An image or region that a metric cannot be computed on."""


def _array(x: Any, what: str) -> np.ndarray:
    a = getattr(x, "rgb", x)
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3:
        raise MetricError(f"{what}: expected an (H, W, C) or (H, W) image, got shape {a.shape}")
    bad = ~np.isfinite(a)
    if bad.any():
        n_nan = int(np.isnan(a).sum())
        n_inf = int(bad.sum()) - n_nan
        ys, xs = np.nonzero(bad.any(axis=2))
        raise MetricError(
            f"{what} has {n_nan} NaN and {n_inf} infinite values "
            f"(first at pixel x={xs[0]}, y={ys[0]}); metrics need finite images")
    return a


def box_to_slices(shape: tuple[int, int], box: Sequence[float]) -> tuple[slice, slice]:
    """(rows, cols) slices of the pixels a normalised (x0, y0, x1, y1) box overlaps."""
    h, w = int(shape[0]), int(shape[1])
    if len(box) != 4:
        raise MetricError(f"a box is (x0, y0, x1, y1), got {list(box)}")
    x0, y0, x1, y1 = (float(v) for v in box)
    if not all(np.isfinite([x0, y0, x1, y1])):
        raise MetricError(f"box {list(box)} has non-finite coordinates")
    if not (0.0 <= x0 < x1 <= 1.0 and 0.0 <= y0 < y1 <= 1.0):
        raise MetricError(f"box {list(box)} must satisfy 0 <= x0 < x1 <= 1 and 0 <= y0 < y1 <= 1 "
                          "(normalised image coordinates, x right, y down)")
    c0, c1 = int(np.floor(x0 * w)), int(np.ceil(x1 * w))
    r0, r1 = int(np.floor(y0 * h)), int(np.ceil(y1 * h))
    return slice(r0, max(r1, r0 + 1)), slice(c0, max(c1, c0 + 1))


def region_mask(shape: tuple[int, int], region: Region) -> np.ndarray:
    """A boolean (H, W) mask for None (everything), a normalised box or a mask."""
    h, w = int(shape[0]), int(shape[1])
    if region is None:
        return np.ones((h, w), dtype=bool)
    arr = np.asarray(region)
    if arr.dtype == bool:
        if arr.shape != (h, w):
            raise MetricError(f"region mask has shape {arr.shape}, the image is {(h, w)}")
        if not arr.any():
            raise MetricError("region mask selects no pixel")
        return arr
    rows, cols = box_to_slices((h, w), region)
    m = np.zeros((h, w), dtype=bool)
    m[rows, cols] = True
    return m


def _pair(img: Any, ref: Any, region: Region) -> tuple[np.ndarray, np.ndarray]:
    """(x, ref) as (N, C) arrays of the region's pixels."""
    x = _array(img, "image")
    r = _array(ref, "reference")
    if x.shape != r.shape:
        raise MetricError(f"image shape {x.shape[:2] + x.shape[2:]} differs from the "
                          f"reference shape {r.shape}")
    m = region_mask(x.shape[:2], region)
    return x[m], r[m]


def mse(img: Any, ref: Any, region: Region = None) -> float:
    """Mean squared error: mean over the region's pixels and channels of (x - ref)^2."""
    x, r = _pair(img, ref, region)
    return float(np.mean((x - r) ** 2))


def relmse(img: Any, ref: Any, region: Region = None, eps: float = EPS) -> float:
    """Relative MSE: mean over the region's pixels and channels of
    (x - ref)^2 / (ref^2 + eps), per channel (eps = 0.01 keeps dark pixels from
    dominating)."""
    x, r = _pair(img, ref, region)
    return float(np.mean((x - r) ** 2 / (r * r + eps)))


def mape(img: Any, ref: Any, region: Region = None, eps: float = EPS,
         discard: float = MAPE_DISCARD) -> float:
    """Mean absolute percentage error as the NASG paper (Huang et al. 2023) defines it:
    |x - ref| / (ref + eps), eps = 0.01, per channel; a pixel's error is the mean
    over its channels; the floor(discard * N) pixels (default 0.1 %) with the highest
    error are discarded and the rest averaged. |ref| is used in the denominator so
    that a (slightly) negative reference cannot divide by ~0."""
    x, r = _pair(img, ref, region)
    per_pixel = np.mean(np.abs(x - r) / (np.abs(r) + eps), axis=1)
    n = per_pixel.size
    k = int(np.floor(discard * n))
    if k > 0:
        per_pixel = np.partition(per_pixel, n - k - 1)[: n - k]
    return float(np.mean(per_pixel))


def seed_variance(images: Sequence[Any], region: Region = None) -> float:
    """The MSE of one render of an unbiased integrator, without a reference.

    For independent renders X_1..X_n of one estimator (seeds), the mean over
    the region's pixels and channels of the unbiased sample variance
    sum_i (X_i - mean)^2 / (n - 1) estimates E[(X - E X)^2], which is the MSE
    against the truth when E X is the truth. It carries no reference noise,
    so it can rank renders whose error is below a reference's floor; a bias
    shows as an MSE against the reference well above it plus the floor."""
    if len(images) < 2:
        raise MetricError(f"a seed variance needs at least 2 renders, got {len(images)}")
    xs = [_array(im, f"render {i}") for i, im in enumerate(images)]
    if any(x.shape != xs[0].shape for x in xs):
        raise MetricError("the renders' shapes differ: " + ", ".join(str(x.shape) for x in xs))
    m = region_mask(xs[0].shape[:2], region)
    a = np.stack([x[m] for x in xs])   # (float64: _array)
    return float(np.mean(a.var(axis=0, ddof=1)))


METRICS = {"mse": mse, "relmse": relmse, "mape": mape}


def all_metrics(img: Any, ref: Any, box: Sequence[float] | None = None) -> dict[str, Any]:
    """{'image': {mse, relmse, mape}, 'caustic': {...} or None (no box)}."""
    out: dict[str, Any] = {"image": {k: f(img, ref) for k, f in METRICS.items()}}
    out["caustic"] = ({k: f(img, ref, box) for k, f in METRICS.items()}
                      if box is not None else None)
    return out


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of an (..., 3) array."""
    rgb = np.asarray(rgb)
    return 0.2126 * rgb[..., 0] + 0.7152 * rgb[..., 1] + 0.0722 * rgb[..., 2]
