"""Which of a short training's learned maps costs a short render: train
twice (--short and --long seconds), then render with the short training's
guide and maps, the long one's, and the short one's with one part swapped
in from the long training at a time, all held fixed (new seeds, --spp
samples a pixel, no time limit). It makes the forty-third session's map
swap reproducible (docs/results.md: double_slabs' 2 s training against its
10 s one, the delta split 3.4x, the pixel split 1.3x, the rest ~1x).

    python bench/swap_maps.py double_slabs --short 2 --long 10 \\
        --params '{"handoff_all": 2}' --spp 16 --seeds 8 \\
        --variants short long short+guide short+rates short+pixel_split short+delta_split short+glass

Variants:
  short, long      one training's guide and maps as learned
  path             the path tracer at the same spp and sampler (the peer
                   whose per-sample variance and seconds the maps' are
                   measured against; no maps)
  short+PART[+..]  the short training's, with PART from the long training:
                     guide        the guided state (STree, chain distributions)
                     rates        chain_rate_map (the chain estimator's rates)
                     traces       guided_trace_map (guided traces per pixel)
                     deep         deep_rate_map (later separators' rates)
                     pixel_split  pixel_split_map
                     delta_split  delta_split_map and delta_branch_map
                   or glass: the short training's delta split with every pixel
                   whose training paths saw delta scattering split at least
                   twice (the held-out check's other choice, its branch map),
                   or glassplain: the glass split with plain extra paths (not
                   trees) in the pixels the training did not split,
                   or grow<R>: the same for the glass pixels within R pixels
                   (a (2R+1)^2 window) of a pixel the short training split
                   (measured on double_slabs, never better than glass:
                   docs/results.md, forty-fourth session)

The maps are held fixed in every render: no pixel split refinement and no
held-out check between the passes (each is a choice of maps by the render's
own samples, which would move both variants alike). The short training runs
with seed --train-seed, the long one with seed 0. Per-sample variance,
weighted variance (the maps' relMSE weights from the short training) and
efficiency (variance x median seconds) as bench/fixed_maps.py reports them.
Writes JSON (--out; default bench/results/swap_maps-<scene>.json)."""

from __future__ import annotations

import argparse
import json
import pathlib
import re
import shlex
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
PARTS = {"guide": ("guide",), "rates": ("chain_rate_map",), "traces": ("guided_trace_map",),
         "deep": ("deep_rate_map",), "pixel_split": ("pixel_split_map",),
         "delta_split": ("delta_split_map", "delta_branch_map"), "glass": (), "glassplain": ()}
HELD = dict(pixel_split_refine=None, delta_split_refine=None, progress=False, seconds_per_spp=None, time=None)


def parse_variant(name: str) -> tuple[str, list[str]]:
    """(the base training, the parts swapped in) of a variant's name."""
    head, *parts = name.split("+")
    if head not in ("short", "long", "path") or (head in ("long", "path") and parts):
        raise ValueError(f"{name!r}: a variant is short, long, path or short+PART[+PART...]")
    bad = [p for p in parts if p not in PARTS and not re.fullmatch(r"grow[1-9]\d*", p)]
    if bad:
        raise ValueError(f"{name!r}: unknown part {bad[0]!r} (one of {', '.join(PARTS)})")
    delta = [p for p in parts if p in ("glass", "glassplain", "delta_split") or p.startswith("grow")]
    if len(set(parts)) != len(parts) or len(delta) > 1:
        raise ValueError(f"{name!r}: a part named twice, or two delta splits (glass, grow<R>, delta_split)")
    return head, parts


def glass_maps(seen: dict, grow: int = 0, plain_new: bool = False) -> dict:
    """The held-out check's other delta split (every glass pixel split at
    least twice) of a training, as render call arguments; grow > 0: only the
    glass pixels within `grow` pixels of one the training split; plain_new:
    the pixels the training did not split get plain extra paths, not trees."""
    d = seen.get("delta_refiner")
    if d is None:
        raise ValueError("the training made no held-out check (no learned delta split, or "
                         "delta_split_online off): no glass split to swap in")
    k = d.glass_map
    if grow > 0:
        from mpg.chain_rates import _box_blur
        near = _box_blur((d.base > 1.0).astype(float), grow, total=True) >= 0.5
        k = np.where(near, k, d.base).astype(np.float32)
    # (plain extra paths only where the integrator branches: the check's own rule)
    plain = d.plain | (plain_new & d.branched & (d.base <= 1.0))
    kmap, bmap = d.maps(np.asarray(k, dtype=np.float32), plain)
    return {"delta_split_map": kmap, "delta_branch_map": bmap}


def variant_call(name: str, short: dict, long: dict) -> dict:
    """The render call (keyword arguments and "integrator") of a variant from
    the two trainings' spied final render calls."""
    head, parts = parse_variant(name)
    if head == "path":
        return dict(HELD, integrator="path", sampler=short["kw"].get("sampler"))
    src = long if head == "long" else short
    call = dict(src["kw"], **HELD, integrator=dict(src["integrator"]))
    for p in parts:
        if p in ("glass", "glassplain") or p.startswith("grow"):
            call.update(glass_maps(short, int(p[4:]) if p.startswith("grow") else 0, p == "glassplain"))
        elif p == "guide":
            call["integrator"]["guide"] = long["integrator"]["guide"]
        else:
            for key in PARTS[p]:
                call[key] = long["kw"].get(key)
    return call


def main() -> int:
    import mpg
    from mpg import chain_rates
    from fixed_maps import mpg_params, print_variants, render_interleaved, spied_training, variance_summary   # bench/
    from pixel_errors import add_param_option, load_scene, scene_params

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--short", type=float, default=2.0, help="the short training render's budget (s)")
    ap.add_argument("--long", type=float, default=10.0, help="the long training render's budget (s)")
    ap.add_argument("--train-seed", type=int, default=0, help="the short training's seed (the long one's is 0)")
    ap.add_argument("--params", default="{}", metavar="JSON", help="mpg parameters of both training renders")
    ap.add_argument("--spp", type=int, default=16, help="samples per pixel of each fixed-map render")
    ap.add_argument("--seeds", type=int, default=8, help="renders per variant")
    ap.add_argument("--variants", nargs="+", default=["short", "long", "short+delta_split"], metavar="NAME")
    add_param_option(ap)
    ap.add_argument("--out", help="results file (default bench/results/swap_maps-<scene>.json)")
    args = ap.parse_args()
    if not (args.short > 0 and args.long > 0):
        ap.error("--short and --long must be > 0")
    if args.spp < 1 or args.seeds < 2:
        ap.error("--spp must be >= 1 and --seeds >= 2 (a variance)")
    for v in args.variants:
        try:
            parse_variant(v)
        except ValueError as e:
            ap.error(str(e))
    if len(set(args.variants)) != len(args.variants):
        ap.error("a variant is named twice")
    params = mpg_params(ap, args.params)
    loaded = load_scene(args.scene, scene_params(ap, args), "swap_maps")
    if loaded is None:
        return 1
    sc = loaded[1]

    runs = {}
    for name, seconds, seed in (("short", args.short, args.train_seed), ("long", args.long, 0)):
        try:
            trained, wall, seen = spied_training(sc, params, seconds, seed)
        except mpg.RenderError as e:
            print(f"swap_maps: {e}", file=sys.stderr)
            return 1
        if "kw" not in seen or "acc" not in seen:
            print(f"swap_maps: the {name} training ({seconds:g} s) learned no per-pixel maps (too short, "
                  "chain_rate given, or no chain work in the scene)", file=sys.stderr)
            return 1
        runs[name] = dict(seen, trained=trained, wall=wall)
        print(f"swap_maps: {name} training: {trained.stats.get('spp_training', 0)} spp in {wall:.2f} s",
              file=sys.stderr, flush=True)
    try:
        calls = {v: variant_call(v, runs["short"], runs["long"]) for v in args.variants}
    except ValueError as e:
        print(f"swap_maps: {e}", file=sys.stderr)
        return 1
    for c in calls.values():
        c["spp"] = args.spp
    imgs, secs = render_interleaved(sc, runs["short"]["integrator"], calls, args.seeds, "swap_maps")

    acc = runs["short"]["acc"]
    weight = chain_rates._weights(chain_rates._finite(acc.sum) / float(acc.n), "relmse", 3)
    glass = (runs["short"]["delta_refiner"].glass if "delta_refiner" in runs["short"]
             else np.asarray(acc.delta_rays) > 0)
    groups = {"glass": glass, "rest": ~glass}

    def split_stats(kw: dict, key: str) -> dict:
        m = kw.get(key)
        if m is None:
            return {"fraction": 0.0, "mean": 1.0}
        m = np.asarray(m)
        return {"fraction": float(np.mean(m > 1)), "mean": float(np.mean(m[m > 1])) if np.any(m > 1) else 1.0}

    result = {"command": shlex.join(["python", "bench/swap_maps.py"] + sys.argv[1:]), "scene": args.scene,
              "params": params, "short": args.short, "long": args.long, "train_seed": args.train_seed,
              "spp": args.spp, "seeds": args.seeds,
              "training_spp": {k: int(r["trained"].stats.get("spp_training", 0)) for k, r in runs.items()},
              "group_fraction": {k: float(m.mean()) for k, m in groups.items()},
              "splits": {v: {"delta": split_stats(c, "delta_split_map"), "pixel": split_stats(c, "pixel_split_map")}
                         for v, c in calls.items()},
              "variants": {v: variance_summary(imgs[v], secs[v], args.spp, weight, groups) for v in args.variants}}
    out = pathlib.Path(args.out) if args.out else ROOT / "bench" / "results" / f"swap_maps-{pathlib.Path(args.scene).stem}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))

    print(f"{args.scene}: trainings {result['training_spp']['short']} spp ({args.short:g} s, seed {args.train_seed}) "
          f"and {result['training_spp']['long']} spp ({args.long:g} s); glass pixels "
          f"{result['group_fraction']['glass']:.1%}")
    print_variants(result["variants"], args.variants[0])
    for v, s in result["splits"].items():
        print(f"  {v:28s} delta split {s['delta']['fraction']:.1%} (mean {s['delta']['mean']:.2f}), "
              f"pixel split {s['pixel']['fraction']:.1%} (mean {s['pixel']['mean']:.2f})")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
    sys.exit(main())
