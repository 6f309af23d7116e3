"""Where an image's error sits against the reference's own: renders of one
integrator (mean squared error per pixel over seeds) less the reference's
per-pixel variance of its mean, summed over the pixels where that variance is
above a threshold and over the rest, as shares of the image's MSE (the sums
are over the whole image's pixel count, so the two parts add up to the MSE
less the reference's floor). In a Mitsuba ptracer + path reference the
pixels with a large variance are the light seen in the glass, which the path
tracer renders there (docs/results.md, twenty-sixth session); with `mpg`, the
same split over the learned delta split's pixels (k > 1, branched or plain).
Writes bench/results/error_regions-<scene>-<integrator>.{json,png} (the
reference, the error map and the reference's variance map, log scale).

    python bench/error_regions.py double_slabs --integrator mpg --time 20 --seeds 2
    python bench/error_regions.py chain_length_4 --param res=128 --integrator path --time 10 --seeds 2
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> int:
    import mpg
    from pixel_errors import (add_param_option, load_with_reference, mpg_integrator,   # bench/
                              reference_with_variance, scene_params)

    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--integrator", default="mpg", help="name, with parameters as in mpg-bench: mpg/delta_plain=false")
    ap.add_argument("--time", type=float, default=20.0)
    ap.add_argument("--seeds", type=int, default=2)
    add_param_option(ap)
    ap.add_argument("--thresholds", type=float, nargs="+", default=[1e-3, 1e-2],
                    help="reference variance (of its mean, per pixel, mean over RGB) above which a pixel counts")
    args = ap.parse_args()
    params = scene_params(ap, args)
    integ = mpg_integrator(ap, args.integrator)
    if args.seeds < 1 or not args.time > 0:
        ap.error("--seeds must be >= 1 and --time > 0")
    loaded = load_with_reference(args.scene, params, "error_regions")
    if loaded is None:
        return 1
    _, sc, info = loaded
    found = reference_with_variance(info, "error_regions")
    if found is None:
        return 1
    ref, var = found
    v = var.astype(float).mean(axis=2)
    err = np.zeros(v.shape)
    kmap = bmap = None
    spp = []
    for seed in range(args.seeds):
        img = mpg.render(sc, integ, time=args.time, seed=seed, progress=False)
        err += ((img.rgb.astype(float) - ref) ** 2).mean(axis=2) / args.seeds
        spp.append(int(img.spp))
        if seed == 0:
            kmap, bmap = img.delta_split_map, img.delta_branch_map
    n = float(err.size)
    d = err - v
    out: dict = {"scene": args.scene, "params": args.param, "integrator": args.integrator, "time": args.time,
                 "seeds": args.seeds, "spp": spp, "mse": float(err.mean()), "reference_floor": float(v.mean()),
                 "mse_above_floor": float(d.mean()), "by_reference_variance": []}
    for t in args.thresholds:
        m = v > t
        out["by_reference_variance"].append({"threshold": t, "pixels": int(m.sum()),
                                             "above_floor": float(d[m].sum() / n),
                                             "rest_above_floor": float(d[~m].sum() / n)})
    if kmap is not None:   # (the first seed's maps; later seeds learn their own)
        split = np.asarray(kmap) > 1
        plain = split & (np.asarray(bmap) == 0) if bmap is not None else np.zeros_like(split)
        out["by_delta_split_seed0"] = {
            "branched_pixels": int((split & ~plain).sum()), "branched_above_floor": float(d[split & ~plain].sum() / n),
            "plain_pixels": int(plain.sum()), "plain_above_floor": float(d[plain].sum() / n),
            "unsplit_above_floor": float(d[~split].sum() / n)}
    stem = f"error_regions-{pathlib.Path(args.scene).stem}-{integ['type']}"
    res_dir = ROOT / "bench" / "results"
    res_dir.mkdir(parents=True, exist_ok=True)
    (res_dir / f"{stem}.json").write_text(json.dumps(out, indent=1))
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(1, 3, figsize=(15, 5.4))
        ax[0].imshow(np.clip(ref, 0, 1) ** (1 / 2.2))
        ax[0].set_title("reference")
        ax[1].imshow(np.log10(np.maximum(err, 1e-6)), vmin=-5, vmax=1, cmap="magma")
        ax[1].set_title(f"{args.integrator}: log10 squared error ({args.seeds} seeds, {args.time:g} s)")
        im = ax[2].imshow(np.log10(np.maximum(v, 1e-6)), vmin=-5, vmax=1, cmap="magma")
        ax[2].set_title("reference: log10 variance of its mean")
        for a in ax:
            a.axis("off")
        fig.colorbar(im, ax=ax, shrink=0.7)
        fig.savefig(res_dir / f"{stem}.png", dpi=70)
    except ImportError:
        pass
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
