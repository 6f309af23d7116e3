"""Per-sample variance and time per sample of several integrators on a small
crop of an evaluation scene: where one estimator renders the same light as well
as another for less time (docs/design-notes.md, "Handing pixels to the path
tracer").

    python bench/crop_variance.py sphere --center 157 147 --integrators path sms_star mpg mpg/chain_handoff=false
    python bench/crop_variance.py double_slabs --center 127 115 --spp 256
    python bench/crop_variance.py sphere --center 155 147 --half 6 --spp 4096 --integrators path \
        --sampler stratified --out bench/results/crop_variance-sphere-focus-stratified.json

For each integrator: the crop's mean per-sample variance (the image variance x
spp), the seconds per sample per pixel, and their product (lower is better).
Also one `sms_star` pass with recorded costs: the chains' second moment
E[X^2] over the crop against a sample's variance -- how much of the noise the
chain estimates carry. Writes bench/results/crop_variance-<scene>.json."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> int:
    import mpg
    from mpg import _core

    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--center", type=int, nargs=2, required=True, metavar=("X", "Y"))
    ap.add_argument("--half", type=int, default=8, help="half the crop's side in pixels")
    ap.add_argument("--spp", type=int, default=512)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--integrators", nargs="+", default=["path", "sms_star", "mpg"],
                    help="names, with parameters as in mpg-bench: mpg/chain_handoff=false")
    ap.add_argument("--sampler", choices=("independent", "stratified"), default=None,
                    help="pixel positions (default: the scene's)")
    ap.add_argument("--out", default=None, help="result file (default bench/results/crop_variance-SCENE.json)")
    args = ap.parse_args()
    (cx, cy), h = args.center, args.half
    path = ROOT / "scenes" / "eval" / f"{args.scene}.xml"
    crop = (f'<integer name="crop_offset_x" value="{cx - h}"/><integer name="crop_offset_y" value="{cy - h}"/>'
            f'<integer name="crop_width" value="{2 * h}"/><integer name="crop_height" value="{2 * h}"/>')
    sc = mpg.load_string(path.read_text().replace("<rfilter", crop + "<rfilter", 1), base_dir=str(path.parent))
    out: dict = {"command": " ".join(sys.argv), "crop": [cx - h, cy - h, 2 * h, 2 * h], "integrators": {}}
    for name in args.integrators:
        t0 = time.monotonic()
        integ, *kv = name.split("/")
        img = mpg.render(sc, dict(type=integ, **dict(x.split("=", 1) for x in kv)), spp=args.spp,
                         seed=args.seed, progress=False, sampler=args.sampler)
        sec = time.monotonic() - t0
        var = float((img.variance * img.spp).mean())
        per = sec / img.spp / (4 * h * h)
        out["integrators"][name] = {"spp": img.spp, "seconds": sec, "mean": float(img.rgb.mean()),
                                    "variance_per_sample": var,
                                    "seconds_per_sample": per, "variance_x_time": var * per}
        print(f"{name:10s} {img.spp:5d} spp  per-sample variance {var:10.4g}  "
              f"{1e6 * per:8.2f} us/sample  product {var * per:.4g}")
    job = _core.RenderJob(sc.core, _core.make_integrator(sc.core, "sms_star", {}), args.spp, args.seed, 0, 0,
                          record_costs=True)
    while not job.wait(0.05):
        pass
    r = job.result()
    n = args.spp
    mean = r["sum"] / n
    var = np.maximum(r["sum_sq"] / n - mean * mean, 0.0).mean() * n / (n - 1)
    share = float((r["chain_m2"] / n).mean() / var) if var > 0 else 0.0
    out["sms_star_chain_m2_over_variance"] = share
    print(f"sms_star: chains' E[X^2] / a sample's variance = {share:.3g}")
    res = ROOT / "bench" / "results"
    res.mkdir(parents=True, exist_ok=True)
    dest = pathlib.Path(args.out) if args.out else res / f"crop_variance-{args.scene}.json"
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps(out, indent=2))
    print(f"wrote {dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
