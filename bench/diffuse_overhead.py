"""Cost of `mpg` where there is nothing to guide (issue 5 target: the
diffuse-only scene renders with `mpg` within 3 % of `path`'s time).

    python bench/diffuse_overhead.py [--scene diffuse_room] [--spp 64] [--repeats 5]

Renders scenes/eval/SCENE.xml with `path` and `mpg` at the same spp, the two
interleaved (path, mpg, path, mpg, ...) after one warm-up each so that a
drift of the machine's speed hits both; reports the best and the median wall
time of each and their ratio. Writes bench/results/diffuse_overhead.json."""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="diffuse_room")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    import mpg

    sc = mpg.load_file(ROOT / "scenes" / "eval" / f"{args.scene}.xml")
    _ = sc.core
    times: dict[str, list[float]] = {"path": [], "mpg": []}
    same = True
    for name in times:                      # warm-up
        mpg.render(sc, integrator=name, spp=1, threads=args.threads, progress=False)
    for _ in range(args.repeats):
        imgs = {}
        for name in times:
            t0 = time.perf_counter()
            imgs[name] = mpg.render(sc, integrator=name, spp=args.spp, seed=1, threads=args.threads,
                                    progress=False)
            times[name].append(time.perf_counter() - t0)
        same = same and bool((imgs["path"].rgb == imgs["mpg"].rgb).all())
        st = imgs["mpg"].stats
    out = {"scene": args.scene, "spp": args.spp, "threads": args.threads, "repeats": args.repeats,
           "seconds": times, "identical_images": same,
           "mpg_training_iterations": st["training_iterations"], "mpg_chain_estimates": st["chain_estimates"]}
    for k in ("best", "median"):
        f = min if k == "best" else statistics.median
        out[f"ratio_{k}"] = f(times["mpg"]) / f(times["path"])
    print(f"{args.scene}, {args.spp} spp, {args.threads} threads: path best {min(times['path']):.3f} s "
          f"median {statistics.median(times['path']):.3f} s; mpg best {min(times['mpg']):.3f} s "
          f"median {statistics.median(times['mpg']):.3f} s; mpg/path best {out['ratio_best']:.3f} "
          f"median {out['ratio_median']:.3f}; identical images: {same}")
    os.makedirs(ROOT / "bench" / "results", exist_ok=True)
    (ROOT / "bench" / "results" / "diffuse_overhead.json").write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
