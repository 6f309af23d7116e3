"""mpg-bench: references, equal-time comparisons, convergence curves and cost tables.

    mpg-bench reference SCENE [--time S | --spp N] [--cache DIR]
    mpg-bench reference --list
    mpg-bench compare --scenes A B --integrators path mitsuba:path mitsuba:ptracer --time 10 --seeds 4
    mpg-bench curves  --scenes A B --integrators path mitsuba:path --times 1 2 4 8 --seeds 4
    mpg-bench costs   --scenes A B --integrators path --time 10

Outputs go to --out (default bench/results/<command>-<timestamp>/): report.md,
results.json and PNG figures. docs/results.md explains the metrics.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from mpg.errors import MPGError

# The default suite: the eval scenes that are not part of a parameter series (when
# scenes/eval exists), else the two development scenes. "series:NAME" on the command
# line expands to a series' scenes in order of their value.
DEFAULT_SUITE = ["sphere", "slab", "double_slabs", "ring", "pool", "plane", "sphere_point",
                 "diffuse_room"]
DEFAULT_SCENES = ["default"]
DEFAULT_INTEGRATORS = ["path", "mitsuba:path", "mitsuba:ptracer"]


def _common(p: argparse.ArgumentParser, scenes: bool = True) -> None:
    if scenes:
        p.add_argument("--scenes", nargs="+", default=DEFAULT_SCENES, metavar="SCENE",
                       help="scene files or names (scenes/eval/NAME.xml, scenes/NAME.xml), "
                       "'series:NAME' (a series of scenes/eval), or 'default' (the default "
                       f"suite: {' '.join(DEFAULT_SUITE)})")
        p.add_argument("--integrators", nargs="+", default=DEFAULT_INTEGRATORS, metavar="ENTRY",
                       help="mpg integrator names, with parameters as NAME/key=value/... "
                       "(e.g. mpg/init=photon), or mitsuba:NAME[@VARIANT]; default "
                       f"{' '.join(DEFAULT_INTEGRATORS)}")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="override a <default> of every scene (e.g. res=64); repeatable")
    p.add_argument("--threads", type=int, help="mpg render threads (default: all cores)")


def _refopts(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cache", help="reference cache (default $MPG_CACHE or "
                   "~/.cache/mpg/references)")
    p.add_argument("--reference-time", type=float,
                   help="budget of a reference made because none is cached "
                   "(default max(10 s, 20 x the longest render))")
    p.add_argument("--out", help="output folder (default bench/results/<command>-<timestamp>)")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="mpg-bench", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("reference", help="make (or list) cached reference images")
    r.add_argument("scene", nargs="?", help="scene file or name")
    g = r.add_mutually_exclusive_group()
    g.add_argument("--time", type=float, help="total budget in seconds")
    g.add_argument("--spp", type=int, help="samples per pixel per renderer")
    r.add_argument("--passes", type=int, default=8,
                   help="independent passes per renderer (at least; default 8)")
    r.add_argument("--seed", type=int, help="base seed (default 1000000)")
    r.add_argument("--method", default="auto", choices=["auto", "mitsuba", "mpg"],
                   help="auto: Mitsuba ptracer+path unless the sidecar says 'mpg' or Mitsuba "
                   "is missing")
    r.add_argument("--integrator", default="path", help="mpg integrator for --method mpg")
    r.add_argument("--camera-delta", metavar="INTEGRATOR",
                   help="--method mpg: render the light seen from the camera through delta "
                   "scattering only (a light in glass or a mirror) apart with this integrator "
                   "(e.g. path), half the budget; for tiny bright lights")
    r.add_argument("--fill", metavar="INTEGRATOR",
                   help="Mitsuba reference: render the pixels its light tracer cannot see with "
                   "this mpg integrator (e.g. sms_star) instead of Mitsuba's path tracer "
                   "(default: the sidecar's reference_fill)")
    r.add_argument("--cache", help="cache folder (default $MPG_CACHE or ~/.cache/mpg/references)")
    r.add_argument("--force", action="store_true", help="render even if cached")
    r.add_argument("--list", action="store_true", help="list the cached references")
    _common(r, scenes=False)

    c = sub.add_parser("compare", help="equal-time comparison against the reference")
    _common(c)
    c.add_argument("--time", type=float, default=10.0, help="seconds per render (default 10)")
    c.add_argument("--seeds", type=int, default=4, help="renders per method (default 4)")
    c.add_argument("--exposure", type=float, default=0.0, help="figure exposure in stops")
    _refopts(c)

    cv = sub.add_parser("curves", help="error against wall time (log-log)")
    _common(cv)
    cv.add_argument("--times", type=float, nargs="+", default=[1, 2, 4, 8],
                    help="time budgets in seconds (default 1 2 4 8)")
    cv.add_argument("--seeds", type=int, default=4, help="renders per method and time (default 4)")
    cv.add_argument("--target-relmse", type=float,
                    help="relMSE whose time-to-reach is tabulated (default: per scene, the "
                    "highest final relMSE over the methods)")
    cv.add_argument("--metric", default="relmse", choices=["mse", "relmse", "mape", "seed_var"],
                    help="metric plotted (default relmse; seed_var: the seeds' variance, an unbiased "
                    "method's MSE without the reference's noise, needs --seeds 2 or more)")
    _refopts(cv)

    co = sub.add_parser("costs", help="per-render statistics table (like MPG Table 2)")
    _common(co)
    g = co.add_mutually_exclusive_group()
    g.add_argument("--time", type=float, help="seconds per render (default 5)")
    g.add_argument("--spp", type=int, help="samples per pixel per render")
    co.add_argument("--out", help="output folder (default bench/results/costs-<timestamp>)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _run(args, argv)
    except MPGError as e:
        print(f"mpg-bench: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("\nmpg-bench: interrupted", file=sys.stderr)
        return 130


def _run(args, argv) -> int:
    from mpg.bench import report
    from mpg.bench.runners import parse_integrator
    from mpg.bench.scenes import BenchError, parse_params, resolve_scene

    params = parse_params(args.param)
    if args.threads is not None and args.threads < 1:
        raise BenchError(f"--threads must be at least 1, got {args.threads}")

    if args.command == "reference":
        from mpg.bench import reference as ref

        if args.list:
            return _list(ref.list_references(args.cache), ref.cache_dir(args.cache))
        if not args.scene:
            raise BenchError("reference: give a SCENE (or --list)")
        sc = resolve_scene(args.scene, params)
        if args.time is None and args.spp is None:
            raise BenchError("reference: give --time SECONDS or --spp N")
        info = ref.make_reference(sc, time=args.time, spp=args.spp, passes=args.passes,
                                  seed=ref.DEFAULT_SEED if args.seed is None else args.seed,
                                  method=args.method, integrator=args.integrator,
                                  cache=args.cache, force=args.force,
                                  camera_delta=args.camera_delta, fill=args.fill)
        print(info["exr"])
        return 0

    scenes = [resolve_scene(s, params) for s in expand_scenes(args.scenes)]
    specs = [parse_integrator(t) for t in args.integrators]
    out = report.out_dir(args.command, args.out)
    if args.command == "compare":
        from mpg.bench import compare

        compare.run(scenes, specs, args.time, args.seeds, out, argv, args.cache,
                    args.reference_time, threads=args.threads, exposure=args.exposure)
    elif args.command == "curves":
        from mpg.bench import curves

        curves.run(scenes, specs, args.times, args.seeds, out, argv, args.cache,
                   args.reference_time, target_relmse=args.target_relmse, metric=args.metric,
                   threads=args.threads)
    elif args.command == "costs":
        from mpg.bench import costs

        time = args.time if (args.time is not None or args.spp is not None) else 5.0
        costs.run(scenes, specs, time, args.spp, out, argv, threads=args.threads)
    print(out)
    print(f"mpg-bench: wrote {out}/report.md", file=sys.stderr)
    return 0


def expand_scenes(names: Sequence[str]) -> list[str]:
    import glob
    import json
    import os

    from mpg.bench.scenes import REPO, BenchError

    eval_dir = next((d for d in (os.path.join("scenes", "eval"),
                                 os.path.join(REPO, "scenes", "eval")) if os.path.isdir(d)), None)
    out: list[str] = []
    for n in names:
        if n == "default":
            have = [s for s in DEFAULT_SUITE
                    if eval_dir and os.path.isfile(os.path.join(eval_dir, s + ".xml"))]
            out += have or ["sphere_glass", "slab_glass"]
        elif n.startswith("series:"):
            series = []
            for f in sorted(glob.glob(os.path.join(eval_dir or "", "*.json"))):
                with open(f) as fh:
                    sc = json.load(fh)
                se = sc.get("series") or {}
                if se.get("name") == n[len("series:"):]:
                    series.append((se.get("value", 0), os.path.splitext(f)[0] + ".xml"))
            if not series:
                raise BenchError(f"no scenes in series '{n[len('series:'):]}' "
                                 f"(in {eval_dir or 'scenes/eval'})")
            out += [p for _, p in sorted(series)]
        else:
            out.append(n)
    return out


def _list(infos, d: str) -> int:
    from mpg.bench import report

    if not infos:
        print(f"no references in {d}")
        return 0
    rows = []
    for i in infos:
        rec = i["recipe"]
        budget = f"{rec['time']:g} s" if rec.get("time") is not None else f"{rec['spp']} spp"
        c = i["convergence"]
        sc = i["scene"]
        params = ",".join(f"{k}={v}" for k, v in sorted(sc.get("params", {}).items()))
        rows.append([sc["name"] + (f"[{params}]" if params else ""),
                     "x".join(str(v) for v in i.get("resolution", [])), rec["method"], budget,
                     report.fmt(c["median_pixel_rel_error"]), report.fmt(c["rse_image_mean"]),
                     report.fmt(c.get("rse_caustic_mean")), i["created"], i["exr"]])
    print(f"references in {d}:\n")
    print(report.md_table(["scene", "res", "method", "budget", "median pixel rel. err",
                           "image-mean rel. SE", "caustic-mean rel. SE", "created", "file"],
                          rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
