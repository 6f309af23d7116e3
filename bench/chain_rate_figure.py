"""Figure for docs/results.md ("Chain rates per pixel"): `mpg` renders of the
evaluation scenes next to the chain-rate maps it learned in training.

    python bench/chain_rate_figure.py [--scenes sphere double_slabs] [--time 30] [--seed 1]

Each row: the image (sRGB, clipped) and the map on a log2 scale from 1/32
(black) to 1 (white; pixels without chain work are 1), blue where the rate is
0 (the path tracer alone). Writes
docs/images/chain-rates.png and bench/results/chain_rate_figure.json (spp and
rate summary per scene)."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> int:
    import mpg
    from mpg.chain_rates import rate_map_grey8
    from mpg.image import to_srgb8, write_png8

    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", nargs="+", default=["sphere", "double_slabs"])
    ap.add_argument("--time", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=str(ROOT / "docs" / "images" / "chain-rates.png"))
    args = ap.parse_args()
    rows, summary = [], {}
    for name in args.scenes:
        sc = mpg.load_file(str(ROOT / "scenes" / "eval" / f"{name}.xml"))
        img = mpg.render(sc, "mpg", time=args.time, seed=args.seed, progress=False)
        q = img.chain_rate_map
        if q is None:
            print(f"{name}: no learned rates ({img.stats.get('chain_rate_mode')})", file=sys.stderr)
            q = np.ones(img.rgb.shape[:2], np.float32)
        rows.append(np.concatenate([to_srgb8(img.rgb), rate_map_grey8(q)], axis=1))
        st = img.stats
        summary[name] = {k: st.get(k) for k in ("spp", "spp_training", "chain_rate_mode", "chain_rate_mean",
                                                "chain_rate_fraction_one", "chain_rate_fraction_min",
                                                "chain_rate_fraction_pt", "chain_handoff")}
        print(name, summary[name])
    write_png8(args.out, np.concatenate(rows, axis=0))
    res = ROOT / "bench" / "results"
    res.mkdir(parents=True, exist_ok=True)
    (res / "chain_rate_figure.json").write_text(json.dumps({"command": " ".join(sys.argv), **summary}, indent=2))
    print("wrote", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
