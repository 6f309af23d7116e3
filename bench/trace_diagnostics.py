"""Diagnostics of the guided trace of handed-off pixels (design-notes, "The
rates choose the guided trace"; docs/results.md, fifteenth session).

    python bench/trace_diagnostics.py everywhere double_slabs --time 20 --seeds 2 --k 1
        mpg as it is against the path tracer with k guided traces at every
        first separator and no chain estimate at all (the learned rate map
        replaced by zeros, the trace map by k everywhere), interleaved per
        seed; prints the MSE less the reference's floor. --set '{"delta_split": 2}':
        more mpg parameters for the traced renders.
    python bench/trace_diagnostics.py classes pool --time 20 [--tails 0]
        mpg with learn_trace off and on (seed 0; --tails 0: without
        trace_tails, as the fifteenth session ran it): per class of pixel (traced
        with learn_trace, at a chain rate in both, ...) the summed squared
        error and variance of each render, and the largest pixel variances.
    python bench/trace_diagnostics.py predict pool --res 32 --spp 512
        a guide from 32 spp, then a training pass's predicted per-sample
        variance of rate 0 with k = 1, 2, 4, 8 traces (chain_rates'
        formula, and with trace_tails) against renders at rate 0 with k traces.
    python bench/trace_diagnostics.py tails pool --res 32 --spp 1024 --seeds 2 --rate 1
        a guide from 32 spp, then training passes (rate --rate, records on,
        pass seeds 19, 20, ...; --rr: the path tracer's rr_depth): the
        rate-0 forms' second moments of the chain paths as the chains
        sample them (trace<k>_tail) against the records' own (trace<k>_seen),
        summed over the image and over the pixels where each is larger.
    python bench/trace_diagnostics.py bound double_slabs --spp 64 --seeds 2 --ks 32 --delta 8
        how far below `path` estimates of the chain light at the first
        separator and of the light seen in the glass can bring the MSE at
        equal samples per pixel: `path` against the path tracer with k
        guided traces at every first separator (rate 0 everywhere, a guide
        from --guide-spp spp at rate 1), alone and with a branched delta
        split of --delta everywhere (1: none), each at --spp, the scene's
        own resolution; as k and the split grow both parts tend to their
        means given the camera path, and what remains is the pixel
        footprint's and the other light's variance.
        Prints each one's MSE less the reference's floor and its seconds.
    python bench/trace_diagnostics.py lobes pool
        ns per lobe of ChainDistribution::pdf_dir over the largest leaves,
        against ns per ray of `path` (one thread): chain_rates.LOBE_COST.

Writes bench/results/trace_diagnostics-<mode>-<scene>.json."""

from __future__ import annotations

import argparse
import importlib
import json
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _reference(scene: str):
    from mpg.bench import reference as refmod
    from pixel_errors import load_scene   # bench/
    loaded = load_scene(scene, {}, "trace_diagnostics")
    if loaded is None:
        sys.exit(1)
    bs, sc = loaded
    info = refmod.find_reference(bs)
    if info is None:
        sys.exit(f"trace_diagnostics: no cached reference of {scene}; make it with mpg-bench reference")
    return sc, refmod.load_reference(info)[0], float(info["convergence"].get("mse_floor_image") or 0.0)


def _guide(sc, spp: int):
    """A guide from one recording pass of the estimator at rate 1."""
    from mpg import _core
    core = sc.core
    job = _core.RenderJob(core, _core.make_integrator(core, "mpg", {"record": True, "chain_rate": 1.0}), spp, 5, 0, 0)
    while not job.wait(0.05):
        pass
    g = _core.GuidingState()
    bmin, bmax = core.bbox
    g.build_from([job.result()["subpaths"]], bmin, bmax, c=1.0, epsilon=0.1, threads=2)
    return g


def everywhere(args) -> dict:
    import mpg
    import mpg.guiding as G
    from mpg import metrics
    sc, ref, floor = _reference(args.scene)
    learn, tmap = G.learn_rates_traced, G.guided_trace_map

    def zeros(*a, **k):
        q, t, info = learn(*a, **k)
        return np.zeros_like(q), t, info
    out = {"mpg": [], f"trace{args.k}": []}
    for seed in range(args.seeds):
        for name in (list(out) if seed % 2 == 0 else list(out)[::-1]):
            traced = name != "mpg"
            G.learn_rates_traced = zeros if traced else learn
            G.guided_trace_map = (lambda acc, **k: np.ones(acc.chain_m2.shape, np.float32)) if traced else tmap
            p = {"type": "mpg", "handoff_guided": args.k if traced else 4, "learn_trace": False}
            if traced:
                p.update(json.loads(args.set))
            img = mpg.render(sc, p, time=args.time, seed=seed, progress=False)
            st = img.stats
            rec = {"seed": seed, "own_mse": metrics.mse(img.rgb, ref) - floor, "spp": int(img.spp),
                   "guided_traces": st.get("guided_traces"), "guided_trace_hits": st.get("guided_trace_hits")}
            out[name].append(rec)
            print(name, rec, flush=True)
    G.learn_rates_traced, G.guided_trace_map = learn, tmap
    for name, rs in out.items():
        print(f"== {name}: own MSE {np.mean([r['own_mse'] for r in rs]):.5g}")
    return out


def classes(args) -> dict:
    import mpg
    sc, ref, floor = _reference(args.scene)
    R = importlib.import_module("mpg.render")
    cap: dict = {}
    render = R.render

    def spy(*a, **k):
        if k.get("chain_rate_map") is not None:
            cap["q"], cap["g"] = k["chain_rate_map"].copy(), k.get("guided_trace_map")
        return render(*a, **k)
    R.render = spy
    res = {}
    try:
        for on in (False, True):
            cap.clear()
            img = mpg.render(sc, {"type": "mpg", "learn_trace": on, "trace_tails": args.tails}, time=args.time,
                             seed=0, progress=False)
            g = cap.get("g")
            res[on] = (((img.rgb.astype(float) - ref) ** 2).mean(axis=2), img.variance.mean(axis=2), cap["q"],
                       np.zeros_like(cap["q"]) if g is None else np.asarray(g), int(img.spp))
    finally:
        R.render = render
    q0, q1, g1 = res[False][2], res[True][2], res[True][3]
    traced = (q1 == 0) & (g1 > 0)
    out: dict = {"spp": [res[False][4], res[True][4]], "classes": {}}
    for name, m in (("traced with learn_trace", traced),
                    ("chain rate in both", (q0 > 0) & (q1 > 0)),
                    ("rate 0 untraced in both", (q0 == 0) & (q1 == 0) & ~traced)):
        c = {"pixels": int(m.sum())}
        for on in (False, True):
            err, var = res[on][0], res[on][1]
            key = "on" if on else "off"
            c[key] = {"err_sum": float(err[m].sum()), "var_sum": float(var[m].sum()),
                      "var_median": float(np.median(var[m])) if m.any() else 0.0,
                      "var_top5": [float(v) for v in np.sort(var[m])[::-1][:5]]}
        if name.startswith("traced") and m.any():
            c["k_counts"] = {str(k): int(np.sum(g1[m] == k)) for k in np.unique(g1[m]).astype(int)}
        out["classes"][name] = c
        print(name, json.dumps(c), flush=True)
    return out


def predict(args) -> dict:
    import mpg
    from mpg import _core
    sc = mpg.load_file(ROOT / "scenes" / "eval" / f"{args.scene}.xml", res=str(args.res))
    g = _guide(sc, 32)
    n, R = args.spp, args.res
    core = sc.core
    job = _core.RenderJob(core, _core.make_integrator(core, "mpg", {"guide": g, "chain_rate": 0.25, "handoff_guided": 4}),
                          n, 19, 0, 0, record_costs=True)
    while not job.wait(0.05):
        pass
    r = job.result()
    nt, mean = np.maximum(r["trace_n"], 1.0), r["sum"] / n
    zero = np.zeros((R, R), np.float32)
    out = {}
    for k in (1, 2, 4, 8):
        ys, y2 = r[f"trace{k}_sum"] / nt[..., None], r[f"trace{k}_sum_sq"] / nt[..., None]
        pred = (y2 - 2 * ys * mean + mean * mean).mean(axis=2) + (1 / k - 1 / 2) * r[f"trace{k}_var"] / nt
        img = mpg.render(sc, {"type": "mpg", "guide": g, "chain_rate": 1.0, "handoff_guided": k}, spp=n, seed=29,
                         progress=False, chain_rate_map=zero, guided_trace_map=np.full((R, R), k, np.float32))
        tails = pred + (r[f"trace{k}_tail"] - r[f"trace{k}_seen"]) / nt
        out[str(k)] = {"predicted": float(pred.sum()), "predicted_tails": float(tails.sum()),
                       "measured": float(img.variance.mean(axis=2).sum() * n)}
        print(k, out[str(k)], flush=True)
    return out


def tails(args) -> dict:
    import mpg
    from mpg import _core
    sc = mpg.load_file(ROOT / "scenes" / "eval" / f"{args.scene}.xml", res=str(args.res))
    g = _guide(sc, 32)
    core = sc.core
    params = {"guide": g, "chain_rate": args.rate, "handoff_guided": 4}
    if args.rr is not None:
        params["rr_depth"] = args.rr
    out = {}
    for seed in range(19, 19 + args.seeds):
        job = _core.RenderJob(core, _core.make_integrator(core, "mpg", params), args.spp, seed, 0, 0, record_costs=True)
        while not job.wait(0.05):
            pass
        r = job.result()
        nt = np.maximum(r["trace_n"], 1.0)
        ic = r["trace_chain_sum"] / nt[..., None]
        o = out[str(seed)] = {"trace_n": float(r["trace_n"].sum()), "chain_mean_sq": float((ic * ic).mean(axis=2).sum())}
        for name in ["0"] + [str(k) for k in (1, 2, 4, 8)]:
            key = "trace_tail0" if name == "0" else f"trace{name}_tail"
            t, sn = r[key] / nt, r[key.replace("tail", "seen")] / nt
            o[name] = {"tail": float(t.sum()), "seen": float(sn.sum()),
                       "tail_where_larger": float(np.where(t > sn, t - sn, 0).sum()),
                       "seen_where_larger": float(np.where(sn > t, sn - t, 0).sum()),
                       "pixels_tail_over_2x": int(np.sum(t > 2 * sn + 1e-12))}
        print(seed, " ".join(f"{k}: {o[k]['tail']:.0f}/{o[k]['seen']:.0f}" for k in ("0", "1", "8")),
              "(tail/seen; 0: the path tracer alone)", flush=True)
    return out


def bound(args) -> dict:
    import mpg
    from mpg import metrics
    sc, ref, floor = _reference(args.scene)
    t0 = time.perf_counter()
    g = _guide(sc, args.guide_spp)
    out: dict = {"floor": floor, "guide_seconds": time.perf_counter() - t0, "runs": {}}
    H, W = ref.shape[:2]
    zero = np.zeros((H, W), np.float32)
    # d > 1: each sample's light seen through delta scattering alone averaged
    # over d branched camera paths (delta_split, delta_branch 8, as mpg's
    # learned map gives where it pays)
    runs = [(0, 1)] + [(k, 1) for k in args.ks] + [(k, args.delta) for k in [0] + list(args.ks) if args.delta > 1]
    for seed in range(args.seeds):
        for k, d in runs:
            name = ("path" if k == 0 and d == 1 else f"trace{k}") + (f"+delta{d}" if d > 1 else "")
            if name == "path":
                img = mpg.render(sc, "path", spp=args.spp, seed=seed, progress=False)
            else:
                img = mpg.render(sc, {"type": "mpg", "guide": g, "chain_rate": 1.0, "handoff_guided": max(k, 1),
                                      "delta_branch": 8},
                                 spp=args.spp, seed=seed, progress=False, chain_rate_map=zero,
                                 guided_trace_map=np.full((H, W), k, np.float32),
                                 delta_split_map=np.full((H, W), d, np.float32))
            rec = {"seed": seed, "own_mse": metrics.mse(img.rgb, ref) - floor,
                   "seconds": float(img.stats["seconds"]), "spp": int(img.spp)}
            out["runs"].setdefault(name, []).append(rec)
            print(name, rec, flush=True)
    base = np.mean([r["own_mse"] for r in out["runs"]["path"]])
    for name, rs in out["runs"].items():
        m = np.mean([r["own_mse"] for r in rs])
        print(f"== {name}: own MSE {m:.5g} (path / it {base / m:.2f}), "
              f"{np.mean([r['seconds'] for r in rs]):.1f} s for {args.spp} spp")
    return out


def lobes(args) -> dict:
    import mpg
    sc = mpg.load_file(ROOT / "scenes" / "eval" / f"{args.scene}.xml", res="64")
    g = _guide(sc, 64)
    sizes = sorted(((len(g.leaf(i)["xD"]), i) for i in range(g.num_leaves)), reverse=True)[:3]
    d = np.random.default_rng(0).normal(size=(200_000, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    out: dict = {"leaves": []}
    for m, leaf in sizes:
        t0 = time.perf_counter()
        g.pdf_dir(leaf, 1, 0, d)
        dt = (time.perf_counter() - t0) / len(d)
        out["leaves"].append({"leaf": leaf, "samples": m, "ns_per_pdf": dt * 1e9, "ns_per_sample": dt / m * 1e9})
        print(out["leaves"][-1], flush=True)
    img = mpg.render(sc, "path", spp=64, seed=1, threads=1, progress=False)
    st = img.stats
    out["ns_per_ray"] = st["seconds"] / (st["rays"] + st["shadow_rays"] + st["camera_rays"]) * 1e9
    print("path: ns per ray (one thread, shading included)", out["ns_per_ray"])
    return out


def main() -> int:
    sys.path.insert(0, str(ROOT / "bench"))
    ap = argparse.ArgumentParser()
    ap.add_argument("mode", choices=["everywhere", "classes", "predict", "tails", "bound", "lobes"])
    ap.add_argument("scene")
    ap.add_argument("--time", type=float, default=20.0)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--k", type=int, default=1)
    ap.add_argument("--res", type=int, default=32)
    ap.add_argument("--spp", type=int, default=512)
    ap.add_argument("--rate", type=float, default=0.25, help="tails: the training pass's chain rate")
    ap.add_argument("--rr", type=int, default=None, help="tails: the path tracer's rr_depth")
    ap.add_argument("--tails", type=int, default=1, help="classes: trace_tails (0: the fifteenth session's runs)")
    ap.add_argument("--set", default="{}", help="everywhere: JSON of more mpg parameters for the traced renders")
    ap.add_argument("--ks", type=int, nargs="+", default=[8, 32], help="bound: the trace counts")
    ap.add_argument("--delta", type=int, default=2, help="bound: also with this delta split (1: none)")
    ap.add_argument("--guide-spp", type=int, default=16, help="bound: the guide's spp at rate 1")
    args = ap.parse_args()
    out = {"everywhere": everywhere, "classes": classes, "predict": predict, "tails": tails, "bound": bound,
           "lobes": lobes}[args.mode](args)
    path = ROOT / "bench" / "results" / f"trace_diagnostics-{args.mode}-{args.scene}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"command": " ".join(["python", "bench/trace_diagnostics.py"] + sys.argv[1:]),
                                "result": out}, indent=2))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
