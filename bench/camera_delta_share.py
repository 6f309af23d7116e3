"""How much of an equal-time MSE is the light seen from the camera through delta
scattering only (a light's own images in glass or a mirror, e.g. the glints of
a small light in a bumpy slab top).

Every integrator here estimates that light the same way, one camera path per
sample (no separator, so no NEE or chain estimate has it): its share of a
render's MSE is C / spp, with C its per-sample variance (mean over pixels and
channels). C is measured with `path` at camera_delta=only, which renders that
light alone and ends each path at its first non-delta vertex.

    python bench/camera_delta_share.py --scenes sphere double_slabs --time 20 \\
        --compare bench/results/compare-handoff3
    python bench/camera_delta_share.py --scenes emitter_size_001 emitter_size_003 --param res=128 \\
        --compare bench/results/compare-emitter-delta

With --compare DIR (an `mpg-bench compare` folder): per scene and integrator,
the mean spp and MSE of its runs, C / spp, and what is left of the MSE without
it and without the reference's own MSE floor. Writes
bench/results/camera_delta_share.json."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> int:
    import mpg

    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", nargs="+", required=True, help="names in scenes/eval")
    ap.add_argument("--time", type=float, default=20.0, help="seconds of the camera_delta=only render")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--param", action="append", default=[], metavar="K=V", help="scene parameter")
    ap.add_argument("--compare", help="an mpg-bench compare output folder")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "camera_delta_share.json"))
    args = ap.parse_args()
    params = dict(kv.split("=", 1) for kv in args.param)
    runs = {}
    if args.compare:
        data = json.loads((pathlib.Path(args.compare) / "results.json").read_text())
        for sc in data["scenes"]:
            floor = sc["reference"]["convergence"].get("mse_floor_image")
            if floor is None:   # a run from before references reported it: from the EXR
                from mpg.image import read_exr

                floor = float(read_exr(sc["reference"]["exr"])[1].astype(np.float64).mean())
            for m in sc["methods"]:
                rs = m["runs"]
                runs.setdefault(sc["scene"]["name"], {})[m["integrator"]] = {
                    "spp": float(np.mean([r["spp"] for r in rs])),
                    "mse": float(np.mean([r["metrics"]["image"]["mse"] for r in rs])),
                    "mse_floor": floor}
    out = {"command": " ".join(["python", "bench/camera_delta_share.py"] + sys.argv[1:]), "scenes": {}}
    for name in args.scenes:
        sc = mpg.load_file(ROOT / "scenes" / "eval" / f"{name}.xml", **params)
        im = mpg.render(sc, {"type": "path", "camera_delta": "only"}, time=args.time, seed=args.seed,
                        progress=False)
        per_px = im.variance.astype(np.float64).mean(axis=2) * im.spp
        C = float(per_px.mean())
        worst = np.sort(per_px.ravel())[::-1]
        entry = {"spp": im.spp, "C": C, "share_of_10_worst_pixels": float(worst[:10].sum() / max(worst.sum(), 1e-300)),
                 "integrators": {}}
        print(f"{name}: camera_delta=only {im.spp} spp in {args.time:g} s, per-sample variance C = {C:.4g} "
              f"(10 worst pixels: {100 * entry['share_of_10_worst_pixels']:.0f} %)")
        for integ, r in runs.get(name, {}).items():
            part = C / r["spp"]
            rest = r["mse"] - part - (r["mse_floor"] or 0.0)
            entry["integrators"][integ] = dict(r, camera_delta_mse=part, rest=rest)
            print(f"  {integ:28s} {r['spp']:7.0f} spp  MSE {r['mse']:.4g} = C/spp {part:.4g} "
                  f"({100 * part / r['mse']:.0f} %) + reference floor {r['mse_floor'] or 0:.3g} + rest {rest:.4g}")
        out["scenes"][name] = entry
    pathlib.Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    pathlib.Path(args.out).write_text(json.dumps(out, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
