"""Path-tracing throughput: mpg `path` against Mitsuba 3 `path` (scalar_rgb and
llvm_ad_rgb) on the same scene files, same resolution and spp, 2 threads, in
the same run. Each renderer runs in its own process (so its peak memory is its own
ru_maxrss) and renders once to warm up (JIT compilation, file caches)
before the timed render.

    python bench/pt_throughput.py [--spp 64] [--res 256] [--threads 2] [--repeats 3]

Writes bench/results/pt_throughput.json and .md. Speed is reported as samples
per second (pixels x spp / wall time of the render call) and as the ratio of
mpg to each Mitsuba variant measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = ["sphere_glass.xml", "materials.xml"]
RENDERERS = ["mpg", "mitsuba_scalar_rgb", "mitsuba_llvm_ad_rgb"]


def worker(renderer: str, scene: str, spp: int, res: int, threads: int, repeats: int) -> dict:
    path = str(ROOT / "scenes" / scene)
    params = {"res": str(res), "spp": str(spp), "max_depth": "8"}
    if renderer == "mpg":
        import mpg

        sc = mpg.load_file(path, **params)
        mpg.render(sc, spp=1, threads=threads, progress=False)  # warm-up
        times = []
        for k in range(repeats):
            t0 = time.perf_counter()
            mpg.render(sc, spp=spp, threads=threads, seed=k, progress=False)
            times.append(time.perf_counter() - t0)
    else:
        import drjit as dr
        import mitsuba as mi

        mi.set_variant(renderer.replace("mitsuba_", ""))
        dr.set_thread_count(threads)
        sc = mi.load_file(path, **params)
        img = mi.render(sc, spp=spp, seed=100)  # warm-up at the same spp (kernel cache)
        dr.eval(img)
        times = []
        for k in range(repeats):
            t0 = time.perf_counter()
            img = mi.render(sc, spp=spp, seed=k)
            dr.eval(img)
            dr.sync_thread()
            times.append(time.perf_counter() - t0)
    best = min(times)
    return {"seconds": best, "all_seconds": times, "samples_per_second": res * res * spp / best}


def run_one(renderer, scene, args) -> dict:
    cmd = [sys.executable, __file__, "--worker", renderer, scene, "--spp", str(args.spp),
           "--res", str(args.res), "--threads", str(args.threads), "--repeats", str(args.repeats)]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = p.communicate()
    if p.returncode != 0:
        return {"error": (err.strip().splitlines() or ["failed"])[-1]}
    res = json.loads(out.strip().splitlines()[-1])
    res["peak_rss_mb"] = res.pop("_peak_rss_kb", 0) / 1024.0
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", nargs=2, metavar=("RENDERER", "SCENE"))
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results"))
    args = ap.parse_args()

    if args.worker:
        import resource

        r = worker(args.worker[0], args.worker[1], args.spp, args.res, args.threads, args.repeats)
        r["_peak_rss_kb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        print(json.dumps(r))
        return 0

    results = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
               "spp": args.spp, "res": args.res, "threads": args.threads, "scenes": {}}
    for scene in SCENES:
        results["scenes"][scene] = {}
        for r in RENDERERS:
            print(f"{scene}: {r} ...", file=sys.stderr, flush=True)
            results["scenes"][scene][r] = run_one(r, scene, args)
    lines = [f"# Path-tracing throughput ({args.res}x{args.res}, {args.spp} spp, "
             f"{args.threads} threads, best of {args.repeats})", "",
             "| scene | renderer | M samples/s | peak RSS (MB) | mpg / this |",
             "|---|---|---:|---:|---:|"]
    for scene, per in results["scenes"].items():
        base = per["mpg"].get("samples_per_second")
        for r, v in per.items():
            if "error" in v:
                lines.append(f"| {scene} | {r} | error: {v['error']} | | |")
                continue
            ratio = base / v["samples_per_second"] if base else float("nan")
            lines.append(f"| {scene} | {r} | {v['samples_per_second'] / 1e6:.2f} | "
                         f"{v['peak_rss_mb']:.0f} | {ratio:.2f} |")
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "pt_throughput.json"), "w") as f:
        json.dump(results, f, indent=2)
    with open(os.path.join(args.out, "pt_throughput.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
