"""Is one render's mean the reference's? The image mean, the caustic box's
and the upper half's of a render against the scene's cached reference, each
with the render's standard error of that mean (its per-pixel variance of the
mean; the reference's own noise is left out) and z. A bias check against
Mitsuba 3's references (docs/results.md, twenty-second session).

    python bench/region_means.py plane --integrator mpg --time 40 --seed 7

Needs the scene's reference in the cache (mpg-bench reference)."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from pixel_errors import cached_reference


def main() -> int:
    import mpg
    from mpg.metrics import box_to_slices

    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--integrator", default="mpg", help="name, with parameters as in mpg-bench: mpg/light_trace=0")
    ap.add_argument("--time", type=float, default=40.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    found = cached_reference(args.scene, "region_means")
    if found is None:
        return 2
    sc, ref = found
    name, *kv = args.integrator.split("/")
    img = mpg.render(sc.load_mpg(), dict(type=name, **dict(p.split("=", 1) for p in kv)), time=args.time,
                     seed=args.seed, progress=False)
    regions = [("image", np.s_[:, :]), ("upper half", np.s_[: ref.shape[0] // 2, :])]
    if sc.caustic_box is not None:
        regions.insert(1, ("caustic box", box_to_slices(ref.shape[:2], sc.caustic_box)))
    print(f"{args.scene} {args.integrator} seed {args.seed}: {img.spp} spp")
    for label, r in regions:
        a, b = float(img.rgb[r].astype(float).mean()), float(ref[r].astype(float).mean())
        n = img.rgb[r][..., 0].size
        se = float(np.sqrt(img.variance[r].astype(float).sum(axis=(0, 1)).mean()) / n)
        print(f"  {label}: render {a:.5g} reference {b:.5g} (diff {a - b:.3g}, se {se:.2g}, z {(a - b) / se:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
