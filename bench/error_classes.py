"""Where an image's variance comes from, by the kind of path that brought the
light: one render with `record_classes` (mpg.render), each sample's value
split into chain estimates (X / q), the path tracer's shares of shared chain
paths (its balance weight, Bernoulli rounds K'), handed-off pixels' traced
chain light (guided traces and the path tracer's weights against them),
chain paths the path tracer kept whole in pixels of rate 0 ("handed":
untraced) and elsewhere because the estimator does not take them ("unseen":
a type their leaf never saw, known_types; "inactive": no leaf with
unfiltered samples, selective activation; "unowned": a length or light the
estimator does not produce), the light seen through delta scattering only
(glints in the glass, with the delta split's mean), and the rest (NEE,
indirect light).

Per class: the image mean of the variance of each pixel's mean that the
class alone would have (its share of the sum over classes; the classes'
covariances are left out, so the sum differs from the image's variance), the
share of the image's variance held by the pixels each class dominates, the
share of the summed class variances in the largest pixels, and the largest
pixels with their classes. Light from an environment seen through a chain
counts in the rest.

    python bench/error_classes.py sphere --time 20 --seed 0
    python bench/error_classes.py double_slabs --integrator mpg/known_types=false --time 20
    python bench/error_classes.py double_slabs --time 20 --seeds 3

With --seeds N (2+) also each class's variance across the N renders (and
the image's): the within-render variance counts the delta split's Sobol
positions as independent samples and so overstates the *delta* class. And
with --ref-split V, the groups' part in the pixels where the cached
reference's variance is above V (seen through the glass) and in the rest:

    python bench/error_classes.py double_slabs --time 20 --seeds 4 --ref-split 1e-3

Writes bench/results/error_classes-<scene>-<integrator>[-<param>...]-<seed>[-s<seeds>].json
(the integrator's / and = as _), or --out."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def class_variances(class_sum: np.ndarray, class_sum_sq: np.ndarray, n: int) -> np.ndarray:
    """Per pixel and class the variance of the pixel's mean (n samples) that
    the class's part of the sample value alone has (height x width x classes)."""
    if n < 2:
        raise ValueError("need at least 2 samples per pixel")
    m = class_sum / n
    return np.maximum(class_sum_sq / n - m * m, 0.0) * (n / (n - 1)) / n


def summarise(var_c: np.ndarray, names: tuple[str, ...], image_var: np.ndarray, top: int) -> dict:
    """The classes' image-mean variances and shares, the image's variance in the
    pixels each class dominates, and the `top` largest pixels (by the sum over
    classes)."""
    tot_c = var_c.sum(axis=2)
    means = {nm: float(var_c[..., i].mean()) for i, nm in enumerate(names)}
    s = sum(means.values())
    dom = np.argmax(var_c, axis=2)
    iv = float(image_var.sum())
    out = {
        "image_variance": float(image_var.mean()),
        "class_variance": means,
        "class_share": {nm: (v / s if s > 0 else 0.0) for nm, v in means.items()},
        "dominated_pixels": {nm: int(np.sum((dom == i) & (tot_c > 0))) for i, nm in enumerate(names)},
        "dominated_share_of_image_variance": {
            nm: (float(image_var[(dom == i) & (tot_c > 0)].sum()) / iv if iv > 0 else 0.0)
            for i, nm in enumerate(names)},
    }
    flat = np.sort(tot_c.ravel())[::-1]
    out["share_of_largest"] = {str(k): (float(flat[:k].sum() / flat.sum()) if flat.sum() > 0 else 0.0)
                               for k in (10, 100, 1000)}
    pix = []
    for k in np.argsort(tot_c.ravel())[::-1][:top]:
        y, x = divmod(int(k), tot_c.shape[1])
        pix.append({"x": x, "y": y, "variance": float(tot_c[y, x]),
                    **{nm: float(var_c[y, x, i]) for i, nm in enumerate(names)}})
    out["largest"] = pix
    return out


# The classes summed where a seed's learned maps move light between them: a
# pixel's chain light is the estimator's and the path tracer's shares
# (chain, shared) in one seed and traced or handed off in another, so across
# seeds those classes are anticorrelated and only their sum says what the
# chain light at a separator costs; the photons take a share of it at a rate
# learned per seed.
GROUPS = {
    "chain_light": ("chain", "shared", "traced", "handed", "unseen", "inactive", "unowned", "photons"),
    "delta": ("delta", "glints"),
    "other": ("other",),
}


def seed_summary(means: np.ndarray, names: tuple[str, ...]) -> dict:
    """The classes' seeds' variance: each class's image (its share of the
    pixel's mean over RGB) from independent renders (seeds x height x width
    x classes), the image mean of the unbiased variance across the seeds
    per class, and the same of their sum (the image's seeds' variance of the
    RGB mean, covariances included: below mpg.metrics.seed_variance's mean
    of the channels' variances where the channels are not fully correlated). Unlike the
    within-render variance this holds samples that are not independent
    inside one render (the delta split's Sobol positions, stratified pixel
    positions) at their true worth."""
    if means.shape[0] < 2:
        raise ValueError("a seeds' variance needs at least 2 renders")
    per = {nm: float(np.mean(means[:, :, :, i].var(axis=0, ddof=1))) for i, nm in enumerate(names)}
    s = sum(per.values())
    total = means.sum(axis=3)
    v_all = float(np.mean(total.var(axis=0, ddof=1)))
    # what the image's variance loses if a class were exact: var(all) -
    # var(all - class) = var(class) + 2 cov(class, rest). The path tracer's
    # and an estimator's balance-weighted shares of one path are
    # anticorrelated, so a class's own variance overstates what it costs.
    drop = {nm: v_all - float(np.mean((total - means[:, :, :, i]).var(axis=0, ddof=1)))
            for i, nm in enumerate(names)}
    grouped, gdrop = {}, {}
    for g, members in GROUPS.items():
        part = means[:, :, :, [names.index(c) for c in members]].sum(axis=3)
        grouped[g] = float(np.mean(part.var(axis=0, ddof=1)))
        gdrop[g] = v_all - float(np.mean((total - part).var(axis=0, ddof=1)))
    return {"seeds": int(means.shape[0]),
            "class_seed_variance": per,
            "class_seed_share": {nm: (v / s if s > 0 else 0.0) for nm, v in per.items()},
            "class_seed_contribution": drop,
            "group_seed_variance": grouped,
            "group_seed_contribution": gdrop,
            "image_seed_variance": v_all}


def split_by_mask(means: np.ndarray, names: tuple[str, ...], mask: np.ndarray, threshold: float) -> dict:
    """The groups' seeds' variance summed over the pixels in `mask` and over
    the rest, each divided by the image's pixel count (so the parts add up to
    the image means of seed_summary's group_seed_variance)."""
    npx = float(mask.size)
    out = {"threshold": threshold, "pixels_above": int(mask.sum())}
    for part, m in (("above", mask), ("below", ~mask)):
        out[part] = {g: float(means[:, :, :, [names.index(c) for c in members]].sum(axis=3)
                              .var(axis=0, ddof=1)[m].sum() / npx)
                     for g, members in GROUPS.items()}
        out[part]["image"] = float(means.sum(axis=3).var(axis=0, ddof=1)[m].sum() / npx)
    return out


def main() -> int:
    import mpg
    from mpg.render import CLASS_NAMES
    from pixel_errors import (add_param_option, load_scene, load_with_reference, mpg_integrator,   # bench/
                              reference_with_variance, scene_params)

    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--integrator", default="mpg", help="name, with parameters as in mpg-bench: mpg/pixel_split=mse")
    ap.add_argument("--time", type=float, default=20.0)
    ap.add_argument("--spp", type=int, help="samples per pixel instead of --time")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds", type=int, default=1,
                    help="renders with seeds SEED.., SEED+N-1; with 2+ the classes' seeds' variance too")
    ap.add_argument("--top", type=int, default=12, help="largest pixels to list")
    ap.add_argument("--ref-split", type=float, metavar="V",
                    help="with --seeds 2+: also split the groups' seeds' variance between the pixels where "
                         "the cached reference's variance (of its mean, mean over RGB) is above V and the "
                         "rest (bench/error_regions.py's split: the pixels seen through the glass)")
    add_param_option(ap)
    ap.add_argument("--out", help="the JSON file (default: bench/results/error_classes-<scene>-<integrator>-<seed>.json)")
    args = ap.parse_args()
    if not args.time > 0:
        ap.error("--time must be > 0")
    if args.spp is not None and args.spp < 2:
        ap.error("--spp must be >= 2")
    if args.seeds < 1:
        ap.error("--seeds must be >= 1")
    if args.ref_split is not None and args.seeds < 2:
        ap.error("--ref-split needs --seeds 2 or more")
    ref_var = None
    if args.ref_split is not None:
        loaded = load_with_reference(args.scene, scene_params(ap, args), "error_classes")
        found = None if loaded is None else reference_with_variance(loaded[2], "error_classes")
        if found is None:
            return 1
        ref_var = found[1]
    else:
        loaded = load_scene(args.scene, scene_params(ap, args), "error_classes")
    if loaded is None:
        return 1
    integ = mpg_integrator(ap, args.integrator, " (the classes are the core's)")
    # (mpg: its final render records the classes, its training passes do not)
    limit = dict(spp=args.spp) if args.spp is not None else dict(time=args.time)
    means = []   # per seed, each class's image (height x width x classes)
    for seed in range(args.seed, args.seed + args.seeds):
        try:
            img = mpg.render(loaded[1], integ, seed=seed, progress=False, record_classes=True, **limit)
        except mpg.RenderError as e:
            print(f"error_classes: {e}", file=sys.stderr)
            return 1
        if img.class_sum is None or img.spp < 2:
            print("error_classes: fewer than 2 samples per pixel were rendered; give more --time", file=sys.stderr)
            return 1
        if seed == args.seed:
            first = img
        if args.seeds > 1:
            means.append(np.asarray(img.class_sum, dtype=float) / img.spp)
    img = first   # (the within-render numbers are the first seed's)
    var_c = class_variances(img.class_sum, img.class_sum_sq, img.spp)
    out = {"command": "python bench/error_classes.py " + " ".join(sys.argv[1:]),
           "scene": args.scene, "integrator": args.integrator, "seed": args.seed,
           "time": None if args.spp is not None else args.time,
           "spp": img.spp, "classes": list(CLASS_NAMES)}
    out.update(summarise(var_c, CLASS_NAMES, img.variance.astype(float).mean(axis=2), args.top))
    if means:
        out.update(seed_summary(np.stack(means), CLASS_NAMES))
        if ref_var is not None:
            above = ref_var.astype(float).mean(axis=2) > args.ref_split
            if above.shape != means[0].shape[:2]:
                print(f"error_classes: the reference is {above.shape[1]}x{above.shape[0]}, the render "
                      f"{means[0].shape[1]}x{means[0].shape[0]}", file=sys.stderr)
                return 1
            out["ref_split"] = split_by_mask(np.stack(means), CLASS_NAMES, above, args.ref_split)
    # (a scene name, or a file's name without .xml; the integrator with its parameters)
    tag = "-".join([pathlib.Path(args.scene).stem, args.integrator.replace("/", "_").replace("=", "_")]
                   + [p.replace("=", "_") for p in args.param] + [str(args.seed)]
                   + ([f"s{args.seeds}"] if args.seeds > 1 else []))
    path = pathlib.Path(args.out) if args.out else ROOT / "bench" / "results" / f"error_classes-{tag}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k != "largest"}, indent=1))
    for p in out["largest"][:args.top]:
        cls = max(CLASS_NAMES, key=lambda c: p[c])
        if p["variance"] > 0:
            print(f"  ({p['x']}, {p['y']}) variance {p['variance']:.3g}, mostly {cls} ({p[cls] / p['variance']:.0%})")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
