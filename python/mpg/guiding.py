"""Manifold path guiding (MPG, Fan et al. 2023): the training/rendering loop.

Training (Sec. 5.8): iterations of 1, 2, 4, ... spp whose chain solutions are
recorded as sub-path samples; after each iteration the guiding state (STree +
per-leaf chain distributions) is rebuilt from that iteration's samples only.
Training stops at `training_fraction` (30 %) of the budget, and a new iteration
only starts while less than half of the training budget is spent; under a
time budget the last one may continue until the budget is spent
(`training_continue`). Training passes are never splatted into the image.
The rest of the budget renders with the last guiding state (recording off)."""

from __future__ import annotations

import math
import sys
import time as _time
from typing import Any

import numpy as np

from mpg.chain_rates import (HANDOFF_NEGLIGIBLE, JOINT_MIN_SAMPLES, PHOTON_PILOT, STEP_COST, CostAccumulator,
                             _sample_variance, guided_trace_map, learn_delta_split, learn_photon_rate,
                             learn_rates, PixelSplitRefiner, DeltaSplitRefiner, learn_jointly, learn_rates_traced,
                             delta_split_effect)
from mpg.errors import RenderError


def _split_setting(name: str, value, words: tuple[str, ...]):
    """A split parameter: one of `words`, or an integer count in [1, 64]."""
    if str(value) in words:
        return str(value)
    allowed = " or ".join([", ".join(f"'{w}'" for w in words), "an integer in [1, 64]"])
    try:
        k = int(value)
    except (TypeError, ValueError):
        raise RenderError(f"{name} must be {allowed}, got '{value}'") from None
    if not 1 <= k <= 64:
        raise RenderError(f"{name} must be {allowed}, got {k}")
    return k


# mpg's default delta_branch: against 0, in one run (20 s, 2 seeds), MSE 1.77x
# lower on slab, 1.53x pool, 1.39x double_slabs, 1.08x sphere, ring the same
# (bench/results/compare-branch-suite; 3 levels did half as well on double_slabs).
DELTA_BRANCH = 8
# mpg's default delta_split_sobol: the split's extra paths at the points of a
# per-pixel Sobol sequence; against independent positions (20 s, 2 seeds)
# own MSE 1.43x lower on double_slabs, 1.11x slab, the rest level
# (docs/results.md, twenty-fifth session)
DELTA_SPLIT_SOBOL = True
# mpg's default delta_plain: the delta split's extra paths plain where the
# training's records show the trees keeping more than BRANCH_KEEP_MAX of the
# lobe choice's variance; against branched everywhere (3 seeds, docs/results.md,
# twenty-sixth session) own MSE 1.34x lower on chain_length_4, 1.23x on
# double_slabs; the slab, sphere and pool have no such pixel (level; the
# records cost them up to 4 % of their samples)
DELTA_PLAIN = True

# The photon rate the learned one is compared with in the stats'
# light_trace_model_gain: the core's default for mpg in chain mode
# (kMpgLightTrace, module.cpp), also the rate where none is learned
DEFAULT_PHOTON_RATE = 0.25
# The photon rate's pilot pass: camera samples per pixel (their variance: 2
# gives each pixel's unbiased), and the training spp below which no pilot runs
# and the core's default rate stays (the pilot's 2 spp are then more than
# about 2.5 % of the render's: about 2.3x the training's spp at 30 %)
PHOTON_PILOT_SPP = 2
PHOTON_PILOT_MIN_TRAINING = 32
# the render's first pass is sized at this many times the training's seconds
# per spp (render(seconds_per_spp=...); a first pass is never cancelled, so
# one that ran 8x slower than its estimate would overrun a time budget; with
# the margin, 16x)
PASS_HINT_MARGIN = 2.0

# mpg's default max_chain (the longest chain the estimator, the guide and the
# photons take; the core's default, sms_star's, is 6): with 8 the 8-refraction
# caustic of chain_length_4 is no longer the path tracer's alone (128^2, 10 s,
# 2 seeds: MSE 0.0208 -> 0.0194, relMSE 0.172 -> 0.108), level on the suite
# within the seeds' spread (docs/results.md, twenty-second and twenty-third
# sessions). sms_star keeps 6: with 8 it is worse there (0.253 -> 0.277).
MAX_CHAIN = 8

# mpg's default guide_fraction: alpha of MPG Eq. 13, the guided share of seed
# chains, in the render and (unless training_guide_fraction says otherwise) in
# the training passes: the paper's 0.5. Before the Bernoulli trials stopped at
# differing letters, 0.8 measured 1.3-1.8x lower MSE on double_slabs; with the
# cut, 0.5 and 0.8 tie there and on the sphere, and 0.8 is 1.3-1.4x worse on
# ring (design-notes "The guided share of seed chains"; docs/results.md, ninth
# and tenth sessions).
GUIDE_FRACTION = 0.5
# Render passes: chains of a type their leaf never saw go to the path tracer
# (on by default; off: the estimator owns every type, as in MPG).
KNOWN_TYPES = True
# Render passes: in pixels handed to the path tracer whose chains' light is not
# negligible, this many guided traces per first separator (design-notes "The
# guided trace of handed-off pixels"; 0: off). Sphere, 20 s, 3 seeds: own MSE
# 1.21x lower with 1, 1.32x with 4, 16 worse than 4 (docs/results.md,
# fourteenth session).
HANDOFF_GUIDED = 4
# Render passes: in pixels handed to the path tracer, the chain estimator at
# this rate at every separator after a path's first (design-notes "The later
# separators of handed-off pixels"; 0: the path tracer's there too).
HANDOFF_DEEP = 1.0
# training_continue: under a time budget the last training iteration goes on
# until the training budget is spent (MPG Sec. 5.8; render_mpg's training
# loop). "auto" (the default): only where the iterations end with fewer than
# 2 training spp, which learn no map (the sphere at 1 s in most fresh
# processes: MSE 1.27x lower, 32 seeds); true: always, the paper's rule;
# false: never. Always, against never, seeds' variance at 5 s (8 seeds;
# docs/results.md, fortieth session): the ring 2.2x and emitter_size_010
# 1.67x lower, double_slabs and the slab level, the pool, chain_length_4
# and visibility_4 0.91-0.93x, the sphere 0.60x; double_slabs 0.78x at
# 10 s and 0.93x at 20 s: the maps' thresholds were tuned on the shorter
# trainings.
TRAINING_CONTINUE = "auto"
# A training of fewer than TRAINING_MIN_SPP spp learns no map (no variance):
# where it continues (training_continue auto or true) its passes may run
# past the training budget until it has that many spp, up to twice the
# budget and at most TRAINING_MAX_FRACTION of the render's time. From
# mpg-render at 1 s double_slabs' trainings of 1 spp rendered an MSE of
# 0.30, those of 2 spp 0.15 (fresh processes, 32 seeds; docs/results.md,
# forty-first session).
TRAINING_MIN_SPP = 2
TRAINING_MAX_FRACTION = 0.5
# training_clock: what the training budget (training_fraction of a time
# budget) counts. "wall" (the default): everything since the render began.
# "passes": the training passes' own time; the loop's work between them
# (the cost records' sums, the maps' choices, guide builds, the photon
# guide's tracing: ~0.2 s in a fresh process, whatever the budget) comes
# on top, the training's wall time at most TRAINING_MAX_FRACTION of the
# render's (or its training_fraction, if larger). At 1 s that work takes
# half of a 0.3 s training. Passes against wall (docs/results.md,
# forty-first session): at 1 s (fresh processes, 24 seeds) double_slabs
# 1.31x and the sphere 1.29x lower, the pool level, chain_length_4 1.22x
# higher; at 3 s (8 seeds) the ring 1.59x higher and double_slabs, the
# sphere and chain_length_4 1.1x; at 5 s the sphere 1.16x lower and
# double_slabs 1.12x higher. Not the default.
TRAINING_CLOCK = "wall"
# The hand-off (rate 0, chain_handoff) needs this many training spp unless it
# is asked for: with fewer, the window's estimate of the path tracer's
# variance has not seen its tail and the hand-off loses the caustic. Sphere,
# seeds' variance, hand-off on / off: 2 s (7 training spp, 81 % of the pixels
# handed off) 0.00325 / 0.00228, 3 s (15 spp) 0.00082 / 0.00052, 5 s (31 spp)
# 0.00043 / 0.00041, 20 s (127 spp) 0.000109 / 0.000144 (double_slabs at 20 s
# 0.00104 / 0.00136; docs/results.md, thirtieth session).
HANDOFF_MIN_TRAINING = 24
# handoff_all: 0 renders the learned maps; K >= 1 hands every pixel to the
# path tracer with K guided traces; "auto" (the default) chooses between 0
# and HANDOFF_ALL_AUTO_K per render. With 2 in every render double_slabs'
# seeds' variance is 1.4-1.8x lower at 2-20 s, the ring's 1.7x, the slab's
# 1.15x, but chain_length_4's MSE 1.1x and the pool's 4-5x higher
# (docs/results.md, thirty-fourth to thirty-sixth sessions); a race or a
# pilot in the render did not choose reliably (thirty-fourth).
HANDOFF_ALL = "auto"
# auto hands every pixel off with HANDOFF_ALL_AUTO_K traces where the rates'
# model puts that at most HANDOFF_ALL_AUTO_MAX times its own maps' F: the
# model prices the trace forms 2.5-3.2x too high on double_slabs
# (docs/results.md, thirty-fifth session), so the bound is well above 1.
# Its ratio per scene and training (thirty-sixth session): double_slabs
# 1.7-2.6, ring 1.6-5.5, slab 2.5-4.7, the sphere 1.2-10.4, visibility_4
# 4.0-4.7, emitter_size_030 2.4-4.3, chain_length_4 0.9-1.4 (these hand
# off: 1.07-1.80x lower seeds' variance, emitter_size_030 level, the slab
# 0.87x at 20 s, chain_length_4 0.90-0.94x); the pool 12-14.6 (the traces
# 4-5x worse there), emitter_size_010 10.6-42 (there they would gain 1.6x:
# the ratio does not separate the two), emitter_size_003 62-86 (these keep
# the learned maps). The choice does not wait for HANDOFF_MIN_TRAINING
# (thirty-ninth session; the model of every pixel handed off is made from
# the trace records of any training): against the learned maps, seeds'
# variance 1.9-2.1x lower on double_slabs at 3-5 s, 2.1x on the slab at 2 s,
# 2.7x on visibility_4 at 3 s, 1.3x on the ring at 2 s; the sphere 0.67x at
# 2 s, 0.93x at 3 s (relMSE level and 1.25x lower) and 0.91x at 1 s (48
# seeds), chain_length_4 0.95x
HANDOFF_ALL_AUTO_K = 2
HANDOFF_ALL_AUTO_MAX = 8.0
# handoff_all's pixels run the estimator at the separators after a path's
# first at their learned rate where it is positive (min with handoff_deep),
# handoff_deep where the maps handed them off too; off: handoff_deep in all
HANDOFF_ALL_DEEP = True
# The training measures the guided trace, and the rates choose where it runs
# (learn_trace; design-notes "The rates choose the guided trace") ...
LEARN_TRACE = True
# ... with the forms' second moments of the chain paths taken as the chains
# sample them (trace_tails; chain_rates.learn_rates_traced; design-notes "The
# traces' tails"): without it the traces' rare large values escaped the
# training's record where the light is small (pool 8x worse), with it pool
# is level and double_slabs, ring, sphere and slab gain 1.1-2.4x
# (docs/results.md, sixteenth session)
TRACE_TAILS = True
# The rates, traces and delta split learned together (chain_rates.learn_jointly),
# and the samples with chain light a guided trace form's window needs (None: the
# path tracer alone's HANDOFF_MIN_HITS, 64). With joint_maps and trace_min_hits
# 16, own MSE at 20 s, 3 seeds: double_slabs 1.24x, sphere 1.20x, ring 1.16x
# lower, slab 0.95x, pool level, either alone left double_slabs level -- but
# emitter_size_003 (128^2, 10 s, 6 seeds) lost 2.3x with the two, 1.8x and 2.4x
# with each alone, at 35 % fewer samples: so both are off by default
# (docs/results.md, seventeenth session). With the joint_min_samples rule and
# the fallback to the maps learned one after the other (eighteenth session)
# emitter_size_003 is level, double_slabs 1.20x, the sphere 1.07x, the ring
# 0.96x, the slab 0.89x, pool 0.98x: one scene's gain, still off
JOINT_MAPS = False
TRACE_MIN_HITS = None
# The pixel split's default (learned for MSE) and the cap on its predicted cost
# per sample (design-notes "Splitting the pixels"; docs/results.md, eleventh session)
PIXEL_SPLIT = "mse"
PIXEL_SPLIT_MAX_COST = 1.1
# The guided traces' defensive share and its lobes' kappa cap (design-notes
# "The guided trace's defensive lobes"): against none, seeds' variance 1.20x
# lower on double_slabs (20 s), 1.37x on the ring, 2.1x on visibility_4
# (10 s), 2.7x on the slab (20 s); the sphere 0.95x at 5 s (16 seeds) and
# 0.86x at 20 s (8; relMSE equal), the pool 0.95x, emitter_size_010 0.88x,
# chain_length_4 level (10 s); kappa 100 and 1500, or a
# share of 0.2, gained less on double_slabs (docs/results.md, thirty-eighth
# session)
TRACE_DEFENSIVE = 0.35
TRACE_DEFENSIVE_KAPPA = 400.0
PIXEL_SPLIT_ONLINE = True
# The learned delta split checked between the render's passes against every
# glass pixel split, by the render's own samples (delta_split_online;
# chain_rates.DeltaSplitRefiner): a short training sees the light's thin
# images in bumpy glass in few pixels (docs/results.md, forty-third session)
DELTA_SPLIT_ONLINE = True
# ... and there each split pixel's count set by its extra paths' own variance
# and rays as the render measures them (delta_split_measured;
# DeltaSplitRefiner.measured_counts)
DELTA_SPLIT_MEASURED = True
# Photons whose sub-path samples join every training guide (photon_guide;
# design-notes "Photons in every guide"; docs/results.md, twenty-eighth
# session): the leaves then know the chain types the light sends, which the
# estimator's own walks in training rarely find (a tiny light's)
PHOTON_GUIDE = 200_000
# The photon guide grows over the training's guide builds: the first holds
# 1/PHOTON_GUIDE_FIRST of its photons, each later one twice the one before,
# up to all of them (the third build on), the same photons (one trace's
# ranges, weighted as the whole trace's). A 1 s training spent a sixth of
# its budget on the 200 000 photons of its first build; on double_slabs
# 100 000 let 16 of 24 trainings reach 3 spp against 5, MSE 1.45x lower
# (docs/results.md, forty-first and forty-second sessions)
PHOTON_GUIDE_FIRST = 4
# Lobes anchored at a point along their sample's omega_D, at this multiple of
# the distance to its light point, and aimed from the query's x_D
# (lobe_anchor; design-notes "Anchored lobes"); 0: centred on omega_D, the
# paper's lobes
LOBE_ANCHOR = 0.0

# Time of one tried chain vertex (a traced seed vertex or a line-search try's
# reprojected one) in units of one path-tracer ray: bench/step_cost.py
# ("ratio per tried vertex") measured 3.1 (sphere), 1.9 (double_slabs), 1.7
# (chain_length_4), 2.1 (emitter_size_003) and 2.0 (visibility_4); the median.
TRY_COST = 2.0
# A line-search limit is used only where it promises at least this much lower
# variance x work than the full search (the prediction is from a few spp).
LIMIT_MARGIN = 0.05
HALVING_LIMITS = range(11)   # the limits the core counts (kHalvingSlots - 1)


def _anchor_param(v) -> float:
    """lobe_anchor: a number in [0, 1e6] (0: off) or "auto" (per leaf; the core's -1)."""
    if isinstance(v, str) and v.strip().lower() == "auto":
        return -1.0
    try:
        a = float(v)
    except (TypeError, ValueError):
        a = math.nan
    if isinstance(v, bool) or not (0.0 <= a <= 1e6):
        raise RenderError(f"lobe_anchor must be a number in [0, 1e6] or auto, got {v!r}")
    return a


def _count_param(name: str, v) -> float:
    """A parameter that is a count of samples: a number >= 0 (not a boolean:
    float(True) would be 1), else a RenderError naming it."""
    try:
        if isinstance(v, (bool, np.bool_)):
            raise TypeError
        x = float(v)
    except (TypeError, ValueError):
        raise RenderError(f"{name} must be a number, got {v!r}") from None
    if not x >= 0.0:
        raise RenderError(f"{name} must be >= 0, got {x}")
    return x


def choose_step_halvings(stats: dict, n: int, variance: float, work: float, m_scale: float,
                         s_scale: float, w_scale: float = 1.0,
                         margin: float = LIMIT_MARGIN) -> tuple[int, dict]:
    """The render's line-search limit (`step_halvings`) from training passes
    run with count_limits (Stats limit_*, summed over n spp).

    Under limit H the chain estimates' second moment at rate 1 changes by dM_H,
    the path tracer's shares of shared paths (b / (a P + b) moves with P) by
    dP_H, and the walks' steps by dS_H (estimates) and dT_H (the path tracer's
    weight rounds): ChainEstimator::tally_limits gives the limited estimator's
    own expectations from the full search's walks and extra Bernoulli rounds.
    The mean does not change (every limit is unbiased), so, to first order
    (cross terms left out), the render's variance x work (`variance`, `work`:
    a sample's, summed over pixels, at the render's rates; with learned rates
    their objective's weighted variance) changes by
        r_H = (1 + (m_scale dM_H + w_scale dP_H) / (n variance))
              (1 + TRY_COST (s_scale dS_H + dT_H) / (n work)),
    the scales carrying the training's rate over to the render's (1/q, 1, 1 at
    one fixed rate q; chain_rates.learn_rates for learned ones). The H with the
    smallest r_H is used if r_H < 1 - margin, else the full search (-1).
    Returns (H, info)."""
    info: dict[str, Any] = {"step_halvings_mode": "auto", "step_halvings": -1, "step_halvings_predicted": 1.0}

    def delta(key: str, h: int) -> float:
        full = stats.get(f"{key}_full", 0.0)
        return stats.get(f"{key}_{h}", full) - full

    if n < 1 or not (variance > 0.0) or not (work > 0.0) or not (stats.get("limit_steps_full", 0.0) > 0.0):
        return -1, info
    ratios, dv, dw = [], [], []
    for h in HALVING_LIMITS:
        if stats.get(f"limit_censored_{h}", 0.0) > 0.0:
            # some count ran into the extra rounds' cap: H finds solutions far
            # less often than the search counted with; not a candidate
            ratios.append(float("inf")), dv.append(float("inf")), dw.append(0.0)
            continue
        dv.append((m_scale * delta("limit_m2", h) + w_scale * delta("limit_pt_m2", h)) / n / variance)
        dw.append(TRY_COST * (s_scale * delta("limit_steps", h) + delta("limit_pt_steps", h)) / n / work)
        r = (1.0 + dv[-1]) * (1.0 + dw[-1])
        ratios.append(float(r) if np.isfinite(r) else float("inf"))
    best = int(np.argmin(ratios))
    info["step_halvings_ratios"] = [round(r, 4) if np.isfinite(r) else None for r in ratios]
    # the predicted relative changes of variance and of work, per limit (None: censored)
    info["step_halvings_dvariance"] = [round(float(x), 4) if np.isfinite(x) else None for x in dv]
    info["step_halvings_dwork"] = [round(float(x), 4) for x in dw]
    if ratios[best] < 1.0 - margin:
        info.update(step_halvings=best, step_halvings_predicted=ratios[best])
        return best, info
    return -1, info


def _learn_photon_rate(core, scene, params: dict, keys: list[str], guide, seed: int, threads: int | None,
                       maps: dict) -> dict:
    """The photons per camera sample for the render (Eq. 5), set in params as
    the rate of the tracer's mode (light_trace, or light_trace_glossy) if that
    is among the `keys` asked to learn ("auto"), from a pilot pass with the
    render's integrator and maps: PHOTON_PILOT_SPP camera samples per pixel
    (their variance) and PHOTON_PILOT photons per camera sample of the pilot
    (at least 1 and at most 64 per pixel and sample; their splats' moments),
    and the work of both (ray units). Its image is not used (the rate must not
    depend on the render's own samples); its pixel positions are independent
    ones even in a stratified render, whose per-pixel Sobol shift would give
    it the render's first two (and two stratified samples would overstate one
    sample's variance). Where the render traces no photons, nothing is run."""
    from mpg import _core

    cam = scene.desc.camera
    npix = int(cam.crop[2]) * int(cam.crop[3])
    pilot_rate = min(64.0, max(1.0, PHOTON_PILOT / npix))   # (64: the core's most per sample)
    # (delta_split_sobol off: the same seed would put the pilot's extra paths
    # on the render's own first points of each pixel's sequence)
    integ = _core.make_integrator(core, "mpg", dict(params, guide=guide, record=False, delta_split_sobol=False,
                                                    **{key: pilot_rate for key in keys}))
    # (the rate of the tracer's mode: a number given for it is used as is)
    key = "light_trace_glossy" if integ.light_trace_glossy_on else "light_trace"
    if not integ.light_tracer_on or key not in keys:
        return {}
    t = _time.monotonic()
    job = _core.RenderJob(core, integ, PHOTON_PILOT_SPP, seed, 3_000_000, threads or 0, **maps)
    while not job.wait(0.05):
        pass
    r = job.result()
    if r["cancelled"] or r["lt_photons"] <= 0:
        return {}
    # a camera sample's variance as the render's are (its rates, splits and
    # traces; the training passes' own, without the splits, at the training
    # rate and with the early iterations' guides, gave rates 3-16x lower:
    # docs/results.md, twenty-third session)
    cam_var = float(np.mean(_sample_variance(r["sum"], r["sum_sq"], float(PHOTON_PILOT_SPP))))
    # the work of the pass's camera samples and of its photons (ray units, as
    # the rates' model counts: chain_rates._costs)
    rs = r["stats"]
    work = sum(rs.get(k, 0.0) for k in ("rays", "shadow_rays", "camera_rays", "lt_rays"))
    lt_cost = float(r["lt_work_rays"]) + STEP_COST * float(r["lt_work_walk_steps"])
    cam_cost = max(work + STEP_COST * rs.get("walk_steps", 0.0) - lt_cost, 0.0) / (npix * PHOTON_PILOT_SPP)
    rate, info = learn_photon_rate(cam_var, cam_cost, r["lt_sum"], r["lt_sum_sq"], int(r["lt_photons"]),
                                   lt_cost, DEFAULT_PHOTON_RATE)
    params[key] = rate
    info["seconds_photon_pilot"] = _time.monotonic() - t
    info["seconds_photon_pilot_pass"] = float(r["seconds"])
    info["photon_pilot"] = int(r["lt_photons"])
    return info


def _order_free_mean(w: np.ndarray) -> float:
    """The mean of `w` whatever its order (sorted, summed in double)."""
    return float(np.sum(np.sort(np.asarray(w, dtype=np.float64))) / max(len(w), 1))


def _training_continues(mode: bool | str, spp_train: int) -> bool:
    """Whether the last training iteration continues to the training budget
    (training_continue: True always, as MPG Sec. 5.8; "auto" only after
    fewer than 2 training spp, which learn no map; False never)."""
    return mode is True or (mode == "auto" and spp_train < 2)


def _continuation_deadline(budget_t: float, time: float, spp_train: int) -> float:
    """The training time (on the training's clock, training_clock) a
    continuation's pass may run to: the training budget, or, while the
    training has fewer than TRAINING_MIN_SPP spp (no map), up to twice it
    and at most TRAINING_MAX_FRACTION of the render's time."""
    if spp_train >= TRAINING_MIN_SPP:
        return budget_t
    return min(2.0 * budget_t, max(budget_t, TRAINING_MAX_FRACTION * time))


def _training_continue_param(v, as_bool) -> bool | str:
    """training_continue: "auto" or a boolean (as_bool: render's parser),
    else a RenderError naming it."""
    if isinstance(v, str) and v.strip().lower() == "auto":
        return "auto"
    try:
        return as_bool("training_continue", v)
    except RenderError:
        raise RenderError(f"training_continue must be auto, true or false, got '{v}'") from None


def _handoff_all_param(v) -> int | None:
    """handoff_all: "auto" (None) or a count of guided traces in 0..64, else
    a RenderError naming it."""
    if isinstance(v, str) and v.strip().lower() == "auto":
        return None
    try:
        k = _count_param("handoff_all", v)   # (a number >= 0; NaN fails it)
    except RenderError:
        k = -1.0
    if not (0 <= k <= 64 and k.is_integer()):
        raise RenderError(f"handoff_all must be auto or a count of guided traces in 0..64, got {v!r}")
    return int(k)


def handoff_all_deep_map(q: np.ndarray, deep: float) -> np.ndarray | None:
    """handoff_all's deep_rate_map from the learned rates q: the later
    separators at min(q, handoff_deep) where q > 0, at handoff_deep where the
    maps handed the pixel to the path tracer (q = 0); None at deep 0 (no
    estimator there)."""
    if not deep > 0.0:
        return None
    return np.where(q > 0.0, np.minimum(q, deep), deep).astype(np.float32)


def _handoff_all_auto(rate_info: dict) -> tuple[int, float | None]:
    """handoff_all=auto's choice: (HANDOFF_ALL_AUTO_K, or 0 for the learned
    maps; the ratio it rests on), from the rates' model of every chain pixel
    at rate 0 with HANDOFF_ALL_AUTO_K traces against the learned maps' (F =
    mean(wV) mean(C); chain_rates.learn_rates_traced's chain_rate_model_*):
    the traces where that ratio is at most HANDOFF_ALL_AUTO_MAX. No model of
    them (no hand-off yet, no trace records, a mean at or below 0): the
    learned maps."""
    k = HANDOFF_ALL_AUTO_K
    v, c = rate_info.get("chain_rate_model_v"), rate_info.get("chain_rate_model_c")
    vk, ck = rate_info.get(f"chain_rate_model_v_all{k}"), rate_info.get(f"chain_rate_model_c_all{k}")
    # (a model at or below 0 is no model: chain_rates' model_f never chooses it)
    if None in (v, c, vk, ck) or not (v > 0.0 and c > 0.0 and vk > 0.0 and ck > 0.0):
        return 0, None
    ratio = float(vk * ck / (v * c))
    if not np.isfinite(ratio):
        return 0, None
    return (k if ratio <= HANDOFF_ALL_AUTO_MAX else 0), ratio


def render_mpg(scene, params: dict, warnings: list[str], spp: int | None, time: float | None,
               seed: int, threads: int | None, progress: bool | None, sampler: str = "independent",
               record_classes: bool = False):
    from mpg import _core
    from mpg.render import _as_bool, render

    frac = float(params.pop("training_fraction", 0.3))
    # light_trace / light_trace_glossy "auto" (mpg's default): the photons per
    # camera sample are learned after training (chain_rates.learn_photon_rate,
    # Eq. 5); the training passes' integrators keep the core's default rate
    # (> 0: the same paths are left to the photons), a number is used as given
    photon_auto = [key for key in ("light_trace", "light_trace_glossy")
                   if str(params.get(key, "auto")).strip().lower() == "auto"]
    for key in photon_auto:
        params.pop(key, None)
    # alpha of Eq. 13 in the render (guide_fraction) and in the training passes
    params.setdefault("guide_fraction", GUIDE_FRACTION)
    if not 0.0 <= float(params["guide_fraction"]) < 1.0:
        raise RenderError(f"guide_fraction must be in [0, 1), got {params['guide_fraction']}")
    train_alpha = float(params.pop("training_guide_fraction", params["guide_fraction"]))
    if not 0.0 <= train_alpha < 1.0:
        raise RenderError(f"training_guide_fraction must be in [0, 1), got {train_alpha}")
    c = float(params.pop("stree_c", 1.0))
    eps = float(params.pop("stree_epsilon", 0.1))
    # Ablations (paper Fig. 14, supplemental Figs. 1-2): spatial filter,
    # split threshold, spatial structure (STree or exact kNN).
    structure_kw = dict(
        filter=str(params.pop("stree_filter", "nearest")),
        threshold=int(params.pop("stree_threshold", 0)),
        structure=str(params.pop("guide_structure", "stree")),
        knn_k=int(params.pop("knn_k", 0)),
        # lobes anchored at x_D + omega_D * a * |x_L - x_D| and aimed from the
        # query's x_D (design-notes "Anchored lobes"); 0: centred on omega_D
        anchor=_anchor_param(params.pop("lobe_anchor", LOBE_ANCHOR)),
    )
    # chain_rate: a number (one rate, as sms_star's) or "auto" (the default): rates
    # per pixel learned from the training passes, which run at chain_rate_train
    # (mpg.chain_rates; design-notes "Chain rates per pixel").
    rate = params.pop("chain_rate", "auto")
    q_min = float(params.pop("chain_rate_min", 1.0 / 32))
    q_train = float(params.pop("chain_rate_train", 0.125))
    objective = str(params.pop("chain_rate_objective", "relmse"))
    # chain_handoff: a pixel may get rate 0, the path tracer alone (mpg.chain_rates, Eq. 2)
    handoff_given = "chain_handoff" in params
    handoff = bool(params.pop("chain_handoff", True))
    handoff_asked_off = not handoff
    handoff_asked = handoff_given and handoff   # (on whatever the training's length)
    # ... where the chains' second moment is below this fraction of the pixel's
    # own variance per sample (or the path tracer found their light often: mpg.chain_rates)
    negligible = float(params.pop("chain_handoff_negligible", HANDOFF_NEGLIGIBLE))
    if not 0.0 <= negligible <= 1.0:
        raise RenderError(f"chain_handoff_negligible must be in [0, 1], got {negligible}")
    if objective not in ("mse", "relmse"):
        raise RenderError(f"chain_rate_objective must be 'mse' or 'relmse', got '{objective}'")
    auto = rate == "auto"   # render() turned any other value into a float or an error
    # delta_split: "auto" (learned with the rates, together with them under
    # joint_maps), or k camera paths per sample
    # for the light seen through delta scattering only everywhere (1: off)
    split_given = "delta_split" in params
    split = _split_setting("delta_split", params.pop("delta_split", "auto"), ("auto",))
    # delta_branch: the split's extra paths follow both lobes at their first N
    # two-lobe delta vertices (design-notes "Branching the paths of the light
    # seen in the glass"); mpg's default, the baselines (path, sms*) keep 0
    params.setdefault("delta_branch", DELTA_BRANCH)
    params.setdefault("delta_split_sobol", DELTA_SPLIT_SOBOL)
    params.setdefault("max_chain", MAX_CHAIN)
    # pixel_split: "mse" (PIXEL_SPLIT, the default) or "relmse" (learned with the
    # rates for that error: each sample of a pixel the mean of k camera samples),
    # "handoff", k everywhere, or "off" (mpg.chain_rates.learn_pixel_split)
    psplit_given = "pixel_split" in params
    # pixel_split_online: the learned split refined between the render's passes
    # by the render's own samples (chain_rates.PixelSplitRefiner)
    psplit_online = _as_bool("pixel_split_online", params.pop("pixel_split_online", PIXEL_SPLIT_ONLINE))
    # delta_split_online: the learned delta split checked between the passes
    # against every glass pixel split (chain_rates.DeltaSplitRefiner)
    dsplit_online = _as_bool("delta_split_online", params.pop("delta_split_online", DELTA_SPLIT_ONLINE))
    # delta_split_measured: ... and each split pixel's count by its extra paths' variance
    dsplit_measured = _as_bool("delta_split_measured", params.pop("delta_split_measured", DELTA_SPLIT_MEASURED))
    psplit = _split_setting("pixel_split", params.pop("pixel_split", PIXEL_SPLIT), ("off", "mse", "relmse", "handoff"))
    # ... with its predicted cost per sample capped ("none": no cap)
    psplit_cap = params.pop("pixel_split_max_cost", PIXEL_SPLIT_MAX_COST)
    if isinstance(psplit_cap, str) and psplit_cap.strip().lower() == "none":
        psplit_cap = None
    if psplit_cap is not None:
        try:
            psplit_cap = float(psplit_cap)
        except (TypeError, ValueError):
            raise RenderError(f"pixel_split_max_cost must be a number or 'none', got {psplit_cap!r}") from None
        if not psplit_cap >= 1.0:
            raise RenderError(f"pixel_split_max_cost must be >= 1, got {psplit_cap}")
    if psplit in ("mse", "relmse", "handoff") and not auto and psplit_given:
        warnings.append(f"pixel_split={psplit} needs learned rates (chain_rate=auto); no split")
    if split == "auto" and split_given and not auto:
        warnings.append("delta_split=auto needs learned rates (chain_rate=auto); no split")
    if handoff_given and not auto:
        warnings.append("chain_handoff applies to learned rates only (chain_rate=auto); ignored")
    for nm, v in (("chain_rate_min", q_min), ("chain_rate_train", q_train)):
        if not 1e-3 <= v <= 1.0:
            raise RenderError(f"{nm} must be in [0.001, 1], got {v}")
    params["chain_rate"] = q_train if auto else rate
    # step_halvings: "auto" (the default) chooses the render's line-search limit
    # from the training passes (choose_step_halvings), which start with the full search
    halvings = params.pop("step_halvings", "auto")
    auto_halvings = halvings == "auto"
    # ... re-chosen after each training iteration; with limit_in_training (the
    # default) the next iterations walk under the choice, which can then only
    # tighten (the counts under limit H judge the limits below it alone)
    limit_in_training = _as_bool("limit_in_training", params.pop("limit_in_training", True))
    # known_types: in the render, a chain to an area light whose type (n, tau)
    # its leaf never saw is the path tracer's (design-notes "Chain types the
    # training never saw"); training passes keep every type, to find them
    params["known_types"] = _as_bool("known_types", params.pop("known_types", KNOWN_TYPES))
    params["handoff_guided"] = int(params.pop("handoff_guided", HANDOFF_GUIDED))
    params["handoff_deep"] = float(params.pop("handoff_deep", HANDOFF_DEEP))
    # trace_defensive: each guided trace's direction, with this probability,
    # from the leaf's lobes with kappa capped at trace_defensive_kappa
    # (design-notes "The guided trace's defensive lobes"); checked by the core
    params["trace_defensive"] = float(params.pop("trace_defensive", TRACE_DEFENSIVE))
    params["trace_defensive_kappa"] = float(params.pop("trace_defensive_kappa", TRACE_DEFENSIVE_KAPPA))
    # handoff_all: every pixel handed off with this many guided traces in
    # place of the learned maps (design-notes "Every pixel handed off")
    handoff_all = _handoff_all_param(params.pop("handoff_all", HANDOFF_ALL))
    training_continue = _training_continue_param(params.pop("training_continue", TRAINING_CONTINUE), _as_bool)
    clock = str(params.pop("training_clock", TRAINING_CLOCK)).strip().lower()
    if clock not in ("passes", "wall"):
        raise RenderError(f"training_clock must be 'passes' or 'wall', got '{clock}'")
    # ... and its later separators at the learned rates (where positive)
    handoff_all_deep = _as_bool("handoff_all_deep", params.pop("handoff_all_deep", HANDOFF_ALL_DEEP))
    # learn_trace: the training passes also record each sample's value with the
    # guided trace (Stats::record_trace), and the learned rates choose per pixel
    # between the path tracer alone and the path tracer with the trace at rate
    # 0 (chain_rates.learn_rates_traced); off: the trace runs in every rate-0
    # pixel whose chain light is not negligible (chain_rates.guided_trace_map)
    asked_trace = "learn_trace" in params
    learn_trace = _as_bool("learn_trace", params.pop("learn_trace", LEARN_TRACE))
    trace_tails = _as_bool("trace_tails", params.pop("trace_tails", TRACE_TAILS))
    # joint_maps: the rates, traces and delta split learned together
    # (chain_rates.learn_jointly); off: one after the other
    joint = _as_bool("joint_maps", params.pop("joint_maps", JOINT_MAPS))
    # delta_plain: the training records where the trees keep the lobe choice's
    # variance and the split takes plain paths there (chain_rates.learn_delta_split)
    plain = _as_bool("delta_plain", params.pop("delta_plain", DELTA_PLAIN))
    # trace_min_hits: the samples with chain light a trace form's window needs
    # (chain_rates.learn_rates_traced)
    asked_hits = "trace_min_hits" in params
    trace_min_hits = params.pop("trace_min_hits", TRACE_MIN_HITS)
    trace_min_hits = None if trace_min_hits is None else _count_param("trace_min_hits", trace_min_hits)
    # joint_min_samples: the effective samples of the light in the glass a
    # window needs for its split to count in what the rates see taken away
    # (chain_rates.learn_jointly)
    asked_min_samples = "joint_min_samples" in params
    joint_min_samples = params.pop("joint_min_samples", JOINT_MIN_SAMPLES)
    joint_min_samples = _count_param("joint_min_samples", joint_min_samples)
    if learn_trace and not auto:
        if asked_trace:   # (the default's learn_trace simply has nothing to do at a fixed rate)
            warnings.append("learn_trace needs learned rates (chain_rate=auto); ignored")
        learn_trace = False
    if joint and not (auto and split == "auto"):
        warnings.append("joint_maps needs learned rates and delta_split=auto; ignored")
    if asked_min_samples and not (joint and auto and split == "auto"):
        warnings.append("joint_min_samples applies to joint_maps only; ignored")
    params["step_halvings"] = -1 if auto_halvings else int(halvings)
    init = str(params.pop("init", "surface"))
    n_photons = int(params.pop("photons", 200_000))
    pg = _count_param("photon_guide", params.pop("photon_guide", PHOTON_GUIDE))
    if pg != int(pg):
        raise RenderError(f"photon_guide must be a whole number of photons (0: off), got {pg}")
    n_photon_guide = int(pg)
    if not 0.0 <= frac < 1.0:
        raise RenderError(f"training_fraction must be in [0, 1), got {frac}")
    if init not in ("surface", "photon"):
        raise RenderError(f"init must be 'surface' or 'photon', got '{init}'")
    if n_photons < 1:
        raise RenderError(f"photons must be >= 1, got {n_photons}")
    try:   # the core's own range checks, before any training work
        _core.check_guide_config(c=c, epsilon=eps, **structure_kw)
    except ValueError as e:
        raise RenderError(str(e)) from None
    core = scene.core
    bmin, bmax = core.bbox
    show = (sys.stderr.isatty() if progress is None else progress)
    t0 = _time.monotonic()
    guide = None
    spp_train = 0
    iterations = 0
    training_cancelled = 0   # (training passes cancelled at the budget: their samples lost)
    training_continued = training_continued_spp = 0   # (the last iteration's passes after it, TRAINING_CONTINUE)
    samples_last = 0
    build_seconds = 0.0
    leaves = 0
    # Effects follow the scene: no caster or no chain emitter -> no training at all.
    try:   # the core's own parameter checks (e.g. chain_rate), as a clear error
        probe = _core.make_integrator(core, "mpg", dict(params, record=True))
    except ValueError as e:
        raise RenderError(str(e)) from None

    # photon_guide: photons traced within the training's budget, whose
    # sub-path samples join every guide the training builds (design-notes
    # "Photons in every guide"), their weights scaled to the mean weight of
    # that iteration's samples; not the photon initialisation's guide
    # (init=photon: the initial photons alone). Grown over the builds
    # (PHOTON_GUIDE_FIRST; design-notes "The photon guide grown over the
    # builds"): build b holds photons [0, N min(1, 2^b / FIRST)) of one
    # N-photon trace, each build tracing only the range it adds.
    pg_state: dict[str, Any] = {"bufs": [], "weights": [], "traced": 0, "builds": 0, "mean": 0.0,
                                "seconds": 0.0, "in_last": 0}

    def photon_guide_want(builds: int) -> int:
        """The photons the guide holds at its build number `builds` (from 0)."""
        share = min(1.0, 2.0 ** builds / PHOTON_GUIDE_FIRST)
        return n_photon_guide if share >= 1.0 else max(1, int(n_photon_guide * share))

    def photon_guide_next_seconds() -> float:
        """What the next build's photons will take to trace, at the speed seen
        so far (0 before any: the first build's are in the training's clock
        anyway, and a continuation only follows a build)."""
        if n_photon_guide <= 0 or pg_state["traced"] <= 0:
            return 0.0
        more = photon_guide_want(pg_state["builds"]) - pg_state["traced"]
        return max(more, 0) * pg_state["seconds"] / pg_state["traced"]

    def photon_guide_buffers() -> list:
        """The photon guide's buffers for the next build (grown to its share)."""
        if n_photon_guide <= 0:
            return []
        want = photon_guide_want(pg_state["builds"])
        pg_state["builds"] += 1
        if want > pg_state["traced"]:
            tp = _time.monotonic()
            b = probe.trace_photons(n_photon_guide, (seed * 0x9E3779B97F4A7C15 + 0x5EED) % 2**64,
                                    threads=threads or 0, begin=pg_state["traced"], end=want)
            pg_state["seconds"] += _time.monotonic() - tp
            pg_state["traced"] = want
            if len(b) > 0:
                pg_state["bufs"].append(b)
                pg_state["weights"].append(b.arrays()["weight"])   # (each range's, read once)
                # (the mean of every sample so far, whatever their order or ranges)
                pg_state["mean"] = _order_free_mean(np.concatenate(pg_state["weights"]))
        return list(pg_state["bufs"])

    def build(buf, photons: bool = True):
        """A guide from one buffer of sub-path samples, or a list of them (one
        training iteration's passes), with the photon guide's samples."""
        state = _core.GuidingState()
        bufs = list(buf) if isinstance(buf, (list, tuple)) else [buf]
        count = sum(len(b) for b in bufs)
        pguide = photon_guide_buffers() if photons and count > 0 else []
        pg_state["in_last"] = sum(len(b) for b in pguide)   # (the newest guide's photon samples)
        if pguide:
            # (any positive scale leaves the image unbiased: the guide only
            # chooses seeds, and the estimator divides by the mixture it samples)
            # (sorted, in double: the buffer's order depends on which thread
            # ran which tile, and the scale must not, or the image would)
            scale = _order_free_mean(np.concatenate([b.arrays()["weight"] for b in bufs if len(b) > 0])) / \
                pg_state["mean"]
            bufs.extend(b.scaled(scale) for b in pguide)
        state.build_from(bufs, bmin, bmax, c=c, epsilon=eps, threads=threads or 2, **structure_kw)
        return state

    photon_samples = 0
    seconds_photons = 0.0
    costs = None
    if handoff and probe.chains_delta_lights:
        # the path tracer cannot reach a point or spot light through a chain:
        # rate 0 would lose that light (the core refuses such a map)
        handoff = False
        handoff_note = "off: the scene has a point or spot chain light"
    else:
        handoff_note = "on" if handoff else "off"
    # (after the hand-off's own switch: a point or spot chain light turns it off)
    if asked_hits and not (learn_trace and handoff and params["handoff_guided"] > 0):
        warnings.append("trace_min_hits applies to learned traces only "
                        "(learn_trace, chain_handoff, handoff_guided > 0); ignored")
    # the training samples' sums (without learned rates: with them, the rates'
    # accumulator has them) and stats, for the line-search limit
    tsum = tsum2 = None
    tstats: dict[str, float] = {}
    tstats_n = 0
    halvings_history: list[int] = []
    halvings_info: dict[str, Any] = {"step_halvings": params["step_halvings"],
                                     "step_halvings_mode": "auto" if auto_halvings else "fixed"}
    if auto_halvings:
        halvings_info["step_halvings_predicted"] = 1.0

    def handoff_now() -> bool:
        """The hand-off with the training so far: on where asked for, by default
        from HANDOFF_MIN_TRAINING training spp on."""
        return handoff and (handoff_asked or costs is None or costs.n >= HANDOFF_MIN_TRAINING)

    def decide_halvings(counts: dict, n: int, tsum, tsum2, n_all: int):
        """(H, info) from `counts` (limit_* and work stats over n spp) and the
        training so far; None while too little is known."""
        if costs is not None:
            if costs.n < 2:
                return None
            qm, ri = learn_rates(costs, q_min=q_min, objective=objective, handoff=handoff_now(),
                                 negligible=negligible)
            if not ri.get("chain_rate_learned"):
                return None
            # the learned rates' model: mean(wV), mean(C) over pixels at the render's map
            pixels = float(qm.size)
            return choose_step_halvings(counts, n, ri["chain_rate_model_v"] * pixels,
                                        ri["chain_rate_model_c"] * pixels, ri["chain_rate_m_scale"],
                                        ri["chain_rate_s_scale"], ri["chain_rate_w_scale"])
        if tsum is None or n_all < 2:
            return None
        # one rate q in training and render: the training samples' own variance and work
        variance = float(np.sum(_sample_variance(tsum, tsum2, n_all)))
        work = (counts.get("rays", 0.0) + STEP_COST * counts.get("walk_steps", 0.0)) / n
        return choose_step_halvings(counts, n, variance, work, 1.0 / float(params["chain_rate"]), 1.0, 1.0)

    train_pass_seconds = 0.0   # the training passes' own wall time (cancelled ones too)
    train_seconds_per_spp = None   # the last training pass's (the render's first pass is sized by it)
    if probe.chains_active and frac > 0.0:
        budget_spp = None if spp is None else max(0, int(frac * spp))
        budget_t = None if time is None else frac * time
        # the training's wall time never passes cap_t (the passes clock's
        # work between passes on top of budget_t; inert for the wall clock)
        cap_t = None if time is None else max(budget_t, TRAINING_MAX_FRACTION * time)

        def used() -> float:
            """The training budget's time used so far, on the training's clock."""
            return train_pass_seconds if clock == "passes" else _time.monotonic() - t0
        if init == "photon":
            # Initial distribution from photons (supplemental Sec. 2) instead of
            # the surface-uniform seeds alone; flux as the weight (Eq. 4).
            tp0 = _time.monotonic()
            buf = probe.trace_photons(n_photons, seed, threads=threads or 0)
            photon_samples = len(buf)
            if photon_samples > 0:
                guide = build(buf, photons=False)
                build_seconds += guide.build_seconds
                leaves = guide.num_leaves
            seconds_photons = _time.monotonic() - tp0
            if show:
                sys.stderr.write(f"mpg: {n_photons} photons -> {photon_samples} sub-path samples, "
                                 f"{leaves} leaves, {seconds_photons:.2f} s\n")
        k = 1
        last_iter_t = last_pass_t = None
        if auto:
            cam = scene.desc.camera
            costs = CostAccumulator((int(cam.crop[3]), int(cam.crop[2])))
        # (a training pass's guided_trace_map of zeros switches its trace records
        # off, Stats::record_trace; only passes that record costs make them)
        no_trace = None if learn_trace or costs is None else np.zeros(costs.chain_m2.shape, dtype=np.float32)

        def training_pass(pass_guide, kp: int, pass_index: int, deadline: float | None = None):
            """One training pass of kp spp with pass_guide (None: the initial
            distribution); its result, or None where it was cancelled at the
            budget (deadline: the seconds it may run to, default the training
            budget; its samples lost). Its cost records and step counts join the
            training's. Training passes run at chain_rate_train under "auto", at
            the render's rate otherwise (measured on sphere, 3 seeds x 30 s, when
            one rate of 1/8 was the default: MSE 0.034 training at 1/8, 0.044 at 1)."""
            nonlocal spp_train, training_cancelled, tsum, tsum2, tstats_n, train_pass_seconds
            integ = _core.make_integrator(core, "mpg", dict(params, record=True, guide=pass_guide, known_types=False,
                                                            count_limits=auto_halvings,
                                                            guide_fraction=train_alpha))
            job = _core.RenderJob(core, integ, kp, seed, pass_index, threads or 0,
                                  record_costs=auto, guided_trace_map=no_trace, light_trace=False,
                                  record_branch=plain)
            until = budget_t if deadline is None else deadline
            used0, pass_t0 = used(), _time.monotonic()   # (the clock before the pass; it runs on in it)
            while not job.wait(0.05):
                now = _time.monotonic()
                if until is not None and (used0 + now - pass_t0 > until or now - t0 > cap_t):
                    job.cancel()
            res = job.result()
            train_pass_seconds += float(res["seconds"])
            if res["cancelled"]:
                training_cancelled += 1
                return None
            spp_train += kp
            if costs is not None:
                costs.add(res, kp, params["chain_rate"])
            if auto_halvings:
                if costs is None:
                    tsum = res["sum"] if tsum is None else tsum + res["sum"]
                    tsum2 = res["sum_sq"] if tsum2 is None else tsum2 + res["sum_sq"]
                for key, v in res["stats"].items():
                    if key.startswith("limit_") or key in ("rays", "walk_steps"):
                        tstats[key] = tstats.get(key, 0.0) + v
                tstats_n += kp
            return res

        def halvings_step() -> None:
            """The step limit chosen from the training so far (auto_halvings)."""
            nonlocal halvings_info, tstats, tstats_n
            if not auto_halvings:
                return
            decided = decide_halvings(tstats, tstats_n, tsum, tsum2, spp_train)
            if decided is not None:
                h, halvings_info = decided
                cur = params["step_halvings"]
                if cur >= 0 and h < 0:
                    # counted under limit cur: no larger limit (nor none) can be judged
                    h = cur
                    halvings_info.update(step_halvings=cur)
                halvings_history.append(h)
                if limit_in_training and h != cur:
                    # the next iterations walk under h; count afresh from them
                    params["step_halvings"] = h
                    tstats, tstats_n = {}, 0

        iter_guide = None
        while True:
            used_t = used()
            if budget_spp is not None and (spp_train + k > budget_spp or spp_train >= budget_spp / 2):
                break
            if budget_t is not None and used_t >= budget_t / 2:
                break
            # nor one that would overrun the budget at the last iteration's speed
            # (it would be cancelled and its samples lost: an iteration with the
            # better guide finds more and longer chains, so it costs more than 2x):
            # twice the last pass, plus the iteration's own work around its pass
            # (the cost records' sums, the step limits' choice: per pixel, not per
            # spp; doubled too, it had stopped the sphere's 1 s training after
            # 1 spp in most fresh processes, leaving the render no maps)
            # (the passes clock: the pass against the budget, and with the work
            # around it against the wall's cap)
            if budget_t is not None and last_iter_t is not None:
                around = max(last_iter_t - last_pass_t, 0.0)
                if used_t + 2.0 * last_pass_t + (0.0 if clock == "passes" else around) > budget_t or \
                        _time.monotonic() - t0 + 2.0 * last_pass_t + around > cap_t:
                    break
            iter_t0 = _time.monotonic()
            r = training_pass(guide, k, 1_000_000 + iterations)
            if r is None:
                break
            iterations += 1
            iter_guide = guide   # (the guide this iteration ran with: a continuation's)
            halvings_step()
            last_iter_t = _time.monotonic() - iter_t0
            last_pass_t = float(r["seconds"])
            train_seconds_per_spp = r["seconds"] / k
            buf = r["subpaths"]
            samples_last = len(buf)
            if samples_last > 0:
                guide = build(buf)
                build_seconds += guide.build_seconds
                leaves = guide.num_leaves
            if show:
                el = _time.monotonic() - t0
                left = (f", {max(0.0, budget_t - used()):.1f} s of training left" if budget_t is not None
                        else f", {max(0, budget_spp - spp_train)} spp of training left")
                sys.stderr.write(f"\rmpg: training iteration {iterations}: {k} spp "
                                 f"({spp_train} in all), {samples_last} sub-path samples, "
                                 f"{leaves} leaves, {el:.1f} s{left}   ")
                sys.stderr.flush()
            k *= 2
        # MPG Sec. 5.8: "when a training iteration is finished, we start a new
        # round if less than half of the training budget is used. Otherwise, we
        # continue the current iteration until the rendering stage starts." So
        # under a time budget the last iteration goes on, with the guide it ran
        # with, in passes of at most its spp sized to the time left (less its
        # own work around a pass and twice its guide's build, for the guide
        # built again at the end from all its samples), until the training
        # budget is spent: always with training_continue true; by default
        # ("auto") only where the iterations end with fewer than 2 spp, which
        # learn no map: the sphere's 1 s training ended after 1 spp (0.14 s of
        # its 0.3 s) in most fresh processes (TRAINING_CONTINUE). A training
        # still under TRAINING_MIN_SPP spp may run past its budget to reach
        # them (at most twice the budget, TRAINING_MAX_FRACTION of the time).
        if _training_continues(training_continue, spp_train) and \
                budget_t is not None and iterations > 0 and training_cancelled == 0:
            k_last = k // 2
            per_spp = max(last_pass_t / k_last, 1e-6)
            around = max(last_iter_t - last_pass_t, 0.0)
            # (and the photons the guide built again adds: the photon guide grows)
            reserve = 2.0 * (guide.build_seconds if guide is not None and samples_last > 0 else 0.0) + \
                photon_guide_next_seconds()
            cont_bufs = [buf]
            while True:
                # (half of the time left, as the render sizes its passes, or the
                # last whole spp that fits: a pass's speed varies, and one
                # cancelled at the budget loses its samples; at the slowest
                # speed seen so far)
                limit = _continuation_deadline(budget_t, time, spp_train)
                wall_left = cap_t - (_time.monotonic() - t0) - around - reserve
                time_left = min(limit - used() - (0.0 if clock == "passes" else around + reserve), wall_left)
                kc = min(k_last, max(int(0.5 * time_left / per_spp), 1 if time_left >= per_spp else 0))
                if budget_spp is not None:
                    kc = min(kc, budget_spp - spp_train)
                if kc < 1:
                    break
                r = training_pass(iter_guide, kc, 2_000_000 + training_continued, deadline=limit)
                if r is None:
                    break
                training_continued += 1
                training_continued_spp += kc
                cont_bufs.append(r["subpaths"])
                per_spp = max(per_spp, float(r["seconds"]) / kc)
            if training_continued > 0:
                halvings_step()
                samples_last = sum(len(b) for b in cont_bufs)
                if samples_last > 0:
                    guide = build(cont_bufs)
                    build_seconds += guide.build_seconds
                    leaves = guide.num_leaves
                if show:
                    sys.stderr.write(f"\rmpg: training iteration {iterations} continued: {training_continued_spp} spp "
                                     f"more ({spp_train} in all), {samples_last} sub-path samples, "
                                     f"{leaves} leaves   ")
                    sys.stderr.flush()
        if show:
            sys.stderr.write("\n")
    rate_info: dict[str, Any] = {}
    qmap = kmap = bmap = None
    split_means = None   # (the means the learned delta split was solved against: DeltaSplitRefiner)
    cam = scene.desc.camera

    def uniform(k: float) -> np.ndarray:
        """A per-pixel map of k everywhere (crop height x width)."""
        return np.full((int(cam.crop[3]), int(cam.crop[2])), float(k), dtype=np.float32)

    def learned(m: np.ndarray, info: dict) -> np.ndarray | None:
        """A learned split map, None when it splits no pixel; its summary joins
        rate_info (the delta split's branch map, info["branch_map"], goes to bmap)."""
        nonlocal bmap, split_means
        info = dict(info)
        b = info.pop("branch_map", None)
        split_means = info.pop("means", split_means)
        rate_info.update(info)
        if not np.any(m > 1):
            return None
        if b is not None:
            bmap = b if not np.all(b > 0) else None   # (None: branched wherever the integrator branches)
        return m

    def branch_where() -> bool | np.ndarray:
        """Where the split's extra paths branch: the learned map, or all (delta_branch > 0) or none."""
        if params["delta_branch"] <= 0:
            return False
        return bmap if bmap is not None else True

    def rates() -> np.ndarray:
        """The render's chain rates per pixel: the learned map, or the one rate."""
        return qmap if qmap is not None else uniform(params["chain_rate"])

    split_wait_warning = None   # (said after handoff_all's choice, which splits every pixel)
    if handoff and not handoff_now():
        handoff = False
        handoff_note = f"off: {costs.n} training spp, fewer than {HANDOFF_MIN_TRAINING}"
        if psplit == "handoff":
            split_wait_warning = (f"pixel_split=handoff splits the pixels handed to the path tracer, and the "
                                  f"hand-off is {handoff_note} (chain_handoff=true keeps it); no split")
        if asked_hits and learn_trace and params["handoff_guided"] > 0:
            warnings.append(f"trace_min_hits applies where the hand-off runs, and it is {handoff_note} "
                            f"(chain_handoff=true keeps it); ignored")
    if costs is not None:
        rate_kw = dict(q_min=q_min, handoff=handoff, negligible=negligible,
                       trace=learn_trace and params["handoff_guided"] > 0, tails=trace_tails,
                       trace_min_hits=trace_min_hits)
        joint_k, kinfo = None, {}
        if joint and split == "auto" and costs.n > 0:
            qmap, tmap, rate_info, joint_k, kinfo = learn_jointly(costs, objective=objective,
                                                                  min_samples=joint_min_samples,
                                                                  branched=params["delta_branch"] > 0, **rate_kw)
        else:
            qmap, tmap, rate_info = learn_rates_traced(costs, objective=objective, **rate_kw)
        if learn_trace:
            rate_info["trace_records"] = float(np.sum(costs.trace_n))   # samples that recorded the traces
        if not rate_info.get("chain_rate_learned"):
            # too little training (< 2 spp): the training rate throughout
            qmap, tmap, rate_info = None, None, {}
        if joint_k is not None and qmap is not None:   # (learned together above)
            kmap = learned(joint_k, kinfo)
        elif split == "auto" and costs.n > 0:
            kmap = learned(*learn_delta_split(costs, rates(), objective=objective,
                                              branched=params["delta_branch"] > 0))
        if kmap is not None and rate_info.get("chain_rate_learned"):
            # the split's effect in the model (delta_split_effect; with
            # joint_maps, dv of the windows with joint_min_samples, as
            # learn_jointly counts it): where the maps were learned one after
            # the other, chain_rate_model_v/_c are the rates' alone and the
            # split takes dv off (V1 clamped at 0) and adds dc; where they were
            # learned together (joint_rounds > 0), v and c hold it already
            dv, dc = delta_split_effect(costs, kmap, objective=objective,
                                        branched=branch_where(),
                                        min_samples=joint_min_samples if joint else 0.0)
            rate_info.update(delta_split_model_dv=dv, delta_split_model_dc=dc)
    if isinstance(split, int) and split > 1:
        kmap, bmap = uniform(split), None
        rate_info.update(delta_split_fraction=1.0, delta_split_mean=float(split))
    # handoff_all: every pixel handed off, in place of the learned maps,
    # decided before the pixel split, the traces' map and the photon pilot,
    # which then see the maps the render runs; it overrides the hand-off's
    # wait for HANDOFF_MIN_TRAINING (asked for explicitly)
    # handoff_all=auto: the traces where the rates' model of them is at most
    # HANDOFF_ALL_AUTO_MAX times its own maps' F (_handoff_all_auto)
    auto_all = handoff_all is None
    auto_k, auto_ratio = _handoff_all_auto(rate_info) if qmap is not None else (0, None)
    if auto_all:
        handoff_all = auto_k
    handoff_all_info: dict[str, Any] = {"handoff_all": handoff_all, "handoff_all_mode": "auto" if auto_all else "fixed"}
    if auto_ratio is not None:
        handoff_all_info["handoff_all_model_ratio"] = auto_ratio
    dmap = None   # (handoff_all's rates at the later separators)
    if handoff_all > 0:
        why = None
        if qmap is None:
            why = "it replaces learned rates (chain_rate=auto, 2 or more training spp), and there are none"
        elif probe.chains_delta_lights:
            why = ("the scene has a point or spot chain light, which the path tracer cannot reach "
                   "through a chain")
        elif handoff_asked_off:
            why = "chain_handoff is false"
        elif params["handoff_guided"] <= 0:
            why = "handoff_guided is 0 (no guided traces)"
        if why is not None:
            if not auto_all:   # (auto: the learned maps, said by handoff_all 0)
                warnings.append(f"handoff_all={handoff_all} is ignored: {why}")
            handoff_all_info["handoff_all"] = 0
        else:   # (the learned maps' summary, chain_rate_*, stays: what the training chose)
            if handoff_all_deep:
                dmap = handoff_all_deep_map(qmap, params["handoff_deep"])
            handoff_all_info["handoff_all_deep"] = dmap is not None
            qmap = np.zeros_like(qmap)
            handoff_note = f"all: handoff_all={'auto, ' if auto_all else ''}{handoff_all}"
    if split_wait_warning is not None and handoff_all_info["handoff_all"] == 0:
        warnings.append(split_wait_warning)
    smap = None
    refiner = None
    # (a training of 1 spp: no map from it, but the refiner's costs, and the
    # render's own samples learn the split; PixelSplitRefiner)
    if psplit in ("mse", "relmse", "handoff") and costs is not None and costs.n >= 1:
        split_kw = dict(objective="mse" if psplit == "handoff" else psplit,
                        where=(rates() <= 0.0) if psplit == "handoff" else None,
                        branched=branch_where(), max_cost=psplit_cap)
        splitter = PixelSplitRefiner(costs, rates(), kmap if kmap is not None else uniform(1), **split_kw)
        smap = learned(*splitter.solve())   # (learn_pixel_split's map)
        if psplit_online and (split_kw["where"] is None or np.any(split_kw["where"])):
            refiner = splitter   # refined between the render's passes by its own samples
    elif isinstance(psplit, int) and psplit > 1:
        smap = uniform(psplit)
        rate_info.update(pixel_split_fraction=1.0, pixel_split_mean=float(psplit))
    # The learned delta split checked by the render's own samples (before the
    # pixel split's refinement, whose model it then updates)
    delta_refine = None
    if dsplit_online and split == "auto" and split_means is not None and costs is not None and costs.n >= 2:
        drefiner = DeltaSplitRefiner(costs, split_means, objective=objective,
                                     branched=params["delta_branch"] > 0, base=kmap)

        glass_ran = [0]   # (the map the pixel split's model last saw: 0 the training's, 1 the glass)

        def delta_refine(ds, ds2, n, paths=None):
            k, b, info = drefiner.update(ds, ds2, n, paths if dsplit_measured else None)
            # (the pixel split's model sees the split's counts where they changed)
            if refiner is not None and (info["delta_split_online_glass"] != glass_ran[0]
                                        or info.get("delta_split_online_measured", 0.0) > 0.0):
                refiner.set_delta_split(k if k is not None else uniform(1),
                                        (b if b is not None else True) if params["delta_branch"] > 0 else False)
                glass_ran[0] = info["delta_split_online_glass"]
            return k, b, info
    if auto_halvings:
        params["step_halvings"] = halvings_info["step_halvings"]
    seconds_training = _time.monotonic() - t0
    rest_spp = None if spp is None else max(1, spp - spp_train)
    rest_t = None if time is None else max(0.05, time - seconds_training)
    gmap = None
    if handoff_all_info["handoff_all"] > 0:
        gmap = np.full(qmap.shape, float(handoff_all), dtype=np.float32)
        rate_info.update(guided_trace_fraction=1.0, guided_trace_mean_k=float(handoff_all))
    elif params.get("handoff_guided") and qmap is not None and np.any(qmap <= 0.0):
        if learn_trace and float(np.sum(costs.trace_rays)) > 0.0:
            # the training measured the trace: the rates chose where it pays
            gmap = tmap   # (its traces per pixel: 0 or one of chain_rates.TRACE_KS)
        else:   # (no guide before the last training pass) where the chains' light is not negligible
            gmap = guided_trace_map(costs, negligible=negligible) * float(params["handoff_guided"])
        rate_info["guided_trace_fraction"] = float(np.mean(gmap[qmap <= 0.0] > 0))
        traced = gmap[(qmap <= 0.0) & (gmap > 0)]
        rate_info["guided_trace_mean_k"] = float(np.mean(traced)) if traced.size else 0.0
    photon_info: dict[str, Any] = {}
    if photon_auto and spp_train >= PHOTON_PILOT_MIN_TRAINING:
        photon_info = _learn_photon_rate(core, scene, params, photon_auto, guide, seed, threads,
                                         dict(chain_rate_map=qmap, delta_split_map=kmap, pixel_split_map=smap,
                                              guided_trace_map=gmap, delta_branch_map=bmap, deep_rate_map=dmap))
        # (the pilot's time comes off the render's budget; seconds_training
        # includes it, seconds_photon_pilot says how much)
        seconds_training = _time.monotonic() - t0
        rest_t = None if time is None else max(0.05, time - seconds_training)
    # The render's first pass is sized by the last training pass's speed, or
    # the photon pilot's where that ran and was slower (it runs the render's
    # integrator, maps and photons), times PASS_HINT_MARGIN: a training pass
    # runs no photons, splits or traces (double_slabs at 5 s: 38.6 ms a spp
    # in training, 45 in the render), and the first pass is never cancelled.
    pass_hint = train_seconds_per_spp
    if pass_hint is not None and photon_info.get("seconds_photon_pilot"):
        pass_hint = max(pass_hint, photon_info["seconds_photon_pilot"] / PHOTON_PILOT_SPP)
    if pass_hint is not None:
        pass_hint *= PASS_HINT_MARGIN
    img = render(scene, integrator=dict(params, type="mpg", guide=guide, record=False),
                 spp=rest_spp, time=rest_t, seed=seed, threads=threads, progress=progress,
                 chain_rate_map=qmap, delta_split_map=kmap, pixel_split_map=smap, sampler=sampler,
                 guided_trace_map=gmap, record_classes=record_classes, delta_branch_map=bmap,
                 deep_rate_map=dmap,
                 seconds_per_spp=pass_hint, pixel_split_refine=None if refiner is None else refiner.update,
                 delta_split_refine=delta_refine)
    st: dict[str, Any] = img.stats
    st["warnings"] = list(dict.fromkeys(st.get("warnings", []) + warnings))
    st["integrator"] = "mpg"
    st["integrator_params"] = {k: v for k, v in params.items() if k != "guide"}
    st["integrator_params"]["chain_rate"] = rate
    st["integrator_params"]["step_halvings"] = halvings
    for key in photon_auto:
        st["integrator_params"][key] = "auto"   # (the learned rate: light_trace_learned)
    st.update(halvings_info)
    if auto_halvings:
        # (the choice after each training iteration, and after its continuation)
        st["step_halvings_history"] = halvings_history
    st.update(handoff_all_info)
    st["chain_rate_mode"] = "per-pixel" if qmap is not None else "fixed"
    st["chain_handoff"] = handoff_note if qmap is not None else "off"
    # per-pixel: mean over the pixels with chain work; fixed: the rate used
    st["chain_rate_mean"] = float(params["chain_rate"])
    st.update(rate_info)
    st.update(photon_info)
    st["spp_training"] = spp_train
    st["spp_rendering"] = img.spp
    st["training_iterations"] = iterations
    st["training_cancelled"] = training_cancelled
    st["training_continued_spp"] = training_continued_spp
    st["training_continue"] = str(training_continue).lower()
    st["training_clock"] = clock
    st["seconds_training"] = seconds_training
    st["seconds_guide_build"] = build_seconds
    st["subpath_samples"] = samples_last
    st["init"] = init
    st["guide_fraction"] = float(params["guide_fraction"])
    st["training_guide_fraction"] = train_alpha
    st["photon_samples"] = photon_samples
    st["photon_guide"] = n_photon_guide
    # (the photons' samples in the final guide: 0 where no training iteration built one)
    st["photon_guide_samples"] = pg_state["in_last"]
    st["photon_guide_traced"] = pg_state["traced"]   # (photons traced: the final guide's, as it grew)
    st["seconds_photon_guide"] = pg_state["seconds"]
    st["seconds_photons"] = seconds_photons
    st["guide_leaves"] = leaves
    st["guide_structure"] = structure_kw["structure"]
    st["lobe_anchor"] = "auto" if structure_kw["anchor"] < 0 else structure_kw["anchor"]
    # (the final guide's leaves that queries reach, with unfiltered samples:
    # the share whose lobes are anchored, and their mean anchor; 0 without a
    # guide, with kNN or with lobe_anchor 0)
    anchors = ([guide.leaf_anchor(i) for i in range(guide.num_leaves) if guide.leaf_active(i)]
               if guide is not None and structure_kw["structure"] == "stree" and structure_kw["anchor"] != 0
               else [])
    st["lobe_anchored_fraction"] = float(np.mean([a > 0 for a in anchors])) if anchors else 0.0
    st["lobe_anchor_mean"] = float(np.mean([a for a in anchors if a > 0])) if any(a > 0 for a in anchors) else 0.0
    st["stree_filter"] = structure_kw["filter"]
    st["guide_bytes"] = (samples_last + st["photon_guide_samples"]) * _core.SUBPATH_SAMPLE_BYTES
    # the final guide's whole memory (its structure, the samples with their
    # filtered copies' indices, every leaf's distribution) and per sample it
    # was built from: guide_bytes above counts the 40-byte samples alone
    # (the guide's own count: the final guide may be an earlier build's, or
    # the photon initialisation's alone)
    st["guide_memory_bytes"] = int(guide.memory_bytes) if guide is not None else 0
    n_built = int(guide.samples_input) if guide is not None else 0
    st["guide_bytes_per_sample"] = st["guide_memory_bytes"] / n_built if n_built else 0.0
    st["seconds"] = _time.monotonic() - t0
    # the core's passes (training, the photon pilot's, the render's) and the
    # rest: the maps' learning, guide builds, photons and bookkeeping between
    # them, while the cores wait (design-notes "Python ↔ C++ boundary")
    st["seconds_passes"] = (st.get("seconds_passes", 0.0) + train_pass_seconds
                            + photon_info.get("seconds_photon_pilot_pass", 0.0))
    st["seconds_between_passes"] = max(st["seconds"] - st["seconds_passes"], 0.0)
    # chain_estimates counts every estimate started, chain_inactive those that
    # selective activation then stopped
    est = st.get("chain_estimates", 0)
    st["activation_rate"] = ((est - st.get("chain_inactive", 0)) / est) if est else 0.0
    split_ran = kmap is not None or st.get("delta_split_paths", 0) > 0   # (or a pass of the check's)
    st["delta_split"] = ("learned" if split == "auto" else str(split)) if split_ran else "off"
    img.chain_rate_map = qmap
    if delta_refine is None:   # (refined: render() set the last ones)
        img.delta_split_map = kmap
        img.delta_branch_map = bmap
    # (on where any pass split: the training's map, or a refined one)
    st["pixel_split"] = str(psplit) if (smap is not None or st.get("pixel_split_samples", 0) > 0) else "off"
    if refiner is None:
        img.pixel_split_map = smap   # (refined: render() set the last one)
    return img
