"""STree build time and memory per sample for N sub-path samples (issue 5
target: 1 M samples in under 1 s on 2 cores), with and without filtering.

    python bench/stree_build.py [--n 1000000] [--repeats 3]

Writes bench/results/stree_build.json."""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    from mpg import _core
    from test_guiding import _samples

    xD, xL, d, n, tau, w = _samples(args.n, seed=5, clusters=64)
    out = {"n": args.n, "threads": args.threads, "bytes_per_sample": _core.SUBPATH_SAMPLE_BYTES, "runs": {}}
    for eps in (0.0, 0.1):
        best = 1e9
        for _ in range(args.repeats):
            g = _core.GuidingState()
            t0 = time.perf_counter()
            g.build(xD, xL, d, n, tau, w, [-1, -1, -1], [1, 1, 1], epsilon=eps, threads=args.threads)
            best = min(best, time.perf_counter() - t0)
        out["runs"][f"eps={eps}"] = {"seconds": best, "leaves": g.num_leaves,
                                     "samples_stored": g.samples_stored,
                                     "stored_per_input": g.samples_stored / args.n}
        print(f"eps={eps}: {best:.3f} s, {g.num_leaves} leaves, "
              f"{g.samples_stored / args.n:.2f} stored per input sample")
    os.makedirs(ROOT / "bench" / "results", exist_ok=True)
    (ROOT / "bench" / "results" / "stree_build.json").write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
