"""What the manifold walk's line search costs and buys: the walk settings
`min_step` and `step_halvings` (docs/design-notes.md, "Step control") on

1. the chain estimator's work (sms_star, 128^2, 8 spp, seed 1): chain time per
   estimate, first-trial convergence, Bernoulli trials per estimate, line-search
   tries and off-surface landings per walk (--scenes);
2. a planar mirror lit by a point light at distances 1 to 0.01 from it (the
   closed-form scene of tests/test_chains.py, 64^2, 3 s): MSE x seconds against
   the closed form, for sms_star and mpg;
3. 200 walks from random seeds towards a light 0.05 above a large mirror
   (the case of tests/test_manifold.py): how many converge, and the tries
   (line-search reprojections) and off-surface landings of those that do;
4. (--suite) variance x time without a reference: mean over pixels of the
   estimated variance of the pixel mean x seconds, 10 s, 2 seeds, 128^2.

    python bench/line_search.py [--scenes double_slabs sphere] [--suite slab ring pool plane sphere_point]

Writes bench/results/line_search.json. Every setting is unbiased (the walk is
a deterministic map from seed to solution, the same in the estimate and its
Bernoulli trials); only the efficiency differs."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

SETTINGS = {"full search": {"step_halvings": -1}, "step_halvings=2": {"step_halvings": 2},
            "min_step=0.5": {"min_step": 0.5}}
# mpg's default: the limit chosen in training (mpg.guiding.choose_step_halvings)
MPG_SETTINGS = dict(SETTINGS, **{"auto": {"step_halvings": "auto"}})


def settings(integ: str) -> dict:
    return MPG_SETTINGS if integ == "mpg" else SETTINGS


def main() -> int:
    import mpg
    from mpg.bench.scenes import resolve_scene
    from test_chains import mirror_expected, mirror_scene

    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", nargs="*", default=["double_slabs", "sphere"])
    ap.add_argument("--suite", nargs="*", default=[])
    args = ap.parse_args()
    out: dict = {"command": " ".join(sys.argv), "work": {}, "mirror": {}, "suite": {}}

    for name in args.scenes:
        bs = resolve_scene(name)
        sc = mpg.load_file(bs.path, **dict(bs.params, res="128"))
        for label, cfg in SETTINGS.items():
            s = mpg.render(sc, integrator=dict({"type": "sms_star"}, **cfg), spp=8, seed=1, progress=False).stats
            est = max(s["chain_estimates"], 1)
            walks = est + s["bernoulli_trials"]
            row = {"us_per_estimate": s["chain_ns"] / est / 1e3, "converged": s["chain_converged"] / est,
                   "trials_per_estimate": s["bernoulli_trials"] / est,
                   "tries_per_walk": s["walk_reprojections"] / walks, "off_surface_per_walk": s["walk_off_surface"] / walks}
            out["work"].setdefault(name, {})[label] = row
            print(f"{name:13s} {label:16s} " + " ".join(f"{k} {v:.3g}" for k, v in row.items()), flush=True)

    for lx in (0.0, 0.9, 0.97, 0.99):
        sc = mpg.load_string(mirror_scene(64, lx))
        exp = mirror_expected(64, lx=lx)
        for integ in ("sms_star", "mpg"):
            for label, cfg in settings(integ).items():
                r = mpg.render(sc, integrator=dict({"type": integ}, **cfg), time=3, seed=1, progress=False)
                v = float(np.mean((r.rgb[..., 0] - exp) ** 2)) * r.stats["seconds"]
                conv = r.stats["chain_converged"] / max(r.stats["chain_estimates"], 1)
                out["mirror"].setdefault(f"{1 - lx:.2f}", {}).setdefault(integ, {})[label] = {
                    "mse_x_seconds": v, "converged": conv, "step_halvings": r.stats.get("step_halvings")}
                print(f"mirror, light {1 - lx:.2f} from it, {integ:8s} {label:16s} MSE x s {v:.3g}"
                      f"  first trials converged {conv:.3f}"
                      + (f"  (chose {r.stats['step_halvings']})" if label == "auto" else ""), flush=True)

    from mpg import _core
    from test_manifold import MIRROR
    big = mpg.load_string(MIRROR).core
    rng = np.random.default_rng(3)
    dirs = [[rng.uniform(-1, 1), -1, rng.uniform(-1, 1)] for _ in range(200)]
    for label, cfg in SETTINGS.items():
        walks = [_core.manifold_walk(big, [0, 1, 0], [0, -1, 0], [1, 0.05, 0], [0, 1, 0], d, "R", cfg) for d in dirs]
        ok = [w for w in walks if w["converged"]]
        tries = np.array([w["reprojections"] for w in ok] or [0])
        off = np.array([w["off_surface"] for w in ok] or [0])
        row = {"converged": len(ok), "tries_median": float(np.median(tries)), "tries_max": int(tries.max()),
               "off_surface_mean": float(off.mean())}
        out["walks"] = dict(out.get("walks", {}), **{label: row})
        print(f"200 walks, light 0.05 above a mirror, {label:16s} " + " ".join(f"{k} {v:.3g}" for k, v in row.items()),
              flush=True)

    for name in args.suite:
        bs = resolve_scene(name)
        sc = mpg.load_file(bs.path, **dict(bs.params, res="128"))
        for integ in ("sms_star", "mpg"):
            for label, cfg in settings(integ).items():
                vals = []
                for seed in range(2):
                    r = mpg.render(sc, integrator=dict({"type": integ}, **cfg), time=10, seed=seed, progress=False)
                    vals.append(float(np.mean(r.variance)) * r.stats["seconds"])
                out["suite"].setdefault(name, {}).setdefault(integ, {})[label] = float(np.mean(vals))
            row = out["suite"][name][integ]
            print(f"{name:13s} {integ:8s} variance x s, relative to the full search: "
                  + " ".join(f"{k} {v / row['full search']:.2f}" for k, v in row.items()), flush=True)

    res = ROOT / "bench" / "results"
    res.mkdir(parents=True, exist_ok=True)
    (res / "line_search.json").write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    t0 = time.perf_counter()
    rc = main()
    print(f"{time.perf_counter() - t0:.0f} s")
    sys.exit(rc)
