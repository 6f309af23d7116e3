"""Where `mpg`'s variance sits against the path tracer's, at equal time: one
render of each (same seed), the `variance` channel (the variance of each
pixel's mean, mean over RGB) summed over the regions of `mpg`'s learned
`chain_rate_map` (rate 0: handed to the path tracer; (0, 1): chains by
roulette; 1) and divided by the pixel count, so the regions add up to the
image's mean variance; the share of the largest pixels; and the largest
pixels with their rate and the path tracer's variance there.

    python bench/variance_regions.py sphere --time 20 --seed 0
    python bench/variance_regions.py double_slabs --time 20 --seed 0 --top 12
    python bench/variance_regions.py sphere --set mis_rate=false   # mpg as before the thirteenth session

Writes bench/results/variance_regions-<scene>-<seed>.json and a figure
(path, log10 variance of both, their log2 ratio, the rate map) beside it."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> int:
    import mpg
    from pixel_errors import load_scene   # bench/, the script's own folder

    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--time", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--top", type=int, default=12, help="largest mpg pixel variances to list")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="scene parameter")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="mpg parameter (value as JSON, else a string), e.g. mis_rate=false")
    args = ap.parse_args()
    if not args.time > 0:
        ap.error("--time must be > 0")
    if any("=" not in p for p in args.param):
        ap.error("--param takes NAME=VALUE, e.g. res=128")
    params = dict(p.split("=", 1) for p in args.param)
    if any("=" not in p for p in args.set):
        ap.error("--set takes NAME=VALUE, e.g. mis_rate=false")
    mpg_params: dict = {}
    for p in args.set:
        k, v = p.split("=", 1)
        try:
            mpg_params[k] = json.loads(v)
        except json.JSONDecodeError:
            mpg_params[k] = v
    loaded = load_scene(args.scene, params, "variance_regions")
    if loaded is None:
        return 1
    sc = loaded[1]
    try:
        imgs = {k: mpg.render(sc, integ, time=args.time, seed=args.seed, progress=False)
                for k, integ in (("path", "path"), ("mpg", dict(type="mpg", **mpg_params)))}
    except mpg.RenderError as e:
        print(f"variance_regions: {e}", file=sys.stderr)
        return 1
    vp = np.asarray(imgs["path"].variance, dtype=float).mean(axis=2)
    vm = np.asarray(imgs["mpg"].variance, dtype=float).mean(axis=2)
    q = imgs["mpg"].chain_rate_map
    n = vm.size
    out: dict = {"command": " ".join(["python", "bench/variance_regions.py"] + sys.argv[1:]),
                 "mpg_params": mpg_params, "spp": {k: int(v.spp) for k, v in imgs.items()},
                 "mean_variance": {"path": float(vp.mean()), "mpg": float(vm.mean())}, "regions": {}}
    if q is not None:
        q = np.asarray(q)
        for name, mask in (("rate 0", q == 0), ("rate in (0, 1)", (q > 0) & (q < 1)), ("rate 1", q >= 1)):
            out["regions"][name] = {"pixels": float(mask.mean()), "path": float(vp[mask].sum() / n),
                                    "mpg": float(vm[mask].sum() / n)}
    srt = np.sort(vm.ravel())[::-1]
    tot = float(srt.sum())
    out["mpg_share_of_largest"] = {str(k): float(srt[:k].sum() / tot) if tot > 0 else 0.0 for k in (10, 100, 1000)}
    top = []
    for i in np.argsort(vm.ravel())[::-1][:args.top]:
        y, x = divmod(int(i), vm.shape[1])
        top.append({"x": x, "y": y, "mpg": float(vm[y, x]), "path": float(vp[y, x]),
                    "rate": float(q[y, x]) if q is not None else None,
                    "mpg_value": float(np.asarray(imgs["mpg"].rgb)[y, x].mean())})
    out["largest"] = top
    print(json.dumps({k: out[k] for k in ("spp", "mean_variance", "regions", "mpg_share_of_largest")}, indent=1))
    for t in top:
        print(f"({t['x']}, {t['y']}) mpg {t['mpg']:.3g} path {t['path']:.3g} rate {t['rate']} value {t['mpg_value']:.3g}")
    res = ROOT / "bench" / "results"
    res.mkdir(parents=True, exist_ok=True)
    stem = res / f"variance_regions-{pathlib.Path(args.scene).stem}-{args.seed}"
    stem.with_suffix(".json").write_text(json.dumps(out, indent=2))
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return 0
    fig, ax = plt.subplots(1, 4, figsize=(20, 5))
    ax[0].imshow(np.clip(np.asarray(imgs["path"].rgb).mean(axis=2), 0, 1), cmap="gray")
    ax[0].set_title(f"path, {imgs['path'].spp} spp")
    lo, hi = -6, -1
    ax[1].imshow(np.log10(vp + 1e-9), vmin=lo, vmax=hi)
    ax[1].set_title("log10 variance, path")
    im = ax[2].imshow(np.log10(vm + 1e-9), vmin=lo, vmax=hi)
    ax[2].set_title(f"log10 variance, mpg ({imgs['mpg'].spp} spp)")
    plt.colorbar(im, ax=ax[2])
    if q is not None:
        im = ax[3].imshow(q, vmin=0, vmax=1)
        ax[3].set_title("mpg's chain rate (0: path tracer)")
        plt.colorbar(im, ax=ax[3])
    for a in ax:
        a.set_xticks([])
        a.set_yticks([])
    plt.tight_layout()
    plt.savefig(stem.with_suffix(".png"), dpi=60)
    return 0


if __name__ == "__main__":
    sys.exit(main())
