"""Where an image's MSE sits by brightness: renders of each integrator against
the cached reference, the image MSE split into bins of the reference's pixel
luminance (each bin's sum of squared errors over the whole pixel count, so
the bins add up to the MSE), beside the same split of the render's own
variance estimate (what the error should be without bias).

    python bench/error_bins.py sphere --integrators path mpg --time 30 --seeds 0 1

Needs the scene's reference in the cache (mpg-bench reference). Writes
bench/results/error_bins-<scene>.json and prints a table."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
EDGES = (0.0, 0.1, 0.5, 2.0, 10.0, float("inf"))


def main() -> int:
    import mpg
    from pixel_errors import cached_reference   # bench/, the script's own folder

    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--integrators", nargs="+", default=["path", "mpg"])
    ap.add_argument("--time", type=float, default=30.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    args = ap.parse_args()

    found = cached_reference(args.scene, "error_bins")
    if found is None:
        return 2
    sc, ref = found
    lum = ref.mean(axis=2)
    scene = sc.load_mpg()
    rows = []
    for integ in args.integrators:
        for seed in args.seeds:
            img = mpg.render(scene, integ, time=args.time, seed=seed, progress=False)
            se = ((img.rgb.astype(np.float64) - ref) ** 2).mean(axis=2)
            var = img.variance.astype(np.float64).mean(axis=2)
            flat = np.sort(se.ravel())[::-1]
            bins = []
            for a, b in zip(EDGES[:-1], EDGES[1:]):
                m = (lum >= a) & (lum < b)
                bins.append({"lum": [a, b], "pixels": int(m.sum()), "mse": float(se[m].sum() / se.size),
                             "variance": float(var[m].sum() / se.size)})
            rows.append({"integrator": integ, "seed": seed, "spp": img.spp, "mse": float(se.mean()),
                         "top_share": {str(k): float(flat[:k].sum() / flat.sum()) for k in (1, 10, 100)},
                         "bins": bins})
    print(f"{args.scene}, {args.time:g} s: MSE part per reference-luminance bin (estimated variance part)")
    head = "| integrator | seed | spp | MSE | " + " | ".join(
        f"[{a:g}, {b:g})" for a, b in zip(EDGES[:-1], EDGES[1:])) + " |"
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for r in rows:
        cells = " | ".join(f"{x['mse']:.2g} ({x['variance']:.2g})" for x in r["bins"])
        print(f"| {r['integrator']} | {r['seed']} | {r['spp']} | {r['mse']:.3g} | {cells} |")
    print("pixels per bin:", [x["pixels"] for x in rows[0]["bins"]])
    out = ROOT / "bench" / "results" / f"error_bins-{args.scene}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"command": " ".join(sys.argv), "time": args.time, "rows": rows}, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
