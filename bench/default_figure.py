"""The built-in default scene rendered by `path` and by `mpg` in the same time,
side by side with their labels (the README's figure):

    python bench/default_figure.py --time 10 --out docs/images/default-path-mpg.png

Each render is time-limited (`mpg`'s training included in its time); the
labels give the integrator, the time and the spp (`mpg`: rendered + trained).
Linear radiance to 8-bit sRGB at exposure 0, as mpg-render's previews."""

from __future__ import annotations

import argparse
import sys


def main() -> int:
    import numpy as np
    from PIL import Image as PILImage
    from PIL import ImageDraw

    import mpg
    from mpg.image import to_srgb8

    ap = argparse.ArgumentParser()
    ap.add_argument("--time", type=float, default=10.0, help="seconds per render")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--res", type=int, nargs=2, default=None, metavar=("W", "H"),
                    help="film size (default: the scene's, 384 x 288)")
    ap.add_argument("--out", default="docs/images/default-path-mpg.png")
    args = ap.parse_args()
    kw = {} if args.res is None else {"res_x": str(args.res[0]), "res_y": str(args.res[1])}
    sc = mpg.load_file(mpg.default_scene_path(), **kw)
    panels = []
    for integ in ("path", "mpg"):
        img = mpg.render(sc, integ, time=args.time, seed=args.seed, progress=False)
        st = img.stats
        label = f"{integ}, {args.time:g} s, {img.spp} spp"
        if integ == "mpg":
            label += f" (+{st.get('spp_training', 0)} training)"
        panels.append((to_srgb8(img.rgb), label))
        print(label, file=sys.stderr)
    h, w = panels[0][0].shape[:2]
    gap, band = 4, 18
    out = np.full((h + band, 2 * w + gap, 3), 255, dtype=np.uint8)
    for i, (rgb8, _) in enumerate(panels):
        out[band:, i * (w + gap):i * (w + gap) + w] = rgb8
    im = PILImage.fromarray(out, mode="RGB")
    draw = ImageDraw.Draw(im)
    for i, (_, label) in enumerate(panels):
        draw.text((i * (w + gap) + 4, 3), label, fill=(0, 0, 0))
    im.save(args.out)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
