"""The render loop: passes of C++ work, time budgets, progress, interruption."""

from __future__ import annotations

import difflib
import math
import signal
import sys
import threading
import time as _time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mpg.errors import RenderError
from mpg.image import Image
from mpg.scene.desc import IntegratorDesc, SceneDesc

# Integrators implemented by the core, and the papers' names that map onto
# them until their own implementation lands (kept as hints, with a warning).
IMPLEMENTED = {"path", "sms", "sms_star", "mpg"}
# Image.class_sum's classes in order (Stats::Class; render(record_classes=True))
CLASS_NAMES = ("chain", "shared", "traced", "handed", "unseen", "inactive", "unowned", "delta", "other",
               "glints", "photons")

PATH_PARAMS = {"max_depth", "rr_depth", "hide_emitters", "camera_delta", "delta_branch", "delta_split_sobol"}
CHAIN_PARAMS = {"tau", "max_chain", "continuation", "uniqueness_threshold", "max_trials",
                "threshold", "max_iterations", "min_step", "step_halvings", "form", "glossy_threshold",
                "mis", "mis_rate", "chain_rate", "light_trace", "light_trace_through",
                "light_trace_area", "light_trace_glossy", "glints"}
GUIDE_PARAMS = {"guide", "record", "guide_fraction", "selective", "guide_n", "guide_tau",
                "guide_dir", "training_fraction", "training_guide_fraction", "stree_c", "stree_epsilon", "stree_filter",
                "stree_threshold", "guide_structure", "knn_k", "product", "init", "photons", "photon_guide", "lobe_anchor",
                "chain_rate_min", "chain_rate_train", "chain_rate_objective", "chain_handoff",
                "chain_handoff_negligible",
                "delta_split", "pixel_split", "pixel_split_max_cost", "pixel_split_online", "delta_split_online",
                "delta_split_measured", "limit_in_training", "known_types",
                "handoff_guided", "handoff_deep", "learn_trace", "trace_tails", "joint_maps",
                "trace_min_hits", "joint_min_samples", "delta_plain", "handoff_all", "handoff_all_deep",
                "trace_defensive", "trace_defensive_kappa", "training_continue", "training_clock"}
BOOL_PARAMS = {"hide_emitters", "delta_split_sobol", "light_trace_through", "light_trace_area", "record", "selective", "guide_n", "guide_tau", "guide_dir", "product",
               "mis", "mis_rate", "chain_handoff", "limit_in_training", "known_types",
               "learn_trace", "trace_tails", "joint_maps", "delta_plain", "pixel_split_online", "delta_split_online",
               "delta_split_measured", "handoff_all_deep"}
FALLBACK_TO_PATH = {"volpath", "ptracer", "path_filtered_ss"}
# The SMS paper's integrators, with their parameter names, map onto `sms`.
SMS_PAPER = {"path_sms_ss", "path_sms_ms"}


@dataclass
class Scene:
    """A loaded scene: its description and (built on first use) the C++ scene."""

    desc: SceneDesc
    _core: Any = field(default=None, repr=False)

    @property
    def core(self):
        if self._core is None:
            from mpg.scene.build import build_scene

            self._core = build_scene(self.desc)
        return self._core

    @property
    def warnings(self) -> list[str]:
        return self.desc.warnings


def _resolve_integrator(scene: Scene, integrator) -> tuple[str, dict, list[str]]:
    warnings: list[str] = []
    if integrator is None:
        idesc = scene.desc.integrator
        name, params = idesc.type, dict(idesc.params)
    elif isinstance(integrator, str):
        name, params = integrator, {}
        if scene.desc.integrator.type == integrator:
            params = dict(scene.desc.integrator.params)
        elif "max_depth" in scene.desc.integrator.params:
            params["max_depth"] = scene.desc.integrator.params["max_depth"]
    elif isinstance(integrator, IntegratorDesc):
        name, params = integrator.type, dict(integrator.params)
    elif isinstance(integrator, dict):
        # the scene's path-length settings apply unless the dict overrides them
        params = {k: v for k, v in scene.desc.integrator.params.items() if k in PATH_PARAMS}
        params.update(integrator)
        name = params.pop("type", "path")
        check_param_names(name, integrator.keys())
    else:
        raise RenderError(f"integrator must be a name or a dict, got {type(integrator).__name__}")
    if name == "manifold_path_guiding":
        # the MPG paper's integrator: its knobs are hints (kept), ours take over
        params = {k: v for k, v in params.items() if k in PATH_PARAMS}
        warnings.append("integrator 'manifold_path_guiding' runs as 'mpg' with mpg's defaults")
        name = "mpg"
    if name in SMS_PAPER:
        params = _sms_paper_params(scene, name, params, warnings)
        name = "sms"
    if name in FALLBACK_TO_PATH:
        warnings.append(
            f"integrator '{name}' is not implemented yet; rendering with 'path' "
            f"(max_depth={params.get('max_depth', -1)})"
        )
        name = "path"
    if name not in IMPLEMENTED:
        raise RenderError(
            f"unknown integrator '{name}' (available: {', '.join(sorted(IMPLEMENTED))})"
        )
    allowed = PATH_PARAMS | (CHAIN_PARAMS if name != "path" else set()) | (
        GUIDE_PARAMS if name == "mpg" else set())
    core_params = {k: v for k, v in params.items() if k in allowed}
    for k in ("max_chain", "max_trials", "max_iterations", "step_halvings", "max_depth",
              "rr_depth", "stree_threshold", "knn_k", "photons", "delta_branch", "handoff_guided"):
        if k == "step_halvings" and str(core_params.get(k)).strip().lower() == "auto":
            if name != "mpg" or "guide" in core_params:
                raise RenderError("step_halvings 'auto' is chosen by mpg's training loop; "
                                  f"with {'a given guide' if name == 'mpg' else repr(name)} it must be an integer")
            core_params[k] = "auto"   # mpg: the line-search limit chosen in training (mpg.guiding)
            continue
        if k in core_params:
            try:
                core_params[k] = int(core_params[k])
            except (TypeError, ValueError):
                raise RenderError(f"parameter {k} must be an integer, got '{core_params[k]}'") from None
    for k in ("continuation", "uniqueness_threshold", "threshold", "min_step", "glossy_threshold",
              "guide_fraction", "training_guide_fraction", "training_fraction", "stree_c",
              "stree_epsilon", "chain_rate",
              "chain_rate_min", "chain_rate_train", "chain_handoff_negligible", "light_trace",
              "light_trace_glossy", "glints", "handoff_deep", "trace_defensive", "trace_defensive_kappa"):
        if k == "chain_rate" and name == "mpg" and str(core_params.get(k)).strip().lower() == "auto":
            if "guide" in core_params:
                raise RenderError("chain_rate 'auto' is learned by mpg's training loop; "
                                  "with a given guide, chain_rate must be a number")
            core_params[k] = "auto"   # mpg: rates learned per pixel in training (mpg.chain_rates)
            continue
        if k in ("light_trace", "light_trace_glossy") and str(core_params.get(k)).strip().lower() == "auto":
            if name != "mpg":
                raise RenderError(f"{k} 'auto' is learned by mpg's training loop; with '{name}' it must be "
                                  "a number")
            if "guide" in core_params:
                del core_params[k]   # (a given guide: no training, the core's default rate)
            else:
                core_params[k] = "auto"   # mpg: learned after training (chain_rates.learn_photon_rate)
            continue
        if k in core_params:
            try:
                core_params[k] = float(core_params[k])
            except (TypeError, ValueError):
                raise RenderError(f"parameter {k} must be a number, got '{core_params[k]}'") from None
    for k in BOOL_PARAMS & core_params.keys():
        core_params[k] = _as_bool(k, core_params[k])
    dropped = sorted(k for k in params if k not in allowed and k != "type")
    if dropped:
        warnings.append(f"integrator '{name}' ignores parameter(s) {', '.join(dropped)}")
    return name, core_params, warnings


KNOWN_PARAMS = PATH_PARAMS | CHAIN_PARAMS | GUIDE_PARAMS


def check_param_names(name: str, keys) -> None:
    """Raise RenderError for a parameter name that none of mpg's own integrators
    (path, sms, sms_star, mpg) has: a typo would otherwise run the defaults with
    only a warning. For what a caller typed (a dict given to render, the CLI's -P);
    a scene file's integrator may carry other renderers' parameters and only warns.
    Names that another of mpg's integrators has still only warn ("ignores")."""
    if name not in IMPLEMENTED:
        return   # the papers' integrators (path_sms_ss, manifold_path_guiding, ...) keep their own names
    for k in keys:
        if k == "type" or k in KNOWN_PARAMS:
            continue
        close = difflib.get_close_matches(str(k), sorted(KNOWN_PARAMS), n=3, cutoff=0.6)
        hint = f" (did you mean {' or '.join(close)}?)" if close else ""
        raise RenderError(f"unknown parameter '{k}' for integrator '{name}'{hint}; "
                          f"known: {', '.join(sorted(KNOWN_PARAMS))}")


def _as_bool(name: str, v) -> bool:
    """A boolean parameter from a bool, a number or the strings true/false/1/0/yes/no."""
    if isinstance(v, str):
        t = v.strip().lower()
        if t in ("true", "1", "yes", "on"):
            return True
        if t in ("false", "0", "no", "off"):
            return False
        raise RenderError(f"parameter {name} must be true or false, got '{v}'")
    return bool(v)


def _sms_paper_params(scene: Scene, name: str, params: dict, warnings: list[str]) -> dict:
    """Translate path_sms_ss / path_sms_ms parameters to `sms`'s.

    ss (single scattering): one vertex, R when every smooth specular shape is a
    conductor, T otherwise; ms: `bounces` vertices of that letter."""
    out = {k: v for k, v in params.items() if k in PATH_PARAMS}
    conductors = dielectrics = 0
    for sh in scene.desc.shapes:
        b = sh.bsdf
        while b.type in ("twosided", "normalmap"):
            b = b.params.get("front") or b.params.get("nested")
            if b is None:
                break
        if b is None:
            continue
        conductors += b.type == "conductor"
        dielectrics += b.type == "dielectric"
    letter = "R" if conductors and not dielectrics else "T"
    n = 1 if name == "path_sms_ss" else int(params.get("bounces", 2))
    out["tau"] = letter * n
    if "solver_threshold" in params:
        out["threshold"] = float(params["solver_threshold"])
    for k in ("max_iterations", "uniqueness_threshold", "max_trials"):
        if k in params:
            out[k] = params[k]
    out["max_trials"] = min(int(out.get("max_trials", 100000)), 100000)
    if params.get("halfvector_constraints") in (True, "true"):
        out["form"] = "half_vector"
    warnings.append(f"integrator '{name}' runs as 'sms' with tau='{out['tau']}'")
    return out


class Progress:
    """A one-line progress bar with ETA on stderr (only when it is a terminal)."""

    def __init__(self, enabled: bool | None = None, stream=None):
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty() if enabled is None else enabled
        self._last = 0.0

    def update(self, frac: float, spp_done: int, spp_total: int | None, elapsed: float,
               force: bool = False) -> None:
        if not self.enabled:
            return
        now = _time.monotonic()
        if not force and now - self._last < 0.1:
            return
        self._last = now
        frac = min(max(frac, 0.0), 1.0)
        width = 30
        n = int(round(frac * width))
        eta = (elapsed / frac - elapsed) if frac > 1e-6 else float("nan")
        spp = f"{spp_done}/{spp_total} spp" if spp_total else f"{spp_done} spp"
        eta_s = f"ETA {eta:6.1f}s" if math.isfinite(eta) else "ETA    ?  "
        self.stream.write(f"\r[{'#' * n}{'.' * (width - n)}] {100 * frac:5.1f}%  {spp}  "
                          f"{elapsed:6.1f}s  {eta_s}")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()


# pixel_split_refine's first call: before the first pass after this many spp
REFINE_FIRST = 4
# delta_split_refine's first call (then at twice the spp of its last call
# and with every pixel_split_refine call): the held-out check weighs two
# whole-image sums, which 2 spp already give, and every sample before it
# runs the training's split. From 2 spp rather than 4: the pool 1.24x
# lower at 2 s, chain_length_4 1.07-1.12x higher at 1 s (docs/results.md,
# forty-fourth session)
DELTA_REFINE_FIRST = 2


def pass_schedule(first: int = 1, cap: int = 32):
    """Deterministic spp per pass: 1, 1, 2, 4, ... capped (same spp -> same passes)."""
    k = first
    yield k
    while True:
        yield k
        k = min(2 * k, cap)


def time_limited_pass_spp(k: int, left: float, budget: float, seconds_per_spp: float | None) -> int:
    """The spp of a time-limited render's next pass: the schedule's k, cut to
    half of the `left` seconds and at most an eighth of the `budget`, at
    `seconds_per_spp` (the slowest pass so far; None: k). A pass the limit
    cuts is dropped whole, so the passes shrink toward the limit and a cut
    one loses little: a full-size pass that overran the limit lost up to half
    of a 30 s chain render, and a chain render's speed varies from pass to
    pass by 2x and more (a sample can run thousands of Bernoulli trials)."""
    if not seconds_per_spp:
        return k
    return max(1, min(k, int(min(0.5 * left, budget / 8) / seconds_per_spp)))


def render(
    scene: Scene,
    integrator: None | str | dict | IntegratorDesc = None,
    spp: int | None = None,
    time: float | None = None,
    seed: int = 0,
    threads: int | None = None,
    progress: bool | None = None,
    chain_rate_map: np.ndarray | None = None,
    delta_split_map: np.ndarray | None = None,
    pixel_split_map: np.ndarray | None = None,
    sampler: str | None = None,
    guided_trace_map: np.ndarray | None = None,
    record_classes: bool = False,
    delta_branch_map: np.ndarray | None = None,
    seconds_per_spp: float | None = None,
    pixel_split_refine=None,
    deep_rate_map: np.ndarray | None = None,
    delta_split_refine=None,
) -> Image:
    """Render `scene` and return an Image.

    spp: samples per pixel (default: the scene's sampler sample_count, when no time is given).
    time: wall-clock budget in seconds; with spp too, whichever comes first. The first
        pass always finishes (a budget shorter than one pass gives a 1-spp image);
        later passes stop within one sample of the limit and are dropped whole.
    The image is bit-identical for a given (seed, spp) whatever the thread count.
    Ctrl-C stops the render and returns what was accumulated (stats['interrupted']).
    chain_rate_map: per-pixel chain rates (crop height x width), mpg's learned ones.
    delta_split_map: per-pixel delta-split counts (crop height x width, integers
      1..64), mpg's learned ones: a pixel's light seen through delta scattering
      only is averaged over k camera paths per sample.
    delta_branch_map: per pixel 1 or 0 (crop height x width), mpg's learned
      one: 0 makes a branching integrator's delta-split paths unbranched there
      (None: branched wherever the integrator branches).
    pixel_split_map: per-pixel sample splits (crop height x width, integers
      1..64), mpg's learned ones: each sample of a pixel is the mean of k
      camera samples.
    guided_trace_map: per-pixel counts of guided traces in pixels of rate 0
      (crop height x width, integers 0..64; 0: none), mpg's learned one; the
      integrator's handoff_guided > 0 still switches the trace on (None: its
      handoff_guided traces in every rate-0 pixel).
    deep_rate_map: per-pixel chain rates at the separators after a path's
      first in pixels of rate 0 (crop height x width, 0 or in [0.001, 1]; 0:
      the path tracer's there too), mpg's handoff_all's (None: the
      integrator's handoff_deep everywhere).
    sampler: 'independent' or 'stratified' pixel positions; None: the scene's
      <sampler> (independent, or stratified for stratified/multijitter/
      ldsampler/orthogonal/low_discrepancy). Stratified positions are points of
      a per-pixel randomly shifted Sobol (0,2)-sequence continued across the
      passes (of one sequence epoch: pixel_split_refine starts new ones): each sample is still unbiased, only a pixel's samples are
      correlated, so the image's `variance` channel (from the samples' spread)
      then usually over-estimates the variance of the pixel means where the
      positions matter (not guaranteed: design-notes).
    record_classes: also sum per pixel each sample's value split by where it
      entered (CLASS_NAMES: chain estimates, the path tracer's shares of shared
      chain paths, handed-off pixels' traced chain light, chain paths the path
      tracer kept whole at rate 0 and elsewhere because the estimator does not
      take them (a type their leaf never saw, no active leaf, not owned),
      light seen through delta scattering only, the rest, the light tracer's
      photons (not a part of the camera samples: their mean times spp, and
      squares that give the photons' variance of the mean, the channels'
      mean as the grey value's);
      mean over RGB) and its squares: Image.class_sum / class_sum_sq (crop
      height x width x classes; bench/error_classes.py); mpg: its final
      render's samples, not the training's.
    seconds_per_spp: with a time and no spp, an estimate of a pass's seconds
      per spp (mpg: twice its training passes'): the first pass is sized by it
      instead of starting at 1 spp and doubling (each pass costs a few ms
      more than its samples: a 2 s sphere render ran 17-18 rendering passes,
      12 with the estimate). The first pass is never cancelled: one that runs
      more than 8x slower than the estimate overruns the budget.
    pixel_split_refine: a callable (ks, ks2, kn, n) -> (pixel split map, info)
        called before a pass once n, the spp so far, reaches REFINE_FIRST and
        then twice the n of its last call; ks / ks2 are the per-pixel sums of k s and
        k s^2 over the samples s so far (k the split each ran at), kn of k.
        mpg's chain_rates.PixelSplitRefiner.update: the map it returns (None: no split)
        runs from that pass on (the image stays unbiased, design-notes "The pixel split
        refined by the render's own samples"), and each call starts a new epoch of the pixels' Sobol sequences
        (RenderJob's sequence_epoch: fresh shifts, sample_offset from 0), so no later
        film position is a function of a shift the earlier samples depended on.
    delta_split_refine: a callable (ds, ds2, n, paths) -> (delta split map, delta
        branch map, info) called before a pass once n reaches DELTA_REFINE_FIRST,
        then at twice the n of its last call and wherever pixel_split_refine is
        called (before it; each call starts a new epoch too);
        ds / ds2 the per-pixel sums and squares of the light each sample's own
        path saw through delta scattering only (RenderJob's record_delta), over
        the n spp so far; paths = (sums, squares, count, rays) per pixel of
        the split's extra paths' values so far (PassResult::split_path_*),
        and the pixel split map those passes last ran with (or None).
        mpg's chain_rates.DeltaSplitRefiner: the maps it returns
        (None: no split; all branched) run from that pass on.
    """
    from mpg import _core

    if spp is None and time is None:
        spp = int(scene.desc.camera.spp)
    if spp is not None and spp < 1:
        raise RenderError(f"spp must be at least 1, got {spp}")
    if time is not None and not (time > 0):
        raise RenderError(f"time must be positive, got {time}")
    if threads is not None and threads < 1:
        raise RenderError(f"threads must be at least 1, got {threads}")
    if sampler is None:
        sampler = scene.desc.camera.sampler
    if sampler not in ("independent", "stratified"):
        raise RenderError(f"sampler must be 'independent' or 'stratified', got {sampler!r}")
    name, params, warnings = _resolve_integrator(scene, integrator)
    if name == "mpg" and "guide" not in params:
        from mpg.guiding import render_mpg

        return render_mpg(scene, params, warnings, spp=spp, time=time, seed=seed, threads=threads,
                          sampler=sampler,
                          progress=progress, record_classes=record_classes)
    try:
        integ = _core.make_integrator(scene.core, name, params)
    except ValueError as e:
        raise RenderError(f"integrator '{name}': {e}") from None
    if name != "path" and not integ.chains_active:
        rest = ("it renders as 'path', with photons for the glossy casters' caustics the camera sees "
                "(light_trace_glossy)" if integ.light_trace_glossy_on else "it renders as 'path'")
        warnings.append(
            f"'{name}': the scene has no shape the manifold walk supports (smooth dielectric or "
            f"conductor, no normal map) or no point/spot/area emitter; {rest}")
    # maps that only the chain estimator reads: said, not silently dropped
    chain_maps = [nm for nm, m in (("chain_rate_map", chain_rate_map), ("guided_trace_map", guided_trace_map),
                                   ("deep_rate_map", deep_rate_map)) if m is not None]
    if chain_maps and (name == "path" or not integ.chains_active):
        warnings.append(f"'{name}' runs no chain estimator on this scene: {', '.join(chain_maps)} ignored")
    # (mpg traces its area lights by default: where it cannot, the estimator
    # keeps them as before, and only an explicit request warns)
    kinds = [k for k, on in (("point/spot", integ.chains_delta_lights),
                             ("area", bool(params.get("light_trace_area")))) if on]
    if integ.light_trace_off and kinds and integ.chains_active:
        warnings.append(f"'{name}': light_trace is off: {integ.light_trace_off}; the chain estimator "
                        f"takes the {' and '.join(kinds)} lights' caustics")
    core_scene = scene.core
    cam = scene.desc.camera
    h, w = int(cam.crop[3]), int(cam.crop[2])
    acc = np.zeros((h, w, 3))
    acc2 = np.zeros((h, w, 3))
    cls_sum = cls_sum2 = None   # (record_classes)
    lt_acc = lt_acc2 = None     # the light tracer's splat sums over all passes
    lt_photons = 0
    stats: dict[str, float] = {}
    done = 0
    passes = 0
    interrupted = False
    time_limited = False
    bar = Progress(progress)
    t0 = _time.monotonic()
    hint = seconds_per_spp if (time is not None and spp is None and seconds_per_spp is not None
                               and 0 < seconds_per_spp < np.inf) else None
    # (an spp budget keeps the fixed schedule: its passes decide the random streams)
    sched = pass_schedule(first=32 if hint else 1)
    pass_seconds_per_spp = None
    seconds_dropped = 0.0
    seconds_passes = 0.0   # (the passes' own wall time, the dropped one's too)
    refine_at, refine_info = REFINE_FIRST, {}
    drefine_at = DELTA_REFINE_FIRST
    epoch, epoch_start = 0, 0   # (RenderJob's sequence_epoch and the spp when it began)
    if pixel_split_refine is not None:
        ks, ks2, kn = np.zeros((h, w, 3)), np.zeros((h, w, 3)), np.zeros((h, w))
        pending_info, ran_map = {}, pixel_split_map   # (the newest solve's stats; the map a counted pass ran with)
    drefine_info = {}   # (the delta split check's stats of the map the last counted pass ran with)
    if delta_split_refine is not None:
        ds_acc, ds_acc2 = np.zeros((h, w, 3)), np.zeros((h, w, 3))
        # (the split's extra paths' values: sums, squares, count and rays)
        sp_acc, sp_acc2, sp_n, sp_rays = np.zeros((h, w, 3)), np.zeros((h, w, 3)), np.zeros((h, w)), np.zeros((h, w))
        # (the same for the delta split: its maps and stats)
        pending_dinfo, ran_delta = {}, (delta_split_map, delta_branch_map)
    # Ctrl-C (and SIGTERM where a caller such as mpg-render maps it to an
    # interrupt) sets a flag the loop checks, instead of raising wherever it
    # lands: a KeyboardInterrupt between two passes (creating a job, adding a
    # pass) escaped the loop and lost the whole image.
    stop = threading.Event()
    saved = []
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            cur = signal.getsignal(sig)
            if sig == signal.SIGINT or cur not in (signal.SIG_DFL, signal.SIG_IGN, None):
                saved.append((sig, signal.signal(sig, lambda signum, frame: stop.set())))
    try:
        while spp is None or done < spp:
            if stop.is_set():
                interrupted = True
                break
            split_due = pixel_split_refine is not None and done >= refine_at
            # (and with every pixel split refinement: one schedule after the
            # first check, so the epochs of the Sobol shifts, which each point
            # starts, are no more than the pixel split's and one)
            delta_due = delta_split_refine is not None and (done >= drefine_at or split_due)
            if split_due or delta_due:
                # (before the pass is sized: its time comes off what is left)
                if delta_due:
                    # (first: the pixel split's model counts the delta split's cost)
                    delta_split_map, delta_branch_map, pending_dinfo = delta_split_refine(
                        ds_acc, ds_acc2, done, (sp_acc, sp_acc2, sp_n, sp_rays, pixel_split_map))
                    drefine_at = 2 * done
                if split_due:
                    pixel_split_map, pending_info = pixel_split_refine(ks, ks2, kn, done)
                    refine_at = 2 * done
                # a new epoch of the Sobol sequences: fresh shifts, counted from 0
                epoch, epoch_start = epoch + 1, done
            k = next(sched)
            if spp is not None:
                k = min(k, spp - done)
            if time is not None:
                left = time - (_time.monotonic() - t0)
                if left <= 0:
                    time_limited = True
                    break
                if spp is None:
                    # (before the first pass: the caller's estimate)
                    k = time_limited_pass_spp(k, left, time, pass_seconds_per_spp or hint)
            pass_t0 = _time.monotonic()
            try:
                job = _core.RenderJob(core_scene, integ, k, seed, passes, threads or 0,
                                      chain_rate_map=chain_rate_map,
                                      delta_split_map=delta_split_map,
                                      pixel_split_map=pixel_split_map,
                                      stratify=sampler == "stratified", sample_offset=done - epoch_start,
                                      guided_trace_map=guided_trace_map, record_classes=record_classes,
                                      delta_branch_map=delta_branch_map, sequence_epoch=epoch,
                                      deep_rate_map=deep_rate_map,
                                      record_delta=delta_split_refine is not None)
            except ValueError as e:   # a bad chain_rate_map (shape, values)
                raise RenderError(str(e)) from None
            cancelled_by_time = False
            try:
                while not job.wait(0.05):
                    if stop.is_set():
                        raise KeyboardInterrupt
                    el = _time.monotonic() - t0
                    # The time limit cancels a pass once one has finished: a
                    # budget shorter than one pass still gives a 1-spp image,
                    # not an empty one (it overruns by at most that pass).
                    if time is not None and el > time and done > 0:
                        job.cancel()
                        cancelled_by_time = True
                    if spp is not None:
                        frac = (done + k * job.progress) / spp
                    else:
                        frac = el / time
                    if time is not None and spp is not None:
                        frac = max(frac, el / time)
                    bar.update(frac, done, spp, el)
            except KeyboardInterrupt:
                job.cancel()
                job.wait(3600.0)
                interrupted = True
                break
            r = job.result()
            seconds_passes += float(r["seconds"])
            if r["cancelled"]:
                time_limited = time_limited or cancelled_by_time
                seconds_dropped = _time.monotonic() - pass_t0
                break
            acc += r["sum"]
            acc2 += r["sum_sq"]
            if pixel_split_refine is not None:
                # (the map this pass ran with; the one the render reports)
                ran_map, refine_info = pixel_split_map, pending_info
                kc = np.ones((h, w)) if ran_map is None else np.maximum(np.floor(ran_map), 1.0)
                ks += kc[..., None] * r["sum"]
                ks2 += kc[..., None] * r["sum_sq"]
                kn += kc * k
            if delta_split_refine is not None:
                ran_delta, drefine_info = (delta_split_map, delta_branch_map), pending_dinfo
                ds_acc += r["delta_sum"]
                ds_acc2 += r["delta_sum_sq"]
                sp_acc += r["split_path_sum"]
                sp_acc2 += r["split_path_sum_sq"]
                sp_n += r["split_path_n"]
                sp_rays += r["split_path_rays"]
            if r["lt_photons"] > 0:
                lt_acc = r["lt_sum"] if lt_acc is None else lt_acc + r["lt_sum"]
                lt_acc2 = r["lt_sum_sq"] if lt_acc2 is None else lt_acc2 + r["lt_sum_sq"]
                lt_photons += int(r["lt_photons"])
            if record_classes:
                cls_sum = r["class_sum"] if cls_sum is None else cls_sum + r["class_sum"]
                cls_sum2 = r["class_sum_sq"] if cls_sum2 is None else cls_sum2 + r["class_sum_sq"]
            rs = r["stats"]
            if rs.get("max_chain_value", 0.0) > stats.get("max_chain_value", 0.0):
                # the largest single chain estimate and its factors (K, G, P(n), ...)
                stats.update({k: v for k, v in rs.items() if k.startswith("max_chain_")})
            for key, v in rs.items():
                if not key.startswith("max_chain_"):
                    stats[key] = stats.get(key, 0.0) + v
            done += k
            passes += 1
            pass_seconds_per_spp = max(pass_seconds_per_spp or 0.0, r["seconds"] / k)
            el = _time.monotonic() - t0
            bar.update(done / spp if spp else el / time, done, spp, el)
    finally:
        for sig, old in saved:
            signal.signal(sig, old)
        bar.close()
    elapsed = _time.monotonic() - t0
    if done > 0:
        mean = acc / done
        if done > 1:
            var = np.maximum(acc2 / done - mean * mean, 0.0) * (done / (done - 1)) / done
        else:
            var = np.full_like(mean, np.inf)
    else:
        mean = np.zeros_like(acc)
        var = np.full_like(acc, np.inf)
    lt_var = None
    if lt_photons > 0:
        # the light-traced part: each photon an independent sample of every
        # pixel's part (most of them 0), so its mean and the variance of the mean
        lt_mean = lt_acc / lt_photons
        mean = mean + lt_mean
        lt_var = np.maximum(lt_acc2 / lt_photons - lt_mean * lt_mean, 0.0) / max(lt_photons - 1, 1)
        var = var + lt_var
    if cls_sum is not None:
        # the photons' class: sum = their mean (grey) times the samples n, and
        # squares such that error_classes' (sq / n - m^2) / (n - 1) is their variance
        ph = np.zeros(cls_sum.shape[:2])
        ph2 = np.zeros(cls_sum.shape[:2])
        if lt_var is not None and done > 0:
            m = lt_mean.mean(axis=2)
            ph = m * done
            ph2 = done * (m * m + lt_var.mean(axis=2) * max(done - 1, 1))
        cls_sum = np.concatenate([cls_sum, ph[..., None]], axis=2)
        cls_sum2 = np.concatenate([cls_sum2, ph2[..., None]], axis=2)
    rejected = int(stats.get("rejected_nan", 0) + stats.get("rejected_inf", 0)
                   + stats.get("rejected_negative", 0))
    out_stats: dict[str, Any] = {
        "integrator": name,
        "integrator_params": params,
        "spp": done,
        "passes": passes,
        "seconds": elapsed,
        "seed": seed,
        "sampler": sampler,
        "threads": threads or 0,
        "interrupted": interrupted,
        "time_limited": time_limited,
        "seconds_dropped": seconds_dropped,  # wall time of a pass the limit cut (its work is dropped)
        # the core's passes' wall time: the rest of `seconds` is the loop's own
        # (mpg: its maps' learning, guide builds and photons, between the passes)
        "seconds_passes": seconds_passes,
        "seconds_per_spp_hint": hint or 0.0,   # the estimate that sized the first pass (0: none)
        "rejected_samples": rejected,
        "samples_per_second": stats.get("samples", 0.0) / elapsed if elapsed > 0 else 0.0,
        "warnings": list(scene.warnings) + warnings,
        **{k: (float(v) if k.startswith(("max_chain_", "chain_m2", "pt_shared_m2", "limit_")) else int(v))
           for k, v in stats.items()},
        **refine_info,
        **drefine_info,
    }
    # (class sums None without record_classes, or when no pass finished)
    img = Image(rgb=mean.astype(np.float32), variance=var.astype(np.float32), spp=done,
                stats=out_stats, class_sum=cls_sum, class_sum_sq=cls_sum2)
    if pixel_split_refine is not None:
        img.pixel_split_map = ran_map   # (the last one a pass that counts ran with)
    if delta_split_refine is not None:
        img.delta_split_map, img.delta_branch_map = ran_delta
    return img
