"""Guiding-state build time for N sub-path samples (issue 5 target: 1 M
samples in under 1 s on 2 cores, per-leaf chain distributions included), for
each spatial-structure variant of the MPG ablations (paper Fig. 14,
supplemental Figs. 1-2), and the query cost of the STree against exact kNN.

    python bench/stree_build.py [--n 1000000] [--repeats 3] [--threads 2] [--queries 2000]

Per variant: the best wall time of the build call (numpy -> C++ conversion
included), its C++ part (`build_seconds`) and tree part (`structure_seconds`),
the process CPU time of that run, leaves, samples stored per input sample
and the built guide's memory per input sample (`GuidingState.memory_bytes`).
The machine's load average is recorded: on a shared machine the wall time of
two threads is only meaningful next to it. Writes bench/results/stree_build.json."""

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

VARIANTS = {
    "nearest eps=0.1": {},
    "nearest eps=0": {"epsilon": 0.0},
    "stochastic eps=0.1": {"filter": "stochastic"},
    "none": {"filter": "none"},
    "nearest eps=0.1, threshold=512": {"threshold": 512},
    "knn": {"structure": "knn"},
}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--queries", type=int, default=2000, help="kNN queries timed (STree: 100x as many)")
    args = ap.parse_args()
    from mpg import _core
    from test_guiding import _samples

    xD, xL, d, n, tau, w = _samples(args.n, seed=5, clusters=64)
    rng = np.random.default_rng(6)
    # queries near the data: sample positions, slightly moved
    qi = rng.integers(0, args.n, 100 * args.queries)
    qD = (xD[qi] + rng.normal(scale=0.01, size=(len(qi), 3))).astype(np.float32)
    qL = (xL[qi] + rng.normal(scale=0.01, size=(len(qi), 3))).astype(np.float32)
    out = {"n": args.n, "threads": args.threads, "bytes_per_sample": _core.SUBPATH_SAMPLE_BYTES,
           "cpu_count": os.cpu_count(), "loadavg_before": os.getloadavg(), "runs": {}}
    for name, kw in VARIANTS.items():
        best = None
        for _ in range(args.repeats):
            g = _core.GuidingState()
            c0 = time.process_time()
            t0 = time.perf_counter()
            g.build(xD, xL, d, n, tau, w, [-1, -1, -1], [1, 1, 1], threads=args.threads, **kw)
            run = {"seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0,
                   "build_seconds": g.build_seconds, "structure_seconds": g.structure_seconds}
            if best is None or run["seconds"] < best["seconds"]:
                best = run
        best.update(leaves=g.num_leaves, samples_stored=g.samples_stored,
                    stored_per_input=g.samples_stored / args.n, threshold=g.threshold,
                    bytes_per_input=g.memory_bytes / args.n)
        nq = args.queries if kw.get("structure") == "knn" else 100 * args.queries
        sec, found = g.time_queries(qD[:nq], qL[:nq])
        best.update(queries=nq, query_us=1e6 * sec / nq, queries_with_distribution=found)
        if kw.get("structure") == "knn":
            best["knn_k"] = g.knn_k
        out["runs"][name] = best
        print(f"{name:32s} {best['seconds']:.3f} s (C++ {best['build_seconds']:.3f}, tree "
              f"{best['structure_seconds']:.3f}, CPU {best['cpu_seconds']:.3f}), {g.num_leaves} leaves, "
              f"{best['stored_per_input']:.2f} stored/input, {best['bytes_per_input']:.0f} B/input, query {best['query_us']:.2f} us", flush=True)
    out["loadavg_after"] = os.getloadavg()
    print(f"load average before/after: {out['loadavg_before'][0]:.2f} / {out['loadavg_after'][0]:.2f} "
          f"on {os.cpu_count()} CPUs")
    os.makedirs(ROOT / "bench" / "results", exist_ok=True)
    (ROOT / "bench" / "results" / "stree_build.json").write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
