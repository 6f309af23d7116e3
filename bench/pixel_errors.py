"""Where an image's error sits: one mpg render (or any integrator) against the
cached reference, the share of MSE and relMSE in its worst pixels, and those
pixels (and the share of MSE in the scene's caustic box and in the image's
upper half, and those regions' means against the reference's with z: a
bias check). With --moments X Y (mpg only), the training statistics the learned
rates saw at that pixel: the chains' second moment E[sum X^2], a sample's
variance, the chain cost at rate 1 against the rest of the sample, and the
rate the pixel got (docs/results.md, "Splitting the pixels, and a floor on the
rates").

    python bench/pixel_errors.py sphere --integrator mpg --time 30 --seed 3 --moments 169 60
    python bench/pixel_errors.py emitter_size_003 --param res=128 --time 10 --seed 1

Needs the scene's reference in the cache (mpg-bench reference; with the
same --param). Writes bench/results/pixel_errors-<scene>-<integrator>-<seed>.json,
or --out."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def cached_reference(scene: str, tool: str, params: dict[str, str] | None = None):
    """(bench scene, reference RGB) of `scene`'s cached reference (with scene
    parameters `params`, e.g. res), or None after saying how to make it."""
    from mpg.bench import reference as refmod
    from mpg.bench.scenes import BenchError, resolve_scene

    try:
        sc = resolve_scene(scene, params or {})
    except BenchError as e:
        print(f"{tool}: {e}", file=sys.stderr)
        return None
    info = find_cached(sc, scene, params or {}, tool)
    return None if info is None else (sc, refmod.load_reference(info)[0])


def find_cached(bs, scene: str, params: dict[str, str], tool: str):
    """The cached reference's info of bench scene `bs`, or None after saying
    how to make it."""
    from mpg.bench import reference as refmod

    info = refmod.find_reference(bs)
    if info is None:
        print(f"{tool}: no cached reference of {scene} {params}; make it with mpg-bench reference",
              file=sys.stderr)
    return info


def reference_with_variance(info, tool: str):
    """(reference RGB, its per-pixel variance of the mean) of a cached
    reference's info, or None after saying it has no variance channel."""
    from mpg.bench import reference as refmod

    ref, var = refmod.load_reference(info)
    if var is None:
        print(f"{tool}: the reference has no variance channel", file=sys.stderr)
        return None
    return ref, var


def add_param_option(ap: argparse.ArgumentParser) -> None:
    """The bench scripts' repeatable --param NAME=VALUE (scene parameters)."""
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                    help="scene parameter, e.g. res=128 (repeatable)")


def parse_variants(ap: argparse.ArgumentParser, texts: list[str], what: str) -> list[dict]:
    """The bench scripts' --variants: each a JSON object of `what`
    (parameters) without 'type'; anything else is the parser's error."""
    try:
        variants = [json.loads(v) for v in texts]
    except json.JSONDecodeError as e:
        ap.error(f"a variant is not JSON: {e}")
    if not all(isinstance(v, dict) and "type" not in v for v in variants):
        ap.error(f"each variant must be a JSON object of {what} without 'type', "
                 "e.g. '{\"chain_rate_min\": 0.0625}'")
    return variants


def scene_params(ap: argparse.ArgumentParser, args) -> dict[str, str]:
    """--param as a dict; a malformed one is the parser's error."""
    if any("=" not in p for p in args.param):
        ap.error("--param takes NAME=VALUE, e.g. res=128")
    return dict(p.split("=", 1) for p in args.param)


def mpg_integrator(ap: argparse.ArgumentParser, text: str, why: str = "") -> dict:
    """An mpg integrator named as mpg-bench names it (NAME/key=value/...,
    runners.parse_integrator) as mpg.render's dict; anything else is the
    parser's error (`why`: what needs the core's integrator)."""
    from mpg.bench.runners import BenchError, parse_integrator

    try:
        spec = parse_integrator(text)
    except BenchError as e:
        ap.error(f"--integrator: {e}")
    if spec.backend != "mpg":
        ap.error(f"--integrator: an mpg integrator{why}")
    return dict(spec.params, type=spec.name)


def load_scene(scene: str, params: dict[str, str], tool: str):
    """(bench scene, mpg scene) of a scene name or path with scene parameters,
    or None after printing why not."""
    import mpg
    from mpg.bench.scenes import BenchError, resolve_scene

    try:
        bs = resolve_scene(scene, params)
        return bs, bs.load_mpg()
    except (BenchError, mpg.SceneError) as e:
        print(f"{tool}: {e}", file=sys.stderr)
        return None


def load_with_reference(scene: str, params: dict[str, str], tool: str):
    """(bench scene, mpg scene, cached reference's info) of a scene name or
    path with scene parameters, or None after saying why not."""
    loaded = load_scene(scene, params, tool)
    if loaded is None:
        return None
    info = find_cached(loaded[0], scene, params, tool)
    return None if info is None else (*loaded, info)


def main() -> int:
    import mpg
    import mpg.guiding as guiding
    from mpg.chain_rates import _costs, _finite, _sample_variance

    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--integrator", default="mpg", help="name, with parameters as in mpg-bench: mpg/pixel_split=mse")
    ap.add_argument("--time", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--top", type=int, default=5, help="pixels to list")
    ap.add_argument("--moments", type=int, nargs=2, metavar=("X", "Y"))
    add_param_option(ap)
    ap.add_argument("--out", help="results file (default bench/results/pixel_errors-<scene>-<integrator>-<seed>.json)")
    args = ap.parse_args()
    params = scene_params(ap, args)
    integ = mpg_integrator(ap, args.integrator)

    found = cached_reference(args.scene, "pixel_errors", params)
    if found is None:
        return 2
    sc, ref = found
    seen: dict = {}
    learn = guiding.learn_rates

    def spy(acc, **kw):   # keep the training statistics the rates are learned from
        q, rinfo = learn(acc, **kw)
        seen.update(acc=acc, q=q)
        return q, rinfo

    guiding.learn_rates = spy
    img = mpg.render(sc.load_mpg(), integ, time=args.time, seed=args.seed, progress=False)
    se = ((img.rgb.astype(float) - ref) ** 2).mean(axis=2)
    rel = se / (ref.mean(axis=2) ** 2 + 0.01)
    out: dict = {"scene": args.scene, "params": params, "integrator": args.integrator, "seed": args.seed,
                 "time": args.time, "spp": img.spp, "mse": float(se.mean()), "relmse": float(rel.mean())}
    # the regions' shares of the error and their means against the reference's,
    # with the render's standard error of the mean (its per-pixel variance of
    # the mean; the reference's own noise left out) and z: a bias check
    regions = [("image", np.s_[:, :]), ("upper_half", np.s_[: se.shape[0] // 2, :])]
    if sc.caustic_box is not None:
        from mpg.metrics import box_to_slices
        regions.insert(1, ("caustic_box", box_to_slices(se.shape, sc.caustic_box)))
    out["region_means"] = {}
    for label, r in regions:
        if label != "image":
            out[f"mse_share_{label}"] = float(se[r].sum() / se.sum())
        a, b = float(img.rgb[r].astype(float).mean()), float(ref[r].astype(float).mean())
        sem = float(np.sqrt(img.variance[r].astype(float).sum(axis=(0, 1)).mean()) / se[r].size)
        out["region_means"][label] = {"render": a, "reference": b, "se": sem, "z": (a - b) / sem}
    for key, e in (("mse", se), ("relmse", rel)):
        flat = np.sort(e.ravel())[::-1]
        out[f"{key}_share_top"] = {str(k): float(flat[:k].sum() / flat.sum()) for k in (1, 10, 100, 1000)}
        pix = []
        for k in np.argsort(e.ravel())[::-1][:args.top]:
            y, x = divmod(int(k), e.shape[1])
            pix.append({"x": x, "y": y, "reference": float(ref[y, x].mean()), "image": float(img.rgb[y, x].mean()),
                        "share": float(e[y, x] / e.sum())})
        out[f"{key}_top_pixels"] = pix
    for k in ("max_chain_value", "max_chain_K", "max_chain_G", "max_chain_n", "max_chain_guided", "max_chain_rate"):
        if k in img.stats:
            out[k] = img.stats[k]
    if args.moments and "acc" in seen:
        x, y = args.moments
        acc, n = seen["acc"], float(seen["acc"].n)
        _, _, c1, _, c0 = _costs(acc, n)
        out["moments"] = {"x": x, "y": y, "training_spp": n, "rate": float(seen["q"][y, x]),
                          "chain_m2": float(_finite(acc.chain_m2)[y, x] / n),
                          "sample_variance": float(_sample_variance(acc.sum, acc.sum_sq, n)[y, x]),
                          "chain_cost_rate1": float(c1[y, x]), "rest_cost": float(c0[y, x])}
    path = (pathlib.Path(args.out) if args.out else
            ROOT / "bench" / "results" / f"pixel_errors-{args.scene}-{integ['type']}-{args.seed}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
