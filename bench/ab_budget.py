"""Equal-time A/B of two builds of mpg's core: per seed one render with core A
and one with core B (and optionally one of a peer integrator with core B), in
turn, each in its own process, at the same time budget; then the seeds'
variance of each (mpg.metrics.seed_variance: a reference-free MSE) and their
ratios. For changes that move no statistics but the time a render has, such
as the training's overhead at short budgets, where a fixed-spp timing
(bench/ab_core.sh) does not show what the saved time buys.

    cp .venv/lib/python3.11/site-packages/mpg/_core*.so /tmp/core_a.so   # before the change
    ... rebuild ...
    cp .venv/lib/python3.11/site-packages/mpg/_core*.so /tmp/core_b.so
    python bench/ab_budget.py /tmp/core_a.so /tmp/core_b.so sphere --time 2 --seeds 24 --peer path

Writes bench/results/ab_budget-<scene>-<time>s.json (or --out FILE); leaves
core B installed."""

from __future__ import annotations

import argparse
import glob
import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]

RENDER = """
import sys, numpy as np, mpg
from mpg.bench.scenes import resolve_scene
bs = resolve_scene(sys.argv[1])
sc = mpg.load_file(bs.path, **bs.params)
img = mpg.render(sc, sys.argv[2], time=float(sys.argv[3]), seed=int(sys.argv[4]), progress=False)
np.save(sys.argv[5], np.asarray(img.rgb, dtype=np.float32))
print(mpg._core.__file__)
print(img.stats["spp"], img.stats.get("spp_training") or 0)
"""


def install(core: str, installed: str) -> None:
    """Put `core` in place of the installed one by a rename (a process that
    has the old one loaded keeps its own file; an in-place copy would change
    it under that process)."""
    tmp = installed + ".ab_budget"
    shutil.copyfile(core, tmp)
    os.replace(tmp, installed)


def main() -> int:
    from mpg import metrics

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("core_a")
    ap.add_argument("core_b")
    ap.add_argument("scene", help="an eval scene name (mpg.bench.scenes)")
    ap.add_argument("--time", type=float, default=2.0)
    ap.add_argument("--seeds", type=int, default=16)
    ap.add_argument("--integrator", default="mpg")
    ap.add_argument("--peer", help="also render this integrator with core B (e.g. path)")
    ap.add_argument("--out")
    args = ap.parse_args()
    for f in (args.core_a, args.core_b):
        if not pathlib.Path(f).is_file():
            ap.error(f"{f}: no such core build")
    so = glob.glob(str(ROOT / ".venv/lib/python3.11/site-packages/mpg/_core*.so"))
    if len(so) != 1:
        ap.error("expected one installed core in .venv/lib/python3.11/site-packages/mpg/")
    installed = so[0]
    for f in (args.core_a, args.core_b):
        if os.path.realpath(f) == os.path.realpath(installed):
            ap.error(f"{f} is the installed core itself: copy it elsewhere first (it is overwritten)")
    runs = [("A", args.core_a, args.integrator), ("B", args.core_b, args.integrator)]
    if args.peer:
        runs.append((args.peer, args.core_b, args.peer))
    images: dict[str, list] = {name: [] for name, _, _ in runs}
    spp: dict[str, list] = {name: [] for name, _, _ in runs}
    with tempfile.TemporaryDirectory() as tmp:
        try:
            for seed in range(args.seeds):
                # (the order rotates from seed to seed: a drift of the machine's
                # speed falls on every build alike)
                for name, core, integ in runs[seed % len(runs):] + runs[:seed % len(runs)]:
                    install(core, installed)
                    out = f"{tmp}/{name}-{seed}.npy"
                    r = subprocess.run([sys.executable, "-c", RENDER, args.scene, integ, str(args.time), str(seed),
                                        out], capture_output=True, text=True, timeout=60 * args.time + 600)
                    if r.returncode != 0:
                        sys.stderr.write(r.stderr)
                        return 1
                    # (its last two lines: the core's path, then spp and training spp)
                    lines = [ln for ln in r.stdout.splitlines() if ln.strip()]
                    used = [ln for ln in lines if ln.endswith(".so")]
                    if not used or os.path.realpath(used[-1]) != os.path.realpath(installed):
                        sys.stderr.write(f"the render loaded {used[-1] if used else '?'}, not {installed} "
                                         f"(run this script with the .venv's python)\n")
                        return 1
                    images[name].append(np.load(out))
                    spp[name].append([int(x) for x in lines[-1].split()])
                    print(f"seed {seed} {name}: spp, training spp {spp[name][-1]}", flush=True)
        finally:
            install(args.core_b, installed)
    res = {"command": " ".join([pathlib.Path(sys.argv[0]).name] + sys.argv[1:]), "scene": args.scene,
           "time": args.time, "seeds": args.seeds, "runs": {}}
    for name, _, integ in runs:
        sv = metrics.seed_variance(images[name])
        # three disjoint thirds of the seeds: how far one number moves
        thirds = [metrics.seed_variance(images[name][i::3]) for i in range(3)] if args.seeds >= 6 else []
        res["runs"][name] = {"integrator": integ, "seed_variance": sv, "thirds": thirds,
                             "spp_mean": float(np.mean([s[0] for s in spp[name]])),
                             "training_spp_mean": float(np.mean([s[1] for s in spp[name]]))}
        print(f"== {name} ({integ}): seeds' variance {sv:.4g} (thirds {', '.join(f'{t:.3g}' for t in thirds)}), "
              f"spp {res['runs'][name]['spp_mean']:.1f}, training spp {res['runs'][name]['training_spp_mean']:.1f}")
    a, b = res["runs"]["A"]["seed_variance"], res["runs"]["B"]["seed_variance"]

    def ratio(x: float, y: float) -> str:
        return f"{x / y:.3g}" if y > 0 else "inf"

    print(f"A / B {ratio(a, b)}")
    if args.peer:
        p = res["runs"][args.peer]["seed_variance"]
        print(f"{args.peer} / A {ratio(p, a)}, {args.peer} / B {ratio(p, b)}")
    out = pathlib.Path(args.out or ROOT / f"bench/results/ab_budget-{pathlib.Path(args.scene).stem}-{args.time:g}s.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
