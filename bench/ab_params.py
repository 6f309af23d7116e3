"""Interleaved A/B of `mpg` parameter sets on one scene at equal time: per seed
the variants run in turn, in reversed order on every other seed (A B, B A,
...), so a drift of the machine's speed during the run falls on all of them
alike (`mpg-bench compare` runs all seeds of one method before the next, and
this machine's speed moved by up to 1.3x between runs of one command).

    python bench/ab_params.py sphere --time 20 --seeds 4 --variants '{}' '{"chain_rate_min": 0.015625}'
    python bench/ab_params.py emitter_size_003 --param res=128 --time 10 --seeds 3 \\
        --variants '{}' '{"chain_rate_min": 0.015625}'

Each variant is a JSON object of `mpg` parameters ('{}': the defaults).
Prints MSE, MSE less the reference's floor (docs/results.md, "Metrics"),
relMSE and spp per run and per variant; needs the scene's reference in the
cache (mpg-bench reference). Writes bench/results/ab_params-<scene>.json."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> int:
    import mpg
    from mpg import metrics
    from mpg.bench import reference as refmod
    from mpg.bench.scenes import resolve_scene

    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--time", type=float, default=20.0)
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                    help="scene parameter, e.g. res=128 (repeatable)")
    ap.add_argument("--variants", nargs="+", required=True, metavar="JSON")
    args = ap.parse_args()
    try:
        variants = [json.loads(v) for v in args.variants]
    except json.JSONDecodeError as e:
        ap.error(f"a variant is not JSON: {e}")
    if not all(isinstance(v, dict) for v in variants):
        ap.error("each variant must be a JSON object, e.g. '{\"chain_rate_min\": 0.0625}'")
    params = dict(p.split("=", 1) for p in args.param)
    bs = resolve_scene(args.scene, params)
    info = refmod.find_reference(bs)
    if info is None:
        print(f"ab_params: no cached reference of {args.scene} {params}; make it with mpg-bench reference",
              file=sys.stderr)
        return 1
    ref = refmod.load_reference(info)[0]
    floor = float(info["convergence"].get("mse_floor_image") or 0.0)
    sc = mpg.load_file(bs.path, **params)
    runs: list[list[dict]] = [[] for _ in variants]
    for seed in range(args.seeds):
        order = list(range(len(variants)))
        if seed % 2:
            order.reverse()
        for i in order:
            img = mpg.render(sc, dict(type="mpg", **variants[i]), time=args.time, seed=seed, progress=False)
            rec = {"seed": seed, "spp": int(img.spp), "mse": metrics.mse(img.rgb, ref),
                   "relmse": metrics.relmse(img.rgb, ref)}
            runs[i].append(rec)
            print(f"{args.scene} seed {seed} {json.dumps(variants[i])}: MSE {rec['mse']:.4g} "
                  f"relMSE {rec['relmse']:.3g} spp {rec['spp']}", flush=True)
    out = {"command": " ".join(sys.argv), "scene": args.scene, "params": params, "time": args.time,
           "mse_floor_image": floor, "variants": []}
    for v, rs in zip(variants, runs):
        m = float(np.mean([r["mse"] for r in rs]))
        summ = {"variant": v, "runs": rs, "mse": m, "mse_above_floor": m - floor,
                "relmse": float(np.mean([r["relmse"] for r in rs])),
                "spp": float(np.mean([r["spp"] for r in rs]))}
        out["variants"].append(summ)
        print(f"== {json.dumps(v)}: MSE {m:.4g} (less floor {m - floor:.4g}) relMSE {summ['relmse']:.3g} "
              f"spp {summ['spp']:.0f}")
    res = ROOT / "bench" / "results"
    res.mkdir(parents=True, exist_ok=True)
    (res / f"ab_params-{args.scene}.json").write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
