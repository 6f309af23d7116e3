"""`mpg`'s learned maps held fixed: train once, then render the final pass
again and again with the same guide and maps (new seeds), and with variants
of the maps, to see what a choice of the maps does to the image's
efficiency and where its variance moves -- the per-sample variance of each
group of pixels (the pixels the maps gave the chain estimator, the path
tracer alone, the path tracer with guided traces) under each variant, and
each variant's time. An equal-time A/B (bench/ab_params.py) retrains per
seed and mixes the training's noise into its answer; here the training is
one, so a map's effect is measured apart from how well the training chose
it (docs/results.md, thirty-fifth session).

    python bench/fixed_maps.py double_slabs --time 10 --spp 32 --seeds 12 \\
        --variants learned all2 all0 est1 est-traced2 pt-traced2

Variants (q the learned rates, g the learned guided traces of rate-0 pixels):
  learned        the maps as learned
  all<K>         every pixel at rate 0 with K guided traces (K >= 1:
                 handoff_all=K's rate and trace maps; all0: no traces)
  est1           the pixels with chain work at a rate q > 0 at rate 1
  est-traced<K>  the same pixels at rate 0 with K guided traces
  pt-traced<K>   the pixels at rate 0 without traces given K traces

The training is `mpg.render(scene, mpg with --params and handoff_all 0, time=--time, seed=0)`;
its final render call's arguments are kept (guide, maps, sampler, photon
rate) and called again with --spp samples and seeds 1000 + i, without a time
limit. Where the render learned a pixel split, each variant's is solved
again from its own rates and refined between the passes by the render's own
samples, as the render does (a fresh refiner per render; --no-online-split:
no refinement). That split spreads the samples over the whole image, so a
variant also moves the variance of pixels whose rates it keeps: the groups
say where the variance is, the efficiency what the variant is worth. The
photon rate stays the one learned for the learned maps (a `handoff_all`
render learns its own), and a 32-spp render refines its split three times
(at 4, 8 and 16 spp) where a long render goes on. The variants run
interleaved per seed (the order rotated), so a drift of the machine's speed
falls on all alike. Per-sample variance: --spp times the seeds' sample
variance of a pixel's mean, mean over RGB (a split pixel's sample is the
mean of its k camera samples); "weighted" weighs each pixel by 1 / (I^2 +
0.01) with I the training's blurred mean, as the maps' relMSE objective
does. "Efficiency" is the image's mean per-sample variance times the
render's median seconds (lower is better; a ratio of two holds at equal
time; each render's fixed overhead is in its seconds), unweighted and
weighted. Writes JSON (--out; default bench/results/fixed_maps-<scene>.json).

It measures the maps at one training's guide and over --seeds x --spp
samples a pixel: where the error is a few rare large values (the traces' in
dark pixels), that can miss what an equal-time A/B over retrained seeds
sees. Thirty-fifth session: the sphere's estimator pixels handed to two
traces made the image 1.18x more efficient here (1.7x with a first version
that kept the training's split map), 1.10x by the seeds' variance at equal
time, with 1.5x the relMSE."""

from __future__ import annotations

import argparse
import json
import pathlib
import re
import shlex
import statistics
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
VARIANT = re.compile(r"^(learned|est1|all(\d+)|est-traced(\d+)|pt-traced(\d+))$")


def variant_maps(name: str, q: np.ndarray, g: np.ndarray, chain: np.ndarray | None = None,
                 deep: float = 1.0) -> dict:
    """The render call's map arguments that a variant replaces. chain: the
    pixels with chain work (None: all); the others keep their rate (1, which
    the rates give a pixel without chain work) in `est1` and `est-traced<K>`.
    deep: the integrator's handoff_deep; `all<K>` runs the later separators
    at the learned rates as handoff_all does (min with deep; deep where q is
    0; none at deep 0)."""
    m = VARIANT.match(name)
    if m is None:
        raise ValueError(name)
    f32 = np.float32
    est = (q > 0) if chain is None else (q > 0) & chain
    if name == "learned":
        return {}
    if name == "est1":
        return {"chain_rate_map": np.where(est, 1.0, q).astype(f32)}
    if m.group(2) is not None:
        out = {"chain_rate_map": np.zeros_like(q, dtype=f32),
               "guided_trace_map": np.full(q.shape, float(m.group(2)), dtype=f32)}
        from mpg.guiding import handoff_all_deep_map
        dmap = handoff_all_deep_map(q, deep)
        if dmap is not None:
            out["deep_rate_map"] = dmap
        return out
    if m.group(3) is not None:
        k = float(m.group(3))
        return {"chain_rate_map": np.where(est, 0.0, q).astype(f32),
                "guided_trace_map": np.where(est, k, g).astype(f32)}
    k = float(m.group(4))
    return {"guided_trace_map": np.where((q <= 0) & (g <= 0), k, g).astype(f32)}


def traces_of(name: str) -> int:
    """The K of a variant's name (0 without one)."""
    m = VARIANT.match(name)
    return int(next((x for x in m.groups()[1:] if x is not None), 0)) if m else 0


def spied_training(sc, params: dict, seconds: float, seed: int) -> tuple:
    """`mpg.render(sc, mpg with params, time=seconds, seed=seed)` with its
    final render call's arguments and the training's records kept: (the
    render, its wall seconds, seen) where seen holds "kw" and "integrator"
    (the final render call's keyword arguments and integrator, maps and
    guide included), "acc" (the training's CostAccumulator), "refiner"
    (the pixel split's (kd, options)) and "delta_refiner" (the delta split's
    held-out check, a DeltaSplitRefiner), each where the render made one."""
    import mpg
    import mpg.guiding  # noqa: F401  (its module, below)
    from mpg import chain_rates
    render_mod = sys.modules["mpg.render"]
    guiding = sys.modules["mpg.guiding"]
    seen: dict = {}
    real_render = render_mod.render
    real_add = chain_rates.CostAccumulator.add
    real_refiner, real_delta = guiding.PixelSplitRefiner, guiding.DeltaSplitRefiner

    def spy_render(scene, integrator=None, **kw):
        if kw.get("chain_rate_map") is not None and "kw" not in seen:
            seen["kw"], seen["integrator"] = dict(kw), integrator
        return real_render(scene, integrator=integrator, **kw)

    def spy_add(acc, result, spp, q):
        seen["acc"] = acc
        return real_add(acc, result, spp, q)

    class SpyRefiner(real_refiner):   # (the pixel split's arguments, to build it again per variant)
        def __init__(self, acc, q, kd, **kw):
            seen["refiner"] = (kd, kw)
            super().__init__(acc, q, kd, **kw)

    class SpyDelta(real_delta):
        def __init__(self, *a, **kw):
            super().__init__(*a, **kw)
            seen["delta_refiner"] = self

    render_mod.render = spy_render   # (guiding.render_mpg imports it at call time)
    chain_rates.CostAccumulator.add = spy_add
    guiding.PixelSplitRefiner, guiding.DeltaSplitRefiner = SpyRefiner, SpyDelta
    try:
        t0 = time.perf_counter()
        trained = mpg.render(sc, dict(type="mpg", **params), time=seconds, seed=seed, progress=False)
        return trained, time.perf_counter() - t0, seen
    finally:
        render_mod.render = real_render
        chain_rates.CostAccumulator.add = real_add
        guiding.PixelSplitRefiner, guiding.DeltaSplitRefiner = real_refiner, real_delta


def render_interleaved(sc, integrator: dict, calls: dict[str, dict], seeds: int, tool: str,
                       refiners: dict | None = None) -> tuple[dict, dict]:
    """Each variant's render call (calls[v]: mpg.render.render's keyword
    arguments) on seeds 1000 + i, the variants interleaved per seed with the
    order rotated, so a drift of the machine's speed falls on all alike.
    refiners[v]: a function that makes a fresh pixel_split_refine per render.
    Returns ({v: [rgb arrays]}, {v: [seconds]})."""
    real_render = sys.modules["mpg.render"].render
    names = list(calls)
    imgs: dict[str, list[np.ndarray]] = {v: [] for v in names}
    secs: dict[str, list[float]] = {v: [] for v in names}
    for i in range(seeds):
        for j in range(len(names)):
            v = names[(i + j) % len(names)]
            call = dict(calls[v], seed=1000 + i)
            if refiners and v in refiners:
                call["pixel_split_refine"] = refiners[v]()
            t0 = time.perf_counter()
            img = real_render(sc, integrator=integrator if "integrator" not in call else call.pop("integrator"),
                              **call)
            secs[v].append(time.perf_counter() - t0)
            imgs[v].append(np.asarray(img.rgb, dtype=np.float64))
        print(f"{tool}: seed {i + 1}/{seeds}", file=sys.stderr, flush=True)
    return imgs, secs


def variance_summary(imgs: list[np.ndarray], secs: list[float], spp: int, weight: np.ndarray,
                     groups: dict[str, np.ndarray]) -> dict:
    """A variant's per-sample variance (spp times the seeds' sample variance
    of a pixel's mean, mean over RGB), weighted and by group, its median
    seconds and its efficiency (variance x seconds)."""
    a = np.stack(imgs)
    var = a.var(axis=0, ddof=1).mean(axis=2) * spp   # a sample's variance (a split one: k camera samples')
    sec = statistics.median(secs)
    npix = var.size
    return {"seconds_median": sec, "seconds": list(secs),
            "variance": float(var.mean()), "variance_weighted": float((weight * var).mean()),
            "efficiency": float(var.mean()) * sec, "efficiency_weighted": float((weight * var).mean()) * sec,
            "group_variance": {k: float(var[m].sum() / npix) for k, m in groups.items()},
            "group_variance_weighted": {k: float((weight * var)[m].sum() / npix) for k, m in groups.items()}}


def print_variants(variants: dict[str, dict], base_name: str) -> None:
    """The variants' table: seconds, variance, efficiency and its gain over
    base_name's, unweighted and weighted, and the variance by group."""
    base = variants[base_name]
    w = max([14] + [len(v) for v in variants])
    print(f"{'variant':{w}s} {'s/render':>9s} {'variance':>9s} {'effic.':>8s} {'vs ' + base_name:>9s} "
          f"{'weighted':>9s}  variance by group (weighted by group)")
    for v, r in variants.items():
        gains = base["efficiency"] / r["efficiency"] if r["efficiency"] > 0 else float("inf")
        wgains = (base["efficiency_weighted"] / r["efficiency_weighted"] if r["efficiency_weighted"] > 0
                  else float("inf"))
        by = ", ".join(f"{k} {x:.4g} ({r['group_variance_weighted'][k]:.4g})" for k, x in r["group_variance"].items())
        print(f"{v:{w}s} {r['seconds_median']:9.3f} {r['variance']:9.4g} {r['efficiency']:8.4g} {gains:8.2f}x "
              f"{wgains:8.2f}x  {by}")


def mpg_params(ap: argparse.ArgumentParser, text: str) -> dict:
    """--params: a JSON object of mpg parameters without 'type' (else the
    parser's usage error)."""
    try:
        params = json.loads(text)
    except json.JSONDecodeError as e:
        ap.error(f"--params is not JSON: {e}")
    if not isinstance(params, dict) or "type" in params:
        ap.error("--params must be a JSON object of mpg parameters without 'type'")
    return params


def main() -> int:
    import mpg
    import mpg.guiding  # noqa: F401  (its module, below)
    from mpg import chain_rates
    from pixel_errors import add_param_option, load_scene, scene_params   # bench/, the script's own folder

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--time", type=float, default=10.0, help="the training render's budget (s)")
    ap.add_argument("--params", default="{}", metavar="JSON", help="mpg parameters of the training render")
    ap.add_argument("--spp", type=int, default=32, help="samples per pixel of each fixed-map render")
    ap.add_argument("--seeds", type=int, default=8, help="renders per variant")
    ap.add_argument("--variants", nargs="+", default=["learned", "all2"], metavar="NAME")
    ap.add_argument("--no-online-split", action="store_true",
                    help="keep the pixel split's first map (no refinement between the passes)")
    add_param_option(ap)
    ap.add_argument("--out", help="results file (default bench/results/fixed_maps-<scene>.json)")
    args = ap.parse_args()
    if not args.time > 0:
        ap.error("--time must be > 0")
    if args.spp < 1 or args.seeds < 2:
        ap.error("--spp must be >= 1 and --seeds >= 2 (a variance)")
    bad = [v for v in args.variants if not VARIANT.match(v)]
    if bad:
        ap.error(f"unknown variant {bad[0]!r}: learned, all<K>, est1, est-traced<K>, pt-traced<K>")
    if len(set(args.variants)) != len(args.variants):
        ap.error("a variant is named twice")
    big = [v for v in args.variants if traces_of(v) > 64]
    if big:
        ap.error(f"{big[0]}: at most 64 guided traces a pixel")
    params = mpg_params(ap, args.params)
    if params.get("handoff_all", 0) not in (0, "0"):   # (0.0 == 0; "0.0" is refused with the rest)
        ap.error("the training keeps its learned maps (handoff_all 0): the variants all<K> are handoff_all's")
    params["handoff_all"] = 0
    if str(params.get("handoff_guided", "")).strip() == "0" and any(traces_of(v) > 0 for v in args.variants):
        ap.error("handoff_guided 0 switches the guided traces off: the variants with traces would run none")
    loaded = load_scene(args.scene, scene_params(ap, args), "fixed_maps")
    if loaded is None:
        return 1
    sc = loaded[1]

    try:
        trained, seconds_training_render, seen = spied_training(sc, params, args.time, 0)
    except mpg.RenderError as e:
        print(f"fixed_maps: {e}", file=sys.stderr)
        return 1
    if "kw" not in seen or "acc" not in seen:
        print("fixed_maps: the render learned no per-pixel maps (too short a training, or chain_rate "
              "given, or no chain work in the scene)", file=sys.stderr)
        return 1
    real_refiner = sys.modules["mpg.guiding"].PixelSplitRefiner
    kw = dict(seen["kw"])
    online = kw.get("pixel_split_refine") is not None and "refiner" in seen and not args.no_online_split
    resolve_split = "refiner" in seen   # (a learned pixel split: solved again from each variant's rates)
    # (the delta split's held-out check off: it would choose between two delta
    # splits per render, and the maps are held fixed)
    kw.update(spp=args.spp, time=None, pixel_split_refine=None, delta_split_refine=None, progress=False,
              seconds_per_spp=None)
    q = np.asarray(kw["chain_rate_map"], dtype=np.float32)
    g = kw.get("guided_trace_map")
    g = np.zeros_like(q) if g is None else np.asarray(g, dtype=np.float32)
    acc = seen["acc"]
    n = float(acc.n)
    _, _, c1, _, _ = chain_rates._costs(acc, n)
    has = chain_rates._box_blur(c1, 3) > 0.0   # (chain work in the pixel's window: the rates' own test)
    weight = chain_rates._weights(chain_rates._finite(acc.sum) / n, "relmse", 3)
    groups = {"estimator": has & (q > 0), "path tracer alone": has & (q <= 0) & (g <= 0),
              "guided traces": has & (q <= 0) & (g > 0), "no chain work": ~has}

    deep = float(seen["integrator"].get("handoff_deep", 1.0))
    maps = {v: variant_maps(v, q, g, has, deep) for v in args.variants}
    refine_args: dict[str, tuple] = {}   # (a variant's pixel split refiner: its rates, kd, options)
    for v, m in maps.items():
        if resolve_split:
            # The pixel split as the render learns it: from the variant's rates
            # (its first map) and refined between the passes by the render's
            # own samples (a fresh refiner per render: the same start each time)
            kd, skw = seen["refiner"]
            qv = m.get("chain_rate_map", q)
            where = skw.get("where")
            if where is not None:   # (pixel_split=handoff: the variant's rate-0 pixels)
                skw = dict(skw, where=qv <= 0.0)
            if online:
                refine_args[v] = (qv, kd, skw)
            smap_v, _ = real_refiner(acc, qv, kd, **skw).solve()
            m["pixel_split_map"] = smap_v if np.any(smap_v > 1) else None
    calls = {v: dict(kw, **maps[v]) for v in args.variants}
    refiners = {v: (lambda a=a: real_refiner(acc, a[0], a[1], **a[2]).update) for v, a in refine_args.items()}
    imgs, secs = render_interleaved(sc, seen["integrator"], calls, args.seeds, "fixed_maps", refiners)

    result = {"command": shlex.join(["python", "bench/fixed_maps.py"] + sys.argv[1:]), "scene": args.scene,
              "params": params, "time": args.time, "spp": args.spp, "seeds": args.seeds,
              "training_spp": int(trained.stats.get("spp_training", 0)),
              "seconds_training_render": seconds_training_render,
              "online_pixel_split": online,
              "group_fraction": {k: float(m.mean()) for k, m in groups.items()}, "variants": {}}
    for v in args.variants:
        result["variants"][v] = variance_summary(imgs[v], secs[v], args.spp, weight, groups)
    out = pathlib.Path(args.out) if args.out else ROOT / "bench" / "results" / f"fixed_maps-{pathlib.Path(args.scene).stem}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))

    print(f"{args.scene}: training {result['training_spp']} spp; pixels: " +
          ", ".join(f"{k} {f:.1%}" for k, f in result["group_fraction"].items()))
    print_variants(result["variants"], args.variants[0])
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
    sys.exit(main())
