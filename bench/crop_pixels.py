"""Render a few pixels of an eval scene for a long time (a crop window) and
print them beside the cached reference's: a check of the reference where a
method and the reference disagree.

    python bench/crop_pixels.py emitter_size_001 --x 73 --y 54 --size 5 --spp 200000 --integrator path --param res=128

Values are the mean over RGB; ± is the standard error of the mean. Needs a
cached reference of the scene with the same parameters (mpg-bench reference).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "python"))

import mpg  # noqa: E402
from mpg.bench import reference as refmod  # noqa: E402
from mpg.bench.scenes import resolve_scene  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--x", type=int, required=True, help="crop's left column (full film)")
    ap.add_argument("--y", type=int, required=True, help="crop's top row (full film)")
    ap.add_argument("--size", type=int, default=5)
    ap.add_argument("--spp", type=int, default=100000)
    ap.add_argument("--integrator", default="path", help="a name or a JSON object")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE")
    a = ap.parse_args(argv)
    params = dict(p.split("=", 1) for p in a.param)
    bs = resolve_scene(a.scene, params)
    xml = pathlib.Path(bs.path).read_text()
    crop = (f'<integer name="crop_offset_x" value="{a.x}"/><integer name="crop_offset_y" value="{a.y}"/>'
            f'<integer name="crop_width" value="{a.size}"/><integer name="crop_height" value="{a.size}"/>')
    if '<rfilter type="box"/>' not in xml:
        raise SystemExit("crop_pixels: the scene's film has no one-line box filter to put the crop beside")
    xml = xml.replace('<rfilter type="box"/>', '<rfilter type="box"/>' + crop, 1)
    sc = mpg.load_string(xml, base_dir=str(pathlib.Path(bs.path).parent), **params)
    integ = json.loads(a.integrator) if a.integrator.lstrip().startswith("{") else a.integrator
    img = mpg.render(sc, integrator=integ, spp=a.spp, seed=a.seed, progress=False)
    info = refmod.find_reference(bs)
    np.set_printoptions(precision=4, suppress=True, linewidth=160)
    print(f"{a.scene} {params} crop x {a.x}.. y {a.y}.. size {a.size}, {integ}, {img.spp} spp")
    print("render:\n", img.rgb.mean(axis=2))
    print("± (standard error):\n", np.sqrt(img.variance.mean(axis=2)))
    if info is None:
        print("no cached reference")
    else:
        ref, _ = refmod.load_reference(info)
        r = ref[a.y:a.y + a.size, a.x:a.x + a.size, :3].mean(axis=2)
        print(f"reference ({info['recipe'].get('method')}, {info['created']}):\n", r)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
