"""Per-pixel chain rates learned from mpg's training passes.

A separator runs the chain estimator with probability q and weights its result
1/q (Russian roulette on the chain estimate, design-notes "Chain estimates by
roulette"). With X_j the chain estimates of one camera sample, the roulette adds
(1/q - 1) E[sum_j X_j^2] to the pixel's variance and saves (1 - q) of their
cost. One rate for the whole image is a compromise: where the chain estimator
carries the light (a caustic from a small light) q should be 1, where the path
tracer finds the same light well it should be small.

With `mis_rate` (the default) the shared chain paths' weights move with q too
(the path tracer's density b / q against the estimator's a P), so M_p below is
the estimator's share at the training rate q_t, and V_p(q) is exact at q = q_t
only: away from q_t it overstates the second moment on both sides, which pulls
the rates towards q_t (design-notes, "The rate in the balance heuristic").

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

Rate 0 hands the pixel to the path tracer: no chain estimates, and the path
tracer keeps the chain paths it finds whole instead of its MIS share. Per
pixel this is a third option beside q in [q_min, 1]: variance
V1_p + dv_p with dv_p = w_p E[(A - I_p)^2] - V1_p (A the sample's value with
the path tracer alone, recorded in the same training samples), at cost
c0_p - mis_p (the path tracer's MIS rounds go too). In the linearised F each
pixel takes the option with the smaller share:
  rate 0  iff  dv_p mean(C) - mis_p mean(V) < (1/q_p - 1) M_p mean(C) + q_p c1_p mean(V)   (2)
At a caustic's focus the path tracer finds the light through the glass at a
per-sample variance close to the estimator's (MIS), at 1/12 of the time per
sample (bench/crop_variance.py). Where it rarely finds the light its variance is mostly unseen in
training, so rate 0 is only open to pixels whose window saw HANDOFF_MIN_HITS
hits, or whose chains' light is negligible (HANDOFF_NEGLIGIBLE).

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

# Rate 0 needs this many training samples, in the pixel's window, in which the
# path tracer found the chains' light: with fewer, its variance is mostly
# unseen (sphere, 30 s: without this floor the dim reflection caustic of the
# small light went to the path tracer, relMSE 0.008 -> 0.03).
HANDOFF_MIN_HITS = 64
# ... or the chains' second moment in the window below this fraction of the
# pixel's own variance per sample: even if the path tracer never found their
# light, its square would stay below the noise up to ~1 000 spp (for the
# window's mean second moment).
HANDOFF_NEGLIGIBLE = 1e-3


# Time of one lobe of a guided-trace density (ChainDistribution::pdf_dir: a
# dot product and a test per lobe, the exponential for the few near) in units
# of one path-tracer ray: 2.1-2.8 ns per lobe over leaves of 2 700-3 000 lobes
# against 334-336 ns per ray of `path` (shading included), pool at 64^2, one
# thread (python bench/trace_diagnostics.py lobes pool, fifteenth session). A focus leaf's 3 000 lobes
# cost ~20 rays a density: the traces' hits and the path tracer's weights
# pay it, and counted as rays alone the traces looked 1.5x cheaper than they
# were (slab: 308 -> 202 spp).
LOBE_COST = 1.0 / 128.0

# The counts of guided traces a rate-0 pixel may get (learn_rates_traced): the
# k of Stats::kTraceKs, each formed in training from two recorded traces.
TRACE_KS = (1, 2, 4, 8)
# ... and the traces recorded per training sample
TRACES_RECORDED = 2


class CostAccumulator:
    """Per-pixel sums over training passes (crop height x width)."""

    # the arrays a record_costs pass returns under these names, summed as they are
    PASS_SUMS = ("sum", "sum_sq", "chain_m2", "chain_steps", "walk_steps", "rays", "alt_sum",
                 "alt_sum_sq", "alt_hits", "delta_rays", "delta_sum", "delta_sum_sq",
                 "trace_n", "trace_hits", "trace_rays", "trace_lobes", "trace_pt_lobes",
                 "trace_tail0", "trace_seen0", "trace_chain_sum",
                 "bdelta_n", "bdelta_rays", "bdelta_within", "udelta_within") + tuple(
                     f"trace{k}_{x}" for k in TRACE_KS for x in ("sum", "sum_sq", "var", "tail", "seen"))

    def __init__(self, shape: tuple[int, int]):
        self.n = 0
        self.sum = np.zeros(shape + (3,))
        self.sum_sq = np.zeros(shape + (3,))
        self.chain_m2 = np.zeros(shape)
        self.chain_steps = np.zeros(shape)   # walk steps (+1 per estimate) inside chain estimates
        self.walk_steps = np.zeros(shape)    # all walk steps (the path tracer's MIS rounds too)
        self.rays = np.zeros(shape)
        self.rate_sum = np.zeros(shape)   # sum over passes of q * spp (the rate each pass ran at)
        # the samples' "path tracer alone" values (Stats::sample_alt_delta): sums and squares
        self.alt_sum = np.zeros(shape + (3,))
        self.alt_sum_sq = np.zeros(shape + (3,))
        self.alt_hits = np.zeros(shape)   # samples in which the path tracer found owned chain light
        self.delta_rays = np.zeros(shape)  # rays traced after delta scattering only (Stats::delta_prefix_rays)
        # the samples' light seen through delta scattering only (Stats::sample_delta_L): sums and squares
        self.delta_sum = np.zeros(shape + (3,))
        self.delta_sum_sq = np.zeros(shape + (3,))
        # the samples' values at rate 0 with k guided traces (Stats::record_trace;
        # over the recorded samples, the path tracer alone's where no trace
        # ran) formed from two recorded traces, and the sums
        # of one trace's variance, per k in TRACE_KS (trace<k>_*); the samples
        # in which the path tracer or a trace found chain light; the traces' rays
        for k in TRACE_KS:
            setattr(self, f"trace{k}_sum", np.zeros(shape + (3,)))
            setattr(self, f"trace{k}_sum_sq", np.zeros(shape + (3,)))
            setattr(self, f"trace{k}_var", np.zeros(shape))
            # the chain paths' second moment under k traces, as the chains sample them
            # (Stats::sample_tail; trace_tail0: the path tracer alone's)
            setattr(self, f"trace{k}_tail", np.zeros(shape))
            setattr(self, f"trace{k}_seen", np.zeros(shape))   # ... as the records see them
        self.trace_tail0 = np.zeros(shape)
        self.trace_seen0 = np.zeros(shape)
        self.trace_chain_sum = np.zeros(shape + (3,))   # ... and the chain paths' values
        self.trace_n = np.zeros(shape)   # the samples that recorded them (one in four)
        self.trace_hits = np.zeros(shape)
        self.trace_rays = np.zeros(shape)
        self.trace_lobes = np.zeros(shape)      # the lobes their densities visited (LOBE_COST)
        self.trace_pt_lobes = np.zeros(shape)   # ... and the path tracer's weights against them
        # the records of two branched and two plain delta paths of one camera
        # ray (PassResult::bdelta_*; a branching integrator's passes, one sample
        # in Stats::kBranchRecordEvery): the samples that recorded them, their
        # rays, and the sums of (B1 - B2)^2 / 2 and (U1 - U2)^2 / 2
        self.bdelta_n = np.zeros(shape)
        self.bdelta_rays = np.zeros(shape)
        self.bdelta_within = np.zeros(shape)
        self.udelta_within = np.zeros(shape)

    def add(self, result: dict, spp: int, q: float | np.ndarray) -> None:
        """A pass's sums (RenderJob.result()). The first pass's own arrays,
        writable views of its job's buffers, become the sums, not copied:
        adding them into fresh zeros faulted ~21 MB of new pages at 256^2,
        30 ms of a 1 s render's 0.3 s training. Later adds then change them
        in place, so the caller must not read that result's sums after."""
        first = self.n == 0
        self.n += spp
        for key in self.PASS_SUMS:
            if key in result or not key.startswith(("bdelta_", "udelta_")):   # (records of branching integrators only)
                cur, new = getattr(self, key), result[key]
                if (first and isinstance(new, np.ndarray) and new.dtype == np.float64
                        and new.shape == cur.shape and new.flags.writeable):
                    setattr(self, key, new)
                else:
                    cur[...] += new
        self.rate_sum += np.broadcast_to(np.asarray(q, dtype=float), self.rate_sum.shape) * spp


def _window_sums(a: np.ndarray, r: int, axis: int) -> np.ndarray:
    """Per index i along `axis` the sum over [i - r, i + r], clipped at the
    ends: 2r + 1 shifted adds of a zero-padded copy for small windows (every
    radius the maps use, 1-6), a cumulative sum's differences for larger ones."""
    n = a.shape[axis]
    sl = [slice(None)] * a.ndim

    def at(start: int, stop: int) -> tuple:
        sl[axis] = slice(start, stop)
        return tuple(sl)

    shape = list(a.shape)
    if 2 * r + 1 <= 15:
        shape[axis] = n + 2 * r
        p = np.zeros(shape)
        p[at(r, r + n)] = a
        out = p[at(0, n)].copy()
        for j in range(1, 2 * r + 1):
            out += p[at(j, j + n)]
        return out
    shape[axis] = n + 1 + 2 * r
    e = np.empty(shape)   # r zeros, 0, the cumulative sums, r copies of the total
    e[at(0, r + 1)] = 0.0
    np.cumsum(a, axis=axis, out=e[at(r + 1, r + 1 + n)])
    e[at(r + 1 + n, n + 1 + 2 * r)] = e[at(r + n, r + n + 1)]
    return e[at(2 * r + 1, 2 * r + 1 + n)] - e[at(0, n)]


def _box_blur(a: np.ndarray, r: int, nonneg: bool = True, total: bool = False) -> np.ndarray:
    """Mean (total: sum) over a (2r+1)^2 window, clipped at the borders
    (separable window sums; the summed-area table before the forty-first
    session rounded ~1e-12 off a 256^2 image's sums and took twice as long)."""
    if r <= 0:
        return a
    h, w = a.shape
    tot = _window_sums(_window_sums(np.asarray(a, dtype=float), r, 0), r, 1)
    if not total:
        ny = np.minimum(np.arange(h) + r + 1, h) - np.maximum(np.arange(h) - r, 0)
        nx = np.minimum(np.arange(w) + r + 1, w) - np.maximum(np.arange(w) - r, 0)
        tot /= ny[:, None] * nx[None, :]
    # (a cumulative sum's differences can round a non-negative input below 0)
    return np.maximum(tot, 0.0, out=tot) if nonneg else tot


def _finite(a) -> np.ndarray:
    """A rejected sample's NaN/Inf square must not poison the statistics.
    Read-only: an all-finite float array is returned as it is, not copied
    (the common case; nan_to_num's copy took a sixth of the maps' learning)."""
    a = np.asarray(a, dtype=float)
    if np.isfinite(a).all():
        v = a.view()
        v.flags.writeable = False   # (the caller's array itself: a write would corrupt it)
        return v
    return np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0)


def _rgb_mean(a: np.ndarray) -> np.ndarray:
    """a.mean(axis=2) of an (h, w, 3) array, the same bits, ~10x faster
    (numpy reduces a last axis of 3 slowly); other shapes as mean(axis=2)."""
    if a.ndim != 3 or a.shape[2] != 3:
        return a.mean(axis=2)
    return (a[..., 0] + a[..., 1] + a[..., 2]) / 3.0


def _sample_variance(s, s2, n: float) -> np.ndarray:
    """Per-pixel variance of one sample (mean over RGB) from sums and squares of n samples."""
    m = _finite(s) / n
    return _rgb_mean(np.maximum(_finite(s2) / n - m * m, 0.0)) * (n / (n - 1))


def _alt_mse(acc: "CostAccumulator", n, mean: np.ndarray, pre: str = "alt", n_all: float | None = None) -> np.ndarray:
    """Per-pixel E[(A - I)^2] (mean over RGB) of the path tracer alone's values A
    (pre "trace<k>": with two traces weighted for k) about the training mean
    I, scaled by n / (n - 1) as _sample_variance is: where A = L the two are equal.
    n may be per pixel (the traces' records, a subset of the n_all samples
    whose mean I is): the mean is over those, the correction n_all / (n_all - 1)
    (I is the mean of all of them, whatever the subset's size)."""
    n = np.asarray(n, dtype=float)
    if n.ndim:   # per pixel (the traces' records, n >= 2 where there are any)
        n = np.maximum(n, 2.0)
    nc = n[..., None] if n.ndim else n
    a_mean = _finite(getattr(acc, pre + "_sum")) / nc
    a_m2 = _finite(getattr(acc, pre + "_sum_sq")) / nc
    nn = n if n_all is None else n_all
    return _rgb_mean(np.maximum(a_m2 - 2.0 * a_mean * mean + mean * mean, 0.0)) * (nn / (nn - 1))


def _costs(acc: "CostAccumulator", n: float) -> tuple:
    """(q_t, chain steps, c1, mis, c0) per pixel: the training passes' mean
    rate, the walk steps inside chain estimates, the chain cost per sample at
    q = 1, the path tracer's MIS-round cost and the rest of a sample's cost
    (ray units)."""
    q_t = acc.rate_sum / n
    steps = _finite(acc.chain_steps)
    c1 = STEP_COST * steps / (np.maximum(q_t, 1e-3) * n)
    mis = STEP_COST * np.maximum(_finite(acc.walk_steps) - steps, 0.0) / n
    c0 = _finite(acc.rays) / n + mis
    return q_t, steps, c1, mis, c0


def _weights(mean: np.ndarray, objective: str, radius: int) -> np.ndarray:
    """The objective's per-pixel weight: 1 (mse) or 1 / (I^2 + 0.01), I the
    (blurred) training mean, as metrics.relmse weighs the error (relmse)."""
    if objective == "relmse":
        return 1.0 / (_box_blur(_rgb_mean(mean), radius) ** 2 + 0.01)
    if objective == "mse":
        return np.ones(mean.shape[:2])
    raise ValueError(f"objective must be 'mse' or 'relmse', got '{objective}'")


def learn_rates(acc: CostAccumulator, q_min: float = 1.0 / 32, radius: int = 3,
                iterations: int = 50, objective: str = "relmse",
                handoff: bool = True, min_hits: float = HANDOFF_MIN_HITS,
                negligible: float = HANDOFF_NEGLIGIBLE) -> tuple[np.ndarray, dict]:
    """Per-pixel rates by Eq. (1) of the module docstring, and a summary
    (learn_rates_traced without its map of the guided trace)."""
    q, _, info = learn_rates_traced(acc, q_min=q_min, radius=radius, iterations=iterations,
                                    objective=objective, handoff=handoff, min_hits=min_hits,
                                    negligible=negligible)
    return q, info


def learn_rates_traced(acc: CostAccumulator, q_min: float = 1.0 / 32, radius: int = 3,
                       iterations: int = 50, objective: str = "relmse",
                       handoff: bool = True, min_hits: float = HANDOFF_MIN_HITS,
                       negligible: float = HANDOFF_NEGLIGIBLE,
                       trace: bool = False, tails: bool = True, v_offset: float = 0.0,
                       c_offset: float = 0.0, trace_min_hits: float | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Per-pixel rates by Eq. (1) of the module docstring, the count of guided
    traces of handed-off pixels per pixel (0 or one of TRACE_KS; only rate-0
    pixels trace), and a summary.

    M_p and c1_p are averaged over a (2 radius + 1)^2 window first: a pixel of a
    short training run holds a handful of chain estimates.

    handoff: a pixel may also get rate 0, where the path tracer alone renders its
    chain light better for the time: no chain estimates there, and the path
    tracer keeps the chain paths it finds whole (Eq. (2) of the module
    docstring), if its window holds at least min_hits samples in which the
    path tracer found the chains' light, or the chains' light there is
    negligible.

    Where the training passes recorded the guided trace (acc.trace_rays > 0)
    and `trace` is set (learn_trace), rate 0 has more forms: the path tracer
    with k = 1, 2, 4 or 8 guided traces at the first separator
    (Stats::record_trace). Training drew two traces a sample; Y_k, the value
    with the two weighted for k and averaged, has the mean of the k traces'
    value T_k, and E[(T_k - I)^2] = E[(Y_k - I)^2] + (1/k - 1/2) Var(Z_k),
    Z_k = k f / (b + k g) one trace's share scaled to the whole, whose
    variance the pair gives ((Z_1 - Z_2)^2 / 2). Its excess variance is then
    taken as dv is from the path tracer alone's, at k / 2 of the recorded
    traces' rays added to the cost. A pixel takes the form with the smallest
    share of F (the same linearised rule); the trace forms need
    trace_min_hits (None: min_hits) samples in the window in which the path
    tracer or a trace found chain light, and chain light that is not
    negligible. The traces are recorded in
    one sample of four (acc.trace_n; their cost took a training iteration's
    worth of time when every sample recorded them), and the hits counted are
    theirs. A trace form's cost is k traces' rays and lobes (LOBE_COST) and
    the path tracer's weights' lobes. trace False: the path tracer alone
    only.

    tails: the trace forms' second moment of the chain paths is the chains'
    (acc.trace<k>_tail: each chain path's value times its value under the
    form, sampled by the chains and by the path tracer in their MIS shares)
    in place of the records' own (acc.trace<k>_seen): the same expectation,
    but the rare paths the path tracer and the traces seldom reach -- a small
    light's image the lobes miss in part -- come at the chains' rate, where
    the records' few samples per pixel miss them (pool).

    v_offset, c_offset: what the delta split (learn_delta_split) takes from
    mean(wV) and adds to mean(C) (delta_split_effect), so that the rates see
    the variance that is left beside the chains' (learn_jointly)."""
    shape = acc.chain_m2.shape
    if trace_min_hits is None:
        trace_min_hits = min_hits
    info: dict = {"chain_rate_min_allowed": q_min}
    if acc.n < 2:
        info["chain_rate_learned"] = False
        return np.ones(shape, dtype=np.float32), np.zeros(shape, dtype=np.float32), info
    n = float(acc.n)

    finite = _finite
    m2_raw = finite(acc.chain_m2) / n                     # E[sum_j X_j^2] per sample (unbiased)
    # q_t: the training passes' mean rate per pixel; c1: chain cost per sample at
    # q = 1 (ray units); mis: the path tracer's MIS rounds (pt_weight's walks),
    # part of c0, gone at rate 0
    q_t, steps, c1, mis, c0 = _costs(acc, n)
    mean = finite(acc.sum) / n
    var_t = _sample_variance(acc.sum, acc.sum_sq, n)
    wgt = _weights(mean, objective, radius)
    m2 = m2_raw * wgt
    # V1 = V(q_t) - (1/q_t - 1) M: only its image mean enters Eq. (1)
    v1_raw = float(np.mean(wgt * var_t - (1.0 / q_t - 1.0) * m2))
    v1_mean = max(v1_raw - v_offset, 0.0)
    m2_b = _box_blur(m2, radius)
    c1_b = _box_blur(c1, radius)
    has = c1_b > 0.0   # chain work here (M = 0: all cost, no light -> q_min)
    # Rate 0, the path tracer alone (Eq. 2): its excess variance over the
    # estimator's at q = 1, dv = w E[(A - I)^2] - V1_p, at the chains' cost
    # (and the MIS rounds') saved. (A - I)^2 about the training mean I, not A's
    # own mean: where the path tracer rarely finds the light its mean falls
    # short, and the missing light counts as error.
    dv_b = np.zeros(shape)
    mis_b = _box_blur(mis, radius)
    eligible = np.zeros(shape, dtype=bool)
    # rate 0's forms after the path tracer alone (form 1): (traces, excess
    # variance, cost added, eligible) of forms 2, 3, ... (one per TRACE_KS)
    traced: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
    if handoff:
        alt_mse = _alt_mse(acc, n, mean)
        # V1 = w var_t - (1/q_t - 1) M, the pixel's variance at q = 1 (weighted)
        dv_b = _box_blur(wgt * alt_mse - wgt * var_t + (1.0 / q_t - 1.0) * m2, radius, nonneg=False)
    # Rate 0 is open to a pixel only where the window saw the path tracer
    # find that light often (its second moment from a few rare hits -- a dim
    # reflection caustic of a small light -- is mostly an underestimate), or
    # where the chains' light cannot matter: E[X]^2 <= E[X^2] below HANDOFF_NEGLIGIBLE
    # of the pixel's own variance per sample (double_slabs: the glints of
    # the light in the slabs' bumpy tops set the variance). Not the window's
    # mean variance: one glint of a tiny light (emitter_size_003) set the
    # window mean of every pixel around it, and the whole 7x7 window lost
    # its caustic to the path tracer, which never finds that light (black
    # squares, relMSE 0.83-0.91 against sms_star's 0.04-0.08)
    negl = _negligible_chain_light(m2_raw, var_t, radius, negligible)
    if handoff:
        eligible = has & ((_box_blur(finite(acc.alt_hits), radius, total=True) >= min_hits) | negl)
    # (the traces' forms are modelled without the per-pixel hand-off too: the
    # model of every pixel handed off, chain_rate_model_*_all<k>, for
    # handoff_all=auto, whose choice does not wait for HANDOFF_MIN_TRAINING;
    # no pixel may choose them then)
    if trace and float(np.sum(finite(acc.trace_rays))) > 0.0:
        # the guided trace's forms of rate 0 (the traces' rays per sample added)
        # (recorded in one sample of four, whose hits must reach trace_min_hits.
        # Their rare large values -- g small where the lobes miss part of a
        # small light's image -- are what a short record misses: pool's
        # traced pixels rendered 15x the chains' variance where the record
        # had seen the traces 3x better; requiring the path tracer's own
        # min_hits as well left no traced pixel on double_slabs either.
        # Hence `tails`: the chains' view of those values, below.)
        n_t = np.maximum(finite(acc.trace_n), 1.0)
        el = has & ~negl & (_box_blur(finite(acc.trace_hits), radius, total=True) >= trace_min_hits) & handoff
        # one trace's cost per sample, and the path tracer's weights' (any k)
        ray1 = (finite(acc.trace_rays) + LOBE_COST * finite(acc.trace_lobes)) / (n_t * TRACES_RECORDED)
        pt_w = LOBE_COST * finite(acc.trace_pt_lobes) / n_t
        for k in TRACE_KS:
            mse_k = _alt_mse(acc, finite(acc.trace_n), mean, f"trace{k}", n_all=n) + \
                (1.0 / k - 1.0 / TRACES_RECORDED) * finite(getattr(acc, f"trace{k}_var")) / n_t
            if tails:
                mse_k = mse_k + (finite(getattr(acc, f"trace{k}_tail")) -
                                 finite(getattr(acc, f"trace{k}_seen"))) / n_t
            dv_k = wgt * np.maximum(mse_k, 0.0) - wgt * var_t + (1.0 / q_t - 1.0) * m2
            dc_k = k * ray1 + pt_w
            traced.append((k, _box_blur(dv_k, radius, nonneg=False), _box_blur(dc_k, radius), el))
            # the model of every pixel handed off with k traces: image means of
            # the fields themselves, not of their window means (a mean over
            # the image needs no window, and the windows clipped at the
            # borders weigh a border pixel's value up to 3x: on a 16x16 image
            # that turned the mean variance negative in 2 seeds of 8, leaving
            # handoff_all=auto no model; on the 256x256 scenes the two agree
            # to 4 digits, docs/results.md, forty-second session)
            v_all = v1_mean + float(np.mean(np.where(has, dv_k, 0.0)))
            c_all = float(np.mean(c0 + np.where(has, dc_k - mis, 0.0))) + c_offset
            info[f"chain_rate_model_v_all{k}"], info[f"chain_rate_model_c_all{k}"] = v_all, c_all
    forms_dv = [dv_b] + [t[1] for t in traced]
    forms_dc = [-mis_b] + [t[2] - mis_b for t in traced]
    forms_ok = [eligible] + [t[3] for t in traced]

    def means(q, pt):
        """mean(wV) and mean(C) of a map (blurred M, c1, dv: what the choices
        see); pt per pixel: 0 rate q, 1 the path tracer alone, 2, 3, ... the
        path tracer with TRACE_KS[pt - 2] traces."""
        conds = [pt == f + 1 for f in range(len(forms_dv))]
        v = v1_mean + float(np.mean(np.select(conds, forms_dv, (1.0 / q - 1.0) * m2_b)))
        c = float(np.mean(c0 + np.select(conds, forms_dc, q * c1_b))) + c_offset
        return v, c

    def zero_form(v_mean, c_mean):
        """Per pixel the best form of rate 0 (1, 2, ...; 0 where none may) and its share."""
        form = np.zeros(shape, dtype=np.int8)
        best = np.full(shape, np.inf)
        for f, (dv, dc, ok) in enumerate(zip(forms_dv, forms_dc, forms_ok)):
            g = np.where(ok, dv * c_mean + dc * v_mean, np.inf)
            better = g < best
            form = np.where(better, f + 1, form).astype(np.int8)
            best = np.where(better, g, best)
        return form, best

    def model_f(cand):
        """F = mean(wV) mean(C) of a (q, pt) map; inf where a mean is not positive."""
        v, c = means(*cand)
        return v * c if v > 0.0 and c > 0.0 else np.inf

    ratio = np.where(has, m2_b / np.where(has, c1_b, 1.0), 0.0)

    def fixed_point(allow_pt):
        q = np.ones(shape)
        pt = np.zeros(shape, dtype=np.int8)
        for _ in range(iterations):
            v_mean, c_mean = means(q, pt)
            if not (v_mean > 0.0 and c_mean > 0.0):
                break
            q_new = np.where(has, np.clip(np.sqrt(ratio * c_mean / v_mean), q_min, 1.0), 1.0)
            pt_new = pt
            if allow_pt:
                # the pixel's share of F = mean(V) mean(C), linearised: rate q
                # adds (1/q - 1) M C + q c1 V, rate 0 adds dv C - mis V
                g_q = (1.0 / q_new - 1.0) * m2_b * c_mean + q_new * c1_b * v_mean
                form, g0 = zero_form(v_mean, c_mean)
                pt_new = np.where(g0 < g_q, form, 0).astype(np.int8)
            if np.max(np.abs(q_new - q)) < 1e-4 and np.array_equal(pt_new, pt):
                return q_new, pt_new
            q, pt = q_new, pt_new
        return q, pt

    q, pt = np.ones(shape), np.zeros(shape, dtype=np.int8)
    if np.any(has):
        q, pt = fixed_point(False)
        if handoff and any(np.any(ok) for ok in forms_ok):
            # F is not convex once pixels switch between options, and the
            # linearised fixed point can stop short: keep the best of it, the
            # map without rate 0, and that map with every eligible pixel at 0
            # (in its better form at the first map's means)
            cands = [(q, pt), fixed_point(True), (q, zero_form(*means(q, pt))[0])]
            q, pt = min(cands, key=model_f)
    v_model, c_model = means(q, pt)
    # pixels without chain work keep 1: the rate is never used there
    q = np.where(has & np.isfinite(q), q, 1.0)
    q = np.where(pt > 0, 0.0, q)
    on = has & (pt == 0)
    # How a change of the chain estimates' second moment (dM, summed over
    # pixels, at rate 1) and of their walks' work (dS, at the training rate)
    # carries over to the render's map: mean(wV) moves by dM m_scale / pixels
    # and mean(C) by dS s_scale / pixels, taking both to fall on the pixels as
    # the training's M and chain work do; w_scale weighs the path tracer's
    # shares of shared paths, which no rate scales (mpg.guiding.choose_step_halvings).
    qs = np.where(on, q, 1.0)
    m_tot, c_tot = float(np.sum(m2_raw)), float(np.sum(c1))
    info.update(
        chain_rate_model_v=v_model, chain_rate_model_c=c_model,
        # (V1's image mean before the offset: learn_jointly's model of other splits)
        chain_rate_model_v1=v1_raw,
        chain_rate_m_scale=float(np.sum(np.where(on, wgt * m2_raw / qs, 0.0))) / m_tot if m_tot > 0 else 0.0,
        # ... and the path tracer's shares of shared paths (no rate; none at rate 0)
        chain_rate_w_scale=float(np.sum(np.where(on, wgt * m2_raw, 0.0))) / m_tot if m_tot > 0 else 0.0,
        chain_rate_s_scale=(float(np.sum(np.where(on, q * c1, 0.0))) / c_tot if c_tot > 0 else 0.0)
        / float(np.mean(np.maximum(q_t, 1e-3))),
    )
    info.update(
        chain_rate_learned=True,
        chain_rate_mean=float(np.mean(q[on])) if np.any(on) else 1.0,
        chain_rate_fraction_one=float(np.mean(q[has] >= 1.0)) if np.any(has) else 1.0,
        chain_rate_fraction_min=float(np.mean(on[has] & (q[has] <= q_min))) if np.any(has) else 0.0,
        chain_rate_fraction_pt=float(np.mean(pt[has] > 0)) if np.any(has) else 0.0,
        chain_rate_fraction_trace=float(np.mean(pt[has] >= 2)) if np.any(has) else 0.0,
    )
    kmap = np.zeros(shape, dtype=np.float32)
    for f, t in enumerate(traced):
        kmap[pt == f + 2] = t[0]
    return q.astype(np.float32), kmap, info


# The delta split (learn_delta_split): at most this many camera paths per
# sample for the light seen through delta scattering only.
DELTA_SPLIT_MAX = 16


# A branched delta path (delta_branch) in rays of an unbranched one, over all
# pixels of double_slabs and sphere at 128^2 (path, delta_split_map = 2, 64 spp:
# extra rays per extra path, branched over unbranched): 1.65 / 1.52 at 3
# levels, 2.13 / 1.73 at 8.
TREE_COST = 2.0

# What a branched delta path leaves of the variance of the light seen through
# delta scattering only, as a fraction of an unbranched sample's: measured
# 1/23-1/26 on the sphere's and double_slabs' pixels that see the light in the
# glass (tests/test_delta_split.py::
# test_branched_paths_stay_unbiased_and_cut_the_glints_variance). The pixel
# split's model (learn_pixel_split, branched=True) uses it.
BRANCH_RESIDUAL = 1.0 / 24.0


# _delta_parts: where the (2 radius + 1)^2 window saw none of the light in the
# glass, its variance over a window DELTA_FILL_SCALE times as wide instead
# (radius 3: 13x13; radius 0, no window: none). A
# short training sees a light's small images in glass in a few pixels only:
# the sphere's 7 training spp of a 2 s render saw it in 7 of the 100 pixels
# that hold its variance, the 7x7 windows reached 52 of them, and the
# pixels left unsplit held 27 % of that light's variance (a 13x13 max filter
# reached 98.5 %; docs/results.md, thirty-first session). Only under
# DELTA_FILL_MAX_TRAINING training spp: a longer training's narrow window that
# saw none of it is evidence, and the fill then added split pixels for
# nothing. Seeds' variance with the fill against without: 7 training spp (2 s)
# 1.33x lower on the sphere (32 seeds), 1.07x on double_slabs and 1.10x on
# the slab (16); 15 (the sphere at 3 s) 1.07x higher, 1 seed of 16 better;
# 31 (5 s) level for 3-6 % fewer spp; the sphere at 20 s 1.2x higher.
DELTA_FILL_SCALE = 2
DELTA_FILL_MAX_TRAINING = 8


def _delta_parts(acc: CostAccumulator, objective: str, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(b, o) per pixel: the weighted variance of the light seen through delta
    scattering only (blurred over the window; where the window saw none of it
    in a training of under DELTA_FILL_MAX_TRAINING spp, over one
    DELTA_FILL_SCALE times as wide) and a delta path's cost in rays
    (1 + the rays a sample traced after delta scattering only)."""
    n = float(acc.n)
    var_d = _sample_variance(acc.delta_sum, acc.delta_sum_sq, n)
    wgt = _weights(_finite(acc.sum) / n, objective, radius)
    wv = wgt * var_d
    b = _box_blur(wv, radius)
    if DELTA_FILL_SCALE > 1 and radius > 0 and n < DELTA_FILL_MAX_TRAINING:
        # "saw none" from a count of the window's pixels that saw it: the
        # summed-area table can leave ~1e-17 where the window holds nothing
        seen = _box_blur((wv > 0.0).astype(float), radius, total=True) >= 0.5
        b = np.where(seen, b, _box_blur(wv, DELTA_FILL_SCALE * radius))
    return b, 1.0 + _finite(acc.delta_rays) / n


# learn_delta_split: a window's records of the branched and plain paths
# (PassResult::bdelta_*) count only where it holds at least this many;
# elsewhere the split's paths branch, as the integrator says.
BRANCH_MIN_RECORDS = 32.0

# learn_delta_split: where a branched path keeps more than this fraction of a
# plain path's variance at a fixed film position (_branch_keep), the split's
# extra paths are plain ones. A tree takes away the choice between reflection
# and refraction at its first delta_branch vertices, and the delta split's
# Sobol positions most of the rest (the pixel footprint's); a tree that keeps
# much of the choice's variance pays 2-6x a plain path's rays for little.
# Measured: double_slabs' trees keep ~0 of it where the light is seen in the
# glass, chain_length_4's (four bumpy slabs, past the 8 levels and the
# roulette) a median 0.4; 0.05 and 0.1 rendered alike, 0.2 a little worse
# on chain_length_4 (docs/results.md, twenty-sixth session).
BRANCH_KEEP_MAX = 0.1


def _branch_keep(acc: CostAccumulator, objective: str, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """(keep, ok) per pixel: the window's weighted variance of a branched
    delta path at a fixed film position over a plain path's (the records'
    sums of (B1 - B2)^2 / 2 and (U1 - U2)^2 / 2, each pair from one camera
    ray), and where it is measured (at least BRANCH_MIN_RECORDS records in
    the window and a plain-path variance above 0)."""
    n_win = _box_blur(_finite(acc.bdelta_n), radius, total=True)
    wgt = _weights(_finite(acc.sum) / max(float(acc.n), 1.0), objective, radius)
    wb = _box_blur(wgt * _finite(acc.bdelta_within), radius, total=True)
    wu = _box_blur(wgt * _finite(acc.udelta_within), radius, total=True)
    # (a window whose plain records are all 0 -- mirrors only -- keeps the
    # table's round-off: not measured)
    ok = (n_win >= BRANCH_MIN_RECORDS) & (wu > 1e-9 * max(float(wu.max()), 1e-300))
    keep = np.where(ok, wb / np.where(wu > 0.0, wu, 1.0), 0.0)
    return keep, ok


def delta_effective_samples(acc: CostAccumulator, radius: int = 3) -> np.ndarray:
    """Per pixel the effective number of training samples that carried the
    light seen through delta scattering only in the (2 radius + 1)^2 window,
    (sum x)^2 / sum x^2 over the window's samples (per channel, weighed by
    the channels' sums): 1 where a
    single sample holds it all (a tiny light's image in the glass, seen once),
    the count of hits where they are alike."""
    s1 = np.stack([_box_blur(_finite(acc.delta_sum)[..., c], radius, total=True) for c in range(3)], axis=2)
    s2 = np.stack([_box_blur(_finite(acc.delta_sum_sq)[..., c], radius, total=True) for c in range(3)], axis=2)
    n_c = np.where(s2 > 0.0, s1 * s1 / np.where(s2 > 0.0, s2, 1.0), 0.0)
    # per channel, then weighted by each channel's sum (a coloured light's dark
    # channels do not count it down)
    w = np.sum(s1, axis=2)
    return np.where(w > 0.0, np.sum(n_c * s1, axis=2) / np.where(w > 0.0, w, 1.0), 0.0)


def _branch_where(branched: bool | np.ndarray, shape: tuple) -> np.ndarray:
    """Per pixel whether the split's extra paths branch: `branched` as a map
    (learn_delta_split's info["branch_map"]) or one bool for all."""
    if isinstance(branched, np.ndarray):
        return np.asarray(branched, dtype=float) > 0.0
    return np.full(shape, bool(branched))


def delta_split_effect(acc: CostAccumulator, k: np.ndarray, radius: int = 3, objective: str = "relmse",
                       branched: bool | np.ndarray = False, min_samples: float = 0.0) -> tuple[float, float]:
    """(dv, dc): what a delta split map k takes from mean(wV) and adds to
    mean(C) (ray units), in learn_delta_split's model: k - 1 branched paths
    leave BRANCH_RESIDUAL / (k - 1) of the light's variance B at TREE_COST o
    each, k unbranched ones 1 / k of it at o each; branched: one bool for all
    pixels or learn_delta_split's branch map. min_samples: only pixels
    whose window carried that light in at least this many effective samples
    (delta_effective_samples) count in dv; all split pixels count in dc."""
    if acc.n < 2:
        return 0.0, 0.0
    b, o = _delta_parts(acc, objective, radius)
    k = np.asarray(k, dtype=float)
    kept, cost = _split_terms(o, k, branched)
    split = k > 1.0
    seen = split if min_samples <= 0.0 else split & (delta_effective_samples(acc, radius) >= min_samples)
    dv = float(np.mean(np.where(seen, b * (1.0 - kept), 0.0)))
    dc = float(np.mean(np.where(split, cost, 0.0)))
    return dv, dc


def _split_terms(o: np.ndarray, k: np.ndarray, branched: bool | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel (kept, cost) of a delta split k: the share of the light's
    variance its paths leave (k - 1 branched: BRANCH_RESIDUAL / (k - 1); k
    plain: 1 / k) and their extra cost in rays (TREE_COST o or o a path)."""
    k = np.asarray(k, dtype=float)
    km1 = np.maximum(k - 1.0, 1.0)
    br = _branch_where(branched, k.shape)
    kept = np.where(br, BRANCH_RESIDUAL / km1, 1.0 / np.maximum(k, 1.0))
    return kept, np.where(br, TREE_COST * o * km1, o * km1)


def learn_delta_split(acc: CostAccumulator, q: np.ndarray, radius: int = 3, objective: str = "relmse",
                      k_max: int = DELTA_SPLIT_MAX, branched: bool = False,
                      means: tuple[float, float] | None = None) -> tuple[np.ndarray, dict]:
    """Per-pixel count k of camera paths that estimate the light seen through
    delta scattering only (design-notes "Splitting the light seen in the
    glass").

    A sample's variance is V = R + B, B that light's part (the light's own
    images in glass and mirrors, glints in bumpy glass) and R the rest. With k
    paths for it, B / k, at (k - 1) o more cost, o = 1 + the rays a sample traced
    after delta scattering only. Minimising F = mean(wV) mean(C), as
    learn_rates does (C the cost per sample at the learned rates q, or as
    `means` gives it; w the objective's weight), over each pixel's k gives

        k_p = sqrt(w_p B_p mean(C) / (o_p mean(wV)))            (Eq. 3)

    rounded, in [1, k_max]. B_p is the training samples' variance of that
    light, averaged over the (2 radius + 1)^2 window like learn_rates' moments;
    where training saw none of it, k = 1 (a tiny light's glints may then be
    missed: the split only ever lowers what training saw). Any fixed k >= 1
    leaves the image unbiased.

    branched (the extra paths are branched, delta_branch > 0): one extra path
    then takes nearly all of B away (the sample's own delta part is left out;
    on the sphere's light in the glass a branched path's variance was 1/24 of
    an unbranched one's), at TREE_COST o. To first order in F, that lowers F
    iff w_p B_p / mean(wV) > TREE_COST o_p / mean(C): k = 2 there, 1
    elsewhere (a second branched path would only halve the small rest).
    Except where the training's records (_branch_keep) show the trees keeping
    more than BRANCH_KEEP_MAX of a plain path's variance at a fixed film
    position (deep stacks of bumpy glass, past the tree's levels): there the
    split's paths are plain ones, k as above. info["branch_map"] (1: branched,
    0: plain; the caller pops it) says which.

    means: (mean(wV), mean(C)) to weigh the split against, the render's as
    the rates' model predicts it (learn_jointly); None: the training
    samples' variance and the cost at rates q."""
    shape = acc.delta_rays.shape
    info: dict = {}
    if acc.n < 2:
        return np.ones(shape, dtype=np.float32), info
    n = float(acc.n)

    b, o = _delta_parts(acc, objective, radius)
    if means is None:
        _, _, c1, mis, c0 = _costs(acc, n)
        c_mean = float(np.mean(c0 + np.where(q <= 0.0, -mis, np.clip(q, 0.0, 1.0) * c1)))
        var_t = _sample_variance(acc.sum, acc.sum_sq, n)
        v_mean = float(np.mean(_weights(_finite(acc.sum) / n, objective, radius) * var_t))
    else:
        v_mean, c_mean = float(means[0]), float(means[1])
    k = np.ones(shape)
    plain = np.zeros(shape, dtype=bool)
    if v_mean > 0.0 and c_mean > 0.0:
        k = np.clip(np.rint(np.sqrt(b * c_mean / (o * v_mean))), 1.0, float(k_max))
        k = np.where(np.isfinite(k), k, 1.0)
        if branched:
            # plain paths (Eq. 3's k) where the records say a tree keeps more
            # than BRANCH_KEEP_MAX of the choice's variance; else k = 2 branched
            keep, ok = _branch_keep(acc, objective, radius)
            plain = ok & (keep > BRANCH_KEEP_MAX)
            k = np.where(plain, k, np.where(b * c_mean > TREE_COST * o * v_mean, 2.0, 1.0))
    split = k > 1.0
    info.update(delta_split_fraction=float(np.mean(split)),
                delta_split_mean=float(np.mean(k[split])) if np.any(split) else 1.0)
    if branched:
        info["delta_split_plain_fraction"] = float(np.mean(plain[split])) if np.any(split) else 0.0
    # per pixel whether the split's paths branch (popped by the caller)
    info["branch_map"] = np.where(split & plain, 0.0, 1.0).astype(np.float32)
    # the training's own (v_mean, c_mean) the counts were solved against
    # (popped by the caller; DeltaSplitRefiner weighs its choice against
    # them). Not for `means` given: learn_jointly's already hold a split's
    # effect, which the check would count twice (no check there).
    if means is None:
        info["means"] = (v_mean, c_mean)
    return k.astype(np.float32), info


# DeltaSplitRefiner.measured_counts: a split pixel's count is set by its
# extra paths' own variance where the render measured at least this many in
# the (2 SPLIT_PATHS_RADIUS + 1)^2 window.
SPLIT_PATHS_MIN = 8.0
SPLIT_PATHS_RADIUS = 1
# ... and at most this many paths (the render's count maps allow 64)
SPLIT_PATHS_MAX = 64
# ... solved in at most this many rounds of Eq. 3 and the means it leads to
SPLIT_PATHS_ROUNDS = 4


class DeltaSplitRefiner:
    """The learned delta split checked between the render's passes by the
    render's own samples (design-notes "The delta split's held-out check").

    learn_delta_split's counts rest on B_p, the variance of the light seen
    through delta scattering only in the pixel's window, and a short
    training sees the light's thin images in bumpy glass in few of its
    pixels: it splits where it saw them, and its mean(wV) misses most of
    that light (double_slabs at 2 s: 18.7 in the render's first 5 spp
    against 4.5 for the training's whole mean(wV)). The render's passes
    record each sample's own path's part of that light (RenderJob's
    record_delta), and they are independent of the training's choice of
    pixels, so their sum over the glass is unbiased where each pixel's is
    noise. Before a pass, `update` compares in the model's F = mean(wV)
    mean(C) (learn_delta_split's, with the training's costs o, weights and
    branch choices, and the render's light in place of the training's part
    of mean(wV)) the training's split (`base`) with every pixel whose camera
    paths saw delta scattering ("glass") split at least twice, and runs the
    better one. With trainings' maps held fixed, the glass split beat the
    learned one 1.0-2x in efficiency on double_slabs (by training seed) and
    1.7x on the slab, and cost the sphere 0.8x, whose one image the training
    saw; in renders the pool 1.6x lower at 2 s, the slab 1.2x, the rest
    level (docs/results.md, forty-third session). Re-solving Eq. 3 per pixel with
    the render's samples pooled in was level at 1-2 s and lost on the
    sphere and ring at 5 s (more split pixels for ~10 % fewer spp). Then,
    given the paths' record (update's `paths`, delta_split_measured), each
    pixel the chosen map splits gets its count from the split's own extra
    paths' variance and rays (measured_counts): not the training's one
    plain path pooled with the render's, but the paths the count divides,
    branched where they branch. The
    image stays unbiased: each pass's counts are fixed before it, and any
    count k >= 1 leaves a sample unbiased."""

    def __init__(self, acc: CostAccumulator, means: tuple[float, float], objective: str = "relmse",
                 radius: int = 3, branched: bool = False, base: np.ndarray | None = None):
        if acc.n < 2:
            raise ValueError("the delta split's check needs a training of at least 2 spp")
        n = float(acc.n)
        self.v_mean, self.c_mean = float(means[0]), float(means[1])
        self.branched = bool(branched)
        self.plain = np.zeros(acc.delta_rays.shape, dtype=bool)
        if self.branched and self.v_mean > 0.0 and self.c_mean > 0.0:
            # (the training's records decide where the paths are plain, as in learn_delta_split)
            keep, ok = _branch_keep(acc, objective, radius)
            self.plain = ok & (keep > BRANCH_KEEP_MAX)
        self.base = (np.ones(acc.delta_rays.shape, dtype=np.float32) if base is None
                     else np.maximum(np.asarray(base, dtype=np.float32), 1.0))
        self.w = _weights(_finite(acc.sum) / n, objective, radius)
        self.o = 1.0 + _finite(acc.delta_rays) / n
        self.glass = self.o > 1.0
        self.glass_map = np.where(self.glass, np.maximum(self.base, 2.0), self.base).astype(np.float32)
        # (the training's own part of v_mean that is this light's: replaced by the render's)
        self.v_delta = float(np.mean(self.w * _sample_variance(acc.delta_sum, acc.delta_sum_sq, n)))
        self.updates = 0

    def model_f(self, k: np.ndarray, wb: np.ndarray) -> float:
        """F = mean(wV) mean(C) of delta split k in learn_delta_split's model
        (delta_split_effect's dv and dc) with wb the weighted variance per
        pixel of that light (one plain path's), which also replaces the
        training's part of mean(wV) that is this light's."""
        split = k > 1.0
        kept, cost = _split_terms(self.o, k, self.branched & ~self.plain)
        dv = float(np.mean(np.where(split, wb * (1.0 - kept), 0.0)))
        dc = float(np.mean(np.where(split, cost, 0.0)))
        v = max(self.v_mean - self.v_delta, 0.0) + float(np.mean(wb))
        return max(v - dv, 0.0) * (self.c_mean + dc)

    def update(self, ds: np.ndarray, ds2: np.ndarray, n: int,
               paths: tuple | None = None) -> tuple[np.ndarray | None, np.ndarray | None, dict]:
        """(counts or None: no split, branch map or None: all branch, info)
        for the next passes from the render's n spp so far (n >= 2): ds / ds2
        the per-pixel sums and squares (height x width x 3) of its samples'
        own paths' light seen through delta scattering only; paths (sums,
        squares, count, rays per pixel of the split's extra paths' values so
        far, PassResult::split_path_*, and the pixel split map they last
        ran with or None) or None: each split pixel's count from its extra
        paths' own variance (measured_counts)."""
        if n < 2:
            raise ValueError("the delta split's check needs at least 2 samples of the render")
        self.updates += 1
        wb = self.w * _sample_variance(ds, ds2, float(n))
        fb, fg = self.model_f(self.base, wb), self.model_f(self.glass_map, wb)
        glass = bool(np.any(self.glass)) and fg < fb
        k = self.glass_map if glass else self.base
        info = {"delta_split_online_updates": self.updates, "delta_split_online_glass": int(glass),
                "delta_split_online_glass_gain": fb / fg if fg > 0.0 else 1.0}
        if paths is not None:
            k, binfo = self.measured_counts(k, wb, *paths)
            info.update(binfo)
        split = k > 1.0
        info.update(delta_split_online_fraction=float(np.mean(split)),
                    delta_split_online_mean=float(np.mean(k[split])) if np.any(split) else 1.0)
        return (*self.maps(k), info)

    def measured_counts(self, k: np.ndarray, wb: np.ndarray, ps: np.ndarray, ps2: np.ndarray,
                        pn: np.ndarray, prays: np.ndarray, kpix: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
        """Counts k with each split pixel's count set by its extra paths' own
        variance V_x and rays r_x as the render measured them so far (ps /
        ps2 over pn paths, prays their rays; pooled over the
        SPLIT_PATHS_RADIUS window, where it holds SPLIT_PATHS_MIN paths):
        minimising F = mean(wV) mean(C) (Eq. 3 again), a branched pixel's m =
        k - 1 extra paths (the sample's own left out) m = sqrt(w V_x mean(C)
        / (r_x mean(wV))), a plain pixel's k paths (its own included) k =
        sqrt(w V_x mean(C) / (r_x mean(wV))), rounded, in [1, SPLIT_PATHS_MAX]
        (with a pixel split, kpix sub-samples a sample each tracing the
        count, 1/kpix of that: the sample averages kpix times the paths at
        kpix times their rays);
        elsewhere k as given. The training's window saw the light's thin
        slivers in bumpy glass spread over 7x7 pixels and few of its samples
        met them; the render's extra paths measure each pixel's own (design-
        notes "The split's counts from its own paths"). Pooled, not per pixel: a
        sliver covering 7 % of a pixel is missed by 8 paths more than half
        the time. Any count fixed before a pass keeps the image unbiased."""
        split = k > 1.0
        r = SPLIT_PATHS_RADIUS
        pn = _finite(pn)
        safe = np.where(pn > 0.0, pn, 1.0)
        # the squared deviations about each pixel's own mean (mean over RGB), pooled
        dev = _rgb_mean(np.maximum(_finite(ps2) - _finite(ps) ** 2 / safe[..., None], 0.0))
        dof = _box_blur(np.maximum(pn - 1.0, 0.0), r, total=True)
        cnt = _box_blur(pn, r, total=True)
        ok = split & (cnt >= SPLIT_PATHS_MIN) & (dof > 0.0)
        if not np.any(ok):
            return k, {"delta_split_online_measured": 0.0}
        vx = _box_blur(dev, r, total=True) / np.where(dof > 0.0, dof, 1.0)
        wvx = np.where(ok, self.w * vx, 0.0)
        rx = np.where(ok, np.maximum(_box_blur(_finite(prays), r, total=True) / np.where(cnt > 0.0, cnt, 1.0), 1.0), 1.0)
        br = self.branched & ~self.plain
        kept, cost = _split_terms(self.o, k, br)
        # (the unmeasured pixels' parts, the model's, at the counts as they stand)
        rest_v = max(self.v_mean - self.v_delta, 0.0) + float(np.mean(np.where(ok, 0.0, np.where(split, wb * kept, wb))))
        rest_c = self.c_mean + float(np.mean(np.where(ok, 0.0, np.where(split, cost, 0.0))))
        k_new = k.astype(np.float64)
        # (a pixel split's kpix sub-samples each trace the count: kpix times the
        # paths a sample, at kpix times their rays)
        kp = np.ones(k.shape) if kpix is None else np.maximum(np.floor(np.asarray(kpix, dtype=float)), 1.0)
        # Eq. 3 at the means it leads to: a few rounds of the fixed point,
        # from the counts as they stand (one round weighed a count of 10
        # against the means at 2, which hold that pixel's variance 9 times)
        for _ in range(SPLIT_PATHS_ROUNDS):
            # the paths' count (branched: the extra ones; plain: all k)
            paths = np.where(br, np.maximum(k_new - 1.0, 1.0), np.maximum(k_new, 1.0))
            v = rest_v + float(np.mean(np.where(ok, wvx / (kp * paths), 0.0)))
            c = rest_c + float(np.mean(np.where(ok, kp * rx * np.maximum(k_new - 1.0, 0.0), 0.0)))
            if not (v > 0.0 and c > 0.0):
                break
            x = np.sqrt(wvx * c / (rx * v)) / kp
            x = np.rint(np.where(np.isfinite(x), x, 1.0))
            # (a branched pixel keeps at least one extra path: with none it
            # falls back on its own plain path, whose variance the check
            # above weighed; a plain pixel's count is Eq. 3's whole)
            k_next = np.where(ok, np.clip(np.where(br, np.maximum(x, 1.0) + 1.0, x), 1.0, float(SPLIT_PATHS_MAX)),
                              k_new)
            if np.array_equal(k_next, k_new):
                break
            k_new = k_next
        info = {"delta_split_online_measured": float(np.mean(ok[split])) if np.any(split) else 0.0,
                "delta_split_online_measured_mean": float(np.mean(k_new[ok])),
                "delta_split_online_measured_max": float(np.max(k_new[ok]))}
        return k_new.astype(np.float32), info

    def maps(self, k: np.ndarray, plain: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The render's (delta split map, delta branch map) of counts k: None
        for no split, and for a branch map where every split pixel branches;
        plain (default: the training's records' choice) the pixels whose extra
        paths are plain."""
        split = k > 1.0
        if not np.any(split):
            return None, None
        b = np.where(split & (self.plain if plain is None else plain), 0.0, 1.0).astype(np.float32)
        return k, (None if np.all(b > 0) else b)


# learn_jointly: at most this many rounds of the delta split and the rates.
JOINT_ROUNDS = 3
# learn_jointly: the split's variance counts in what the rates see taken away
# only where the window carried the light in the glass in at least this many
# effective samples (delta_effective_samples). emitter_size_003's tiny light
# put its whole dv in windows of 1-4 (one glint of 13 000 in 127 samples):
# taken away, the rates saw almost no variance left, ran the chains at 1.5x
# the cost and rendered 1.6x worse (12 seeds); double_slabs' and the
# sphere's split pixels had medians of 12 and 11 (docs/results.md,
# eighteenth session).
JOINT_MIN_SAMPLES = 8.0


def learn_jointly(acc: CostAccumulator, objective: str = "relmse", branched: bool = False,
                  rounds: int = JOINT_ROUNDS, radius: int = 3, min_samples: float = JOINT_MIN_SAMPLES,
                  **rate_kw) -> tuple[np.ndarray, np.ndarray, dict, np.ndarray, dict]:
    """The rates, guided traces and delta split learned together: (q, traces,
    rates' info, delta split k, split's info).

    Each of learn_rates_traced and learn_delta_split weighs a pixel's gain
    against the image's mean variance, mean(wV) (the linearised share of F =
    mean(wV) mean(C)). Learned one after the other, each saw in mean(wV) the
    variance the other takes away -- the light seen in the glass in the
    rates', the chains' in the split's -- and chose too little: on
    double_slabs one guided trace at every first separator and two branched
    delta paths everywhere rendered 10.6x below `path` at equal samples per
    pixel, each alone 1.6x and 2.2x (their variances add), yet the learned
    maps traced 14 % of the chain pixels and split 2 % of all (docs/results.md,
    seventeenth session; the two options are off by default there: a tiny
    light's scene lost 2.3x with them). So: the rates alone; then, per round, the split
    weighed against the rates' predicted means (chain_rate_model_v/_c) and
    the rates again with what that split takes from mean(wV) and adds to
    mean(C) (delta_split_effect) -- until the split stops changing, at most
    `rounds` rounds. Each round's maps lower F in the model, but F = mean(wV)
    mean(C) is not convex along a split, so the joint maps are kept only if
    their F is no higher than that of the maps learned one after the other
    (the rates alone and learn_delta_split against the training's means,
    what joint_maps off renders), else those (joint_rounds 0; also when
    the first round splits nothing). The split's dv counts only in windows that carried its
    light in at least min_samples effective samples (delta_effective_samples):
    a variance made of one or two glints is no ground to re-plan the image's
    budget on. radius: all three's window; rate_kw:
    learn_rates_traced's other arguments."""
    q, t, info = learn_rates_traced(acc, objective=objective, radius=radius, **rate_kw)
    k = np.ones(acc.chain_m2.shape, dtype=np.float32)
    b_prev = np.ones(acc.chain_m2.shape, dtype=np.float32)
    kinfo: dict = {"branch_map": b_prev}
    done = 0
    if not info.get("chain_rate_learned"):
        return q, t, info, k, kinfo
    # the maps learned one after the other, and their F in the model
    k_seq, kinfo_seq = learn_delta_split(acc, q, radius=radius, objective=objective, branched=branched)
    dv, dc = delta_split_effect(acc, k_seq, radius=radius, objective=objective,
                                branched=kinfo_seq["branch_map"] if branched else False, min_samples=min_samples)
    alone = (q, t, info)
    # (as learn_rates_traced's model with that split's offsets: V1 less dv, at
    # least 0, then the forms' and rates' terms the rates alone added)
    v1 = info["chain_rate_model_v1"]
    v_seq = max(v1 - dv, 0.0) + info["chain_rate_model_v"] - max(v1, 0.0)
    c_seq = info["chain_rate_model_c"] + dc

    def model_f(v, c):
        return v * c if v > 0.0 and c > 0.0 else np.inf
    for done in range(1, rounds + 1):
        k_new, kinfo = learn_delta_split(acc, q, radius=radius, objective=objective, branched=branched,
                                         means=(info["chain_rate_model_v"], info["chain_rate_model_c"]))
        if np.array_equal(k_new, k) and np.array_equal(kinfo["branch_map"], b_prev):
            break
        k, b_prev = k_new, kinfo["branch_map"]
        dv, dc = delta_split_effect(acc, k, radius=radius, objective=objective,
                                    branched=b_prev if branched else False, min_samples=min_samples)
        q, t, info = learn_rates_traced(acc, objective=objective, radius=radius, v_offset=dv, c_offset=dc,
                                        **rate_kw)
    # kept if a split was learned together (round 1 splitting nothing leaves
    # the rates alone, unsplit: not what joint_maps off renders) and the
    # model's F is no higher than the maps' learned one after the other
    if (done == 0 or not np.any(k > 1.0) or
            model_f(info["chain_rate_model_v"], info["chain_rate_model_c"]) > model_f(v_seq, c_seq)):
        q, t, info = alone
        k, kinfo, done = k_seq, kinfo_seq, 0
        info = dict(info, joint_cost_ratio=1.0)
    else:   # (the kept maps' predicted cost per sample against the rates' alone)
        c_alone = alone[2]["chain_rate_model_c"]
        info["joint_cost_ratio"] = float(info["chain_rate_model_c"] / c_alone) if c_alone > 0 else 1.0
    info["joint_rounds"] = done
    return q, t, info, k, kinfo


def rate_map_grey8(q: np.ndarray, q_low: float = 1.0 / 32) -> np.ndarray:
    """A rate map as 8-bit RGB (H, W, 3): grey on a log2 scale from q_low
    (black) to 1 (white); rate 0 (the path tracer alone) blue. For mpg-render
    --chain-rate-map and the docs figure."""
    q = np.asarray(q, dtype=float)
    lo = np.log2(q_low)
    g = np.clip((np.log2(np.maximum(q, 1e-3)) - lo) / -lo, 0.0, 1.0)
    out = np.repeat(np.round(g * 255.0).astype(np.uint8)[..., None], 3, axis=2)
    out[q <= 0.0] = (40, 90, 220)
    return out


# The pixel split (learn_pixel_split): at most this many camera samples averaged per sample.
PIXEL_SPLIT_MAX = 16


def learn_pixel_split(acc: CostAccumulator, q: np.ndarray, kd: np.ndarray, radius: int = 1,
                      objective: str = "mse", k_max: int = PIXEL_SPLIT_MAX,
                      iterations: int = 30,
                      where: np.ndarray | None = None,
                      branched: bool | np.ndarray = False,
                      max_cost: float | None = None) -> tuple[np.ndarray, dict]:
    """Per-pixel count k of camera samples averaged in each sample of the pixel
    (design-notes "Splitting the pixels").

    With the learned rates q and delta splits kd, a sample of pixel p has
    variance V_p and cost C_p; k of them averaged, V_p / k at k C_p. Minimising
    F = mean(w V / k) mean(k C), the same F as learn_rates and
    learn_delta_split, over each k_p gives

        k_p = sqrt(w_p V_p mean(k C) / (C_p mean(w V / k)))          (Eq. 4)

    a fixed point, rounded, in [1, k_max]. From the training samples (rate q_t,
    no splits): V_p = var_t + (1/q - 1/q_t) M at q > 0, the path tracer
    alone's E[(A - I)^2] at q = 0, less (1 - 1/kd) of the light seen through
    delta scattering only; C_p = c0 + q c1 (c0 - mis at q = 0) + (kd - 1) o.
    w V is averaged over the (2 radius + 1)^2 window. This is adaptive
    sampling with a map fixed before the render: any fixed k >= 1 leaves the
    image unbiased, and where training saw no variance k = 1 (a firefly no
    training sample saw is not split; PixelSplitRefiner then learns it again
    from the render's own samples).

    branched (the delta split's extra paths are branched, delta_branch > 0,
    and a split sample leaves its own delta part out; one bool or
    learn_delta_split's branch map): where kd > 1 and branched the light
    seen through delta scattering only keeps BRANCH_RESIDUAL of its variance,
    not 1 / kd, and each extra path costs TREE_COST o, as in
    learn_delta_split.

    max_cost: a cap on the predicted cost of a sample, mean(k C) / mean(C).
    Every extra sample of a split pixel is taken from all the others, whose
    spp falls by that factor; where the training saw no variance (a rare
    firefly) the model does not count that loss. Above the cap, k_p =
    clamp(rint(s sqrt(...)), 1, k_max) with the fixed point's image means
    and the largest s in (0, 1] (bisection) that keeps the cost at or below
    it."""
    if acc.n < 2:
        return np.ones(acc.delta_rays.shape, dtype=np.float32), {}
    return PixelSplitRefiner(acc, q, kd, radius=radius, objective=objective, k_max=k_max, iterations=iterations,
                             where=where, branched=branched, max_cost=max_cost).solve()


def _pixel_split_model(acc: CostAccumulator, q: np.ndarray, kd: np.ndarray, radius: int, objective: str,
                       branched: bool | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """learn_pixel_split's per-pixel weight w, a sample's variance V and cost C
    at the render's rates and delta splits, from the training (acc.n >= 1;
    V needs 2 spp: from a training of 1 spp it is 0 everywhere, for the
    render's own samples to fill in, PixelSplitRefiner)."""
    n = float(acc.n)
    q = np.asarray(q, dtype=float)
    kd = np.maximum(np.asarray(kd, dtype=float), 1.0)
    q_t, _, c1, mis, c0 = _costs(acc, n)
    mean = _finite(acc.sum) / n
    qc = np.clip(q, 1e-3, 1.0)
    br = _branch_where(branched, kd.shape) & (kd > 1.0)
    if n >= 2:
        var_t = _sample_variance(acc.sum, acc.sum_sq, n)
        m2 = _finite(acc.chain_m2) / n
        alt_mse = _alt_mse(acc, n, mean)
        var_d = _sample_variance(acc.delta_sum, acc.delta_sum_sq, n)
        v = np.where(q > 0.0, var_t + (1.0 / qc - 1.0 / np.maximum(q_t, 1e-3)) * m2, alt_mse)
        kept = np.where(br, BRANCH_RESIDUAL, 1.0 / kd)
        v = np.maximum(v - (1.0 - kept) * var_d, 0.0)
    else:
        v = np.zeros(q.shape)
    o = 1.0 + _finite(acc.delta_rays) / n
    c = c0 + np.where(q > 0.0, qc * c1, -mis) + (kd - 1.0) * o * np.where(br, TREE_COST, 1.0)
    c = np.maximum(c, 1e-6)
    return _weights(mean, objective, radius), v, c


def _solve_pixel_split(wv: np.ndarray, c: np.ndarray, k_max: int, iterations: int,
                       where: np.ndarray | None, max_cost: float | None) -> tuple[np.ndarray, dict]:
    """Eq. 4's fixed point for the window means wv of w V and the costs c,
    capped at max_cost (learn_pixel_split).

    Only the pixels with wv != 0 (within `where`) can take k > 1: Eq. 4 gives
    the others sqrt(0) -> 1. The per-pixel arithmetic runs on those alone
    (a few % of the image; on all of it, the refiner's solves took 20 ms
    each between the render's passes), the image means of the fixed point on
    the whole map as before; the cap's bisection sums the candidates' extra
    cost alone (the same map but where a cost lies within rounding of the
    cap)."""
    info: dict = {}
    cand = wv != 0.0   # (NaN included: it maps to 1 as before)
    if where is not None:
        cand &= where
    idx = np.flatnonzero(cand)
    wv_c, c_c = wv.ravel()[idx], c.ravel()[idx]
    k = np.ones(wv.shape)

    def eq4(k: np.ndarray, scale: float = 1.0) -> np.ndarray:
        """Eq. 4's map at the image means of k, its square root times scale."""
        c_mean, v_mean = float(np.mean(k * c)), float(np.mean(wv / k))
        kc = np.clip(np.rint(scale * np.sqrt(wv_c * c_mean / (c_c * v_mean))), 1.0, float(k_max))
        out = np.ones(wv.shape)
        out.ravel()[idx] = np.where(np.isfinite(kc), kc, 1.0)
        return out

    for _ in range(iterations):
        if not (float(np.mean(k * c)) > 0.0 and float(np.mean(wv / k)) > 0.0):
            break
        k_new = eq4(k)
        if np.array_equal(k_new, k):
            break
        k = k_new
    cost = float(np.mean(k * c) / np.mean(c))
    if max_cost is not None and cost > max_cost:
        fixed = k   # the fixed point whose means the capped map keeps
        c_mean, v_mean = float(np.mean(fixed * c)), float(np.mean(wv / fixed))
        base = np.sqrt(wv_c * c_mean / (c_c * v_mean))
        c_sum = float(np.sum(c))

        def capped(scale: float) -> np.ndarray:
            """eq4(fixed, scale) on the candidates, its means computed once."""
            kc = np.clip(np.rint(scale * base), 1.0, float(k_max))
            return np.where(np.isfinite(kc), kc, 1.0)

        lo, hi = 0.0, 1.0   # cost at lo <= max_cost (scale 0: all ones), at hi > max_cost
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            # (mean(k C) / mean(C), the pixels at k = 1 summed once)
            if (c_sum + float(np.dot(capped(mid) - 1.0, c_c))) / c_sum <= max_cost:
                lo = mid
            else:
                hi = mid
        k = np.ones(wv.shape)
        k.ravel()[idx] = capped(lo)
        info.update(pixel_split_capped=cost, pixel_split_scale=lo)
    split = k > 1.0
    info.update(pixel_split_fraction=float(np.mean(split)),
                pixel_split_mean=float(np.mean(k[split])) if np.any(split) else 1.0,
                pixel_split_cost=float(np.mean(k * c) / np.mean(c)))
    return k.astype(np.float32), info


def split_sample_variance(ks: np.ndarray, ks2: np.ndarray, kn: np.ndarray, n: int) -> np.ndarray:
    """Per pixel (mean over RGB) the variance V of one camera sample, from n
    independent samples s of one mean, each the mean of k camera samples
    (Var(s) = V / k): ks, ks2 the sums of k s and k s^2, kn of k. About the
    precision-weighted mean m = ks / kn, E[sum k (s - m)^2] = (n - 1) V (the
    weighted sample variance with weights 1 / Var), and sum k (s - m)^2 =
    ks2 - ks^2 / kn."""
    ks, kn = _finite(ks), np.maximum(np.asarray(kn, dtype=float), 1e-300)[..., None]
    return _rgb_mean(np.maximum(_finite(ks2) - ks * ks / kn, 0.0)) / (n - 1)


class PixelSplitRefiner:
    """The pixel split refined between the render's passes by its own samples
    (design-notes "The pixel split refined by the render's own samples");
    `solve()` alone is learn_pixel_split's map from the training.

    The training's model of a sample's variance V at the render's maps misses
    what no training sample saw: after a training of 3 spp the few pixels
    that held 87 % of the sphere's variance at 1 s were split in some seeds
    and not in others. The render's passes see the same pixels many times
    over. Before a pass, `update` re-solves Eq. 4 (the same costs, window,
    objective and cap) with V the training's model and the render's own
    estimate pooled by their samples, and the next passes run with that map.
    The image stays unbiased: a sample is the mean of k camera samples drawn
    after k was fixed, so E[sample | k] = I whatever earlier samples chose
    k, and the pixel is the plain mean of a number of samples the schedule
    fixes. (Each update starts a new epoch of the pixels' Sobol sequences in
    the render, whose shifts the earlier samples never saw.)

    A training of 1 spp (a short render's whose training could not go on:
    the sphere at 1 s from a fresh process trained 1 spp, or 3 when a few
    ms allowed, before the training's continuation) has costs but no
    variance: its model's V is 0, `solve()` splits nothing, and the updates
    pool the render's own estimate alone (n_t = 0)."""

    def __init__(self, acc: CostAccumulator, q: np.ndarray, kd: np.ndarray, radius: int = 1,
                 objective: str = "mse", k_max: int = PIXEL_SPLIT_MAX, iterations: int = 30,
                 where: np.ndarray | None = None, branched: bool | np.ndarray = False,
                 max_cost: float | None = None):
        if acc.n < 1:
            raise ValueError("the pixel split's refiner needs a training of at least 1 spp (its costs)")
        self.w, self.v, self.c = _pixel_split_model(acc, q, kd, radius, objective, branched)
        self._model_args = (acc, q, radius, objective)   # (set_delta_split)
        # (a training of 1 spp has no variance: the render's own samples alone)
        self.n_t = float(acc.n) if acc.n >= 2 else 0.0
        self.radius, self.k_max, self.iterations = radius, k_max, iterations
        self.where, self.max_cost = where, max_cost
        self.updates = 0

    def set_delta_split(self, kd: np.ndarray, branched: bool | np.ndarray = False) -> None:
        """The model again for a new delta split (DeltaSplitRefiner's): the
        training's V and C at those counts and branch choices."""
        acc, q, radius, objective = self._model_args
        self.w, self.v, self.c = _pixel_split_model(acc, q, kd, radius, objective, branched)

    def solve(self, v: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
        """Eq. 4's map (capped) for a sample's variance v per pixel (None: the training's model)."""
        return _solve_pixel_split(_box_blur(self.w * (self.v if v is None else v), self.radius), self.c,
                                  self.k_max, self.iterations, self.where, self.max_cost)

    def update(self, ks: np.ndarray, ks2: np.ndarray, kn: np.ndarray, n: int) -> tuple[np.ndarray | None, dict]:
        """The map for the next passes (None: no pixel split) from the render's n spp so far: per pixel
        ks / ks2 the sums of k s and k s^2 and kn of k over its samples s (k
        the count each ran at; split_sample_variance)."""
        if n < 2:
            raise ValueError("the pixel split's refinement needs at least 2 samples of the render")
        k, info = self.solve((self.n_t * self.v + n * split_sample_variance(ks, ks2, kn, n)) / (self.n_t + n))
        self.updates += 1
        # (the render's stats: beside the training's pixel_split_* of the map it started with)
        return (k if np.any(k > 1.0) else None), {"pixel_split_online_updates": self.updates,
                        "pixel_split_online_fraction": info["pixel_split_fraction"],
                        "pixel_split_online_mean": info["pixel_split_mean"],
                        "pixel_split_online_cost": info["pixel_split_cost"],
                        "pixel_split_online_scale": float(info.get("pixel_split_scale", 1.0))}


def guided_trace_map(acc: CostAccumulator, radius: int = 3,
                     negligible: float = HANDOFF_NEGLIGIBLE) -> np.ndarray:
    """Where the guided trace of handed-off pixels runs (handoff_guided; 1 or 0
    per pixel): where the chains' light is not negligible, i.e. the window's
    second moment of the chain estimates above `negligible` of the pixel's own
    variance per sample -- the other side of the hand-off's "negligible" rule.
    A pixel handed off because its variance is the light seen in the glass
    (double_slabs' glints) gains nothing from more chain paths and would pay
    for the traces. Only its rate-0 pixels matter to the render."""
    if acc.n < 2:
        return np.ones(acc.chain_m2.shape, dtype=np.float32)
    n = float(acc.n)
    m2_raw = _finite(acc.chain_m2) / n
    var_t = _sample_variance(acc.sum, acc.sum_sq, n)
    return (~_negligible_chain_light(m2_raw, var_t, radius, negligible)).astype(np.float32)


def _negligible_chain_light(m2_raw: np.ndarray, var_t: np.ndarray, radius: int,
                            negligible: float) -> np.ndarray:
    """Pixels whose window's chain second moment (per sample) is at most
    `negligible` of the pixel's own variance per sample: the hand-off's
    "negligible" rule (learn_rates) and the guided trace's off pixels."""
    return _box_blur(m2_raw, radius) <= negligible * var_t


# mpg's photons per camera sample, learned (light_trace / light_trace_glossy
# "auto", the default): clamped to this range, and the pilot traces this many
# photons per camera sample of its own (at least 1 and at most 64 per pixel
# and sample; 2 x 65 536 with guiding.PHOTON_PILOT_SPP) to measure them.
PHOTON_RATE_MIN = 1.0 / 32
PHOTON_RATE_MAX = 4.0
PHOTON_PILOT = 65536


def learn_photon_rate(cam_var: float, cam_cost: float, lt_sum: np.ndarray, lt_sum_sq: np.ndarray,
                      photons: int, lt_cost: float, r0: float) -> tuple[float, dict]:
    """Photons per camera sample r for the image's MSE after a fixed time
    (design-notes "The photon rate, learned").

    A render pass of s samples per pixel over P pixels traces N = r s P
    photons; each photon is one independent sample of every pixel's light-
    traced part (RenderJob::light_trace: the splat's pixel gets its value, the
    others 0). Pixel p's variance is V_p / s from its camera samples (the rest
    of its paths: the path tracer and the estimator leave the photons' paths
    to them) plus v_p / N, v_p the variance of one photon's contribution to p.
    The pass costs s P (c + r d), c and d the work of one camera sample and of
    one photon (ray units, as the rates' model counts it: rays traced plus
    STEP_COST per manifold-walk step; a count, so the rate, and the image, of
    a render by spp do not depend on the machine's timing). The image's MSE
    after a fixed time is then proportional
    to F(r) = (mean_p V_p + mean_p v_p / (r P)) (c + r d), least at

        r = sqrt(mean_p(v_p) c / (P mean_p(V_p) d))                    (Eq. 5)

    (the balance of Eq. 1, for the photons as one more estimator of a fixed
    share of the paths). cam_var: mean over the pixels (and RGB) of a camera
    sample's variance; cam_cost: c; lt_sum / lt_sum_sq (height x width x 3):
    the pilot's splat sums over `photons` photons, whose work was lt_cost (d =
    lt_cost / photons); r0: the rate the pilot is compared with in the
    info's predicted gain F(r0) / F(r). Any r > 0 leaves the image unbiased;
    r is clamped to [PHOTON_RATE_MIN, PHOTON_RATE_MAX]: a pilot that saw no
    photon land (v = 0) gets the minimum, a camera without variance the
    maximum."""
    n = float(photons)
    p = float(lt_sum.shape[0] * lt_sum.shape[1])
    info: dict = {}
    if n < 1 or not (lt_cost > 0.0 and cam_cost > 0.0):
        return r0, info
    m = _finite(lt_sum) / n
    v = float(np.mean(np.maximum(_finite(lt_sum_sq) / n - m * m, 0.0))) * (n / max(n - 1.0, 1.0))
    a = float(cam_var) if np.isfinite(cam_var) else 0.0
    c, d = float(cam_cost), float(lt_cost) / n
    if v <= 0.0:
        r = PHOTON_RATE_MIN
    elif a <= 0.0:
        r = PHOTON_RATE_MAX
    else:
        r = float(np.clip(np.sqrt(v * c / (p * a * d)), PHOTON_RATE_MIN, PHOTON_RATE_MAX))

    def f(x: float) -> float:
        return (a + v / (x * p)) * (c + x * d)

    info.update(light_trace_learned=r, light_trace_model_v_camera=a, light_trace_model_v_photon=v / p,
                light_trace_model_c_camera=c, light_trace_model_c_photon=d,
                light_trace_model_gain=f(r0) / f(r) if f(r) > 0.0 else 1.0)
    return r, info
