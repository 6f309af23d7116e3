"""The cost of a manifold-walk vertex step in path-tracer rays: the constant
`mpg.chain_rates.STEP_COST` that turns counted work into time for the
per-pixel chain rates.

    python bench/step_cost.py [--scenes sphere double_slabs chain_length_4 emitter_size_003 visibility_4]

Per scene (128^2, one thread, so that wall time is CPU time): `sms_star` gives
ns per chain step (stat chain_ns / chain_steps), `path` gives ns per ray (wall
time / camera + extension + shadow rays); their ratio is a step's cost in rays.
A chain step counts the traced seed and the accepted Newton iterations only;
a third render with count_limits counts every tried vertex (the seed and each
line-search try, stat limit_steps_full) on the same kind of paths, which
gives the cost of a tried vertex in rays: mpg.guiding.TRY_COST.
Writes bench/results/step_cost.json."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> int:
    import mpg
    from mpg import _core
    from mpg.bench.scenes import resolve_scene

    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", nargs="+",
                    default=["sphere", "double_slabs", "chain_length_4", "emitter_size_003", "visibility_4"])
    ap.add_argument("--spp", type=int, default=16)
    args = ap.parse_args()
    out = {"command": " ".join(sys.argv), "scenes": {}}
    for name in args.scenes:
        bs = resolve_scene(name)
        sc = mpg.load_file(bs.path, **dict(bs.params, res="128"))
        sc.core
        chain = mpg.render(sc, integrator="sms_star", spp=args.spp, seed=1, threads=1, progress=False).stats
        t = time.perf_counter()
        path = mpg.render(sc, integrator="path", spp=args.spp, seed=1, threads=1, progress=False).stats
        wall = time.perf_counter() - t
        ns_step = chain["chain_ns"] / max(chain["chain_steps"], 1)
        ns_ray = wall * 1e9 / (path["rays"] + path["shadow_rays"] + path["camera_rays"])
        # tried vertices per chain step, counted (not timed: the counting adds rounds)
        integ = _core.make_integrator(sc.core, "sms_star", {"count_limits": True})
        job = _core.RenderJob(sc.core, integ, args.spp, 1, 0, 1)
        job.wait(1e9)
        cl = job.result()["stats"]
        tried = cl["limit_steps_full"] / max(cl["chain_steps"], 1)
        out["scenes"][name] = {"ns_per_chain_step": ns_step, "ns_per_ray": ns_ray, "ratio": ns_step / ns_ray,
                               "tried_per_chain_step": tried, "try_ratio": ns_step / tried / ns_ray}
        print(f"{name:18s} {ns_step:8.1f} ns/step {ns_ray:7.1f} ns/ray  ratio {ns_step / ns_ray:.2f}"
              f"  tried vertices/step {tried:.2f}  ratio per tried vertex {ns_step / tried / ns_ray:.2f}")
    res = ROOT / "bench" / "results"
    res.mkdir(parents=True, exist_ok=True)
    (res / "step_cost.json").write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
