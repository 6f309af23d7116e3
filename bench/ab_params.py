"""Interleaved A/B of `mpg` parameter sets on one scene at equal time: per seed
the variants run in turn, the order rotated by one from seed to seed (A B,
B A, ...; with three, A B C, B C A, C A B), so a drift of the machine's speed
during the run falls on all of them alike (this machine's speed moved by up to
1.3x between runs of one command; `mpg-bench compare` interleaves its methods
the same way since the fourteenth session). This script takes the variants as
JSON, checks them and prints the MSE less the reference's floor per variant.

    python bench/ab_params.py sphere --time 20 --seeds 4 --variants '{}' '{"chain_rate_min": 0.015625}'
    python bench/ab_params.py emitter_size_003 --param res=128 --time 10 --seeds 3 \\
        --variants '{}' '{"chain_rate_min": 0.015625}'

Each variant is a JSON object of `mpg` parameters ('{}': the defaults).
Prints MSE, MSE less the reference's floor (docs/results.md, "Metrics"),
with 2+ seeds the seeds' variance (mpg.metrics.seed_variance: the MSE with
no reference noise in it), relMSE and spp per run and per variant (and the render stats --stats names,
per run: e.g. chain_rate_model_v chain_rate_model_c, the rates' model); needs the scene's reference in the
cache (mpg-bench reference). Writes bench/results/ab_params-<scene>-<hash of
the arguments>.json after every run (or --out FILE), so an interrupted run
keeps what it has."""

from __future__ import annotations

import argparse
import hashlib
import json
import pathlib
import shlex
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> int:
    import mpg
    import importlib

    from mpg import metrics
    render_mod = importlib.import_module("mpg.render")   # (mpg.render is also the function)
    from mpg.bench import reference as refmod
    from pixel_errors import add_param_option, load_with_reference, parse_variants, scene_params   # bench/

    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--time", type=float, default=20.0)
    ap.add_argument("--seeds", type=int, default=4)
    add_param_option(ap)
    ap.add_argument("--variants", nargs="+", required=True, metavar="JSON")
    ap.add_argument("--stats", nargs="+", default=[], metavar="KEY",
                    help="render stats to record and print per run (e.g. chain_rate_model_v spp_rendering)")
    ap.add_argument("--out", help="results file (default bench/results/ab_params-<scene>-<hash>.json)")
    args = ap.parse_args()
    if not args.time > 0:
        ap.error("--time must be > 0")
    if args.seeds < 1:
        ap.error("--seeds must be >= 1")
    variants = parse_variants(ap, args.variants, "mpg parameters")
    params = scene_params(ap, args)
    for v in variants:
        try:
            render_mod.check_param_names("mpg", v)
        except render_mod.RenderError as e:
            ap.error(f"{json.dumps(v)}: {e}")
    loaded = load_with_reference(args.scene, params, "ab_params")
    if loaded is None:
        return 1
    _, sc, info = loaded
    ref = refmod.load_reference(info)[0]
    floor = float(info["convergence"].get("mse_floor_image") or 0.0)
    command = shlex.join(["python", "bench/ab_params.py"] + sys.argv[1:])
    if args.out:
        out_path = pathlib.Path(args.out)
    else:
        key = hashlib.sha1(json.dumps([args.scene, params, args.time, args.seeds, variants]).encode()).hexdigest()
        out_path = ROOT / "bench" / "results" / f"ab_params-{pathlib.Path(args.scene).stem}-{key[:10]}.json"
    out_path.parent.mkdir(parents=True, exist_ok=True)
    runs: list[list[dict]] = [[] for _ in variants]
    images: list[list[np.ndarray]] = [[] for _ in variants]   # (for the seeds' variance)

    def summary() -> dict:
        out = {"command": command, "scene": args.scene, "params": params, "time": args.time,
               "mse_floor_image": floor, "variants": []}
        for v, rs, ims in zip(variants, runs, images):
            m = float(np.mean([r["mse"] for r in rs])) if rs else float("nan")
            sv = metrics.seed_variance(ims) if len(ims) >= 2 else None
            out["variants"].append({"variant": v, "runs": rs, "mse": m, "mse_above_floor": m - floor,
                                    "seed_variance": sv,
                                    "relmse": float(np.mean([r["relmse"] for r in rs])) if rs else float("nan"),
                                    "spp": float(np.mean([r["spp"] for r in rs])) if rs else 0.0})
        return out

    for seed in range(args.seeds):
        n = len(variants)
        for i in [(seed + j) % n for j in range(n)]:
            try:
                img = mpg.render(sc, dict(type="mpg", **variants[i]), time=args.time, seed=seed, progress=False)
            except mpg.RenderError as e:
                print(f"ab_params: {json.dumps(variants[i])}: {e}", file=sys.stderr)
                return 1
            if img.spp == 0:
                print(f"ab_params: {json.dumps(variants[i])} rendered no sample in {args.time} s", file=sys.stderr)
                return 1
            rec = {"seed": seed, "spp": int(img.spp), "mse": metrics.mse(img.rgb, ref),
                   "relmse": metrics.relmse(img.rgb, ref)}
            if args.stats:
                rec["stats"] = {k: img.stats.get(k) for k in args.stats}
                missing = [k for k in args.stats if k not in img.stats]
                if missing:
                    print(f"ab_params: no stat {', '.join(missing)} in this render (recorded as null)",
                          file=sys.stderr)
            runs[i].append(rec)
            images[i].append(np.asarray(img.rgb, dtype=np.float32))
            extra = "".join(f" {k} {v:.4g}" if isinstance(v, float) else f" {k} {v}"
                            for k, v in rec.get("stats", {}).items())
            print(f"{args.scene} seed {seed} {json.dumps(variants[i])}: MSE {rec['mse']:.4g} "
                  f"relMSE {rec['relmse']:.3g} spp {rec['spp']}{extra}", flush=True)
            out_path.write_text(json.dumps(summary(), indent=2))
    for s in summary()["variants"]:
        sv = f" seed var. {s['seed_variance']:.4g}" if s["seed_variance"] is not None else ""
        print(f"== {json.dumps(s['variant'])}: MSE {s['mse']:.4g} (less floor {s['mse_above_floor']:.4g}){sv} "
              f"relMSE {s['relmse']:.3g} spp {s['spp']:.0f}")
    print(f"wrote {out_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
