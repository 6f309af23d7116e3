"""Per-pixel chain rates learned from mpg's training passes.

A separator runs the chain estimator with probability q and weights its result
1/q (Russian roulette on the chain estimate, design-notes "Chain estimates by
roulette"). With X_j the chain estimates of one camera sample, the roulette adds
(1/q - 1) E[sum_j X_j^2] to the pixel's variance and saves (1 - q) of their
cost. One rate for the whole image is a compromise: where the chain estimator
carries the light (a caustic from a small light) q should be 1, where the path
tracer finds the same light well it should be small.

For the image's MSE after a fixed time, with per pixel p
  V_p(q_p) = V1_p + (1/q_p - 1) M_p   (variance of one sample; M_p = E[sum X_j^2])
  C_p(q_p) = c0_p + q_p c1_p          (cost of one sample; c1_p = chain cost at q = 1)
the error is mean(V) / N with N = T / mean(C) samples per pixel, so we minimise
F(q) = mean_p V_p(q_p) * mean_p C_p(q_p). Setting dF/dq_p = 0:
  q_p = sqrt(M_p * mean(C) / (c1_p * mean(V)))                       (1)
(the efficiency-optimal splitting/roulette factor of Rath et al. 2022, "EARS",
Eq. 8, with the image mean in place of their per-pixel error estimate), a fixed
point solved by iteration, clamped to [q_min, 1]. With objective "relmse" (mpg's
default) each pixel's V and M are weighted by 1 / (I_p^2 + 0.01) as relMSE
weighs the error: a few bright pixels whose noise no rate can change (a small
light seen through glass) then no longer drive every rate down.

The statistics come from the training passes only, whose random numbers the
render never reuses: the rates are fixed before the render starts, so the image
stays unbiased for any rates in (0, 1] (E[1{u < q} X / q] = E[X]).
"""

from __future__ import annotations

import numpy as np


# Time of one manifold-walk vertex step (a traced or reprojected vertex) in units
# of one path-tracer ray, measured on the evaluation scenes at 128^2 by
# bench/step_cost.py (ns per chain step of sms_star / ns per ray of `path`, one
# thread: sphere 3.2, double_slabs 4.7, chain_length_4 4.2, emitter_size_003
# 4.7, visibility_4 4.7). The costs are
# counted, not timed, so that the learned rates -- and the image -- are the same
# on every run and thread count; a wrong factor only moves the rates off their
# optimum by its square root.
STEP_COST = 4.0


class CostAccumulator:
    """Per-pixel sums over training passes (crop height x width)."""

    def __init__(self, shape: tuple[int, int]):
        self.n = 0
        self.sum = np.zeros(shape + (3,))
        self.sum_sq = np.zeros(shape + (3,))
        self.chain_m2 = np.zeros(shape)
        self.chain_steps = np.zeros(shape)   # walk steps (+1 per estimate) inside chain estimates
        self.walk_steps = np.zeros(shape)    # all walk steps (the path tracer's MIS rounds too)
        self.rays = np.zeros(shape)
        self.rate_sum = np.zeros(shape)   # sum over passes of q * spp (the rate each pass ran at)

    def add(self, result: dict, spp: int, q: float | np.ndarray) -> None:
        self.n += spp
        self.sum += result["sum"]
        self.sum_sq += result["sum_sq"]
        self.chain_m2 += result["chain_m2"]
        self.chain_steps += result["chain_steps"]
        self.walk_steps += result["walk_steps"]
        self.rays += result["rays"]
        self.rate_sum += np.broadcast_to(np.asarray(q, dtype=float), self.rate_sum.shape) * spp


def _box_blur(a: np.ndarray, r: int) -> np.ndarray:
    """Mean over a (2r+1)^2 window, clipped at the borders (summed-area table)."""
    if r <= 0:
        return a
    h, w = a.shape
    s = np.zeros((h + 1, w + 1))
    s[1:, 1:] = np.cumsum(np.cumsum(a, axis=0), axis=1)
    y0 = np.clip(np.arange(h) - r, 0, h)
    y1 = np.clip(np.arange(h) + r + 1, 0, h)
    x0 = np.clip(np.arange(w) - r, 0, w)
    x1 = np.clip(np.arange(w) + r + 1, 0, w)
    tot = s[y1][:, x1] - s[y0][:, x1] - s[y1][:, x0] + s[y0][:, x0]
    cnt = (y1 - y0)[:, None] * (x1 - x0)[None, :]
    return np.maximum(tot / cnt, 0.0)   # the table's differences can round below 0


def learn_rates(acc: CostAccumulator, q_min: float = 1.0 / 32, radius: int = 3,
                iterations: int = 50, objective: str = "relmse") -> tuple[np.ndarray, dict]:
    """Per-pixel rates by Eq. (1) of the module docstring, and a summary.

    M_p and c1_p are averaged over a (2 radius + 1)^2 window first: a pixel of a
    short training run holds a handful of chain estimates."""
    shape = acc.chain_m2.shape
    info: dict = {"chain_rate_min_allowed": q_min}
    if acc.n < 2:
        info["chain_rate_learned"] = False
        return np.ones(shape, dtype=np.float32), info
    n = float(acc.n)

    def finite(a):   # a rejected sample's NaN/Inf square must not poison the rates
        return np.nan_to_num(np.asarray(a, dtype=float), nan=0.0, posinf=0.0, neginf=0.0)

    q_t = acc.rate_sum / n                                # the training passes' mean rate per pixel
    m2 = finite(acc.chain_m2) / n                         # E[sum_j X_j^2] per sample (unbiased)
    steps = finite(acc.chain_steps)
    c1 = STEP_COST * steps / (np.maximum(q_t, 1e-3) * n)  # chain cost per sample at q = 1 (ray units)
    c0 = (finite(acc.rays) + STEP_COST * np.maximum(finite(acc.walk_steps) - steps, 0.0)) / n
    mean = finite(acc.sum) / n
    sum_sq = finite(acc.sum_sq)
    var_t = np.maximum(sum_sq / n - mean * mean, 0.0).mean(axis=2) * (n / (n - 1))
    # objective "relmse": each pixel's variance weighted by 1 / (I^2 + 0.01), I
    # its (blurred) training mean, as metrics.relmse weighs the error
    if objective == "relmse":
        wgt = 1.0 / (_box_blur(mean.mean(axis=2), radius) ** 2 + 0.01)
    elif objective == "mse":
        wgt = np.ones(shape)
    else:
        raise ValueError(f"objective must be 'mse' or 'relmse', got '{objective}'")
    m2 = m2 * wgt
    # V1 = V(q_t) - (1/q_t - 1) M: only its image mean enters Eq. (1)
    v1_mean = max(float(np.mean(wgt * var_t - (1.0 / q_t - 1.0) * m2)), 0.0)
    m2_b = _box_blur(m2, radius)
    c1_b = _box_blur(c1, radius)
    has = c1_b > 0.0   # chain work here (M = 0: all cost, no light -> q_min)
    q = np.ones(shape)
    if np.any(has):
        ratio = np.where(has, m2_b / np.where(has, c1_b, 1.0), 0.0)
        for _ in range(iterations):
            v_mean = v1_mean + float(np.mean((1.0 / q - 1.0) * m2))
            c_mean = float(np.mean(c0 + q * c1))
            if not (v_mean > 0.0 and c_mean > 0.0):
                break
            q_new = np.where(has, np.clip(np.sqrt(ratio * c_mean / v_mean), q_min, 1.0), 1.0)
            if np.max(np.abs(q_new - q)) < 1e-4:
                q = q_new
                break
            q = q_new
    # pixels without chain work keep 1: the rate is never used there
    q = np.where(has & np.isfinite(q), q, 1.0)
    info.update(
        chain_rate_learned=True,
        chain_rate_mean=float(np.mean(q[has])) if np.any(has) else 1.0,
        chain_rate_fraction_one=float(np.mean(q[has] >= 1.0)) if np.any(has) else 1.0,
        chain_rate_fraction_min=float(np.mean(q[has] <= q_min)) if np.any(has) else 0.0,
    )
    return q.astype(np.float32), info


def rate_map_grey8(q: np.ndarray, q_low: float = 1.0 / 32) -> np.ndarray:
    """A rate map as 8-bit grey RGB (H, W, 3): log2 scale from q_low (black) to
    1 (white), for mpg-render --chain-rate-map and the docs figure."""
    lo = np.log2(q_low)
    g = np.clip((np.log2(np.maximum(np.asarray(q, dtype=float), 1e-3)) - lo) / -lo, 0.0, 1.0)
    return np.repeat(np.round(g * 255.0).astype(np.uint8)[..., None], 3, axis=2)
