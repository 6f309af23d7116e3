"""What a render pass costs beyond its samples: the same number of samples
per pixel rendered as many 1-spp passes and as a few longer ones, with one
thread and with all, interleaved and repeated so that a drift of the
machine's speed hits both. `mpg`'s time-limited renders cap a pass at an
eighth of the budget (render.time_limited_pass_spp), so a 1 s render of a
256x256 scene runs 1-spp passes; this measures what that costs.

    python bench/pass_overhead.py [--scene double_slabs] [--integrator path] [--spp 32] [--long 8] [--repeats 3]

Per thread count: the wall time of SPP passes of 1 spp and of SPP / LONG
passes of LONG spp (the core's RenderJob in a loop, as mpg.render runs it,
without the Python loop's own work), the best of the repeats, their
difference per 1-spp pass (ms) and their ratio. Writes
bench/results/pass_overhead.json (or --out)."""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]


def run_passes(core, integ, passes: int, spp: int, threads: int, seed: int) -> float:
    """Wall seconds of `passes` render passes of `spp` spp each."""
    from mpg import _core

    t0 = time.perf_counter()
    for p in range(passes):
        job = _core.RenderJob(core, integ, spp, seed, p, threads)
        while not job.wait(0.01):
            pass
        job.result()
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", default="double_slabs", help="scenes/eval/SCENE.xml")
    ap.add_argument("--integrator", default="path", help="a core integrator (its default parameters)")
    ap.add_argument("--spp", type=int, default=32, help="samples per pixel of each form")
    ap.add_argument("--long", type=int, default=8, help="spp of a long pass (divides --spp)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 0], help="thread counts (0: all cores)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    if args.spp < 1 or args.long < 1 or args.spp % args.long:
        ap.error("--spp must be a positive multiple of --long")
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")
    import mpg
    from mpg import _core
    from mpg.bench.report import write_json

    path = ROOT / "scenes" / "eval" / f"{args.scene}.xml"
    if not path.exists():
        ap.error(f"no scene {path}")
    sc = mpg.load_file(path)
    core = sc.core
    integ = _core.make_integrator(core, args.integrator, {})
    out: dict = {"command": " ".join(["python", "bench/pass_overhead.py"] + sys.argv[1:]),
                 "scene": args.scene, "integrator": args.integrator, "spp": args.spp, "long": args.long,
                 "cores": os.cpu_count(), "threads": {}}
    run_passes(core, integ, 2, 1, 0, 99)   # (warm-up)
    for th in args.threads:
        short, long_ = [], []
        for r in range(args.repeats):
            short.append(run_passes(core, integ, args.spp, 1, th, 1000 + r))
            long_.append(run_passes(core, integ, args.spp // args.long, args.long, th, 2000 + r))
        s, l = min(short), min(long_)
        row = {"short_seconds": s, "long_seconds": l, "ratio": s / l,
               "overhead_ms_per_pass": 1000.0 * (s - l) / args.spp,
               "ms_per_spp_long": 1000.0 * l / args.spp, "short_all": short, "long_all": long_}
        out["threads"][str(th)] = row
        name = "all cores" if th == 0 else f"{th} thread{'s' if th > 1 else ''}"
        print(f"{name:>10}: {args.spp} x 1 spp {s:.3f} s, {args.spp // args.long} x {args.long} spp {l:.3f} s: "
              f"{row['ratio']:.3f}x, {row['overhead_ms_per_pass']:.2f} ms a pass beyond its samples "
              f"({row['ms_per_spp_long']:.1f} ms a spp in long passes)")
    dest = pathlib.Path(args.out) if args.out else ROOT / "bench" / "results" / "pass_overhead.json"
    dest.parent.mkdir(parents=True, exist_ok=True)
    write_json(str(dest), out)
    print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
