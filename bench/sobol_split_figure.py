"""Figure for docs/results.md ("The delta split's extra paths on a Sobol
sequence"): a crop of double_slabs where the light is seen through the bumpy
slabs as thin bright slivers, from the cached reference and from two `mpg`
renders of equal time, the delta split's extra paths at independent film
positions (`delta_split_sobol` false) and on the per-pixel Sobol sequence
(the default); below each render its absolute error against the reference.

    python bench/sobol_split_figure.py [--time 20] [--seed 0]

Writes docs/images/sobol-split.png (nearest-neighbour zoom, sRGB, clipped;
the error row scaled so that 1.0 is white) and prints each render's MSE over
the crop and the whole image, with its spp. Needs the scene's reference in the
cache (mpg-bench reference double_slabs)."""

from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "python"))


def main(argv=None) -> int:
    import mpg
    from mpg.bench import reference as refmod
    from mpg.bench.scenes import resolve_scene
    from mpg.image import to_srgb8, write_png8

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--time", type=float, default=20.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--x", type=int, default=136, help="crop's left column")
    ap.add_argument("--y", type=int, default=82, help="crop's top row")
    ap.add_argument("--size", type=int, default=44)
    ap.add_argument("--zoom", type=int, default=5)
    ap.add_argument("--out", default=str(ROOT / "docs" / "images" / "sobol-split.png"))
    a = ap.parse_args(argv)
    bs = resolve_scene("double_slabs", {})
    info = refmod.find_reference(bs)
    if info is None:
        raise SystemExit("sobol_split_figure: no cached reference of double_slabs (mpg-bench reference double_slabs)")
    ref, _ = refmod.load_reference(info)
    ref = ref[..., :3]
    sc = mpg.load_file(bs.path)
    ys, xs = slice(a.y, a.y + a.size), slice(a.x, a.x + a.size)

    def zoom(img: np.ndarray) -> np.ndarray:
        return np.repeat(np.repeat(img, a.zoom, axis=0), a.zoom, axis=1)

    top, bottom = [zoom(to_srgb8(ref[ys, xs]))], [zoom(np.zeros((a.size, a.size, 3), np.uint8))]
    for sobol in (False, True):
        img = mpg.render(sc, {"type": "mpg", "delta_split_sobol": sobol}, time=a.time, seed=a.seed, progress=False)
        err = img.rgb - ref
        print(f"delta_split_sobol {str(sobol).lower():5s}: {img.spp} spp, MSE crop {np.mean(err[ys, xs] ** 2):.4g}, "
              f"image {np.mean(err ** 2):.4g}")
        top.append(zoom(to_srgb8(img.rgb[ys, xs])))
        e = np.clip(np.abs(err[ys, xs]).mean(axis=2, keepdims=True), 0.0, 1.0)
        bottom.append(zoom(np.repeat(np.round(e * 255.0).astype(np.uint8), 3, axis=2)))
    gap = np.full((a.size * a.zoom, 4, 3), 255, np.uint8)

    def row(tiles):
        out = [tiles[0]]
        for t in tiles[1:]:
            out += [gap, t]
        return np.concatenate(out, axis=1)
    fig = np.concatenate([row(top), np.full((4, row(top).shape[1], 3), 255, np.uint8), row(bottom)], axis=0)
    pathlib.Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    write_png8(a.out, fig)
    print(f"wrote {a.out}: reference | independent | Sobol; below, |error| (1.0 white)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
